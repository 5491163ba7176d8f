"""Hostile model files: each one is a single clean error naming the file, member and field,
found before anything large is allocated, and no input file is ever written over.

The fixtures are our writers' files edited the way an attacker would (``tests/fuzzlib``
builds the zips, bombs and image headers); the long run of all of it is ``scripts/fuzz.py``.
"""

from __future__ import annotations

import gzip
import json
import struct
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from gscodec_shac.errors import GscodecError, MemoryLimitError, ModelFormatError
from gscodec_shac.io.bounded import BoundedZip, Inflater, decode_rgba, image_size, load_json, read_npz
from gscodec_shac.io.gsplat_ckpt import read_gsplat_checkpoint
from gscodec_shac.io.models import read_model
from gscodec_shac.io.sog import read_sog
from gscodec_shac.io.spz import read_spz
from tests.fuzzlib import models
from tests.fuzzlib import zipfile_raw as rawzip

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.filterwarnings("ignore::gscodec_shac.io.model_common.FormatNote")


@pytest.fixture(scope="module")
def seeds() -> dict[str, models.Seed]:
    return models.make_seeds()


def _write(root: Path, seed: models.Seed, files=None, links=None) -> Path:
    return models.write_case(root, seed, files if files is not None else dict(seed.files), links or {})


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gscodec_shac", *args], cwd=cwd, capture_output=True, text=True,
                          env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "1"})


# ------------------------------------------------------------------ JSON
@pytest.mark.parametrize("text, message", [
    (b"[" * 100_000 + b"]" * 100_000, "nests 100000 levels"),
    (b'{"count": ' + b"9" * 400 + b"}", "integer 999999999999...999999 (400 characters) is beyond 2^63"),
    (b'{"count": 9223372036854775808}', "beyond 2^63"),
    (b'{"mins": [1e999]}', "the number 1e999 is beyond float64"),
    (b'{"a": NaN}', "NaN is not a number"),
    (b" " * (2 << 20), "more than 1.0 MiB"),
])
def test_json_documents_are_bounded_and_numbers_refused_by_name(text, message):
    with pytest.raises(ModelFormatError, match=message.replace("(", r"\(").replace(")", r"\)").replace("^", r"\^")):
        load_json(text, "scene/meta.json")
    assert load_json(b'{"count": 9223372036854775807, "x": 1.5e308}', "ok") == {"count": 2**63 - 1, "x": 1.5e308}


# ------------------------------------------------------------------ zip / npz
def _zip(tmp_path: Path, members: list[rawzip.Member], name: str = "x.zip") -> Path:
    path = tmp_path / name
    path.write_bytes(rawzip.build(members))
    return path


@pytest.mark.parametrize("member, message", [
    (rawzip.Member("../x", b"hi"), "member '../x': a member name must be a relative path"),
    (rawzip.Member("/etc/passwd", b"hi"), "must be a relative path"),
    (rawzip.Member("a.bin", b"hi", method=14), "compression method 14 is not supported"),
    (rawzip.Member("a.bin", b"hi", crc=12345), "member 'a.bin': corrupt"),
    (rawzip.Member("a.bin", b"hi", flags=1), "is encrypted"),
    (rawzip.Member("a.bin", b"hi", size=2**31), "which no zip writer makes"),
])
def test_zip_directories_are_checked_before_a_member_is_read(tmp_path, member, message):
    path = _zip(tmp_path, [member])
    with pytest.raises(ModelFormatError, match=message):
        with BoundedZip(path) as bundle:
            bundle.read(member.name, 1 << 20)


def test_a_deflate_bomb_member_is_refused_by_its_declared_size_and_never_inflated(tmp_path):
    bomb = rawzip.Member("meta.json", models._deflate_bomb(256 << 20), method=8, size=256 << 20, crc=0, raw=b"")
    path = _zip(tmp_path, [bomb])
    tracemalloc.start()
    try:
        with pytest.raises(ModelFormatError, match="declares 256.0 MiB, more than the 1.0 MiB"):
            with BoundedZip(path) as bundle:
                bundle.read("meta.json", 1 << 20, "SOG meta.json")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 << 20
    lie = rawzip.replace(rawzip.deflated("a.bin", bytes(1 << 20)), size=1000)  # inflates past its declared size
    with pytest.raises(ModelFormatError, match="member 'a.bin'"):
        with BoundedZip(_zip(tmp_path, [lie], "lie.zip")) as bundle:
            bundle.read("a.bin", 1 << 20)


def test_npz_shapes_and_dtypes_are_checked_before_allocating(tmp_path):
    def npy(header: str, body: bytes = b"") -> bytes:
        text = header.encode() + b" " * (-(len(header) + 11) % 64) + b"\n"
        return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text + body

    huge = npy("{'descr': '<f4', 'fortran_order': False, 'shape': (1099511627776,), }", bytes(16))
    with pytest.raises(ModelFormatError, match=r"member 'w.npy': shape \(1099511627776,\) of float32 needs "
                                               r"4,398,046,511,104 bytes, the member holds 16"):
        read_npz(_zip(tmp_path, [rawzip.Member("w.npy", huge)], "huge.npz"))
    pickled = npy("{'descr': '|O', 'fortran_order': False, 'shape': (1,), }", bytes(8))
    with pytest.raises(ModelFormatError, match="dtype object is not allowed"):
        read_npz(_zip(tmp_path, [rawzip.Member("w.npy", pickled)], "obj.npz"))
    good = npy("{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }", np.arange(6, dtype="<f4").tobytes())
    arrays = read_npz(_zip(tmp_path, [rawzip.deflated("w.npy", good)], "good.npz"))
    assert np.array_equal(arrays["w"], np.arange(6, dtype=np.float32).reshape(2, 3))


# ------------------------------------------------------------------ images and SOG
def test_image_headers_are_read_before_decoding(tmp_path):
    assert image_size(models._webp_header(16383, 16383)) == (16383, 16383)
    assert image_size(models._big_png(16000, 16000, zeros=False)) == (16000, 16000)
    with pytest.raises(ModelFormatError, match="x.webp: a 16383x16383 image, more than the 1,000 pixels"):
        decode_rgba(models._webp_header(16383, 16383), "x.webp", 1000)
    with pytest.raises(ModelFormatError, match="x.webp: the image is empty"):
        decode_rgba(b"", "x.webp", 1000)


@pytest.mark.parametrize("image, message", [
    (b"", "the image is empty"),
    (models._webp_header(16383, 16383), "a 16383x16383 image, more than the"),
    (models._big_png(4096, 2048, zeros=True), "a 4096x2048 image, more than the"),
])
def test_sog_images_are_measured_before_decoding(tmp_path, seeds, image, message):
    seed = seeds["sogdir"]
    files = dict(seed.files)
    files["scene/quats.webp"] = image
    with pytest.raises(ModelFormatError, match=f"quats.webp: {message}"):
        read_sog(_write(tmp_path, seed, files))


def test_sog_meta_values_of_the_wrong_type_are_clean_errors(tmp_path, seeds):
    seed = seeds["sogdir"]
    meta = json.loads(seed.files["scene/meta.json"])
    meta["shN"]["bands"] = [1, 2]
    files = dict(seed.files, **{"scene/meta.json": json.dumps(meta).encode()})
    with pytest.raises(ModelFormatError, match="key 'shN.bands' must be 1, 2 or 3, got \\[1, 2\\]"):
        read_sog(_write(tmp_path, seed, files))


def test_a_sog_member_named_dot_dot_is_never_read_or_written_outside(tmp_path, seeds):
    members = rawzip.members_of(seeds["sog"].files["scene.sog"])
    members = [rawzip.replace(m, name="../quats.webp") if m.name == "quats.webp" else m for m in members]
    (tmp_path / "in").mkdir()
    path = tmp_path / "in" / "scene.sog"
    path.write_bytes(rawzip.build(members))
    before = sorted(p.name for p in tmp_path.rglob("*"))
    with pytest.raises(ModelFormatError, match="member '../quats.webp': a member name must be a relative path"):
        read_model(path)
    assert sorted(p.name for p in tmp_path.rglob("*")) == before
    meta = json.loads(seeds["sogdir"].files["scene/meta.json"])
    meta["quats"]["files"] = ["../quats.webp"]
    files = dict(seeds["sogdir"].files, **{"scene/meta.json": json.dumps(meta).encode()})
    (tmp_path / "quats.webp").write_bytes(seeds["sogdir"].files["scene/quats.webp"])
    with pytest.raises(ModelFormatError, match="must name files beside meta.json"):
        read_sog(_write(tmp_path / "d", seeds["sogdir"], files))


@pytest.mark.parametrize("target", ["/proc/self/mem", "/etc/hostname", "../outside.webp"])
def test_symlinks_leaving_an_input_folder_are_refused(tmp_path, seeds, target):
    seed = seeds["sogdir"]
    files = dict(seed.files)
    files.pop("scene/quats.webp")
    (tmp_path / "outside.webp").write_bytes(seed.files["scene/quats.webp"])
    path = _write(tmp_path, seed, files, {"scene/quats.webp": target})
    with pytest.raises(ModelFormatError, match="quats.webp is a symlink that leaves"):
        read_model(path)
    dynamic = seeds["dynamic"]
    files = dict(dynamic.files)
    files.pop("model/deformation.npz")
    (tmp_path / "w.npz").write_bytes(dynamic.files["model/deformation.npz"])
    path = _write(tmp_path, dynamic, files, {"model/deformation.npz": str(tmp_path / "w.npz")})
    from gscodec_shac.deform import load_dynamic_model

    with pytest.raises(ModelFormatError, match="deformation.npz is a symlink that leaves"):
        load_dynamic_model(path)


# ------------------------------------------------------------------ SPZ, compressed.ply
def test_spz_inflation_stops_at_the_bytes_the_header_needs(tmp_path, seeds):
    body = gzip.decompress(seeds["spz3"].files["scene.spz"])
    trailing = tmp_path / "trailing.spz"
    trailing.write_bytes(models._gzip_bomb(len(body) + (64 << 20), body))
    tracemalloc.start()
    try:
        with pytest.raises(ModelFormatError, match="goes on past the end its header implies"):
            read_spz(trailing)
        header = bytearray(body[:16])
        struct.pack_into("<I", header, 8, 2**26)
        (tmp_path / "bomb.spz").write_bytes(models._gzip_bomb(64 << 20, bytes(header)))
        with pytest.raises(ModelFormatError, match="more than .* gzip bytes can hold"):
            read_spz(tmp_path / "bomb.spz")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 << 20


def test_the_memory_budget_is_checked_before_a_model_is_read(tmp_path, seeds, monkeypatch):
    monkeypatch.setenv("GSCODEC_MAX_MEMORY", "10K")
    for fmt in ("spz3", "sog", "splat", "cply"):
        with pytest.raises(MemoryLimitError, match="more than the 10.0 KiB"):
            read_model(_write(tmp_path / fmt, seeds[fmt]))


def test_compressed_ply_header_is_limited_to_64_kib(tmp_path, seeds):
    data = seeds["cply"].files["scene.compressed.ply"]
    big = data.replace(b"\nend_header", b"\ncomment " + b"x" * (1 << 20) + b"\nend_header", 1)
    (tmp_path / "big.compressed.ply").write_bytes(big)
    with pytest.raises(ModelFormatError, match="no 'end_header' in the first 65,536 bytes"):
        read_model(tmp_path / "big.compressed.ply")
    short = data.replace(b"element vertex 64", b"element vertex 6400", 1)
    (tmp_path / "short.compressed.ply").write_bytes(short)
    with pytest.raises(ModelFormatError, match="need .* bytes of data, the file holds"):
        read_model(tmp_path / "short.compressed.ply")


# ------------------------------------------------------------------ gsplat pickles
def test_a_pickle_payload_in_a_checkpoint_never_runs(tmp_path, seeds):
    marker = tmp_path / "ran"
    members = rawzip.members_of(seeds["pt"].files["ckpt.pt"])
    code = ("import pickle, sys\nclass Evil:\n    def __reduce__(self):\n        return (open, (sys.argv[1], 'w'))\n"
            "sys.stdout.buffer.write(pickle.dumps({'splats': {'means': Evil()}}, protocol=2))\n")
    payload = subprocess.run([sys.executable, "-c", code, str(marker)], capture_output=True, check=True).stdout
    members = [rawzip.Member(m.name, payload) if m.name.endswith("data.pkl") else m for m in members]
    path = tmp_path / "evil.pt"
    path.write_bytes(rawzip.build(members))
    with pytest.raises(ModelFormatError) as caught:
        read_gsplat_checkpoint(path)
    message = str(caught.value)
    assert "holds Python objects other than tensors" in message and "weights_only" not in message
    assert not marker.exists()
    result = _cli("info", str(path), cwd=tmp_path)
    assert result.returncode == 2 and result.stderr.count("error:") == 1 and "weights_only" not in result.stderr
    assert not marker.exists()


# ------------------------------------------------------------------ inputs and outputs (CLI)
def test_every_file_of_a_multi_file_input_is_protected(tmp_path, seeds):
    sog = _write(tmp_path, seeds["sogdir"])
    dyn = _write(tmp_path, seeds["dynamic"])
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    for args in (["encode", "scene", "scene/quats.webp", "--force"],
                 ["encode", "scene/meta.json", "scene/sh0.webp", "--force"],
                 ["encode", "model", "model/deformation.npz", "--force"]):
        result = _cli(*args, cwd=tmp_path)
        assert result.returncode == 2 and "refusing to write over an input" in result.stderr, result.stderr
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
    assert sog.is_dir() and dyn.is_dir()


def test_a_dangling_symlink_output_is_kept_without_force(tmp_path, seeds):
    _write(tmp_path, seeds["spz3"])
    (tmp_path / "dangling.gsc").symlink_to(tmp_path / "nowhere.gsc")
    result = _cli("encode", "scene.spz", "dangling.gsc", cwd=tmp_path)
    assert result.returncode == 2 and "exists; pass --force" in result.stderr
    assert (tmp_path / "dangling.gsc").is_symlink() and not (tmp_path / "nowhere.gsc").exists()
    result = _cli("encode", "scene.spz", "dangling.gsc", "--force", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert not (tmp_path / "dangling.gsc").is_symlink() and not (tmp_path / "nowhere.gsc").exists()


def test_decode_writes_an_unbundled_sog(tmp_path, seeds):
    _write(tmp_path, seeds["spz3"])
    assert _cli("encode", "scene.spz", "s.gsc", cwd=tmp_path).returncode == 0
    (tmp_path / "out").mkdir()
    result = _cli("decode", "s.gsc", "out/meta.json", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    cloud, _ = read_model(tmp_path / "out")
    assert cloud.num_gaussians == models.SEED_GAUSSIANS
    (tmp_path / "again").mkdir()
    (tmp_path / "again" / "quats.webp").write_bytes(b"keep")
    result = _cli("decode", "s.gsc", "again/meta.json", cwd=tmp_path)
    assert result.returncode == 2 and "again/quats.webp: the output exists" in result.stderr
    assert (tmp_path / "again" / "quats.webp").read_bytes() == b"keep"


def test_inflater_refuses_the_first_byte_past_the_end():
    import zlib

    inflater = Inflater(zlib.compress(b"abcdef"), "x")
    assert inflater.read(3) == b"abc"
    with pytest.raises(ModelFormatError, match="x: the data goes on past the end"):
        inflater.finish()
    with pytest.raises(ModelFormatError, match="x: truncated"):
        Inflater(zlib.compress(b"abc"), "x").read(4)
    assert isinstance(ModelFormatError("x"), GscodecError)
