"""Bad PLY input: each case is read correctly or refused with one clear PlyFormatError."""

from __future__ import annotations

import io
import time
import warnings
from pathlib import Path

import numpy as np
import plyfile
import pytest

from gscodec_shac.errors import PlyFormatError
from gscodec_shac.io.ply import OPACITY_LOGIT_LIMIT, read_ply, write_ply
from gscodec_shac.synthetic import make_synthetic_scene


@pytest.fixture(scope="module")
def cloud():
    return make_synthetic_scene(60, seed=5, n_cameras=1, width=16, height=12).cloud


@pytest.fixture()
def good(tmp_path, cloud) -> Path:
    path = tmp_path / "good.ply"
    write_ply(path, cloud)
    return path


def _table(path: Path) -> np.ndarray:
    return plyfile.PlyData.read(str(path))["vertex"].data.copy()


def _write(path: Path, table: np.ndarray, **options) -> Path:
    plyfile.PlyData([plyfile.PlyElement.describe(table, "vertex")], **options).write(str(path))
    return path


def _split(path: Path) -> tuple[bytes, bytes]:
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    return data[:end], data[end:]


def test_nan_and_inf_say_how_many_and_where(good, tmp_path):
    table = _table(good)
    table["x"][3] = np.nan
    table["f_rest_7"][[4, 9]] = np.inf
    table["opacity"][5] = -np.inf
    with pytest.raises(PlyFormatError) as error:
        read_ply(_write(tmp_path / "nan.ply", table))
    message = str(error.value)
    assert "4 non-finite value(s)" in message and "in 4 vertices" in message
    assert "x: 1 (vertex 3)" in message and "f_rest_7: 2 (vertex 4, 9)" in message and "opacity: 1 (vertex 5)" in message


def test_infinite_opacity_offers_and_applies_the_clamp(good, tmp_path):
    table = _table(good)
    table["opacity"][[2, 6]] = [np.inf, -np.inf]
    path = _write(tmp_path / "inf.ply", table)
    with pytest.raises(PlyFormatError, match=r"clamped to \+-20 as the RD harness does: read_ply\(path, clamp_opacity=True\)"):
        read_ply(path)
    clamped = read_ply(path, clamp_opacity=True)
    assert clamped.opacities[2] == OPACITY_LOGIT_LIMIT and clamped.opacities[6] == -OPACITY_LOGIT_LIMIT
    np.testing.assert_array_equal(np.delete(clamped.opacities, [2, 6]), np.delete(read_ply(good).opacities, [2, 6]))
    table["opacity"][3] = np.nan  # NaN is not an 8-bit alpha: no clamp offered
    with pytest.raises(PlyFormatError, match="fix or remove those Gaussians"):
        read_ply(_write(tmp_path / "nan.ply", table), clamp_opacity=True)


@pytest.mark.parametrize("split", [False, True])
def test_values_beyond_float32_are_refused(good, tmp_path, monkeypatch, split):
    """Also when the rows are read in two threads (numpy's error state is per thread: no warning leaks)."""
    from gscodec_shac.io import ply

    monkeypatch.setattr(ply, "SPLIT_READ_ROWS", 2 if split else 1 << 62)
    table = _table(good)
    wide = np.empty(table.shape, dtype=[(n, "<f8") for n in table.dtype.names])
    for name in table.dtype.names:
        wide[name] = table[name]
    np.testing.assert_array_equal(read_ply(_write(tmp_path / "double.ply", wide)).means, read_ply(good).means)
    wide["scale_0"][1] = 1e300
    wide["scale_1"][-1] = -1e300  # in the second half of the rows
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an overflow warning from either thread would fail here
        with pytest.raises(PlyFormatError, match=r"beyond float32 range.*scale_0: 1 \(vertex 1\)"):
            read_ply(_write(tmp_path / "huge.ply", wide))


def test_missing_and_extra_properties(good, tmp_path):
    table = _table(good)
    from numpy.lib.recfunctions import repack_fields

    names = [n for n in table.dtype.names if n not in ("rot_2", "scale_1")]
    with pytest.raises(PlyFormatError, match="missing properties: scale_1, rot_2"):
        read_ply(_write(tmp_path / "missing.ply", repack_fields(table[names])))
    extra = np.empty(table.shape, dtype=table.dtype.descr + [("confidence", "<f4"), ("label", "<i4")])
    for name in table.dtype.names:
        extra[name] = table[name]
    extra["confidence"], extra["label"] = 0.5, np.arange(len(table))
    back = read_ply(_write(tmp_path / "extra.ply", extra))
    assert back.extra["label"].tolist() == list(range(len(table))) and back.extra["confidence"][0] == 0.5
    np.testing.assert_array_equal(back.sh_rest, read_ply(good).sh_rest)


@pytest.mark.parametrize("kind", ["u1", "<i4", "<u2"])
def test_integer_types_for_gaussian_properties_are_refused(good, tmp_path, kind):
    table = _table(good)
    typed = np.empty(table.shape, dtype=[(n, kind if n == "opacity" else "<f4") for n in table.dtype.names])
    for name in table.dtype.names:
        typed[name] = table[name] if name != "opacity" else 1
    with pytest.raises(PlyFormatError, match="property 'opacity' is .*; an Inria 3DGS PLY stores it as float"):
        read_ply(_write(tmp_path / "int.ply", typed))


def test_list_properties_are_refused(good, tmp_path):
    table = _table(good)
    vertex = plyfile.PlyElement.describe(table, "vertex")
    faces = plyfile.PlyElement.describe(np.array([([0, 1, 2],)], dtype=[("vertex_indices", "O")]), "face")
    plyfile.PlyData([vertex, faces]).write(str(tmp_path / "faces.ply"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the 'face' element is reported as ignored
        assert read_ply(tmp_path / "faces.ply").num_gaussians == len(table)


def test_big_endian_and_ascii_are_read_exactly(good, tmp_path, cloud):
    table = _table(good)
    for name, options in (("big.ply", {"byte_order": ">"}), ("ascii.ply", {"text": True})):
        back = read_ply(_write(tmp_path / name, table, **options))
        assert back.equals(read_ply(good)), name
        write_ply(tmp_path / f"again_{name}", back)  # extra properties come back in native order
        assert (tmp_path / f"again_{name}").read_bytes() == good.read_bytes()


def test_a_vertex_count_that_disagrees_with_the_data(good, tmp_path):
    header, body = _split(good)
    count = len(_table(good))
    for claimed, pattern in ((count + 1, "need .* bytes of data, the file holds"),
                             (count - 1, "bytes after the last element"), (10**15, "need .* bytes of data")):
        path = tmp_path / f"n{claimed}.ply"
        path.write_bytes(header.replace(f"element vertex {count}".encode(), f"element vertex {claimed}".encode()) + body)
        tic = time.perf_counter()
        with pytest.raises(PlyFormatError, match=pattern):
            read_ply(path)
        assert time.perf_counter() - tic < 1.0
    (tmp_path / "trailing.ply").write_bytes(header + body + b"junk")
    with pytest.raises(PlyFormatError, match="4 bytes after the last element"):
        read_ply(tmp_path / "trailing.ply")
    text = _write(tmp_path / "a.ply", _table(good), text=True).read_bytes()
    for name, data, pattern in (("more.ply", text + b"1 2 3\n", "holds 61 data lines, .* say 60"),
                                ("fewer.ply", text.replace(b"element vertex 60", b"element vertex 61"), "say 61")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(PlyFormatError, match=pattern):
            read_ply(tmp_path / name)


def test_zero_gaussians(good, tmp_path):
    header, _ = _split(good)
    (tmp_path / "zero.ply").write_bytes(header.replace(b"element vertex 60", b"element vertex 0"))
    with pytest.raises(PlyFormatError, match="zero vertices"):
        read_ply(tmp_path / "zero.ply")


@pytest.mark.parametrize(
    "data, pattern",
    [
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n", "no 'end_header'"),
        (b"ply\nformat binary_middle_endian 1.0\nend_header\n", "unsupported format"),
        (b"ply\nformat ascii 1.0\nelement vertex -4\nend_header\n", "non-negative count"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty floaty x\nend_header\n0\n", "bad property line"),
        (b"ply\nformat ascii 1.0\nproperty float x\nend_header\n", "a property before any element"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n", "missing properties"),
        (b"ply\n" + b"comment " + b"x" * 70_000 + b"\n", "no 'end_header' in the first"),
        (b"solid cube\n", "not a PLY file"),
    ],
)
def test_malformed_headers(tmp_path, data, pattern):
    (tmp_path / "bad.ply").write_bytes(data)
    with pytest.raises(PlyFormatError, match=pattern):
        read_ply(tmp_path / "bad.ply")


def _playcanvas_compressed(n: int = 300) -> bytes:
    """A PlayCanvas/SuperSplat compressed.ply: quantised chunks, packed vertices, uchar SH."""
    chunks = np.zeros((n + 255) // 256, dtype=[(f"{a}_{b}", "<f4") for a in ("min", "max") for b in "xyz"]
                      + [(f"{a}_scale_{b}", "<f4") for a in ("min", "max") for b in "xyz"])
    vertex = np.zeros(n, dtype=[("packed_position", "<u4"), ("packed_rotation", "<u4"), ("packed_scale", "<u4"),
                                ("packed_color", "<u4")])
    sh = np.zeros(n, dtype=[(f"f_rest_{i}", "u1") for i in range(45)])
    buffer = io.BytesIO()
    plyfile.PlyData([plyfile.PlyElement.describe(chunks, "chunk"), plyfile.PlyElement.describe(vertex, "vertex"),
                     plyfile.PlyElement.describe(sh, "sh")], comments=["Generated by SuperSplat"]).write(buffer)
    return buffer.getvalue()


def test_a_playcanvas_compressed_ply_is_named_without_a_warning(tmp_path):
    path = tmp_path / "scene.compressed.ply"
    path.write_bytes(_playcanvas_compressed())
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no raw UserWarning first
        with pytest.raises(PlyFormatError, match="a PlayCanvas/SuperSplat compressed PLY .* not an Inria 3DGS PLY; "
                           "decompress it first"):
            read_ply(path)


def test_a_directory_and_a_missing_file(tmp_path):
    with pytest.raises(PlyFormatError, match="is a directory, not a PLY file"):
        read_ply(tmp_path)
    with pytest.raises(PlyFormatError, match="no such file"):
        read_ply(tmp_path / "none.ply")
