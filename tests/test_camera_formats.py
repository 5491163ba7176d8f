"""Tests of the camera files in gscodec_shac.io: every reader/writer, the dispatcher and the errors.

Real-data tests use ../shared/data/scenes and skip when it is absent.
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest

from gscodec_shac.camera import Camera, orbit_cameras, test_split
from gscodec_shac.errors import CameraFormatError
from gscodec_shac.geometry import quat_to_rotmat, rotmat_to_quat
from gscodec_shac.io.cameras import load_cameras
from gscodec_shac.io.colmap import (
    qvec_to_rotmat,
    read_colmap,
    read_colmap_cameras,
    write_colmap_binary,
    write_colmap_text,
)
from gscodec_shac.io.inria_cameras import read_inria_cameras, write_inria_cameras
from gscodec_shac.io.llff import read_llff_poses
from gscodec_shac.io.nerf import read_nerf_transforms
from tests.conftest import SHARED_SCENES
from tests.test_camera import _camera

SCENES = SHARED_SCENES
SNOWMIKU = SCENES / "snowmiku_capture"
BONSAI = SCENES / "mipnerf360_bonsai"
BONSAI_JSON = SCENES / "bonsai_cpu_sh3" / "cameras.json"
CHAIR = SCENES / "nerf_synthetic" / "chair"


def _need(*paths: Path):
    """Mark a test as using shared data and skip it when any of ``paths`` is absent."""
    missing = [str(p) for p in paths if not p.exists()]
    skip = pytest.mark.skipif(bool(missing), reason=f"shared data not available: {', '.join(missing)}")
    return lambda test: pytest.mark.shared_data(skip(test))


def _stem(name: str) -> str:
    return name.rsplit(".", 1)[0]


def _assert_same_cameras(a: list[Camera], b: list[Camera], atol: float = 1e-12) -> None:
    assert [c.name for c in a] == [c.name for c in b]
    for x, y in zip(a, b):
        assert (x.width, x.height, x.fx, x.fy, x.cx, x.cy) == (y.width, y.height, y.fx, y.fy, y.cx, y.cy)
        np.testing.assert_allclose(x.R, y.R, rtol=0, atol=atol)
        np.testing.assert_allclose(x.t, y.t, rtol=0, atol=atol * max(1.0, float(np.abs(x.t).max())))


# --------------------------------------------------------------------------- #
# Inria cameras.json
# --------------------------------------------------------------------------- #


def test_inria_round_trip(tmp_path):
    original = orbit_cameras([1.0, 2.0, 0.5], 3.0, 5, 120, 80, 50.0)
    path = tmp_path / "cameras.json"
    write_inria_cameras(path, original)
    entry = json.loads(path.read_text())[2]
    assert set(entry) == {"id", "img_name", "width", "height", "position", "rotation", "fx", "fy"}
    assert entry["id"] == 2 and entry["img_name"] == "orbit_002"
    np.testing.assert_allclose(entry["position"], original[2].center)
    np.testing.assert_allclose(entry["rotation"], original[2].R.T)  # camera-to-world
    _assert_same_cameras(read_inria_cameras(path), original, atol=1e-12)


def test_inria_image_extension_found_on_disk(tmp_path):
    cameras = orbit_cameras([0, 0, 0], 2.0, 3, 16, 16, 40.0)
    write_inria_cameras(tmp_path / "cameras.json", cameras)
    (tmp_path / "orbit_000.JPG").write_bytes(b"x")
    (tmp_path / "orbit_001.png").write_bytes(b"x")
    read = read_inria_cameras(tmp_path / "cameras.json", image_dir=tmp_path)
    assert [c.image_path for c in read] == [tmp_path / "orbit_000.JPG", tmp_path / "orbit_001.png", None]


def test_inria_writer_strips_extension_and_warns_on_off_centre_principal_point(tmp_path):
    with pytest.warns(UserWarning, match="off-centre principal point"):
        write_inria_cameras(tmp_path / "c.json", [_camera("a.JPG", cx=20.0)])
    assert json.loads((tmp_path / "c.json").read_text())[0]["img_name"] == "a"


# --------------------------------------------------------------------------- #
# COLMAP
# --------------------------------------------------------------------------- #


def test_quaternion_conversions_are_inverse():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        np.testing.assert_allclose(rotmat_to_quat(qvec_to_rotmat(q)), q, atol=1e-12)
    np.testing.assert_allclose(qvec_to_rotmat([2.0, 0, 0, 0]), np.eye(3))  # normalised first
    # 90 degrees about z: x -> y
    rot_z90 = qvec_to_rotmat([math.sqrt(0.5), 0, 0, math.sqrt(0.5)])
    np.testing.assert_allclose(rot_z90 @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_rotmat_to_quat_of_a_nearly_orthonormal_matrix():
    """A Camera accepts max |R R^T - I| <= 1e-4; the rotation written is within 2x that of the nearest one."""
    rng = np.random.default_rng(1)
    noisy = quat_to_rotmat(rng.normal(size=(200, 4))) + rng.normal(scale=2e-5, size=(200, 3, 3))
    off = np.abs(noisy @ np.swapaxes(noisy, 1, 2) - np.eye(3)).max(axis=(1, 2))
    u, _, vt = np.linalg.svd(noisy)
    error = np.abs(quat_to_rotmat(rotmat_to_quat(noisy)) - u @ vt).max(axis=(1, 2))
    assert np.all(error <= 2 * off)
    assert np.array_equal(rotmat_to_quat(noisy[7]), rotmat_to_quat(noisy)[7])  # one matrix or a stack


@pytest.mark.parametrize("writer", [write_colmap_text, write_colmap_binary])
def test_colmap_round_trip_sorts_and_shares_intrinsics(tmp_path, writer):
    cameras = orbit_cameras([0.0, 1.0, 0.0], 2.5, 6, 100, 60, 45.0)[::-1]  # written unsorted
    cameras.append(_camera("extra_wide", fx=20.0, fy=21.0, cx=30.5, cy=22.0))
    writer(tmp_path, cameras)
    intrinsics = read_colmap_cameras(tmp_path)
    assert len(intrinsics) == 2 and {c.model for c in intrinsics.values()} == {"PINHOLE"}
    read = read_colmap(tmp_path)
    _assert_same_cameras(read, sorted(cameras, key=lambda c: c.name), atol=1e-13)
    assert (tmp_path / f"points3D{'.txt' if writer is write_colmap_text else '.bin'}").is_file()


def test_colmap_binary_reader_skips_2d_points(tmp_path):
    write_colmap_binary(tmp_path, [_camera("solo.png")])
    q = rotmat_to_quat(np.eye(3))
    record = struct.pack("<i7di", 7, *q, 0.0, 0.0, 4.0, 1) + b"solo.png\0" + struct.pack("<Q", 2)
    record += struct.pack("<ddq", 1.5, 2.5, -1) + struct.pack("<ddq", 3.5, 4.5, 12)
    (tmp_path / "images.bin").write_bytes(struct.pack("<Q", 1) + record)
    (cam,) = read_colmap(tmp_path, image_dir=tmp_path)
    assert cam == _camera("solo.png")  # image_path None: the file does not exist
    (tmp_path / "images.bin").write_bytes(struct.pack("<Q", 1) + record[:-10])
    with pytest.raises(CameraFormatError, match=r"images\.bin: truncated COLMAP binary file .*2D points of image 7"):
        read_colmap(tmp_path)


def test_colmap_text_images_with_points_and_comments(tmp_path):
    (tmp_path / "cameras.txt").write_text("# comment\n\n3 SIMPLE_PINHOLE 64 48 50 32 24\n")
    (tmp_path / "images.txt").write_text(
        "# header\n# more\n"
        "2 1 0 0 0 0 0 4 3 b image.jpg\n"
        "10.0 20.0 -1 11.0 21.0 5\n"
        "1 1 0 0 0 0 0 4 3 a.jpg\n"
    )
    read = read_colmap(tmp_path)
    assert [c.name for c in read] == ["a.jpg", "b image.jpg"]  # sorted; names may contain spaces
    assert read[0] == _camera("a.jpg")


def _write_text_model(directory: Path, camera_line: str, image_line: str = "1 1 0 0 0 0 0 4 1 a.jpg") -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "cameras.txt").write_text(camera_line + "\n")
    (directory / "images.txt").write_text(image_line + "\n\n")
    return directory


def test_colmap_distorted_model_needs_undistortion(tmp_path):
    model = _write_text_model(tmp_path, "1 SIMPLE_RADIAL 64 48 50 32 24 0.03")
    message = r"cameras\.txt: camera model SIMPLE_RADIAL has lens distortion; undistort"
    with pytest.raises(CameraFormatError, match=message):
        read_colmap(model)
    with pytest.warns(UserWarning, match="ignoring the lens distortion"):
        (cam,) = read_colmap(model, allow_distortion=True)
    assert cam == _camera("a.jpg")


def test_colmap_zero_distortion_is_pinhole(tmp_path):
    model = _write_text_model(tmp_path, "1 OPENCV 64 48 50 50 32 24 0 0 0 0")
    assert read_colmap(model) == [_camera("a.jpg")]


@pytest.mark.parametrize(
    ("camera_line", "image_line", "message"),
    [
        ("1 PINHOLE 64 48 50 50 32 24", "1 1 0 0 0 0 0 4 2 a.jpg",
         "uses camera id 2, which cameras.txt does not define"),
        ("1 FISHEYE_X 64 48 50 50 32 24", "1 1 0 0 0 0 0 4 1 a.jpg", "unknown COLMAP camera model 'FISHEYE_X'"),
        ("1 PINHOLE 64 48 50 50 32", "1 1 0 0 0 0 0 4 1 a.jpg", "PINHOLE needs 4 parameters, got 3"),
        ("1 PINHOLE 64 48 50 fifty 32 24", "1 1 0 0 0 0 0 4 1 a.jpg", "line 1 has a value that is not a number"),
        ("1 PINHOLE 64 48 50 50 32 24", "1 1 0 0 0 0 0 4 1", "line 1 is not 'IMAGE_ID QW"),
        ("1 PINHOLE 64 48 50 50 32 24", "1 0 0 0 0 0 0 4 1 a.jpg", "zero or non-finite norm"),
        ("1 PINHOLE 64 0 50 50 32 24", "1 1 0 0 0 0 0 4 1 a.jpg", "height 0 is not a positive integer"),
    ],
)
def test_colmap_text_errors(tmp_path, camera_line, image_line, message):
    model = _write_text_model(tmp_path, camera_line, image_line)
    with pytest.raises(CameraFormatError, match=message):
        read_colmap(model)


def test_colmap_duplicate_image_names(tmp_path):
    images = "1 1 0 0 0 0 0 4 1 a.jpg\n\n2 1 0 0 0 0 0 4 1 a.jpg"
    model = _write_text_model(tmp_path, "1 PINHOLE 64 48 50 50 32 24", images)
    with pytest.raises(CameraFormatError, match="image name 'a.jpg' appears twice"):
        read_colmap(model)


def test_colmap_binary_errors(tmp_path):
    write_colmap_binary(tmp_path, [_camera("a.png")])
    data = (tmp_path / "cameras.bin").read_bytes()
    (tmp_path / "cameras.bin").write_bytes(data[:30])
    with pytest.raises(CameraFormatError, match=r"cameras\.bin: truncated COLMAP binary file \(30 bytes"):
        read_colmap_cameras(tmp_path)
    (tmp_path / "cameras.bin").write_bytes(data[:12] + struct.pack("<i", 42) + data[16:])
    with pytest.raises(CameraFormatError, match="unknown COLMAP model id 42"):
        read_colmap_cameras(tmp_path)
    (tmp_path / "cameras.bin").write_bytes(data + b"\0\0")
    with pytest.raises(CameraFormatError, match="2 unexpected bytes"):
        read_colmap_cameras(tmp_path)
    (tmp_path / "cameras.bin").write_bytes(data[:12] + struct.pack("<i", 4) + data[16:])  # OPENCV needs 8 params
    with pytest.raises(CameraFormatError, match="truncated"):
        read_colmap_cameras(tmp_path)


def test_colmap_missing_files(tmp_path):
    with pytest.raises(CameraFormatError, match="no such COLMAP sparse model folder"):
        read_colmap(tmp_path / "nope")
    with pytest.raises(CameraFormatError, match=r"has no cameras\.bin or cameras\.txt"):
        read_colmap(tmp_path)
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 64 48 50 50 32 24\n")
    with pytest.raises(CameraFormatError, match=r"has no images\.bin or images\.txt"):
        read_colmap(tmp_path)


# --------------------------------------------------------------------------- #
# NeRF transforms and LLFF
# --------------------------------------------------------------------------- #


def _transforms(tmp_path: Path, **extra) -> Path:
    # OpenGL camera at z=4 looking down -z (towards the origin), y up.
    data = {"camera_angle_x": 2 * math.atan(0.5), "frames": [{"file_path": "./train/r_0", "transform_matrix": [
        [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]}]}
    data.update(extra)
    path = tmp_path / "transforms_train.json"
    path.write_text(json.dumps(data))
    return path


def test_nerf_opengl_to_opencv(tmp_path):
    (cam,) = read_nerf_transforms(_transforms(tmp_path, w=100, h=80))
    assert cam.name == "r_0" and cam.image_path is None
    assert (cam.width, cam.height, cam.cx, cam.cy) == (100, 80, 50, 40)
    assert (cam.fx, cam.fy) == pytest.approx((100.0, 100.0))
    np.testing.assert_allclose(cam.center, [0, 0, 4])
    uv, depth = cam.project(np.array([[0, 0, 0], [0, 1, 0], [1, 0, 0]], dtype=float))
    assert depth[0] == pytest.approx(4.0)
    np.testing.assert_allclose(uv[0], [50, 40])
    assert uv[1, 1] < 40  # world +y (OpenGL camera up) is at the top of the image
    assert uv[2, 0] > 50  # world +x is to the right


def test_nerf_size_from_first_image(tmp_path):
    import cv2

    (tmp_path / "train").mkdir()
    cv2.imwrite(str(tmp_path / "train" / "r_0.png"), np.zeros((30, 40, 4), np.uint8))
    (cam,) = read_nerf_transforms(_transforms(tmp_path))
    assert (cam.width, cam.height) == (40, 30) and cam.image_path == tmp_path / "train" / "r_0.png"
    assert cam.fx == pytest.approx(40.0)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("{not json", "invalid JSON at line 1"),
        ('{"camera_angle_x": 0.7}', "the file has no 'frames' key"),
        ('{"camera_angle_x": 0.7, "w": 8, "h": 8, "frames": [{"file_path": "a"}]}',
         "frame 0: there is no 'transform_matrix' key"),
        ('{"w": 8, "h": 8, "frames": [{"file_path": "a", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}]}',
         "neither a 'camera_angle_x' nor an 'fl_x'"),
        ('{"camera_angle_x": 0.7, "frames": [{"file_path": "a", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}]}',
         "no 'w'/'h' keys and its first image 'a' was not found"),
        ('{"camera_angle_x": 0.7, "w": 8, "h": 8, "frames": [{"file_path": "a", '
         '"transform_matrix": [[2,0,0,0],[0,1,0,0],[0,0,1,0]]}]}',
         "not orthonormal"),
    ],
)
def test_nerf_errors(tmp_path, content, message):
    path = tmp_path / "transforms_train.json"
    path.write_text(content)
    with pytest.raises(CameraFormatError, match=message):
        read_nerf_transforms(path)


def test_llff_conversion(tmp_path):
    truth = orbit_cameras([0.5, 0, 0], 3.0, 4, 400, 300, 60.0)
    rows = []
    for cam in truth:
        right, down, forward = cam.R  # rows of R = camera axes in world
        pose = np.stack([down, right, -forward, cam.center, [300, 400, cam.fx]], axis=1)
        rows.append(np.concatenate([pose.ravel(), [0.1, 10.0]]))
    np.save(tmp_path / "poses_bounds.npy", np.array(rows))
    read = read_llff_poses(tmp_path / "poses_bounds.npy")
    assert [c.name for c in read] == ["00000", "00001", "00002", "00003"]
    for a, b in zip(read, truth):
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, atol=1e-12)
        assert (a.width, a.height, a.fx, a.fy) == (400, 300, pytest.approx(b.fx), pytest.approx(b.fy))
    (tmp_path / "images").mkdir()
    with pytest.raises(CameraFormatError, match="has 4 poses but .* has 0 images"):
        read_llff_poses(tmp_path / "poses_bounds.npy")
    np.save(tmp_path / "bad.npy", np.zeros((3, 15)))
    with pytest.raises(CameraFormatError, match=r"shape \(N, 17\), got \(3, 15\)"):
        read_llff_poses(tmp_path / "bad.npy")
    (tmp_path / "junk.npy").write_bytes(b"not numpy")
    with pytest.raises(CameraFormatError, match="not a readable .npy"):
        read_llff_poses(tmp_path / "junk.npy")


# --------------------------------------------------------------------------- #
# Generic bad inputs and dispatch
# --------------------------------------------------------------------------- #


def test_missing_invalid_and_incomplete_json(tmp_path):
    with pytest.raises(CameraFormatError, match=r"nope\.json: no such cameras\.json file"):
        read_inria_cameras(tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text('[{"id": 0,')
    with pytest.raises(CameraFormatError, match=r"bad\.json: invalid JSON at line 1"):
        read_inria_cameras(bad)
    entry = _camera("v0").to_inria_dict(0)
    del entry["fx"]
    bad.write_text(json.dumps([entry]))
    with pytest.raises(CameraFormatError, match=r"bad\.json: camera entry 0 has no 'fx' key"):
        read_inria_cameras(bad)
    entry = _camera("v0").to_inria_dict(0)
    entry["rotation"] = [[1, 0, 0], [0, 1, 0], [0, 0, 2]]
    bad.write_text(json.dumps([entry]))
    with pytest.raises(CameraFormatError, match=r"bad\.json: camera entry 0: .*rotation R is not orthonormal"):
        read_inria_cameras(bad)
    bad.write_text(json.dumps({"a": 1}))
    with pytest.raises(CameraFormatError, match="expected a JSON list"):
        read_inria_cameras(bad)
    bad.write_text("[]")
    with pytest.raises(CameraFormatError, match="contains no cameras"):
        read_inria_cameras(bad)


def test_load_cameras_dispatch(tmp_path):
    cameras = orbit_cameras([0, 0, 0], 2.0, 3, 32, 24, 50.0)
    write_colmap_binary(tmp_path / "cap" / "sparse" / "0", cameras)
    (tmp_path / "cap" / "images").mkdir()
    (tmp_path / "cap" / "images" / "orbit_001").write_bytes(b"x")
    read = load_cameras(tmp_path / "cap")
    _assert_same_cameras(read, cameras, atol=1e-13)
    assert read[1].image_path == tmp_path / "cap" / "images" / "orbit_001"
    _assert_same_cameras(load_cameras(tmp_path / "cap" / "sparse" / "0" / "images.bin"), cameras, atol=1e-13)
    (tmp_path / "model").mkdir()
    write_inria_cameras(tmp_path / "model" / "cameras.json", cameras)
    _assert_same_cameras(load_cameras(tmp_path / "model"), cameras, atol=1e-12)
    transforms = _transforms(tmp_path / "model", w=8, h=8)
    assert len(load_cameras(transforms)) == 1
    (tmp_path / "empty").mkdir()
    message = r"empty: no cameras found \(looked for sparse/0/.*cameras\.json.*poses_bounds\.npy"
    with pytest.raises(CameraFormatError, match=message):
        load_cameras(tmp_path / "empty")
    with pytest.raises(CameraFormatError, match="no such camera file or capture folder"):
        load_cameras(tmp_path / "missing")
    (tmp_path / "other.json").write_text('{"foo": 1}')
    with pytest.raises(CameraFormatError, match="neither an Inria cameras.json"):
        load_cameras(tmp_path / "other.json")
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(CameraFormatError, match="unrecognised camera file"):
        load_cameras(tmp_path / "notes.txt")


# --------------------------------------------------------------------------- #
# Real data
# --------------------------------------------------------------------------- #


@_need(SNOWMIKU / "cameras.json", SNOWMIKU / "colmap" / "sparse" / "0" / "cameras.bin")
def test_snowmiku_cameras_json_agrees_with_colmap_bin():
    views = read_inria_cameras(SNOWMIKU / "cameras.json", image_dir=SNOWMIKU / "images_8")
    assert len(views) == 97
    (intr,) = read_colmap_cameras(SNOWMIKU / "colmap" / "sparse" / "0").values()
    assert (intr.model, intr.width, intr.height) == ("PINHOLE", 3958, 2968)
    fx, fy, cx, cy = intr.pinhole
    assert fx == pytest.approx(3276.92, abs=0.01) and (cx, cy) == (1979.0, 1484.0)
    for cam in views:
        assert (cam.width, cam.height) == (intr.width, intr.height)
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == pytest.approx((fx, fy, cx, cy), rel=1e-12)
    assert all(c.image_path is not None and c.image_path.suffix == ".jpg" for c in views)
    # no images.bin in that model: reading the full model names the missing file
    with pytest.raises(CameraFormatError, match=r"has no images\.bin or images\.txt"):
        read_colmap(SNOWMIKU / "colmap" / "sparse" / "0")
    assert len(load_cameras(SNOWMIKU)) == 97  # capture folder -> cameras.json


@_need(SNOWMIKU / "colmap" / "distorted" / "cameras.bin")
def test_snowmiku_distorted_model_is_refused():
    (intr,) = read_colmap_cameras(SNOWMIKU / "colmap" / "distorted").values()
    assert (intr.model, intr.width, intr.height) == ("SIMPLE_RADIAL", 4032, 3024)
    assert intr.params[3] == pytest.approx(0.032123, abs=1e-6) and not intr.is_pinhole
    with pytest.raises(CameraFormatError, match="SIMPLE_RADIAL has lens distortion; undistort the images first"):
        read_colmap(SNOWMIKU / "colmap" / "distorted")


def _fraction_in_view(cam: Camera, points: np.ndarray) -> float:
    uv, depth = cam.project(points)
    inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    return float(inside.mean())


@_need(SNOWMIKU / "cameras.json", SNOWMIKU / "input.ply")
def test_snowmiku_sfm_points_project_into_the_views():
    plyfile = pytest.importorskip("plyfile")
    vertex = plyfile.PlyData.read(str(SNOWMIKU / "input.ply"))["vertex"]
    points = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1)
    views = read_inria_cameras(SNOWMIKU / "cameras.json")
    assert _fraction_in_view(views[0], points) > 0.8  # measured 0.826
    assert np.mean([_fraction_in_view(c, points) for c in views]) > 0.6  # measured 0.71
    # reading "rotation" as world-to-camera instead (a transposed R) sees few points
    wrong = [Camera(c.name, c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.R.T, -c.R.T @ c.center) for c in views]
    assert np.mean([_fraction_in_view(c, points) for c in wrong]) < 0.3  # measured 0.11


@pytest.fixture(scope="module")
def bonsai_colmap():
    if not (BONSAI / "sparse" / "0" / "images.txt").is_file():
        pytest.skip(f"shared data not available: {BONSAI / 'sparse' / '0'}")
    return read_colmap(BONSAI / "sparse" / "0", BONSAI / "images")


@pytest.mark.shared_data
def test_bonsai_colmap_text(bonsai_colmap):
    assert len(bonsai_colmap) == 292
    assert [c.name for c in bonsai_colmap] == sorted(c.name for c in bonsai_colmap)
    cam = bonsai_colmap[0]
    assert (cam.name, cam.width, cam.height, cam.cx, cam.cy) == ("DSCF5565.JPG", 800, 533, 400.0, 266.5)
    assert (cam.fx, cam.fy) == (826.8636509966, 826.6119708911)
    assert cam.image_path == BONSAI / "images" / "DSCF5565.JPG"
    train, test = test_split(bonsai_colmap)
    assert (len(train), len(test)) == (255, 37)
    assert test[1].name == "DSCF5573.JPG"


@_need(BONSAI_JSON)
def test_bonsai_inria_json_matches_colmap(bonsai_colmap):
    inria = read_inria_cameras(BONSAI_JSON)
    assert [c.name for c in inria] == [_stem(c.name) for c in bonsai_colmap]
    for a, b in zip(bonsai_colmap, inria):
        small = a.resized(b.width, b.height)  # 800x533 -> 200x133: fx scales by 1/4, fy by 133/533
        assert (small.width, small.height) == (200, 133)
        assert (b.fx, b.fy, b.cx, b.cy) == pytest.approx((small.fx, small.fy, small.cx, small.cy), rel=1e-9)
        np.testing.assert_allclose(b.R, a.R, rtol=0, atol=1e-5)
        np.testing.assert_allclose(b.t, a.t, rtol=0, atol=1e-5 * np.linalg.norm(a.t))
    assert inria[0].fx == pytest.approx(826.8636509966 * 200 / 800, rel=1e-9)


@_need(BONSAI / "poses_bounds.npy")
def test_bonsai_llff_matches_colmap(bonsai_colmap):
    llff = read_llff_poses(BONSAI / "poses_bounds.npy", BONSAI / "images")
    assert [c.name for c in llff] == [c.name for c in bonsai_colmap]
    for a, b in zip(bonsai_colmap, llff):
        assert (b.width, b.height) == (800, 533)
        assert (b.fx, b.fy, b.cx, b.cy) == pytest.approx((a.fx, a.fy, a.cx, a.cy), rel=1e-9)
        np.testing.assert_allclose(b.R, a.R, rtol=0, atol=1e-5)
        np.testing.assert_allclose(b.t, a.t, rtol=0, atol=1e-5 * np.linalg.norm(a.t))
        assert b.image_path == a.image_path
    loaded = load_cameras(BONSAI / "poses_bounds.npy")  # images/ next to the file is the default
    assert len(loaded) == 292 and loaded[0] == llff[0]


@pytest.mark.shared_data
def test_bonsai_binary_round_trip(bonsai_colmap, tmp_path):
    write_colmap_binary(tmp_path / "bin", bonsai_colmap)
    write_colmap_text(tmp_path / "txt", bonsai_colmap)
    assert len(read_colmap_cameras(tmp_path / "bin")) == 1  # one shared PINHOLE camera
    from_bin = read_colmap(tmp_path / "bin", BONSAI / "images")
    from_txt = read_colmap(tmp_path / "txt", BONSAI / "images")
    _assert_same_cameras(from_bin, bonsai_colmap, atol=1e-14)
    assert from_bin == from_txt  # repr() floats in text: both formats bit-identical
    assert [c.image_path for c in from_bin] == [c.image_path for c in bonsai_colmap]
    # and quaternions match the ones in the original images.txt
    original = [line.split() for line in (BONSAI / "sparse" / "0" / "images.txt").read_text().splitlines()
                if line.strip() and not line.startswith("#")]
    q_file = np.array([[float(v) for v in items[1:5]] for items in original[:5]])
    q_ours = np.array([rotmat_to_quat(c.R) for c in bonsai_colmap[:5]])
    np.testing.assert_allclose(q_ours, q_file * np.sign(q_file[:, :1]), atol=1e-11)


@_need(CHAIR / "transforms_train.json")
def test_nerf_synthetic_chair():
    chair = read_nerf_transforms(CHAIR / "transforms_train.json")
    assert len(chair) == 100 and chair[0].name == "r_0"
    assert all((c.width, c.height) == (800, 800) for c in chair)  # read from the RGBA PNG
    assert chair[0].fx == pytest.approx(1111.11, abs=0.01) and chair[0].fy == chair[0].fx
    assert chair[0].image_path == CHAIR / "train" / "r_0.png"
    for cam in chair:
        assert np.linalg.norm(cam.center) == pytest.approx(4.031, abs=0.01)
        # the optical axis passes near the origin, which is in front of the camera at the image centre
        uv, depth = cam.project(np.zeros((1, 3)))
        assert depth[0] == pytest.approx(4.031, abs=0.01)
        np.testing.assert_allclose(uv[0], [400, 400], atol=0.5)
    assert len(load_cameras(CHAIR)) == 100  # folder -> transforms_train.json
