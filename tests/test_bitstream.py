"""The .gsc container: round trip, sizes, and one BitstreamError for every kind of damage."""

import threading
import zlib

import numpy as np
import pytest

from gscodec_shac.codec.container import MAGIC, PREAMBLE_SIZE, Bitstream, is_gsc
from gscodec_shac.errors import BitstreamError
from gscodec_shac.codec import Decoder, Encoder
from gscodec_shac.codec.rate_points import parse_rate_points

CASE_SECONDS = 20.0


def _quick_point(**changes):
    point = {"codec": "png", "bits": 10, "sh": {"stage": "pca", "n_components": 6}, "sort": {"method": "morton"}}
    point.update(changes)
    return parse_rate_points({"points": {"quick": point}}, "test")["quick"]


@pytest.fixture(scope="module")
def encoded(small_cloud):
    return Encoder(_quick_point()).encode(small_cloud).to_bytes()


def decode_bounded(data: bytes) -> BaseException | None:
    """Decode in a thread; fail the test if it does not finish in CASE_SECONDS. Returns the error."""
    outcome: list = []

    def work():
        try:
            Decoder().decode(data)
            outcome.append(None)
        except BaseException as exc:  # noqa: BLE001 - reported to the test
            outcome.append(exc)

    thread = threading.Thread(target=work, daemon=True)
    thread.start()
    thread.join(CASE_SECONDS)
    assert not thread.is_alive(), f"decoding a damaged file of {len(data)} bytes did not finish in {CASE_SECONDS} s"
    return outcome[0]


def test_round_trip_is_byte_identical_and_sizes_add_up(encoded):
    stream = Bitstream.from_bytes(encoded)
    assert stream.to_bytes() == encoded
    assert stream.version == (1, 0)
    assert sum(stream.sizes().values()) == len(encoded) == stream.total_bytes()
    assert sum(stream.attribute_sizes().values()) == len(encoded)
    assert stream.sizes()["sh_state"] > 0
    assert {"positions", "rotation", "scale", "opacity", "sh_dc", "sh", "sh_state"} <= set(stream.attribute_sizes())


def test_chunks_carry_crc_and_codec_metadata(encoded):
    stream = Bitstream.from_bytes(encoded)
    for chunk in stream.chunks:
        entry = chunk.table_entry()
        assert entry["crc32"] == zlib.crc32(chunk.data) and entry["size"] == len(chunk.data)
    codecs = stream.header["codecs"]
    assert codecs and all({"name", "version", "options"} <= set(c) for c in codecs)
    assert stream.header["producer"].startswith("gscodec-shac ")


@pytest.mark.parametrize("fraction", np.linspace(0.0, 0.999, 41))
def test_truncation_raises_one_bitstream_error(encoded, fraction):
    cut = int(len(encoded) * fraction)
    error = decode_bounded(encoded[:cut])
    assert isinstance(error, BitstreamError), repr(error)


def test_truncation_at_every_preamble_and_header_offset(encoded):
    for cut in list(range(0, PREAMBLE_SIZE + 1)) + [PREAMBLE_SIZE + 7, len(encoded) - 1]:
        assert isinstance(decode_bounded(encoded[:cut]), BitstreamError)


@pytest.mark.parametrize("seed", range(30))
def test_random_byte_flips_raise_one_bitstream_error(encoded, seed):
    rng = np.random.default_rng(seed)
    data = bytearray(encoded)
    for position in rng.integers(0, len(data), size=int(rng.integers(1, 4))):
        data[position] ^= int(rng.integers(1, 256))
    error = decode_bounded(bytes(data))
    assert isinstance(error, BitstreamError), repr(error)


def test_foreign_and_empty_files(tmp_path):
    for data in (b"", b"ply\nformat binary_little_endian 1.0\n", bytes(range(256)) * 4, MAGIC[:5]):
        assert isinstance(decode_bounded(data), BitstreamError)
    ply = tmp_path / "x.ply"
    ply.write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    assert not is_gsc(ply)
    with pytest.raises(BitstreamError, match="no such file"):
        Bitstream.read(tmp_path / "missing.gsc")


def test_trailing_bytes_and_unknown_version(encoded):
    with pytest.raises(BitstreamError, match="unexpected bytes"):
        Bitstream.from_bytes(encoded + b"\0")
    future = bytearray(encoded)
    future[8:10] = (2).to_bytes(2, "little")
    with pytest.raises(BitstreamError, match="deflated header does not inflate"):  # a 1.0 header relabelled 2.0
        Bitstream.from_bytes(bytes(future))


def _with_header(encoded: bytes, edit) -> bytes:
    """Re-serialise after editing the header: CRCs are valid, only the content is wrong."""
    stream = Bitstream.from_bytes(encoded)
    edit(stream)
    return stream.to_bytes()


@pytest.mark.parametrize(
    "edit",
    [
        lambda s: s.header.update(num_gaussians=2**40),
        lambda s: s.header.update(num_gaussians=0),
        lambda s: s.header["grid"].update(height=100_000, width=100_000),
        lambda s: s.header["grid"].update(padding="spiral"),
        lambda s: s.header.update(sh_degree=9),
        lambda s: s.header.pop("codecs"),
        lambda s: s.header["codecs"][0].update(name="nonexistent"),
        lambda s: s.header["attributes"].pop("scale"),
        lambda s: s.header["attributes"]["sh"].update(channels=500),
        lambda s: s.header["attributes"]["opacity"]["quantizer"].update(min=[0.0, 1.0]),
        lambda s: s.chunks[-1].meta.update(raw_size=1 << 40),
        lambda s: s.chunk("scale").meta.update(shape=[3, 4096, 4096]),
        lambda s: s.chunk("scale").meta.update(codec=99),
        lambda s: s.chunk("scale").meta.update(channels=[0, 2]),
        lambda s: s.chunks.remove(s.chunk("opacity")),
        lambda s: setattr(s.chunk("opacity"), "data", b"\x00" * 50),
        lambda s: setattr(s.chunk("sh_state"), "data", zlib.compress(b"SHST" + b"\xff" * 40)),
        lambda s: (setattr(s.chunk("sh_state"), "data", zlib.compress(b"SHST" + b"\xff" * 40)),
                   s.chunk("sh_state").meta.update(raw_size=44)),
    ],
)
def test_inconsistent_headers_with_valid_crcs_are_rejected(encoded, edit):
    error = decode_bounded(_with_header(encoded, edit))
    assert isinstance(error, BitstreamError), repr(error)


def test_write_is_atomic(tmp_path, encoded):
    stream = Bitstream.from_bytes(encoded)
    target = tmp_path / "out.gsc"
    assert stream.write(target) == len(encoded)
    assert target.read_bytes() == encoded and is_gsc(target)
    with pytest.raises(BitstreamError, match="does not exist"):
        stream.write(tmp_path / "missing" / "out.gsc")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.gsc"]


def test_streams_without_optional_features_stay_version_1(encoded):
    assert Bitstream.from_bytes(encoded).version == (1, 0) and encoded[8:12] == bytes([1, 0, 0, 0])


def test_a_stream_that_needs_a_feature_is_version_2_and_names_it(encoded, monkeypatch):
    from gscodec_shac.codec import container

    monkeypatch.setitem(container.FEATURES, "test_feature", "a feature only this test knows")
    stream = Bitstream.from_bytes(encoded)
    stream.require("test_feature")
    data = stream.to_bytes()
    again = Bitstream.from_bytes(data)
    assert again.version == (2, 0) and again.features == {"test_feature"} and "features" not in again.header
    monkeypatch.delitem(container.FEATURES, "test_feature")
    with pytest.raises(BitstreamError, match="needs test_feature, which this version of gscodec-shac does not"):
        Bitstream.from_bytes(data)
    with pytest.raises(ValueError, match="unknown stream feature"):
        stream.require("no_such_feature")
    future = bytearray(encoded)
    future[8:10] = (3).to_bytes(2, "little")
    with pytest.raises(BitstreamError, match="version 3.0; this decoder reads 1.x to 2.x"):
        Bitstream.from_bytes(bytes(future))
