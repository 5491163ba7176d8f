"""The one header validator (codec/header.py): every rule, one clear error naming the key,
used alike by the decoder, ``info`` and the gsplat drop-in; every real stream accepted."""

from __future__ import annotations

import time
import zlib
from pathlib import Path

import pytest
import yaml

from gscodec_shac.codec import Decoder, Encoder
from gscodec_shac.codec.container import PREAMBLE_SIZE, Bitstream
from gscodec_shac.codec.header import read_header
from gscodec_shac.codec.tiers import read_headers
from gscodec_shac.commands.info import describe_gsc
from gscodec_shac.errors import BitstreamError, GscodecError, MemoryLimitError
from gscodec_shac.gsplat_compat import ShacCompression
from gscodec_shac.limits import MAX_HEADER_BYTES
from gscodec_shac.synthetic import make_synthetic_scene

FIXTURES = Path(__file__).parent / "fixtures" / "streams"


@pytest.fixture(scope="module")
def cloud():
    return make_synthetic_scene(300, seed=3, n_cameras=1, width=32, height=24).cloud


@pytest.fixture(scope="module")
def encoded(cloud) -> bytes:
    """paper_table3:rp2 with PCA: split positions (hi/lo), two rotation chunks, a grid mask."""
    return Encoder("paper_table3:rp2", sh_stage="pca", sh_params={"n_components": 8},
                   codec_options={"preset": "ultrafast"}).encode(cloud).to_bytes()


def _edit(encoded: bytes, edit) -> bytes:
    stream = Bitstream.from_bytes(encoded)
    edit(stream)
    return stream.to_bytes()


def _raw_header(encoded: bytes, text: bytes) -> bytes:
    """``encoded`` with its header replaced by ``text`` (CRC recomputed, chunks kept)."""
    length = int.from_bytes(encoded[12:16], "little")
    preamble = encoded[:12] + len(text).to_bytes(4, "little") + zlib.crc32(text).to_bytes(4, "little")
    return preamble + text + encoded[PREAMBLE_SIZE + length :]


def _header_text(encoded: bytes) -> str:
    return encoded[PREAMBLE_SIZE : PREAMBLE_SIZE + int.from_bytes(encoded[12:16], "little")].decode()


def _set_codec_index(stream, value):
    stream.chunk("scale").meta["codec"] = value


CASES = [
    (lambda s: s.header.update(num_gaussians=10**12), "key 'num_gaussians': must be an integer in 1..67108864"),
    (lambda s: s.header.update(num_gaussians="300"), "key 'num_gaussians'"),
    (lambda s: s.header.update(sh_degree=-1), "key 'sh_degree'"),
    (lambda s: s.header["grid"].update(height=1.5), "key 'grid.height'"),
    (lambda s: s.header["grid"].update(height=4096, width=4096), "key 'grid': a 4096x4096 grid cannot hold 300"),
    (lambda s: s.header.update(grid=[16, 24]), "key 'grid': must be a mapping"),
    (lambda s: s.header["grid"].update(padding="spiral"), "key 'grid.padding': must be one of tail, mask"),
    (lambda s: s.header.update(color="cmyk"), "key 'color'"),
    (lambda s: s.header["sh"].update(stage="wavelet"), "key 'sh.stage'"),
    (lambda s: s.header["sh"].update(features=-3), "key 'sh.features'"),
    (lambda s: s.header["sh"].update(lossless="no"), "key 'sh.lossless': must be true or false"),
    (lambda s: s.header.update(sh=None), "key 'sh': SH degree 3 needs an SH stage entry"),
    (lambda s: s.header.update(attributes=[]), "key 'attributes': must be a mapping"),
    (lambda s: s.header["attributes"].pop("scale"), "key 'attributes': names"),
    (lambda s: s.header["attributes"]["scale"].update(channels=4), "key 'attributes.scale.channels': must be 3"),
    (lambda s: s.header["attributes"]["scale"].update(transform="exp"), "key 'attributes.scale.transform'"),
    (lambda s: s.header["attributes"]["opacity"]["quantizer"].update(min=[1e39]),
     "key 'attributes.opacity.quantizer.min[0]': must be a number"),
    (lambda s: s.header["attributes"]["opacity"]["quantizer"].update(min=["0"]),
     "key 'attributes.opacity.quantizer.min[0]'"),
    (lambda s: s.header["attributes"]["opacity"]["quantizer"].update(max=[-1e30]),
     "key 'attributes.opacity.quantizer.max[0]'"),
    (lambda s: s.header["attributes"]["opacity"]["quantizer"].update(bits=0), "key 'attributes.opacity.quantizer.bits'"),
    (lambda s: s.header["attributes"]["opacity"].update(chunks="opacity"), "key 'attributes.opacity.chunks'"),
    (lambda s: s.header["attributes"]["opacity"].update(chunks=["ghost"]), "chunk 'ghost' is not in the chunk table"),
    (lambda s: _set_codec_index(s, -1), "key 'chunks.scale.codec': must be an integer in 0..1, got -1"),
    (lambda s: _set_codec_index(s, 2**64), "key 'chunks.scale.codec'"),
    (lambda s: s.header["codecs"][0].update(name="nonexistent"), "key 'codecs[0].name'"),
    (lambda s: s.header["codecs"][0].update(options={"preset": [1, 2]}), "key 'codecs[0].options.preset'"),
    (lambda s: s.header.update(codecs={}), "key 'codecs'"),
    (lambda s: s.chunk("scale").meta.update(shape=[3, 4096, 4096]), "key 'chunks.scale.shape': must be [3,"),
    (lambda s: s.chunk("scale").meta.update(bits=9), "key 'chunks.scale.bits': must be 10"),
    (lambda s: s.chunk("scale").meta.update(part="middle"), "key 'chunks.scale.part'"),
    (lambda s: s.chunk("scale").meta.update(channels=[0, 2]), "key 'chunks.scale.shape'"),
    (lambda s: s.chunk("rotation_1").meta.update(channels=[0, 3], shape=[3, 16, 24]),
     "key 'attributes.rotation.chunks': do not cover each channel exactly once"),
    (lambda s: s.chunk("positions_hi").meta.update(bits=9), "key 'chunks.positions_hi.bits': must be 8"),
    (lambda s: s.chunk("scale").meta.update(qp=99), "key 'chunks.scale.qp'"),
    (lambda s: s.chunk("scale").meta.update(attribute="opacity"), "key 'chunks.scale.attribute'"),
    (lambda s: s.chunks.remove(s.chunk("opacity")), "chunk 'opacity' is not in the chunk table"),
    (lambda s: s.add_chunk("extra", b"x"), "key 'chunks': chunk 'extra' belongs to no attribute"),
    (lambda s: s.chunks.remove(s.chunk("sh_state")), "chunk 'sh_state' is missing"),
    (lambda s: s.chunk("sh_state").meta.update(raw_size=10**9), "key 'chunks.sh_state.raw_size'"),
    (lambda s: s.chunk("sh_state").meta.update(raw_size=1032 * len(s.chunk("sh_state").data) + 1),
     "cannot come from"),
    (lambda s: s.chunk("sh_state").meta.update(encoding="lzma"), "key 'chunks.sh_state.encoding'"),
    (lambda s: s.chunk("grid_mask").meta.update(raw_size=7), "key 'chunks.grid_mask.raw_size'"),
    (lambda s: s.header.update(input_gaussians=5), "key 'input_gaussians'"),
    (lambda s: s.header.update(producer=7), "key 'producer'"),
]


@pytest.mark.parametrize("edit, message", CASES, ids=[str(i) for i in range(len(CASES))])
def test_each_rule_is_one_error_naming_the_key_for_decode_and_info(encoded, edit, message):
    data = _edit(encoded, edit)
    with pytest.raises(BitstreamError) as decoded:
        Decoder().decode(data)
    assert message in str(decoded.value) and str(decoded.value).startswith("corrupt .gsc file: ")
    with pytest.raises(BitstreamError) as described:
        describe_gsc(Bitstream.from_bytes(data), "x.gsc")
    assert str(described.value) == f"x.gsc: {decoded.value}"


def test_a_declared_trillion_gaussians_fails_fast(encoded):
    tic = time.perf_counter()
    with pytest.raises(BitstreamError, match="num_gaussians"):
        Decoder().decode(_edit(encoded, lambda s: s.header.update(num_gaussians=10**12)))
    assert time.perf_counter() - tic < 1.0


@pytest.mark.parametrize(
    "text, message",
    [
        (lambda t: t.replace('"num_gaussians":300', '"num_gaussians":NaN'), "NaN is not a number a header may hold"),
        (lambda t: t.replace('"color":', '"color":"rgb","color":'), "key 'color' appears twice"),
        (lambda t: t[:-1] + ',"deep":' + "[" * 20_000 + "]" * 20_000 + "}", "nests 20001 levels deep"),
        (lambda t: t[:-1] + ',"deep":"' + "[" * 20_000 + '"}', None),  # brackets inside a string are text
        (lambda t: t[:-1] + ',"big":' + "9" * 5000 + "}", "not valid JSON"),
        (lambda t: t[:-1] + ',"pad":"' + "x" * MAX_HEADER_BYTES + '"}', "exceeds"),
        (lambda t: "[" + t + "]", "not a JSON object"),
        (lambda t: t.encode("utf-16").decode("latin-1"), "not valid JSON"),
    ],
)
def test_header_json_limits(encoded, text, message):
    data = _raw_header(encoded, text(_header_text(encoded)).encode("utf-8", "surrogatepass"))
    if message is None:
        Decoder().decode(data)
        return
    for read in (Decoder().decode, lambda d: describe_gsc(Bitstream.from_bytes(d), "x")):
        with pytest.raises(BitstreamError, match=message):
            read(data)


def test_the_stage_state_is_checked_against_the_declared_shapes(cloud, encoded):
    other = Encoder("paper_table3:rp2", sh_stage="pca", sh_params={"n_components": 5},
                    codec_options={"preset": "ultrafast"}).encode(cloud.replace(sh_rest=cloud.sh_rest[:, :8]))
    swapped = Bitstream.from_bytes(encoded)
    swapped.chunks[[c.name for c in swapped.chunks].index("sh_state")] = other.chunk("sh_state")
    with pytest.raises(BitstreamError, match="chunk 'sh_state'"):
        Decoder().decode(swapped.to_bytes())


def test_the_memory_budget_is_checked_before_allocating(encoded, monkeypatch):
    monkeypatch.setenv("GSCODEC_MAX_MEMORY", "10K")
    with pytest.raises(MemoryLimitError, match=r"needs about .* more than the 10.0 KiB"):
        Decoder().decode(encoded)
    monkeypatch.setenv("GSCODEC_MAX_MEMORY", "4G")
    assert Decoder().decode(encoded).num_gaussians == 300
    monkeypatch.setenv("GSCODEC_MAX_MEMORY", "lots")
    with pytest.raises(GscodecError, match=r"\$GSCODEC_MAX_MEMORY: 'lots' is not a size such as 2.5MB, 800kB, 3MiB, 512M or 4G"):
        Decoder().decode(encoded)


def test_the_gsplat_drop_in_uses_the_same_validator(tmp_path, encoded):
    bad = _edit(encoded, lambda s: _set_codec_index(s, -1))
    (tmp_path / "splats.gsc").write_bytes(bad)
    with pytest.raises(BitstreamError, match="key 'chunks.scale.codec'"):
        ShacCompression().decompress(tmp_path)
    (tmp_path / "splats.gsc").write_bytes(encoded)
    assert ShacCompression().decompress(tmp_path)["means"].shape == (300, 3)


@pytest.mark.parametrize("path", sorted(FIXTURES.rglob("*.gsc")), ids=lambda p: p.stem)
def test_every_legacy_stream_is_accepted(path):
    for view in read_headers(Bitstream.read(path)):  # a tiered stream: each tier's
        assert view.num_gaussians > 0 and view.peak_memory() > view.decoded_bytes()


def _shipped_points() -> list[str]:
    root = Path(__file__).parents[1] / "rate_points"
    return [f"{file.stem}:{point}" for file in sorted(root.glob("*.yaml"))
            for point in yaml.safe_load(file.read_text())["points"]]


@pytest.mark.parametrize("point", _shipped_points())
def test_streams_of_every_shipped_rate_point_are_accepted(cloud, point):
    stream = Encoder(point, codec_options={"preset": "ultrafast"}).encode(cloud)
    parsed = Bitstream.from_bytes(stream.to_bytes())
    views = read_headers(parsed)
    assert parsed.header["rate_point"]["name"] == point
    shared = len(parsed.chunk("sh_state").data) if len(views) > 1 and parsed.has_chunk("sh_state") else 0
    counted = sum(sum(view.chunk_bytes.values()) for view in views) - (len(views) - 1) * shared  # tiers share it
    assert counted == sum(len(c.data) for c in stream.chunks)
    assert Decoder().decode(stream).num_gaussians == sum(view.num_gaussians for view in views)


def _numeric_paths(value, prefix=()):
    """Every path to a number (not a bool) inside a parsed JSON header."""
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    out = []
    for key, child in items:
        if isinstance(child, (int, float)) and not isinstance(child, bool):
            out.append(prefix + (key,))
        out.extend(_numeric_paths(child, prefix + (key,)))
    return out


@pytest.mark.parametrize("source", ["encoded", "v2.0"])
def test_a_400_digit_integer_in_every_numeric_header_field_is_one_clean_error(encoded, source):
    """JSON allows integers of any size; each numeric header field holding 10**400 (or -10**400)
    ends in a valid result or one BitstreamError for decode and info, never an OverflowError."""
    import json

    from tests.fuzzlib.gsc import _pack, _split

    data = encoded if source == "encoded" else next(iter(sorted((FIXTURES / "v2.0").glob("*.gsc")))).read_bytes()
    text, payloads, version = _split(data)
    header = json.loads(text)
    paths = _numeric_paths(header)
    assert len(paths) > 50
    for sign, path in zip([1, -1] * len(paths), paths):
        edited = json.loads(text)
        parent = edited
        for key in path[:-1]:
            parent = parent[key]
        parent[path[-1]] = sign * 10**400
        case = _pack(json.dumps(edited).encode(), payloads, resign_table=False, version=version)
        for target in (lambda b: Decoder(workers=1).decode(b), lambda b: describe_gsc(Bitstream.from_bytes(b), "x")):
            try:
                target(case)
            except BitstreamError as exc:
                assert len(str(exc)) < 400, str(exc)


def _zero_bomb(size: int) -> bytes:
    """zlib data inflating to ``size`` zero bytes, made in 1 MiB steps (never held whole)."""
    deflater, block = zlib.compressobj(9), bytes(1 << 20)
    parts = [deflater.compress(block) for _ in range(size >> 20)]
    return b"".join(parts) + deflater.flush()


@pytest.mark.parametrize("size, message", [(256 << 20, "key 'chunks.sh_state.raw_size'"),
                                           (16 << 20, "does not hold an SH stage state")])
def test_a_zlib_bomb_in_the_stage_state_is_refused_before_it_is_inflated(encoded, size, message):
    """A 256 MiB bomb exceeds the state limit of a 300-Gaussian stream (refused by the header
    check); a 16 MiB one within it is refused after inflating the state's first 8 bytes."""
    import tracemalloc

    def swap(stream):
        chunk = stream.chunk("sh_state")
        chunk.data, chunk.meta["raw_size"] = _zero_bomb(size), size

    bomb = _edit(encoded, swap)
    tracemalloc.start()
    try:
        with pytest.raises(BitstreamError, match=message):
            Decoder(workers=1).decode(bomb)
        describe_gsc(Bitstream.from_bytes(bomb), "x") if size < 256 << 20 else None  # info does not inflate it
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 * len(bomb) + (8 << 20)
