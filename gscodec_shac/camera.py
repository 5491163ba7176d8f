"""The pinhole camera model: :class:`Camera`, pose helpers and synthetic views.

One type, :class:`Camera`, in the OpenCV convention (camera x right, y down,
z forward) with a world-to-camera pose ``x_cam = R @ x_world + t``. The camera
files of 3DGS captures are read in :mod:`gscodec_shac.io` (one module per
format, :func:`gscodec_shac.io.cameras.load_cameras` for any of them).

:func:`look_at` and :func:`orbit_cameras` make synthetic views (built from
:func:`orbit_basis` and :func:`camera_on_sphere`), :func:`test_split` the standard
"every 8th view" evaluation split. Invalid camera fields raise
:class:`CameraFormatError` with one sentence naming the camera and the problem.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from gscodec_shac.errors import CameraFormatError, ValidationError
from gscodec_shac.limits import MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE

PathLike = str | os.PathLike

#: Maximum |R R^T - I| accepted for a rotation matrix.
ROTATION_TOLERANCE = 1e-4
#: Image extensions tried, in order, when a file name has none.
IMAGE_EXTENSIONS = (".jpg", ".JPG", ".png", ".jpeg", ".PNG", ".JPEG")

# --------------------------------------------------------------------------- #
# Camera
# --------------------------------------------------------------------------- #


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera: intrinsics in pixels plus a world-to-camera pose.

    ``R`` (3x3) and ``t`` (3,) map world points into the OpenCV camera frame,
    ``x_cam = R @ x_world + t``. Arrays are stored as read-only float64 copies.
    Equality (``==``) is exact on every field.
    """

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    R: np.ndarray = field(repr=False)
    t: np.ndarray = field(repr=False)
    image_path: Path | None = None

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "name", str(self.name))
        set_(self, "width", positive_int(self.width, "width", self.name))
        set_(self, "height", positive_int(self.height, "height", self.name))
        check_image_size(self.width, self.height, self.name)
        for key in ("fx", "fy", "cx", "cy"):
            value = finite_float(getattr(self, key), key, self.name)
            if key in ("fx", "fy") and value <= 0:
                raise CameraFormatError(f"camera {self.name!r}: focal length {key}={value} is not positive")
            set_(self, key, value)
        set_(self, "R", _rotation(self.R, self.name))
        set_(self, "t", _vector3(self.t, "translation t", self.name))
        if self.image_path is not None:
            set_(self, "image_path", Path(self.image_path))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        scalars = ("name", "width", "height", "fx", "fy", "cx", "cy", "image_path")
        return all(getattr(self, k) == getattr(other, k) for k in scalars) and (
            np.array_equal(self.R, other.R) and np.array_equal(self.t, other.t)
        )

    __hash__ = None  # type: ignore[assignment]

    @property
    def K(self) -> np.ndarray:
        """The 3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def world_to_camera(self) -> np.ndarray:
        """The 4x4 world-to-camera matrix ``[R | t]``."""
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    @property
    def camera_to_world(self) -> np.ndarray:
        """The 4x4 camera-to-world matrix ``[R^T | center]``."""
        m = np.eye(4)
        m[:3, :3] = self.R.T
        m[:3, 3] = self.center
        return m

    @property
    def center(self) -> np.ndarray:
        """The camera position in world coordinates, ``-R^T t``."""
        return -self.R.T @ self.t

    @property
    def forward(self) -> np.ndarray:
        """The unit viewing direction (camera +z) in world coordinates."""
        return self.R[2].copy()

    @property
    def fov_x(self) -> float:
        """Horizontal field of view in radians (for a centred principal point)."""
        return 2.0 * math.atan(0.5 * self.width / self.fx)

    @property
    def fov_y(self) -> float:
        """Vertical field of view in radians (for a centred principal point)."""
        return 2.0 * math.atan(0.5 * self.height / self.fy)

    def resized(self, width: int, height: int) -> Camera:
        """This camera for images resampled to ``width`` x ``height`` (same pose).

        fx and cx scale by ``width / self.width``, fy and cy by
        ``height / self.height``, as in the Inria loader (which keeps the field of view).
        """
        width = positive_int(width, "width", self.name)
        height = positive_int(height, "height", self.name)
        sx, sy = width / self.width, height / self.height
        return Camera(
            self.name, width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
            self.R, self.t, self.image_path,
        )

    def scaled(self, factor: float) -> Camera:
        """:meth:`resized` to ``round(width * factor)`` x ``round(height * factor)``.

        ``scaled(1 / 8)`` matches Inria ``-r 8`` and COLMAP ``images_8``.
        """
        if not (math.isfinite(factor) and factor > 0):
            raise CameraFormatError(f"camera {self.name!r}: scale factor {factor} is not a positive number")
        if max(self.width, self.height) * factor > MAX_IMAGE_SIDE + 0.5:
            raise CameraFormatError(f"camera {self.name!r}: scaled by {factor:g}, the image would exceed "
                                    f"{MAX_IMAGE_SIDE:,} pixels a side")
        return self.resized(max(1, round(self.width * factor)), max(1, round(self.height * factor)))

    def with_image_path(self, image_path: PathLike | None) -> Camera:
        """A copy with another ``image_path``."""
        return Camera(
            self.name, self.width, self.height, self.fx, self.fy, self.cx, self.cy, self.R, self.t, image_path
        )

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (N, 3) to pixels: returns ``(uv (N, 2), depth (N,))``.

        Pixel (0, 0) is the top-left corner of the first pixel. Points behind the
        camera get a non-positive depth and meaningless ``uv``.
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        cam = points @ self.R.T + self.t
        depth = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.fx * cam[:, 0] / depth + self.cx, self.fy * cam[:, 1] / depth + self.cy], axis=1)
        return uv, depth

    def to_inria_dict(self, id: int) -> dict[str, Any]:  # noqa: A002 - the Inria key is "id"
        """The entry of this camera in an Inria ``cameras.json``.

        ``img_name`` is the name without an image extension (as the Inria trainer
        writes it). The format stores no principal point: readers assume the image centre.
        """
        return {
            "id": int(id),
            "img_name": strip_image_extension(self.name),
            "width": self.width,
            "height": self.height,
            "position": [float(v) for v in self.center],
            "rotation": [[float(v) for v in row] for row in self.R.T],
            "fy": self.fy,
            "fx": self.fx,
        }


# --------------------------------------------------------------------------- #
# Field checks (shared with the readers in gscodec_shac.io)
# --------------------------------------------------------------------------- #


def strip_image_extension(name: str) -> str:
    """``name`` without a known image extension (``a.JPG`` -> ``a``), else unchanged."""
    stem, dot, ext = name.rpartition(".")
    return stem if dot and stem and "." + ext.lower() in {e.lower() for e in IMAGE_EXTENSIONS} else name


def check_image_size(width: int, height: int, name: str) -> None:
    """Refuse an image larger than :data:`~gscodec_shac.limits.MAX_IMAGE_SIDE` a side or
    :data:`~gscodec_shac.limits.MAX_IMAGE_PIXELS` in all, before anything is allocated for it."""
    if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE or width * height > MAX_IMAGE_PIXELS:
        raise CameraFormatError(
            f"camera {name!r}: image size {width}x{height} exceeds the maximum ({MAX_IMAGE_SIDE:,} pixels a side, "
            f"{MAX_IMAGE_PIXELS:,} pixels in all)"
        )


def positive_int(value: Any, key: str, name: str) -> int:
    """``value`` as an int >= 1, else a CameraFormatError naming camera ``name`` and field ``key``."""
    if isinstance(value, bool):
        raise CameraFormatError(f"camera {name!r}: {key} {value!r} is not a number")
    try:
        as_float = float(value)
    except (TypeError, ValueError, OverflowError):
        raise CameraFormatError(f"camera {name!r}: {key} {value!r} is not a number") from None
    if not (math.isfinite(as_float) and as_float == int(as_float) and as_float >= 1):
        raise CameraFormatError(f"camera {name!r}: {key} {value!r} is not a positive integer")
    return int(as_float)


def finite_float(value: Any, key: str, name: str) -> float:
    """``value`` as a finite float, else a CameraFormatError naming camera ``name`` and field ``key``."""
    try:
        result = float(value)
    except (TypeError, ValueError):
        raise CameraFormatError(f"camera {name!r}: {key} {value!r} is not a number") from None
    if not math.isfinite(result):
        raise CameraFormatError(f"camera {name!r}: {key} is not finite ({result})")
    return result


def float_array(value: Any, shape: tuple[int, ...], what: str, name: str) -> np.ndarray:
    """``value`` as a finite float64 array of ``shape``, else a CameraFormatError naming ``what``."""
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CameraFormatError(f"camera {name!r}: {what} is not an array of numbers") from None
    if array.shape != shape:
        raise CameraFormatError(f"camera {name!r}: {what} has shape {array.shape}, expected {shape}")
    if not np.all(np.isfinite(array)):
        raise CameraFormatError(f"camera {name!r}: {what} has non-finite values")
    return array


def _rotation(value: Any, name: str) -> np.ndarray:
    r = float_array(value, (3, 3), "rotation R", name)
    error = float(np.abs(r @ r.T - np.eye(3)).max())
    if error > ROTATION_TOLERANCE:
        raise CameraFormatError(
            f"camera {name!r}: rotation R is not orthonormal (max |R R^T - I| = {error:.3g} > {ROTATION_TOLERANCE})"
        )
    if np.linalg.det(r) < 0:
        raise CameraFormatError(f"camera {name!r}: rotation R is a reflection (determinant -1), not a rotation")
    r.setflags(write=False)
    return r


def _vector3(value: Any, what: str, name: str) -> np.ndarray:
    v = float_array(value, (3,), what, name).copy()
    v.setflags(write=False)
    return v


def from_camera_to_world(
    name: str, width: Any, height: Any, fx: Any, fy: Any, cx: Any, cy: Any,
    rotation_c2w: np.ndarray, center: np.ndarray, image_path: Path | None = None,
) -> Camera:
    """A :class:`Camera` from a camera-to-world rotation and a camera centre (OpenCV axes)."""
    rotation_c2w = float_array(rotation_c2w, (3, 3), "camera-to-world rotation", name)
    center = float_array(center, (3,), "camera position", name)
    r = rotation_c2w.T
    return Camera(name, width, height, fx, fy, cx, cy, r, -r @ center, image_path)


# --------------------------------------------------------------------------- #
# Synthetic views and the evaluation split
# --------------------------------------------------------------------------- #


def look_at(
    name: str, eye: Sequence[float], target: Sequence[float], up: Sequence[float],
    width: int, height: int, fx: float, fy: float | None = None,
) -> Camera:
    """A camera at ``eye`` looking at ``target`` with ``up`` towards the image top."""
    eye_v, target_v, up_v = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    forward = target_v - eye_v
    if not np.all(np.isfinite(forward)) or np.linalg.norm(forward) < 1e-12:
        raise ValidationError(f"look_at: eye {eye_v.tolist()} and target {target_v.tolist()} must differ")
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up_v)
    if np.linalg.norm(right) < 1e-9:
        raise ValidationError(f"look_at: up {up_v.tolist()} is parallel to the viewing direction")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.stack([right, down, forward], axis=1)
    fy = fx if fy is None else fy
    return from_camera_to_world(name, width, height, fx, fy, width / 2.0, height / 2.0, c2w, eye_v)


def orbit_cameras(
    center: Sequence[float],
    radius: float,
    n: int,
    width: int,
    height: int,
    fov_y_deg: float,
    elevation_deg: float = 20.0,
    up: Sequence[float] = (0.0, 0.0, 1.0),
) -> list[Camera]:
    """``n`` cameras evenly spaced on a circle of ``radius`` around ``center``, all looking at it.

    The circle lies ``elevation_deg`` above the plane through ``center``
    perpendicular to ``up``; azimuth 0 is the world axis least aligned with
    ``up``, made perpendicular to it. Square pixels, principal point at the
    image centre; names ``orbit_000``... Deterministic.
    """
    up_v = np.asarray(up, dtype=np.float64)
    center_v = np.asarray(center, dtype=np.float64)
    if n < 1 or not (math.isfinite(radius) and radius > 0):
        raise ValidationError(f"orbit_cameras: need n >= 1 and radius > 0, got n={n}, radius={radius}")
    if not (0 < fov_y_deg < 180) or abs(elevation_deg) >= 89.9:
        raise ValidationError(
            f"orbit_cameras: need 0 < fov_y_deg < 180 and |elevation_deg| < 89.9, got {fov_y_deg}, {elevation_deg}"
        )
    if up_v.shape != (3,) or center_v.shape != (3,) or np.linalg.norm(up_v) < 1e-12:
        raise ValidationError("orbit_cameras: center and up must be 3-vectors and up must be non-zero")
    basis = orbit_basis(up_v)
    elevation = math.radians(elevation_deg)
    return [
        camera_on_sphere(f"orbit_{i:03d}", center_v, radius, 2.0 * math.pi * i / n, elevation, basis, width, height,
                         fov_y_deg)
        for i in range(n)
    ]


def orbit_basis(up: Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(up, e1, e2)``: ``up`` made unit and an orthonormal basis of the plane perpendicular to it.

    ``e1`` is the world axis least aligned with ``up``, made perpendicular to it, and
    ``e2 = up x e1``. ``up`` must be a non-zero 3-vector (the callers check it).
    """
    up_v = np.asarray(up, dtype=np.float64)
    up_v = up_v / np.linalg.norm(up_v)
    ref = np.eye(3)[int(np.argmin(np.abs(up_v)))]
    e1 = ref - (ref @ up_v) * up_v
    e1 /= np.linalg.norm(e1)
    return up_v, e1, np.cross(up_v, e1)


def camera_on_sphere(
    name: str,
    center: np.ndarray,
    radius: float,
    azimuth: float,
    elevation: float,
    basis: tuple[np.ndarray, np.ndarray, np.ndarray],
    width: int,
    height: int,
    fov_y_deg: float,
) -> Camera:
    """A camera at ``radius`` from ``center``, looking at it with ``up`` towards the image top.

    ``basis`` is ``(up, e1, e2)`` from :func:`orbit_basis`; ``azimuth`` (from ``e1``
    towards ``e2``) and ``elevation`` (towards ``up``) are in radians. Square pixels
    with a vertical field of view of ``fov_y_deg``, principal point at the image centre.
    """
    up_v, e1, e2 = basis
    direction = math.cos(elevation) * (math.cos(azimuth) * e1 + math.sin(azimuth) * e2) + math.sin(elevation) * up_v
    focal = 0.5 * height / math.tan(0.5 * math.radians(fov_y_deg))
    return look_at(name, center + radius * direction, center, up_v, width, height, focal)


#: Share of the points (nearest the centre) that make up a scene's dense part.
DENSE_SHARE = 0.9
#: The thinnest principal axis of the dense part is its up axis only when its variance is at most
#: this share of the middle one (a clearly flat scene: a ground, a table top); else ``fallback_up``.
FLAT_RATIO = 0.5


def dense_part(points: np.ndarray, opacities: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """``(centre, dense points, radius)`` of a scene: the :data:`DENSE_SHARE` of its (visible) points
    nearest their median, and the radius of the sphere about the centre holding them.

    Visible: activated opacity >= 0.1 when ``opacities`` is given and at least 16 pass; far
    background Gaussians and floaters fall outside the dense part.
    """
    points = np.asarray(points, dtype=np.float64)
    if opacities is not None:
        solid = np.asarray(opacities) >= 0.1
        if solid.sum() >= 16:
            points = points[solid]
    centre = np.median(points, axis=0)
    distance = np.linalg.norm(points - centre, axis=1)
    radius = max(float(np.quantile(distance, DENSE_SHARE)), 1e-6)
    return centre, points[distance <= radius], radius


def model_up(dense: np.ndarray, fallback_up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """The up axis of a scene from its dense points: the thinnest principal axis when the scene is
    clearly flat along it (see :data:`FLAT_RATIO`), signed to agree with ``fallback_up``; else
    ``fallback_up`` (a scene as wide as it is tall has no up axis in its shape)."""
    fallback = np.asarray(fallback_up, dtype=np.float64)
    fallback = fallback / np.linalg.norm(fallback)
    if len(dense) < 4:
        return fallback
    variances, axes = np.linalg.eigh(np.cov((dense - dense.mean(axis=0)).T))
    if not variances[0] <= FLAT_RATIO * variances[1]:
        return fallback
    axis = axes[:, 0]
    return -axis if axis @ fallback < 0 else axis


def orbit_views(
    points: np.ndarray,
    n_views: int,
    width: int,
    height: int | None = None,
    *,
    up: Sequence[float] | None = (0.0, 0.0, 1.0),
    elevations: Sequence[float] = (-10.0, 15.0, 40.0),
    fov_y_deg: float = 45.0,
    distance: float = 2.5,
    opacities: np.ndarray | None = None,
) -> list[Camera]:
    """``n_views`` cameras on rings around a scene's ``points`` (N, 3), all looking at its centre.

    Centre and extent come from the scene's dense part (:func:`dense_part`; pass ``opacities``
    to leave out transparent Gaussians): centre = its median; radius = ``distance`` x the median
    distance of the points from the centre, but at least far enough that the dense part's
    bounding sphere fits the view (1.05 / sin(fov/2) of its radius), so no camera sits inside
    the scene. ``up=None``: the up axis from the model (:func:`model_up`, else +Z). The views
    are spread round-robin over rings at the given elevations (degrees) with staggered
    azimuths; names ``orbit_000`` ... in that order. Height defaults to 3/4 of the width.
    """
    if n_views < 1 or width < 1:
        raise ValidationError(f"orbit views need n_views >= 1 and width >= 1, got {n_views}, {width}")
    height = max(1, round(0.75 * width)) if height is None else int(height)
    points = np.asarray(points, dtype=np.float64)
    centre, dense, dense_radius = dense_part(points, opacities)
    up_v = model_up(dense) if up is None else np.asarray(up, dtype=np.float64)
    if up_v.shape != (3,) or np.linalg.norm(up_v) < 1e-12:
        raise ValidationError(f"up must be a non-zero 3-vector, got {list(up_v)!r}")
    basis = orbit_basis(up_v)
    spread = max(float(np.median(np.linalg.norm(points - centre, axis=1))), 1e-6)
    half_y = math.radians(fov_y_deg) / 2.0
    half_fov = min(half_y, math.atan(math.tan(half_y) * width / height))  # the narrower of the two
    radius = max(distance * spread, 1.05 * dense_radius / math.sin(half_fov))
    rings = len(elevations)
    cameras = []
    for i in range(n_views):
        ring = i % rings
        azimuth = 2.0 * math.pi * (i / n_views + ring / (2.0 * rings * max(1, n_views // rings)))
        elevation = math.radians(elevations[ring])
        cameras.append(
            camera_on_sphere(f"orbit_{i:03d}", centre, radius, azimuth, elevation, basis, width, height, fov_y_deg)
        )
    return cameras


def spread_views(cameras: Iterable[Camera], count: int, max_width: int | None = None) -> list[Camera]:
    """At most ``count`` of ``cameras``, evenly spread in name order; with ``max_width``, each one
    wider than that resized to it (aspect kept)."""
    ordered = sorted(cameras, key=lambda c: c.name)
    views = [ordered[i] for i in np.linspace(0, len(ordered) - 1, min(count, len(ordered))).round().astype(int)]
    if max_width is None:
        return views
    return [v if v.width <= max_width else v.resized(max_width, max(1, round(v.height * max_width / v.width)))
            for v in views]


def test_split(cameras: Iterable[Camera], every: int = 8) -> tuple[list[Camera], list[Camera]]:
    """``(train, test)``: test is every ``every``-th camera (i % every == 0) in sorted name order.

    The 3DGS / Mip-NeRF 360 evaluation convention; both lists are name-sorted.
    """
    if every < 1:
        raise ValidationError(f"test_split: every must be >= 1, got {every}")
    ordered = sorted(cameras, key=lambda c: c.name)
    train = [c for i, c in enumerate(ordered) if i % every != 0]
    test = [c for i, c in enumerate(ordered) if i % every == 0]
    return train, test


test_split.__test__ = False  # type: ignore[attr-defined]  # not a pytest test despite its name
