"""Pinhole cameras and the camera files of 3DGS captures.

One type, :class:`Camera`, in the OpenCV convention (camera x right, y down,
z forward) with a world-to-camera pose ``x_cam = R @ x_world + t``. Readers turn
every common capture format into a ``list[Camera]``:

* Inria 3DGS ``cameras.json`` (:func:`read_inria_cameras`, :func:`write_inria_cameras`);
* COLMAP sparse models, text and binary (:func:`read_colmap`,
  :func:`read_colmap_cameras`, :func:`write_colmap_text`, :func:`write_colmap_binary`);
* NeRF-synthetic ``transforms_*.json`` (:func:`read_nerf_transforms`);
* LLFF / Mip-NeRF 360 ``poses_bounds.npy`` (:func:`read_llff_poses`);
* any of these found from a path (:func:`load_cameras`).

:func:`orbit_cameras` makes synthetic views, :func:`test_split` the standard
"every 8th view" evaluation split. Every unusable input raises
:class:`CameraFormatError` with one sentence naming the file and the problem.
"""

from __future__ import annotations

import json
import math
import os
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from gscodec_shac.atomic import write_atomic
from gscodec_shac.errors import CameraFormatError, ValidationError

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
        set_(self, "width", _positive_int(self.width, "width", self.name))
        set_(self, "height", _positive_int(self.height, "height", self.name))
        for key in ("fx", "fy", "cx", "cy"):
            value = _finite_float(getattr(self, key), key, self.name)
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
        width = _positive_int(width, "width", self.name)
        height = _positive_int(height, "height", self.name)
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
            "img_name": _strip_image_extension(self.name),
            "width": self.width,
            "height": self.height,
            "position": [float(v) for v in self.center],
            "rotation": [[float(v) for v in row] for row in self.R.T],
            "fy": self.fy,
            "fx": self.fx,
        }


def _strip_image_extension(name: str) -> str:
    stem, dot, ext = name.rpartition(".")
    return stem if dot and stem and "." + ext.lower() in {e.lower() for e in IMAGE_EXTENSIONS} else name


def _positive_int(value: Any, key: str, name: str) -> int:
    try:
        as_float = float(value)
    except (TypeError, ValueError):
        raise CameraFormatError(f"camera {name!r}: {key} {value!r} is not a number") from None
    if not (math.isfinite(as_float) and as_float == int(as_float) and as_float >= 1):
        raise CameraFormatError(f"camera {name!r}: {key} {value!r} is not a positive integer")
    return int(as_float)


def _finite_float(value: Any, key: str, name: str) -> float:
    try:
        result = float(value)
    except (TypeError, ValueError):
        raise CameraFormatError(f"camera {name!r}: {key} {value!r} is not a number") from None
    if not math.isfinite(result):
        raise CameraFormatError(f"camera {name!r}: {key} is not finite ({result})")
    return result


def _float_array(value: Any, shape: tuple[int, ...], what: str, name: str) -> np.ndarray:
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
    r = _float_array(value, (3, 3), "rotation R", name)
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
    v = _float_array(value, (3,), what, name).copy()
    v.setflags(write=False)
    return v


def _from_camera_to_world(
    name: str, width: Any, height: Any, fx: Any, fy: Any, cx: Any, cy: Any,
    rotation_c2w: np.ndarray, center: np.ndarray, image_path: Path | None = None,
) -> Camera:
    """A :class:`Camera` from a camera-to-world rotation and a camera centre (OpenCV axes)."""
    rotation_c2w = _float_array(rotation_c2w, (3, 3), "camera-to-world rotation", name)
    center = _float_array(center, (3,), "camera position", name)
    r = rotation_c2w.T
    return Camera(name, width, height, fx, fy, cx, cy, r, -r @ center, image_path)


# --------------------------------------------------------------------------- #
# Small helpers shared by the readers
# --------------------------------------------------------------------------- #


def _require_file(path: Path, what: str) -> None:
    if not path.exists():
        raise CameraFormatError(f"{path}: no such {what} file")
    if not path.is_file():
        raise CameraFormatError(f"{path}: is a directory, expected a {what} file")


def _load_json(path: Path, what: str) -> Any:
    _require_file(path, what)
    try:
        with open(path, encoding="utf-8") as handle:
            return json.load(handle)
    except json.JSONDecodeError as exc:
        raise CameraFormatError(f"{path}: invalid JSON at line {exc.lineno} column {exc.colno} ({exc.msg})") from None
    except UnicodeDecodeError:
        raise CameraFormatError(f"{path}: not a text (UTF-8 JSON) file") from None
    except OSError as exc:
        raise CameraFormatError(f"{path}: cannot be read ({exc.strerror or exc})") from None


def _key(entry: dict, key: str, path: Path, where: str) -> Any:
    if key not in entry:
        raise CameraFormatError(f"{path}: {where} has no {key!r} key")
    return entry[key]


def _find_image(directory: Path | None, name: str) -> Path | None:
    """``directory / name`` if it is a file, else with the first extension found on disk."""
    if directory is None or not name:
        return None
    exact = directory / name
    if exact.suffix and exact.is_file():
        return exact
    for ext in IMAGE_EXTENSIONS:
        candidate = directory / (name + ext)
        if candidate.is_file():
            return candidate
    return None


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, read with OpenCV."""
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise CameraFormatError(f"{path}: cannot be decoded as an image")
    return int(image.shape[1]), int(image.shape[0])


def _atomic_write(path: Path, data: bytes) -> None:
    write_atomic(path, data, error=CameraFormatError)


# --------------------------------------------------------------------------- #
# Inria cameras.json
# --------------------------------------------------------------------------- #

_INRIA_KEYS = ("img_name", "width", "height", "position", "rotation", "fx", "fy")


def read_inria_cameras(path: PathLike, image_dir: PathLike | None = None) -> list[Camera]:
    """Read an Inria 3DGS ``cameras.json`` (file order is kept).

    ``rotation`` is camera-to-world and ``position`` the camera centre; the
    principal point is the image centre. With ``image_dir``, ``image_path`` is
    ``image_dir / img_name`` plus the extension found on disk, or None.
    """
    path = Path(path)
    data = _load_json(path, "cameras.json")
    if not isinstance(data, list):
        raise CameraFormatError(f"{path}: not an Inria cameras.json (expected a JSON list of cameras)")
    if not data:
        raise CameraFormatError(f"{path}: contains no cameras")
    directory = Path(image_dir) if image_dir is not None else None
    cameras = []
    for index, entry in enumerate(data):
        if not isinstance(entry, dict):
            raise CameraFormatError(f"{path}: camera entry {index} is not a JSON object")
        where = f"camera entry {index}"
        values = {key: _key(entry, key, path, where) for key in _INRIA_KEYS}
        name = str(values["img_name"])
        try:
            width = _positive_int(values["width"], "width", name)
            height = _positive_int(values["height"], "height", name)
            cameras.append(
                _from_camera_to_world(
                    name, width, height, values["fx"], values["fy"], width / 2.0, height / 2.0,
                    values["rotation"], values["position"], _find_image(directory, name),
                )
            )
        except CameraFormatError as exc:
            raise CameraFormatError(f"{path}: {where}: {exc}") from None
    return cameras


def write_inria_cameras(path: PathLike, cameras: Sequence[Camera]) -> None:
    """Write ``cameras`` as an Inria ``cameras.json`` (ids 0..N-1), atomically.

    Warns when a principal point is off the image centre: the format cannot store it.
    """
    path = Path(path)
    off = [c.name for c in cameras if abs(c.cx - c.width / 2) > 1e-3 or abs(c.cy - c.height / 2) > 1e-3]
    if off:
        warnings.warn(
            f"{path}: {len(off)} camera(s) (first {off[0]!r}) have an off-centre principal point, "
            "which cameras.json cannot store",
            stacklevel=2,
        )
    entries = [camera.to_inria_dict(i) for i, camera in enumerate(cameras)]
    _atomic_write(path, json.dumps(entries).encode("utf-8"))


# --------------------------------------------------------------------------- #
# COLMAP sparse models
# --------------------------------------------------------------------------- #


@dataclass(frozen=True)
class ColmapModel:
    """A COLMAP camera model: id, name, parameter count, single focal length."""

    model_id: int
    name: str
    num_params: int
    single_focal: bool  # params start (f, cx, cy) instead of (fx, fy, cx, cy)
    fisheye: bool = False


COLMAP_MODELS: tuple[ColmapModel, ...] = (
    ColmapModel(0, "SIMPLE_PINHOLE", 3, True),
    ColmapModel(1, "PINHOLE", 4, False),
    ColmapModel(2, "SIMPLE_RADIAL", 4, True),
    ColmapModel(3, "RADIAL", 5, True),
    ColmapModel(4, "OPENCV", 8, False),
    ColmapModel(5, "OPENCV_FISHEYE", 8, False, True),
    ColmapModel(6, "FULL_OPENCV", 12, False),
    ColmapModel(7, "FOV", 5, False),
    ColmapModel(8, "SIMPLE_RADIAL_FISHEYE", 4, True, True),
    ColmapModel(9, "RADIAL_FISHEYE", 5, True, True),
    ColmapModel(10, "THIN_PRISM_FISHEYE", 12, False, True),
    ColmapModel(11, "RAD_TAN_THIN_PRISM_FISHEYE", 16, False, True),
)
_MODEL_BY_ID = {m.model_id: m for m in COLMAP_MODELS}
_MODEL_BY_NAME = {m.name: m for m in COLMAP_MODELS}


@dataclass(frozen=True)
class ColmapIntrinsics:
    """One entry of a COLMAP ``cameras.txt`` / ``cameras.bin``."""

    camera_id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]

    @property
    def is_pinhole(self) -> bool:
        """True for SIMPLE_PINHOLE/PINHOLE, and for non-fisheye models whose distortion is all zero."""
        spec = _MODEL_BY_NAME[self.model]
        extra = self.params[3 if spec.single_focal else 4 :]
        return self.model in ("SIMPLE_PINHOLE", "PINHOLE") or (not spec.fisheye and not any(extra))

    @property
    def pinhole(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy), ignoring any distortion parameters."""
        p = self.params
        if _MODEL_BY_NAME[self.model].single_focal:
            return p[0], p[0], p[1], p[2]
        return p[0], p[1], p[2], p[3]


@dataclass(frozen=True)
class _ColmapImage:
    image_id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str


def _colmap_file(sparse_dir: Path, stem: str) -> Path:
    """``stem.bin`` if present, else ``stem.txt`` (the Inria loader's preference)."""
    if not sparse_dir.is_dir():
        if sparse_dir.exists():
            raise CameraFormatError(f"{sparse_dir}: is not a directory, expected a COLMAP sparse model folder")
        raise CameraFormatError(f"{sparse_dir}: no such COLMAP sparse model folder")
    for ext in (".bin", ".txt"):
        candidate = sparse_dir / (stem + ext)
        if candidate.is_file():
            return candidate
    raise CameraFormatError(f"{sparse_dir}: COLMAP model has no {stem}.bin or {stem}.txt")


class _Reader:
    """Sequential little-endian reader that turns truncation into CameraFormatError."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self.data = path.read_bytes()
        except OSError as exc:
            raise CameraFormatError(f"{path}: cannot be read ({exc.strerror or exc})") from None
        self.pos = 0

    def unpack(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise CameraFormatError(
                f"{self.path}: truncated COLMAP binary file ({len(self.data)} bytes, ended while reading {what})"
            )
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return values

    def skip(self, size: int, what: str) -> None:
        if self.pos + size > len(self.data):
            raise CameraFormatError(
                f"{self.path}: truncated COLMAP binary file ({len(self.data)} bytes, ended while reading {what})"
            )
        self.pos += size

    def cstring(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise CameraFormatError(f"{self.path}: truncated COLMAP binary file (ended while reading {what})")
        raw = self.data[self.pos : end]
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise CameraFormatError(f"{self.path}: {what} is not valid UTF-8") from None

    def finish(self) -> None:
        extra = len(self.data) - self.pos
        if extra:
            raise CameraFormatError(f"{self.path}: {extra} unexpected bytes after the last COLMAP record")


def _read_cameras_bin(path: Path) -> dict[int, ColmapIntrinsics]:
    reader = _Reader(path)
    (count,) = reader.unpack("Q", "the camera count")
    cameras: dict[int, ColmapIntrinsics] = {}
    for index in range(count):
        camera_id, model_id, width, height = reader.unpack("iiQQ", f"camera {index}")
        spec = _MODEL_BY_ID.get(model_id)
        if spec is None:
            raise CameraFormatError(f"{path}: camera {camera_id} has unknown COLMAP model id {model_id}")
        params = reader.unpack(f"{spec.num_params}d", f"the parameters of camera {camera_id}")
        _add_camera(cameras, ColmapIntrinsics(camera_id, spec.name, width, height, tuple(params)), path)
    reader.finish()
    return cameras


def _read_cameras_txt(path: Path) -> dict[int, ColmapIntrinsics]:
    cameras: dict[int, ColmapIntrinsics] = {}
    for number, line in _text_lines(path):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        items = line.split()
        if len(items) < 4:
            raise CameraFormatError(f"{path}: line {number} is not 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]'")
        spec = _MODEL_BY_NAME.get(items[1])
        if spec is None:
            raise CameraFormatError(f"{path}: line {number} has unknown COLMAP camera model {items[1]!r}")
        if len(items) != 4 + spec.num_params:
            raise CameraFormatError(
                f"{path}: line {number}: model {spec.name} needs {spec.num_params} parameters, got {len(items) - 4}"
            )
        try:
            camera_id, width, height = int(items[0]), int(items[2]), int(items[3])
            params = tuple(float(v) for v in items[4:])
        except ValueError:
            raise CameraFormatError(f"{path}: line {number} has a value that is not a number") from None
        _add_camera(cameras, ColmapIntrinsics(camera_id, spec.name, width, height, params), path)
    return cameras


def _add_camera(cameras: dict[int, ColmapIntrinsics], camera: ColmapIntrinsics, path: Path) -> None:
    if camera.camera_id in cameras:
        raise CameraFormatError(f"{path}: camera id {camera.camera_id} appears twice")
    cameras[camera.camera_id] = camera


def _text_lines(path: Path) -> list[tuple[int, str]]:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise CameraFormatError(f"{path}: not a COLMAP text file (not UTF-8 text)") from None
    except OSError as exc:
        raise CameraFormatError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    return list(enumerate(text.splitlines(), start=1))


def _read_images_bin(path: Path) -> list[_ColmapImage]:
    reader = _Reader(path)
    (count,) = reader.unpack("Q", "the image count")
    images = []
    for index in range(count):
        values = reader.unpack("i7di", f"image {index}")
        name = reader.cstring(f"the name of image {values[0]}")
        (num_points,) = reader.unpack("Q", f"the 2D point count of image {values[0]}")
        reader.skip(24 * num_points, f"the 2D points of image {values[0]}")
        images.append(_ColmapImage(values[0], np.array(values[1:5]), np.array(values[5:8]), values[8], name))
    reader.finish()
    return images


def _read_images_txt(path: Path) -> list[_ColmapImage]:
    """Two lines per image (the second, the 2D points, may be empty); '#' lines are comments."""
    lines = [(n, line) for n, line in _text_lines(path) if not line.lstrip().startswith("#")]
    images = []
    for i in range(0, len(lines), 2):
        number, line = lines[i]
        if not line.strip():
            if all(not rest.strip() for _, rest in lines[i:]):
                break  # trailing blank lines
            raise CameraFormatError(f"{path}: line {number} is empty where an image line was expected")
        items = line.split(maxsplit=9)
        if len(items) != 10:
            raise CameraFormatError(
                f"{path}: line {number} is not 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME'"
            )
        try:
            image_id, camera_id = int(items[0]), int(items[8])
            pose = np.array([float(v) for v in items[1:8]])
        except ValueError:
            raise CameraFormatError(f"{path}: line {number} has a value that is not a number") from None
        images.append(_ColmapImage(image_id, pose[:4], pose[4:], camera_id, items[9].strip()))
    return images


def qvec_to_rotmat(qvec: Sequence[float]) -> np.ndarray:
    """Rotation matrix of a quaternion (w, x, y, z); the quaternion is normalised first."""
    q = np.asarray(qvec, dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not (math.isfinite(norm) and norm > 1e-12):
        raise CameraFormatError(f"quaternion {q.tolist()} has zero or non-finite norm")
    w, x, y, z = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotmat_to_qvec(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (COLMAP's eigenvector method)."""
    (rxx, ryx, rzx), (rxy, ryy, rzy), (rxz, ryz, rzz) = np.asarray(rotation, dtype=np.float64)
    k = np.array(
        [
            [rxx - ryy - rzz, 0, 0, 0],
            [ryx + rxy, ryy - rxx - rzz, 0, 0],
            [rzx + rxz, rzy + ryz, rzz - rxx - ryy, 0],
            [ryz - rzy, rzx - rxz, rxy - ryx, rxx + ryy + rzz],
        ]
    ) / 3.0
    values, vectors = np.linalg.eigh(k)
    q = vectors[[3, 0, 1, 2], np.argmax(values)]
    return -q if q[0] < 0 else q


def read_colmap_cameras(sparse_dir: PathLike) -> dict[int, ColmapIntrinsics]:
    """The intrinsics of a COLMAP model (``cameras.bin``, else ``cameras.txt``), by camera id."""
    path = _colmap_file(Path(sparse_dir), "cameras")
    cameras = _read_cameras_bin(path) if path.suffix == ".bin" else _read_cameras_txt(path)
    if not cameras:
        raise CameraFormatError(f"{path}: contains no cameras")
    return cameras


def read_colmap(
    sparse_dir: PathLike, image_dir: PathLike | None = None, *, allow_distortion: bool = False
) -> list[Camera]:
    """Cameras of a COLMAP sparse model (``cameras.*`` + ``images.*``), sorted by image name.

    Only SIMPLE_PINHOLE and PINHOLE (or other models with all-zero distortion)
    are accepted: distorted models must be undistorted first (``colmap
    image_undistorter``, as the Inria ``convert.py`` does). With
    ``allow_distortion=True`` the distortion is ignored with a warning.
    With ``image_dir``, ``image_path`` is ``image_dir / NAME`` when that file exists.
    """
    sparse_dir = Path(sparse_dir)
    intrinsics = read_colmap_cameras(sparse_dir)
    cameras_path = _colmap_file(sparse_dir, "cameras")
    _check_distortion(intrinsics, cameras_path, allow_distortion)
    images_path = _colmap_file(sparse_dir, "images")
    images = _read_images_bin(images_path) if images_path.suffix == ".bin" else _read_images_txt(images_path)
    if not images:
        raise CameraFormatError(f"{images_path}: contains no images")
    _check_unique([im.image_id for im in images], "image id", images_path)
    _check_unique([im.name for im in images], "image name", images_path)
    directory = Path(image_dir) if image_dir is not None else None
    cameras = []
    for image in sorted(images, key=lambda im: im.name):
        if image.camera_id not in intrinsics:
            raise CameraFormatError(
                f"{images_path}: image {image.name!r} uses camera id {image.camera_id}, "
                f"which {cameras_path.name} does not define"
            )
        cameras.append(_colmap_camera(image, intrinsics[image.camera_id], directory, images_path))
    return cameras


def _check_distortion(intrinsics: dict[int, ColmapIntrinsics], path: Path, allow: bool) -> None:
    distorted = sorted({c.model for c in intrinsics.values() if not c.is_pinhole})
    if not distorted:
        return
    if not allow:
        raise CameraFormatError(
            f"{path}: camera model {', '.join(distorted)} has lens distortion; undistort the images first "
            "(colmap image_undistorter, as the Inria convert.py does) or pass allow_distortion=True"
        )
    warnings.warn(
        f"{path}: ignoring the lens distortion of camera model {', '.join(distorted)}; "
        "renders will not match the distorted images",
        stacklevel=3,
    )


def _check_unique(values: list, what: str, path: Path) -> None:
    seen: set = set()
    for value in values:
        if value in seen:
            raise CameraFormatError(f"{path}: {what} {value!r} appears twice")
        seen.add(value)


def _colmap_camera(image: _ColmapImage, intr: ColmapIntrinsics, directory: Path | None, path: Path) -> Camera:
    fx, fy, cx, cy = intr.pinhole
    image_path = None
    if directory is not None and (directory / image.name).is_file():
        image_path = directory / image.name
    try:
        rotation = qvec_to_rotmat(image.qvec)
        return Camera(image.name, intr.width, intr.height, fx, fy, cx, cy, rotation, image.tvec, image_path)
    except CameraFormatError as exc:
        raise CameraFormatError(f"{path}: image {image.name!r}: {exc}") from None


def _shared_intrinsics(cameras: Sequence[Camera]) -> tuple[list[tuple], list[int]]:
    """Distinct (width, height, fx, fy, cx, cy) in first-use order, and each camera's 1-based id."""
    keys: dict[tuple, int] = {}
    ids = []
    for camera in cameras:
        key = (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)
        ids.append(keys.setdefault(key, len(keys) + 1))
    return list(keys), ids


def _check_writable(sparse_dir: Path, cameras: Sequence[Camera]) -> None:
    if not cameras:
        raise CameraFormatError(f"{sparse_dir}: no cameras to write")
    _check_unique([c.name for c in cameras], "image name", sparse_dir)
    sparse_dir.mkdir(parents=True, exist_ok=True)


def write_colmap_text(sparse_dir: PathLike, cameras: Sequence[Camera]) -> None:
    """Write ``cameras`` as a COLMAP text model (PINHOLE, shared intrinsics, no 2D points).

    Writes ``cameras.txt`` and ``images.txt``, plus an empty ``points3D.txt``
    when none exists, so that COLMAP and the 3DGS loaders accept the folder.
    """
    sparse_dir = Path(sparse_dir)
    _check_writable(sparse_dir, cameras)
    intrinsics, ids = _shared_intrinsics(cameras)
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    for cid, (w, h, fx, fy, cx, cy) in enumerate(intrinsics, start=1):
        lines.append(f"{cid} PINHOLE {w} {h} {fx!r} {fy!r} {cx!r} {cy!r}")
    _atomic_write(sparse_dir / "cameras.txt", ("\n".join(lines) + "\n").encode("utf-8"))
    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
    ]
    for image_id, (camera, cid) in enumerate(zip(cameras, ids), start=1):
        pose = " ".join(repr(float(v)) for v in (*rotmat_to_qvec(camera.R), *camera.t))
        lines += [f"{image_id} {pose} {cid} {camera.name}", ""]
    _atomic_write(sparse_dir / "images.txt", ("\n".join(lines) + "\n").encode("utf-8"))
    if not (sparse_dir / "points3D.txt").exists():
        _atomic_write(sparse_dir / "points3D.txt", b"# 3D point list (empty)\n")


def write_colmap_binary(sparse_dir: PathLike, cameras: Sequence[Camera]) -> None:
    """Write ``cameras`` as a COLMAP binary model (see :func:`write_colmap_text`)."""
    sparse_dir = Path(sparse_dir)
    _check_writable(sparse_dir, cameras)
    intrinsics, ids = _shared_intrinsics(cameras)
    chunks = [struct.pack("<Q", len(intrinsics))]
    for cid, (w, h, fx, fy, cx, cy) in enumerate(intrinsics, start=1):
        chunks.append(struct.pack("<iiQQ4d", cid, 1, w, h, fx, fy, cx, cy))
    _atomic_write(sparse_dir / "cameras.bin", b"".join(chunks))
    chunks = [struct.pack("<Q", len(cameras))]
    for image_id, (camera, cid) in enumerate(zip(cameras, ids), start=1):
        chunks.append(struct.pack("<i7di", image_id, *rotmat_to_qvec(camera.R), *camera.t, cid))
        chunks.append(camera.name.encode("utf-8") + b"\0" + struct.pack("<Q", 0))
    _atomic_write(sparse_dir / "images.bin", b"".join(chunks))
    if not (sparse_dir / "points3D.bin").exists():
        _atomic_write(sparse_dir / "points3D.bin", struct.pack("<Q", 0))


# --------------------------------------------------------------------------- #
# NeRF-synthetic transforms_*.json
# --------------------------------------------------------------------------- #

_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0])
_FRAME_INTRINSICS = ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h")


def read_nerf_transforms(path: PathLike, image_dir: PathLike | None = None) -> list[Camera]:
    """Read a NeRF-synthetic / instant-ngp ``transforms_*.json`` (frame order is kept).

    ``transform_matrix`` is camera-to-world in the OpenGL/Blender convention
    (y up, z backward); the camera y and z axes are flipped to get OpenCV.
    fx comes from ``fl_x`` or ``camera_angle_x``, fy from ``fl_y``,
    ``camera_angle_y`` or fx; the size from ``w``/``h`` or else the first image
    (read with OpenCV). Top-level intrinsics may be overridden per frame.
    ``file_path`` is resolved against ``image_dir`` (default: the JSON's folder);
    a missing extension is searched on disk. Camera names are the file stems.
    """
    path = Path(path)
    data = _load_json(path, "transforms")
    if not isinstance(data, dict):
        raise CameraFormatError(f"{path}: not a NeRF transforms file (expected a JSON object with 'frames')")
    frames = _key(data, "frames", path, "the file")
    if not isinstance(frames, list) or not frames:
        raise CameraFormatError(f"{path}: 'frames' is empty or not a list")
    base = Path(image_dir) if image_dir is not None else path.parent
    size: tuple[int, int] | None = None
    cameras = []
    for index, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise CameraFormatError(f"{path}: frame {index} is not a JSON object")
        where = f"frame {index}"
        file_path = str(_key(frame, "file_path", path, where))
        image_path = _resolve_frame_image(base, file_path)
        params = {k: v for k, v in data.items() if k in _FRAME_INTRINSICS}
        params.update({k: v for k, v in frame.items() if k in _FRAME_INTRINSICS})
        if "w" not in params or "h" not in params:
            if size is None:
                size = _first_image_size(path, image_path, file_path)
            params.setdefault("w", size[0])
            params.setdefault("h", size[1])
        try:
            cameras.append(_nerf_camera(frame, params, image_path, file_path))
        except CameraFormatError as exc:
            raise CameraFormatError(f"{path}: {where}: {exc}") from None
    return cameras


def _resolve_frame_image(base: Path, file_path: str) -> Path | None:
    relative = Path(file_path)
    found = _find_image(base / relative.parent, relative.name)
    if found is None and str(relative.parent) not in ("", "."):
        found = _find_image(base, relative.name)
    return found


def _first_image_size(path: Path, image_path: Path | None, file_path: str) -> tuple[int, int]:
    if image_path is None:
        raise CameraFormatError(
            f"{path}: has no 'w'/'h' keys and its first image {file_path!r} was not found to read the size from"
        )
    return image_size(image_path)


def _nerf_camera(frame: dict, params: dict, image_path: Path | None, file_path: str) -> Camera:
    """One frame's camera; errors are prefixed with the file and frame by the caller."""
    name = _strip_image_extension(Path(file_path).name)
    width = _positive_int(params["w"], "w", name)
    height = _positive_int(params["h"], "h", name)
    if "fl_x" in params:
        fx = _finite_float(params["fl_x"], "fl_x", name)
    elif "camera_angle_x" in params:
        fx = 0.5 * width / math.tan(0.5 * _finite_float(params["camera_angle_x"], "camera_angle_x", name))
    else:
        raise CameraFormatError("there is neither a 'camera_angle_x' nor an 'fl_x' key")
    if "fl_y" in params:
        fy = _finite_float(params["fl_y"], "fl_y", name)
    elif "camera_angle_y" in params:
        fy = 0.5 * height / math.tan(0.5 * _finite_float(params["camera_angle_y"], "camera_angle_y", name))
    else:
        fy = fx
    cx = params.get("cx", width / 2.0)
    cy = params.get("cy", height / 2.0)
    if "transform_matrix" not in frame:
        raise CameraFormatError("there is no 'transform_matrix' key")
    matrix = np.array(frame["transform_matrix"], dtype=object)
    if matrix.shape not in ((4, 4), (3, 4)):
        raise CameraFormatError(f"transform_matrix has shape {matrix.shape}, expected 4x4 or 3x4")
    c2w = _float_array(matrix[:3].tolist(), (3, 4), "transform_matrix", name)
    rotation = c2w[:, :3] @ _OPENGL_TO_OPENCV  # flip the camera y and z axes
    return _from_camera_to_world(name, width, height, fx, fy, cx, cy, rotation, c2w[:, 3], image_path)


# --------------------------------------------------------------------------- #
# LLFF / Mip-NeRF 360 poses_bounds.npy
# --------------------------------------------------------------------------- #


def read_llff_poses(path: PathLike, image_dir: PathLike | None = None) -> list[Camera]:
    """Read an LLFF / Mip-NeRF 360 ``poses_bounds.npy`` (N x 17).

    Each row is a 3x5 matrix ``[R | center | (H, W, f)]`` (camera-to-world, columns
    [down, right, back]) plus near/far bounds; axes are converted to OpenCV
    [right, down, forward]. Rows follow the sorted image names of ``image_dir``
    (default: ``images`` next to the file, when present); the intrinsics are
    scaled from the full-resolution ``hwf`` to the size of the first image
    there. Without images, cameras are named ``00000``... at full resolution.
    """
    path = Path(path)
    _require_file(path, "poses_bounds.npy")
    try:
        data = np.load(path, allow_pickle=False)
    except Exception:  # numpy raises ValueError/OSError/EOFError for non-.npy input
        raise CameraFormatError(f"{path}: not a readable .npy array") from None
    if data.ndim != 2 or data.shape[1] != 17 or data.shape[0] == 0:
        raise CameraFormatError(f"{path}: poses_bounds must have shape (N, 17), got {data.shape}")
    if not np.issubdtype(data.dtype, np.number) or not np.all(np.isfinite(data)):
        raise CameraFormatError(f"{path}: poses_bounds has non-numeric or non-finite values")
    poses = data[:, :15].reshape(-1, 3, 5).astype(np.float64)
    if image_dir is None and (path.parent / "images").is_dir():
        image_dir = path.parent / "images"
    names, paths, size = _llff_images(path, image_dir, len(poses))
    cameras = []
    for index, pose in enumerate(poses):
        full_h, full_w, focal = pose[:, 4]
        width, height = size if size is not None else (int(round(full_w)), int(round(full_h)))
        fx, fy = focal * width / full_w, focal * height / full_h
        c2w = np.stack([pose[:, 1], pose[:, 0], -pose[:, 2]], axis=1)
        try:
            cameras.append(
                _from_camera_to_world(
                    names[index], width, height, fx, fy, width / 2.0, height / 2.0, c2w, pose[:, 3], paths[index]
                )
            )
        except CameraFormatError as exc:
            raise CameraFormatError(f"{path}: row {index}: {exc}") from None
    return cameras


def _llff_images(
    path: Path, image_dir: PathLike | None, count: int
) -> tuple[list[str], list, tuple[int, int] | None]:
    """Image names, paths and (width, height) of the first image, or numbered names when no images."""
    if image_dir is None:
        return [f"{i:05d}" for i in range(count)], [None] * count, None
    directory = Path(image_dir)
    if not directory.is_dir():
        raise CameraFormatError(f"{directory}: no such image directory (for {path.name})")
    suffixes = {ext.lower() for ext in IMAGE_EXTENSIONS}
    files = sorted(p for p in directory.iterdir() if p.is_file() and p.suffix.lower() in suffixes)
    if len(files) != count:
        raise CameraFormatError(f"{path}: has {count} poses but {directory} has {len(files)} images")
    return [p.name for p in files], files, image_size(files[0])


# --------------------------------------------------------------------------- #
# Dispatch, synthetic cameras, split
# --------------------------------------------------------------------------- #

_LOOKED_FOR = (
    "sparse/0/ or a folder with cameras.{bin,txt} + images.{bin,txt} (COLMAP), cameras.json (Inria), "
    "transforms.json or transforms_train.json (NeRF), poses_bounds.npy (LLFF)"
)


def load_cameras(path: PathLike, image_dir: PathLike | None = None, *, allow_distortion: bool = False) -> list[Camera]:
    """Read cameras from any supported file, COLMAP model folder or capture folder.

    Files are recognised by content (.json: a list is Inria, an object with
    ``frames`` is NeRF) or name (``poses_bounds.npy``, ``cameras.*``/``images.*``).
    A capture folder is searched in this order: ``sparse/0``, a COLMAP model in the
    folder itself, ``cameras.json``, ``transforms.json``, ``transforms_train.json``,
    ``poses_bounds.npy``. ``image_dir`` defaults to the capture's ``images`` folder.
    """
    path = Path(path)
    if not path.exists():
        raise CameraFormatError(f"{path}: no such camera file or capture folder")
    if path.is_file():
        return _load_file(path, image_dir, allow_distortion)
    found = _find_in_folder(path)
    if found is None:
        raise CameraFormatError(f"{path}: no cameras found (looked for {_LOOKED_FOR})")
    if image_dir is None and (path / "images").is_dir():
        image_dir = path / "images"
    if found.is_dir():
        return read_colmap(found, image_dir, allow_distortion=allow_distortion)
    return _load_file(found, image_dir, allow_distortion)


def _is_colmap_dir(directory: Path) -> bool:
    def has(stem: str) -> bool:
        return any((directory / f"{stem}{ext}").is_file() for ext in (".bin", ".txt"))

    return directory.is_dir() and has("cameras") and has("images")


def _find_in_folder(folder: Path) -> Path | None:
    for candidate in (folder / "sparse" / "0", folder / "sparse", folder):
        if _is_colmap_dir(candidate):
            return candidate
    for name in ("cameras.json", "transforms.json", "transforms_train.json", "poses_bounds.npy"):
        if (folder / name).is_file():
            return folder / name
    return None


def _load_file(path: Path, image_dir: PathLike | None, allow_distortion: bool) -> list[Camera]:
    if path.suffix == ".npy":
        return read_llff_poses(path, image_dir)
    if path.stem in ("cameras", "images", "points3D") and path.suffix in (".bin", ".txt"):
        return read_colmap(path.parent, image_dir, allow_distortion=allow_distortion)
    if path.suffix.lower() == ".json":
        data = _load_json(path, "camera JSON")
        if isinstance(data, list):
            return read_inria_cameras(path, image_dir)
        if isinstance(data, dict) and "frames" in data:
            return read_nerf_transforms(path, image_dir)
        raise CameraFormatError(
            f"{path}: JSON is neither an Inria cameras.json (a list) nor NeRF transforms (with 'frames')"
        )
    raise CameraFormatError(f"{path}: unrecognised camera file (expected {_LOOKED_FOR})")


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
    return _from_camera_to_world(name, width, height, fx, fy, width / 2.0, height / 2.0, c2w, eye_v)


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
    up_v = up_v / np.linalg.norm(up_v)
    ref = np.eye(3)[int(np.argmin(np.abs(up_v)))]
    e1 = ref - (ref @ up_v) * up_v
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up_v, e1)
    focal = 0.5 * height / math.tan(0.5 * math.radians(fov_y_deg))
    elevation = math.radians(elevation_deg)
    cameras = []
    for i in range(n):
        azimuth = 2.0 * math.pi * i / n
        direction = math.cos(elevation) * (math.cos(azimuth) * e1 + math.sin(azimuth) * e2) + math.sin(elevation) * up_v
        cameras.append(look_at(f"orbit_{i:03d}", center_v + radius * direction, center_v, up_v, width, height, focal))
    return cameras


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
