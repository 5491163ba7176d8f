"""Tests of gscodec_shac.camera: the Camera type, its validation, orbits and the test split."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gscodec_shac.camera import Camera, camera_on_sphere, orbit_basis, orbit_cameras, spread_views, test_split
from gscodec_shac.errors import CameraFormatError, GscodecError, ValidationError


def _camera(name: str = "cam", **overrides) -> Camera:
    """A valid camera at (0, 0, -4) looking down +z at the origin."""
    values = dict(width=64, height=48, fx=50.0, fy=50.0, cx=32.0, cy=24.0, R=np.eye(3), t=np.array([0.0, 0.0, 4.0]))
    values.update(overrides)
    return Camera(name, **values)


# --------------------------------------------------------------------------- #
# Camera
# --------------------------------------------------------------------------- #


def test_camera_matrices_and_projection():
    angle = 0.3
    rz = np.array([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]])
    cam = _camera(R=rz, t=[0.5, -0.2, 3.0], cx=30.0)
    np.testing.assert_allclose(cam.K, [[50, 0, 30], [0, 50, 24], [0, 0, 1]])
    np.testing.assert_allclose(cam.world_to_camera @ cam.camera_to_world, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(cam.R @ cam.center + cam.t, 0, atol=1e-12)
    np.testing.assert_allclose(cam.forward, rz[2])
    assert cam.fov_x == pytest.approx(2 * math.atan(32 / 50))
    assert cam.fov_y == pytest.approx(2 * math.atan(24 / 50))
    point = np.array([[0.1, 0.2, 1.0]])
    uv, depth = cam.project(point)
    x = rz @ point[0] + cam.t
    assert depth[0] == pytest.approx(x[2])
    np.testing.assert_allclose(uv[0], [50 * x[0] / x[2] + 30, 50 * x[1] / x[2] + 24])


def test_camera_is_immutable_and_compares_exactly():
    cam = _camera()
    with pytest.raises(ValueError):
        cam.R[0, 0] = 2.0
    assert cam == _camera()
    assert cam != _camera(fx=50.0000001)
    assert cam != _camera(t=[0, 0, 4.000001])


def test_resized_and_scaled_keep_the_field_of_view():
    cam = _camera(width=3958, height=2968, fx=3276.9, fy=3276.9, cx=1979.0, cy=1484.0)
    small = cam.scaled(1 / 8)
    assert (small.width, small.height) == (495, 371)  # Inria -r 8 and images_8 sizes
    assert small.fx == pytest.approx(3276.9 * 495 / 3958)
    assert small.fy == pytest.approx(3276.9 * 371 / 2968)
    assert (small.cx, small.cy) == (pytest.approx(247.5), pytest.approx(185.5))
    assert small.fov_x == pytest.approx(cam.fov_x)
    assert small.fov_y == pytest.approx(cam.fov_y)
    np.testing.assert_array_equal(small.R, cam.R)
    with pytest.raises(CameraFormatError, match="scale factor"):
        cam.scaled(0)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"R": np.diag([1.0, 1.0, 1.1])}, "rotation R is not orthonormal"),
        ({"R": np.diag([1.0, 1.0, -1.0])}, "reflection"),
        ({"R": np.eye(4)}, r"shape \(4, 4\)"),
        ({"width": 0}, "width 0 is not a positive integer"),
        ({"height": 10.5}, "height 10.5 is not a positive integer"),
        ({"fx": -1.0}, "focal length fx=-1.0 is not positive"),
        ({"cy": float("nan")}, "cy is not finite"),
        ({"t": [0.0, float("inf"), 1.0]}, "translation t has non-finite values"),
        ({"fy": "abc"}, "fy 'abc' is not a number"),
    ],
)
def test_camera_validation(overrides, message):
    with pytest.raises(CameraFormatError, match=message):
        _camera(**overrides)


def test_camera_format_error_is_a_gscodec_error():
    assert issubclass(CameraFormatError, GscodecError)


# --------------------------------------------------------------------------- #
# orbit_cameras and test_split
# --------------------------------------------------------------------------- #


def test_orbit_cameras_look_at_the_centre():
    center = np.array([1.0, -2.0, 0.5])
    orbit = orbit_cameras(center, 3.0, 12, 160, 120, 45.0, elevation_deg=30.0, up=(0, 0, 1))
    assert len(orbit) == 12 and orbit[0].name == "orbit_000"
    for cam in orbit:
        uv, depth = cam.project(np.stack([center, center + [0, 0, 0.1]]))
        np.testing.assert_allclose(uv[0], [80, 60], atol=1e-9)
        assert depth[0] == pytest.approx(3.0)
        assert uv[1, 1] < 60  # "up" is at the top of the image
        assert (cam.center - center)[2] == pytest.approx(3.0 * math.sin(math.radians(30)))
        assert cam.fov_y == pytest.approx(math.radians(45.0))
    assert orbit_cameras(center, 3.0, 12, 160, 120, 45.0, elevation_deg=30.0, up=(0, 0, 1)) == orbit
    angles = [math.atan2(*(c.center - center)[1::-1]) for c in orbit]
    np.testing.assert_allclose(np.diff(np.unwrap(angles)), 2 * math.pi / 12)
    with pytest.raises(ValidationError, match="elevation"):
        orbit_cameras(center, 3.0, 4, 16, 16, 45.0, elevation_deg=90.0)


def test_split_every_eighth_in_name_order():
    views = [_camera(f"v{i:03d}") for i in range(17)][::-1]
    train, test = test_split(views)
    assert [c.name for c in test] == ["v000", "v008", "v016"]
    assert len(train) == 14 and [c.name for c in train] == sorted(c.name for c in train)
    assert len(test_split([_camera(f"v{i:03d}") for i in range(292)])[1]) == 37


def test_orbit_basis_and_camera_on_sphere_build_the_orbit():
    up, e1, e2 = orbit_basis((0.0, 0.0, 2.0))
    np.testing.assert_allclose(np.stack([e1, e2, up]), np.eye(3), atol=1e-15)  # right-handed, unit, orthogonal
    up, e1, e2 = orbit_basis((0.3, -1.0, 0.2))
    np.testing.assert_allclose(np.stack([e1, e2, up]) @ np.stack([e1, e2, up]).T, np.eye(3), atol=1e-15)
    assert np.dot(np.cross(e1, e2), up) == pytest.approx(1.0)
    center = np.array([1.0, -2.0, 0.5])
    orbit = orbit_cameras(center, 3.0, 5, 64, 48, 50.0, elevation_deg=-12.0, up=(0.3, -1.0, 0.2))
    basis = orbit_basis((0.3, -1.0, 0.2))
    for i, cam in enumerate(orbit):
        assert camera_on_sphere(cam.name, center, 3.0, 2 * math.pi * i / 5, math.radians(-12.0), basis, 64, 48,
                                50.0) == cam


# --------------------------------------------------------------------------- orbit views of real scenes
def test_the_up_axis_of_a_flat_scene_is_its_thinnest_axis():
    from gscodec_shac.camera import model_up

    rng = np.random.default_rng(0)
    slab = rng.normal(size=(5000, 3)) * [4.0, 0.3, 3.0]  # flat along y
    assert abs(model_up(slab, (0.0, -1.0, 0.0)) @ [0.0, -1.0, 0.0]) == pytest.approx(1.0, abs=1e-2)
    assert model_up(slab, (0.0, 1.0, 0.0))[1] > 0.99  # signed to agree with the fallback
    ball = rng.normal(size=(5000, 3))  # no thinnest axis: the fallback
    assert model_up(ball, (0.0, 0.0, 1.0)).tolist() == [0.0, 0.0, 1.0]


def test_orbit_views_see_a_real_scene_from_outside():
    """kacy (no cameras, a room-like capture): before, the orbit sat inside it and every view
    was 92-100% covered; now every camera is outside the dense part's bounding sphere, which
    fits each view, and part of each frame is background as in a view of the whole scene."""
    from gscodec_shac.camera import dense_part, orbit_views
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.render.renderer import Renderer
    from tests.conftest import shared_scene

    cloud = read_ply(shared_scene("kacy_sh3_9k", "point_cloud.ply"))
    opacities = cloud.activated_opacities()
    centre, dense, radius = dense_part(cloud.means, opacities)
    cameras = orbit_views(cloud.means, 6, 64, opacities=opacities)
    renderer = Renderer(cloud)
    for camera in cameras:
        assert np.linalg.norm(camera.center - centre) > radius, camera.name
        uv, depth = camera.project(dense)
        inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
        assert inside.mean() > 0.95, (camera.name, inside.mean())
        covered = (renderer.render(camera, background=(0.0, 0.0, 0.0)).image.max(axis=2) > 0.02).mean()
        assert 0.2 < covered < 0.85, (camera.name, covered)


def test_spread_views_picks_evenly_in_name_order_and_caps_the_width():
    cameras = orbit_cameras(np.zeros(3), 3.0, 9, 400, 300, 45.0)
    picked = spread_views(reversed(cameras), 3)
    names = sorted(c.name for c in cameras)
    assert [c.name for c in picked] == [names[0], names[4], names[8]]
    assert all(c.width == 400 for c in picked)
    small = spread_views(cameras, 100, max_width=200)
    assert len(small) == 9 and all((c.width, c.height) == (200, 150) for c in small)
    assert spread_views(cameras, 2, max_width=1000)[0].width == 400  # narrower ones are kept as they are
    assert spread_views([], 4) == []
