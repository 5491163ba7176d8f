"""Gaussian model formats: SPZ, .splat, SOG, compressed.ply, gsplat checkpoints and read_model/write_model.

Every fixture is made here: written by our writers or built byte by byte from the
format's layout, so a reader is checked against the spec, not only against our writer.
"""

from __future__ import annotations

import gzip
import io
import json
import struct
import warnings
import zipfile

import numpy as np
import plyfile
import pytest
import torch

from gscodec_shac import sh
from gscodec_shac.errors import ModelFormatError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.geometry import quat_to_rotmat
from gscodec_shac.io.compressed_ply import read_compressed_ply
from gscodec_shac.io.gsplat_ckpt import read_gsplat_checkpoint, write_gsplat_checkpoint
from gscodec_shac.io.model_common import OPACITY_LOGIT_LIMIT, FormatNote, flip_axes, sh_axis_signs
from gscodec_shac.io.models import detect_format, model_bytes, read_model, write_model
from gscodec_shac.io.ply import write_ply
from gscodec_shac.io.sog import read_sog, write_sog
from gscodec_shac.io.splat import read_splat, write_splat
from gscodec_shac.io.spz import read_spz, write_spz

SH_C0 = 0.28209479177387814
# readers called directly warn their notes (read_model returns them); expected here
pytestmark = pytest.mark.filterwarnings("ignore::gscodec_shac.io.model_common.FormatNote")


def _cloud(n: int = 600, degree: int = 3, seed: int = 0) -> GaussianCloud:
    """A cloud inside every format's range (SH in [-1, 1), opacities not saturating 8 bits)."""
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return GaussianCloud(
        means=rng.uniform(-3, 3, (n, 3)), scales=rng.uniform(-6, 0, (n, 3)), quats=rng.normal(size=(n, 4)),
        opacities=rng.uniform(-4, 4, n), sh_dc=rng.uniform(-1.5, 1.5, (n, 3)), sh_rest=rng.uniform(-0.9, 0.9, (n, k, 3)),
    )


def _same_rotation(a: np.ndarray, b: np.ndarray) -> float:
    """Largest component difference of unit quaternions up to sign."""
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return float(np.minimum(np.abs(a - b).max(axis=1), np.abs(a + b).max(axis=1)).max())


def _alpha(logits: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-logits.astype(np.float64)))


def _notes(call):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", FormatNote)
        result = call()
    return result, [str(w.message) for w in caught if issubclass(w.category, FormatNote)]


# ---------------------------------------------------------------- axis flips
def test_flip_axes_keeps_the_rendered_scene():
    cloud = _cloud(50, degree=4)
    flipped = flip_axes(cloud, (1.0, -1.0, -1.0))
    f = np.diag([1.0, -1.0, -1.0])
    assert np.allclose(flipped.means, cloud.means @ f)
    rot, rot_flipped = quat_to_rotmat(cloud.normalized_quats()), quat_to_rotmat(flipped.normalized_quats())
    assert np.allclose(rot_flipped, f @ rot @ f, atol=1e-6)
    directions = np.random.default_rng(1).normal(size=(50, 3))
    before = sh.eval_sh(cloud.sh_coefficients(), directions, clamp=False)
    after = sh.eval_sh(flipped.sh_coefficients(), directions @ f, clamp=False)
    assert np.allclose(before, after, atol=1e-5)
    assert flip_axes(flipped, (1.0, -1.0, -1.0)).equals(cloud)
    assert set(np.unique(sh_axis_signs((1, -1, -1), 4))) == {-1.0, 1.0}


# ---------------------------------------------------------------------- SPZ
@pytest.mark.parametrize("version", [2, 3])
def test_spz_round_trip_within_its_precision(tmp_path, version):
    cloud = _cloud()
    write_spz(tmp_path / "a.spz", cloud, version=version, sh1_bits=8, sh_rest_bits=8)
    back = read_spz(tmp_path / "a.spz")
    assert back.num_gaussians == cloud.num_gaussians and back.sh_degree == 3
    assert np.abs(back.means - cloud.means).max() <= 2.0**-13 + 1e-6
    assert np.abs(back.scales - cloud.scales).max() <= 1 / 32 + 1e-6
    assert np.abs(_alpha(back.opacities) - _alpha(cloud.opacities)).max() <= 0.5 / 255 + 1e-6
    assert np.abs(back.sh_dc - cloud.sh_dc).max() <= 0.5 / 255 / 0.15 + 1e-5
    assert np.abs(back.sh_rest - cloud.sh_rest).max() <= 0.5 / 128 + 1e-6
    # version 2 stores x, y, z on 8 bits and rebuilds w = sqrt(1 - |xyz|^2), coarse where w is small
    assert _same_rotation(back.quats, cloud.quats) < (0.003 if version == 3 else 0.1)


def test_spz_default_sh_bits_coarsen_as_niantic(tmp_path):
    cloud = _cloud(200)
    write_spz(tmp_path / "a.spz", cloud)
    raw = gzip.decompress((tmp_path / "a.spz").read_bytes())
    n, k = 200, 15
    sh_bytes = np.frombuffer(raw[-n * k * 3:], dtype=np.uint8).reshape(n, k, 3)
    assert np.all(sh_bytes[:, :3] % 8 == 0) and np.all(sh_bytes[:, 3:] % 16 == 0)
    assert np.abs(read_spz(tmp_path / "a.spz").sh_rest - cloud.sh_rest).max() <= 8.5 / 128 + 1e-6  # half a bucket + rounding


def test_spz_reads_bytes_built_from_the_layout(tmp_path):
    """Two Gaussians of SH degree 1, version 2 and 3 rotations, packed by hand (RUB on disk)."""
    fixed = np.array([[4096, -2048, 1], [-8192, 0, 40960]], dtype=np.int64)  # x 2**12
    positions = np.stack([fixed & 255, (fixed >> 8) & 255, (fixed >> 16) & 255], axis=-1).astype(np.uint8)
    alphas = np.array([255, 64], np.uint8)
    colors = np.array([[128, 0, 255], [200, 100, 50]], np.uint8)
    scales = np.array([[160, 0, 255], [80, 96, 112]], np.uint8)
    sh_bytes = np.full((2, 3, 3), 128, np.uint8)
    sh_bytes[0, 0] = (192, 64, 128)  # l=1 m=-1 (RGB): +0.5, -0.5, 0
    # version 3: identity (w largest, index 3 in xyzw) and 90 degrees about x (x and w equal)
    identity = np.uint32(3 << 30)
    magnitude = 511  # 1/sqrt(2) in 9 bits
    about_x = np.uint32((0 << 30) | (0 << 20) | (0 << 10) | magnitude)  # largest x; y, z zero, w = 1/sqrt2
    for version, rotations, expected_quats in (
        (3, np.array([identity, about_x], "<u4"), [[1, 0, 0, 0], [0.7071, 0.7071, 0, 0]]),
        (2, np.array([[128, 128, 128], [218, 128, 128]], np.uint8), None),
    ):
        header = struct.pack("<IIIBBBB", 0x5053474E, version, 2, 1, 12, 0, 0)
        body = b"".join(a.tobytes() for a in (positions, alphas, colors, scales, rotations, sh_bytes))
        (tmp_path / "h.spz").write_bytes(gzip.compress(header + body))
        raw = read_spz(tmp_path / "h.spz", coordinates="raw")
        assert np.allclose(raw.means, [[1, -0.5, 2**-12], [-2, 0, 10]])
        assert np.allclose(raw.scales, [[0, -10, 255 / 16 - 10], [-5, -4, -3]])
        assert np.allclose(raw.sh_dc[1], (np.array([200, 100, 50]) / 255 - 0.5) / 0.15, atol=1e-6)
        assert raw.opacities[0] == OPACITY_LOGIT_LIMIT and np.isclose(_alpha(raw.opacities[1:]), 64 / 255).all()
        assert np.allclose(raw.sh_rest[0, 0], (0.5, -0.5, 0.0)) and np.allclose(raw.sh_rest[1], 0.0)
        if expected_quats is not None:
            assert np.allclose(raw.quats, expected_quats, atol=2e-3)
        else:
            assert np.allclose(raw.quats[0], (1, 0, 0, 0), atol=1e-2) and raw.quats[1, 1] > 0.7
        rdf = read_spz(tmp_path / "h.spz")  # the default: RUB on disk -> RDF
        assert np.allclose(rdf.means, raw.means * (1, -1, -1))
        assert np.allclose(rdf.sh_rest[0, 0], -raw.sh_rest[0, 0])  # y-odd coefficient flips


def test_spz_version_1_float16_positions(tmp_path):
    positions = np.array([[0.5, -1.25, 3.0]], dtype="<f2")
    header = struct.pack("<IIIBBBB", 0x5053474E, 1, 1, 0, 0, 0, 0)
    body = positions.tobytes() + bytes([128]) + bytes([128] * 3) + bytes([160] * 3) + bytes([128] * 3)
    (tmp_path / "v1.spz").write_bytes(gzip.compress(header + body))
    assert np.allclose(read_spz(tmp_path / "v1.spz", coordinates="raw").means, [[0.5, -1.25, 3.0]])


def test_spz_clamps_infinite_logits_with_a_counted_note(tmp_path):
    cloud = _cloud(40).replace(opacities=np.r_[np.full(3, 30.0), np.full(2, -30.0), np.zeros(35)])
    write_spz(tmp_path / "a.spz", cloud)
    back, notes = read_model(tmp_path / "a.spz")
    assert len(notes) == 1 and "5 infinite opacity logit(s)" in notes[0] and "3 with alpha 1, 2 with alpha 0" in notes[0]
    assert np.all(np.isfinite(back.opacities)) and back.opacities.max() == OPACITY_LOGIT_LIMIT


def test_spz_wide_scene_uses_fewer_fractional_bits(tmp_path):
    cloud = _cloud(20).replace(means=np.full((20, 3), 5000.0))
    notes = write_model(tmp_path / "wide.spz", cloud)
    assert any("fractional bits" in n for n in notes)
    assert np.abs(read_spz(tmp_path / "wide.spz").means - 5000.0).max() < 2.0**-9


def test_spz_errors_name_the_problem(tmp_path):
    good = tmp_path / "a.spz"
    write_spz(good, _cloud(30))
    data = gzip.decompress(good.read_bytes())
    cases = {
        "truncated": (gzip.compress(data[:100]), "truncated SPZ"),
        "magic": (gzip.compress(b"XXXX" + data[4:]), "bad magic"),
        "version": (gzip.compress(data[:4] + struct.pack("<I", 7) + data[8:]), "version 7"),
        "gzip": (good.read_bytes()[:50], "corrupt or truncated SPZ"),
        "foreign": (b"hello world", "not an SPZ file"),
        "empty": (gzip.compress(data[:8] + struct.pack("<I", 0) + data[12:16]), "holds no Gaussians"),
    }
    for name, (raw, message) in cases.items():
        path = tmp_path / f"{name}.spz"
        path.write_bytes(raw)
        with pytest.raises(ModelFormatError, match=message):
            read_spz(path)
    with pytest.raises(ModelFormatError, match="version 5 cannot be written"):
        write_spz(tmp_path / "v5.spz", _cloud(5), version=5)
    assert not (tmp_path / "v5.spz").exists()


def test_spz_version_4_round_trip_equals_version_3(tmp_path):
    """Version 4 holds the same streams as version 3, zstd-compressed behind a plain header."""
    cloud = _cloud(200, degree=2)
    write_spz(tmp_path / "v3.spz", cloud, version=3)
    write_spz(tmp_path / "v4.spz", cloud, version=4)
    assert (tmp_path / "v4.spz").read_bytes()[:8] == struct.pack("<II", 0x5053474E, 4)
    v3, v4 = read_spz(tmp_path / "v3.spz"), read_spz(tmp_path / "v4.spz")
    for name in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"):
        assert np.array_equal(getattr(v3, name), getattr(v4, name)), name


def test_spz_version_4_names_what_it_needs(tmp_path):
    header = struct.pack("<IIIBBBBI12x", 0x5053474E, 4, 1, 0, 12, 0, 5, 32)
    (tmp_path / "v4.spz").write_bytes(header + bytes(16 * 5))
    try:
        import zstandard  # noqa: F401
    except ImportError:
        with pytest.raises(ModelFormatError, match="install 'zstandard'"):
            read_spz(tmp_path / "v4.spz")
    else:
        with pytest.raises(ModelFormatError, match="corrupt"):
            read_spz(tmp_path / "v4.spz")


# ------------------------------------------------------------------- .splat
def test_splat_round_trip_and_layout(tmp_path):
    cloud = _cloud(300, degree=2)
    (_, notes) = _notes(lambda: write_splat(tmp_path / "a.splat", cloud))
    assert any("degree-2 AC coefficients are dropped" in n for n in notes)
    assert (tmp_path / "a.splat").stat().st_size == 32 * 300
    back = read_splat(tmp_path / "a.splat")
    assert back.sh_degree == 0
    assert np.array_equal(back.means, cloud.means)
    assert np.abs(back.scales - cloud.scales).max() < 1e-5
    dc_visible = np.clip(0.5 + SH_C0 * cloud.sh_dc, 0, 1)
    assert np.abs(0.5 + SH_C0 * back.sh_dc - dc_visible).max() <= 0.5 / 255 + 1e-6
    assert np.abs(_alpha(back.opacities) - _alpha(cloud.opacities)).max() <= 0.5 / 255 + 1e-6
    assert _same_rotation(back.quats, cloud.quats) < 0.02


def test_splat_reads_a_hand_built_record(tmp_path):
    record = struct.pack("<3f3f4B4B", 1.0, 2.0, -3.0, 0.5, 1.0, 2.0, 255, 128, 0, 255, 128, 128, 128, 255)
    (tmp_path / "one.splat").write_bytes(record + record[:27] + bytes([0, 0, 128, 128, 128]))
    cloud, notes = read_model(tmp_path / "one.splat")
    assert cloud.num_gaussians == 2
    assert np.allclose(cloud.means[0], (1, 2, -3)) and np.allclose(np.exp(cloud.scales[0]), (0.5, 1, 2))
    assert np.allclose(0.5 + SH_C0 * cloud.sh_dc[0], (1.0, 128 / 255, 0.0), atol=1e-6)
    assert np.allclose(cloud.quats[0], (0, 0, 0, 1), atol=1e-6)  # w, x, y, z = 0, 0, 0, 127/128 -> z axis
    assert np.allclose(cloud.quats[1], (-1, 0, 0, 0))
    assert cloud.opacities[0] == OPACITY_LOGIT_LIMIT and "1 with alpha 1, 1 with alpha 0" in notes[0]


def test_splat_errors(tmp_path):
    (tmp_path / "odd.splat").write_bytes(bytes(33))
    with pytest.raises(ModelFormatError, match="not a multiple of 32"):
        read_splat(tmp_path / "odd.splat")
    (tmp_path / "empty.splat").write_bytes(b"")
    with pytest.raises(ModelFormatError, match="holds no Gaussians"):
        read_splat(tmp_path / "empty.splat")
    nan = struct.pack("<3f3f8B", float("nan"), 0, 0, 1, 1, 1, *([128] * 8))
    (tmp_path / "nan.splat").write_bytes(nan)
    with pytest.raises(ModelFormatError, match="NaN or infinite"):
        read_splat(tmp_path / "nan.splat")
    huge = _cloud(3).replace(scales=np.full((3, 3), 100.0))
    with pytest.raises(ModelFormatError, match="overflow float32"):
        write_splat(tmp_path / "huge.splat", huge)
    assert not (tmp_path / "huge.splat").exists()


# ---------------------------------------------------------------------- SOG
@pytest.mark.parametrize("target", ["scene.sog", "folder/meta.json"])
def test_sog_round_trip(tmp_path, target):
    cloud = _cloud(700, degree=3)
    path = tmp_path / target
    path.parent.mkdir(exist_ok=True)
    write_sog(path, cloud, order="keep", palette_size=128)
    back = read_sog(path if target.endswith(".sog") else path.parent)
    assert back.num_gaussians == 700 and back.sh_degree == 3
    logged = np.log1p(np.abs(cloud.means))
    assert np.abs(back.means - cloud.means).max() <= (logged.max() * 2 / 65535) * np.exp(logged.max()) + 1e-5
    assert np.abs(back.scales - cloud.scales).max() < 0.05
    assert np.abs(back.sh_dc - cloud.sh_dc).max() < 0.05
    assert np.abs(_alpha(back.opacities) - _alpha(cloud.opacities)).max() <= 0.5 / 255 + 1e-6
    assert _same_rotation(back.quats, cloud.quats) < 0.01
    # the palette (128 entries for 700 vectors) keeps the SH roughly, never exactly
    error = np.sqrt(np.mean((back.sh_rest - cloud.sh_rest) ** 2))
    assert 0.01 < error < 0.9 * np.sqrt(np.mean(cloud.sh_rest**2))
    assert model_bytes(path) > len(json.dumps({}))


def test_sog_morton_order_keeps_the_set(tmp_path):
    cloud = _cloud(300, degree=0)
    write_sog(tmp_path / "m.sog", cloud)
    back = read_sog(tmp_path / "m.sog")
    key = lambda c: np.lexsort(np.round(c.means, 2).T)  # noqa: E731
    assert np.abs(back.means[key(back)] - cloud.means[key(cloud)]).max() < 1e-3


def _webp(rgba: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(buffer, "WEBP", lossless=True, exact=True)
    return buffer.getvalue()


def _hand_sog(tmp_path, meta_changes=None, drop=None):
    """Two Gaussians in 4x4 images, values set per the meta.json v2 layout."""
    image = lambda: np.zeros((4, 4, 4), np.uint8)  # noqa: E731
    lo, hi, quats, scales, sh0, labels = image(), image(), image(), image(), image(), image()
    lo[0, 0, :3], hi[0, 0, :3] = (255, 0, 0), (255, 0, 128)  # x = 65535 -> max, z = 32768
    quats[0, 0] = (128, 128, 128, 252)  # w largest, x y z ~ 0
    quats[0, 1] = (255, 128, 128, 253)  # x largest, w = 1/sqrt2 * (255/255*2-1)
    scales[0, 0, :3] = (1, 2, 3)
    sh0[0, 0] = (0, 1, 2, 51)
    sh0[0, 1, 3] = 255
    labels[0, 1, :2] = (1, 0)  # second Gaussian: palette entry 1
    centroids = np.zeros((1, 64 * 3, 4), np.uint8)
    centroids[0, 3:6, :3] = [[1, 1, 1], [2, 2, 2], [0, 1, 2]]  # entry 1, coefficients 0..2
    meta = {
        "version": 2, "count": 2,
        "means": {"mins": [0.0, 0.0, -1.0], "maxs": [np.log(2.0), 0.0, 1.0], "files": ["means_l.webp", "means_u.webp"]},
        "scales": {"codebook": [float(-i) for i in range(256)], "files": ["scales.webp"]},
        "quats": {"files": ["quats.webp"]},
        "sh0": {"codebook": [i / 10 for i in range(256)], "files": ["sh0.webp"]},
        "shN": {"count": 2, "bands": 1, "codebook": [i / 100 for i in range(256)], "files": ["shN_centroids.webp", "shN_labels.webp"]},
    }
    meta.update(meta_changes or {})
    files = {"means_l.webp": lo, "means_u.webp": hi, "quats.webp": quats, "scales.webp": scales, "sh0.webp": sh0,
             "shN_labels.webp": labels, "shN_centroids.webp": centroids}
    with zipfile.ZipFile(tmp_path / "hand.sog", "w") as bundle:
        bundle.writestr("meta.json", json.dumps(meta))
        for name, pixels in files.items():
            if name != drop:
                bundle.writestr(name, _webp(pixels))
    return tmp_path / "hand.sog"


def test_sog_reads_a_hand_built_bundle(tmp_path):
    cloud, notes = read_model(_hand_sog(tmp_path))
    assert np.allclose(cloud.means[0], (1.0, 0.0, np.expm1(-1 + 2 * 32768 / 65535)), atol=1e-6)
    assert np.allclose(cloud.quats[0], (1, 0, 0, 0), atol=0.01)
    assert np.allclose(cloud.quats[1], (1 / np.sqrt(2), 1, 0, 0) / np.linalg.norm((1 / np.sqrt(2), 1)), atol=0.01) or \
        np.allclose(cloud.quats[1][:2], (1 / np.sqrt(2), 1 / np.sqrt(2)), atol=0.01)
    assert np.allclose(cloud.scales[0], (-1, -2, -3)) and np.allclose(cloud.sh_dc[0], (0, 0.1, 0.2))
    assert np.isclose(_alpha(cloud.opacities[0]), 0.2)
    assert cloud.opacities[1] == OPACITY_LOGIT_LIMIT and "1 with alpha 1, 0 with alpha 0" in notes[0]
    assert np.allclose(cloud.sh_rest[1], [[0.01] * 3, [0.02] * 3, [0.0, 0.01, 0.02]]) and np.allclose(cloud.sh_rest[0], 0)


def test_sog_errors(tmp_path):
    with pytest.raises(ModelFormatError, match="lacks quats.webp"):
        read_sog(_hand_sog(tmp_path, drop="quats.webp"))
    with pytest.raises(ModelFormatError, match="version 1"):
        read_sog(_hand_sog(tmp_path, {"version": None}))
    with pytest.raises(ModelFormatError, match="fewer than count"):
        read_sog(_hand_sog(tmp_path, {"count": 17}))
    with pytest.raises(ModelFormatError, match="'codebook' must be a list of 256"):
        read_sog(_hand_sog(tmp_path, {"scales": {"codebook": [1.0], "files": ["scales.webp"]}}))
    (tmp_path / "meta.json").write_text('{"id": "plant", "file": "plant.splat"}')
    with pytest.raises(ModelFormatError, match="not a SOG meta.json"):
        read_model(tmp_path / "meta.json")
    with pytest.raises(ModelFormatError, match="is a directory without a SOG meta.json"):
        read_model(tmp_path)


# --------------------------------------------------------------- compressed.ply
def _compressed_ply(path, with_colors: bool, with_sh: bool) -> None:
    n = 300  # two chunks
    chunk_names = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z", "min_scale_x", "min_scale_y", "min_scale_z",
                   "max_scale_x", "max_scale_y", "max_scale_z"] + (["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"] if with_colors else [])
    chunk = np.zeros(2, dtype=[(c, "<f4") for c in chunk_names])
    for c in chunk_names:
        chunk[c] = (-1.0 if c.startswith("min") else 1.0) if "_" in c[4:] or c[4:] in "xyz" else float(c.startswith("max"))
    chunk["min_x"][1], chunk["max_x"][1] = 10.0, 12.0
    if with_colors:
        chunk["min_r"], chunk["max_r"] = 0.0, 0.5
    vertex = np.zeros(n, dtype=[(c, "<u4") for c in ("packed_position", "packed_rotation", "packed_scale", "packed_color")])
    vertex["packed_position"] = (2047 << 21) | (0 << 11) | 1023  # x max, y min, z ~ middle
    vertex["packed_scale"] = (0 << 21) | (1023 << 11) | 2047
    vertex["packed_color"] = (255 << 24) | (0 << 16) | (128 << 8) | 0  # alpha 0 -> clamped
    vertex["packed_color"][1] = (255 << 24) | (0 << 16) | (128 << 8) | 51
    vertex["packed_rotation"] = (3 << 30) | (512 << 20) | (512 << 10) | 512  # z largest (rot_3), others ~ 0
    elements = [plyfile.PlyElement.describe(chunk, "chunk"), plyfile.PlyElement.describe(vertex, "vertex")]
    if with_sh:
        sh_table = np.zeros(n, dtype=[(f"f_rest_{i}", "u1") for i in range(9)])
        sh_table["f_rest_0"], sh_table["f_rest_3"], sh_table["f_rest_8"] = 255, 0, 127
        elements.append(plyfile.PlyElement.describe(sh_table, "sh"))
    plyfile.PlyData(elements, byte_order="<").write(str(path))


@pytest.mark.parametrize("with_colors, with_sh", [(True, True), (False, False)])
def test_compressed_ply_reads_the_packed_layout(tmp_path, with_colors, with_sh):
    path = tmp_path / "x.compressed.ply"
    _compressed_ply(path, with_colors, with_sh)
    assert detect_format(path) == "compressed-ply"
    cloud, notes = read_model(path)
    assert cloud.num_gaussians == 300 and cloud.sh_degree == (1 if with_sh else 0)
    assert np.allclose(cloud.means[0], (1.0, -1.0, 1023 / 2047 * 2 - 1), atol=1e-6)
    assert np.allclose(cloud.means[299, 0], 12.0)  # second chunk's box
    assert np.allclose(cloud.scales[0], (-1.0, 1.0, 1.0))
    red = 0.5 if with_colors else 1.0
    assert np.allclose(0.5 + SH_C0 * cloud.sh_dc[0], (red, 0.0, 128 / 255), atol=1e-6)
    assert np.isclose(_alpha(cloud.opacities[1]), 0.2)
    assert "299 infinite opacity logit(s)" in notes[0]
    assert np.allclose(cloud.quats[:, 3], 1.0, atol=0.01)
    if with_sh:  # channel-major f_rest: 0 = R of l1m-1, 3 = G of l1m-1, 8 = B of l1m1
        assert np.allclose(cloud.sh_rest[0, 0], (4.0, -4.0, -4.0))  # byte 0 is -4
        assert np.isclose(cloud.sh_rest[0, 2, 2], ((127.5 / 256) - 0.5) * 8)


def test_compressed_ply_errors(tmp_path):
    path = tmp_path / "bad.compressed.ply"
    chunk = np.zeros(1, dtype=[("min_x", "<f4")])
    vertex = np.zeros(3, dtype=[("packed_position", "<u4")])
    plyfile.PlyData([plyfile.PlyElement.describe(chunk, "chunk"), plyfile.PlyElement.describe(vertex, "vertex")]).write(str(path))
    with pytest.raises(ModelFormatError, match="element 'chunk' lacks min_y"):
        read_compressed_ply(path)


# -------------------------------------------------------------- checkpoints
def test_gsplat_checkpoint_round_trip_with_extra_keys(tmp_path):
    cloud = _cloud(50).replace()
    cloud.extra["features"] = np.random.default_rng(0).normal(size=(50, 8)).astype(np.float32)
    write_gsplat_checkpoint(tmp_path / "ckpt_99_rank0.pt", cloud, step=99)
    data = torch.load(tmp_path / "ckpt_99_rank0.pt", weights_only=True)  # as gsplat's trainer loads it
    assert data["step"] == 99 and data["splats"]["sh0"].shape == (50, 1, 3) and data["splats"]["shN"].shape == (50, 15, 3)
    assert data["splats"]["opacities"].shape == (50,)
    back, notes = read_model(tmp_path / "ckpt_99_rank0.pt")
    assert back.equals(cloud) and notes == []


def test_gsplat_checkpoint_variants_and_errors(tmp_path):
    n = 20
    base = {"means": torch.zeros(n, 3), "scales": torch.zeros(n, 3), "quats": torch.ones(n, 4), "opacities": torch.zeros(n)}
    torch.save({"step": 1, "splats": {**base, "features": torch.ones(n, 4), "colors": torch.zeros(n, 3)}}, tmp_path / "app.pt")
    cloud, notes = read_model(tmp_path / "app.pt")
    assert cloud.sh_degree == 0 and np.allclose(cloud.sh_dc, 0.0) and "features" in cloud.extra and "appearance" in notes[0]
    torch.save({**base, "sh0": torch.ones(n, 1, 3), "shN": torch.zeros(n, 3, 3)}, tmp_path / "bare.pt")
    assert read_model(tmp_path / "bare.pt")[0].sh_degree == 1
    torch.save({"step": 1, "model": {}}, tmp_path / "other.pt")
    with pytest.raises(ModelFormatError, match="not a gsplat checkpoint"):
        read_model(tmp_path / "other.pt")
    (tmp_path / "junk.pt").write_bytes(b"junk")
    with pytest.raises(ModelFormatError, match="not a readable torch checkpoint"):
        read_model(tmp_path / "junk.pt")
    torch.save({"splats": {**base, "sh0": torch.ones(n, 1, 3), "shN": torch.zeros(n, 3, 3), "bad": torch.zeros(3)}}, tmp_path / "rows.pt")
    with pytest.raises(ModelFormatError, match="'bad' has shape"):
        read_model(tmp_path / "rows.pt")


# ------------------------------------------------------------ read/write_model
@pytest.mark.parametrize("suffix, fmt", [(".ply", "ply"), (".spz", "spz"), (".splat", "splat"), (".sog", "sog"), (".pt", "gsplat")])
def test_write_model_by_extension_and_detection(tmp_path, suffix, fmt):
    cloud = _cloud(120, degree=1)
    path = tmp_path / f"scene{suffix}"
    write_model(path, cloud)
    assert detect_format(path) == fmt
    renamed = tmp_path / "renamed.bin"  # content sniffing, not the extension (.splat has no signature)
    renamed.write_bytes(path.read_bytes())
    if fmt != "splat":
        assert detect_format(renamed) == fmt
    back, _ = read_model(path)
    assert back.num_gaussians == 120


def test_unknown_formats_are_one_clear_error(tmp_path):
    (tmp_path / "scene.xyz").write_bytes(b"\x00" * 64)
    with pytest.raises(ModelFormatError, match="unknown Gaussian model format; supported: Inria .ply"):
        read_model(tmp_path / "scene.xyz")
    with pytest.raises(ModelFormatError, match="no such file"):
        read_model(tmp_path / "missing.spz")
    with pytest.raises(ModelFormatError, match=r"extension '.gsc'; writable: .ply, .spz"):
        write_model(tmp_path / "out.gsc", _cloud(3))
    zipped = tmp_path / "other.zip"
    with zipfile.ZipFile(zipped, "w") as bundle:
        bundle.writestr("readme.txt", "hi")
    with pytest.raises(ModelFormatError, match="neither a .sog bundle nor a torch checkpoint"):
        read_model(zipped)
    write_ply(tmp_path / "a.ply", _cloud(3))
    assert detect_format(tmp_path / "a.ply") == "ply"


def test_rd_scene_in_a_deployed_format_is_converted_natively(tmp_path, monkeypatch):
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.rd.scenes import prepare_scene
    from gscodec_shac.rd.spec import OrbitSpec, SceneSpec

    monkeypatch.setenv("PATH", str(tmp_path / "empty"))  # no node, no splat-transform
    monkeypatch.setenv("GSCODEC_SHAC_NPM_PREFIX", str(tmp_path / "npm"))
    cloud = _cloud(300, degree=1)
    for name in ("scene.spz", "scene.sog", "scene.pt"):
        write_model(tmp_path / name, cloud)
        spec = SceneSpec(name=name.replace(".", "_"), ply=str(tmp_path / name), orbit=OrbitSpec(n=2, width=16, height=12))
        assert spec.needs_conversion
        prepared = prepare_scene(spec, tmp_path / "out")
        assert prepared.ply.endswith("scene.ply") and read_ply(prepared.ply).num_gaussians == 300
