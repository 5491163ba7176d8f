"""COLMAP sparse models, text and binary: cameras (intrinsics) and images (poses).

:func:`read_colmap` returns the :class:`~gscodec_shac.camera.Camera` of every image,
:func:`read_colmap_cameras` the :class:`ColmapIntrinsics` by camera id;
:func:`write_colmap_text` and :func:`write_colmap_binary` write PINHOLE models.
Poses are world-to-camera quaternions (w, x, y, z) plus translations, converted
with :func:`gscodec_shac.geometry.quat_to_rotmat` / :func:`~gscodec_shac.geometry.rotmat_to_quat`.
"""

from __future__ import annotations

import math
import os
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from gscodec_shac.camera import Camera
from gscodec_shac.atomic import write_atomic
from gscodec_shac.errors import CameraFormatError
from gscodec_shac.geometry import quat_to_rotmat, rotmat_to_quat

PathLike = str | os.PathLike


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
    """Rotation matrix of a COLMAP quaternion (w, x, y, z), normalised first; zero or non-finite ones raise."""
    q = np.asarray(qvec, dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not (math.isfinite(norm) and norm > 1e-12):
        raise CameraFormatError(f"quaternion {q.tolist()} has zero or non-finite norm")
    return quat_to_rotmat(q)


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
    write_atomic(sparse_dir / "cameras.txt", ("\n".join(lines) + "\n").encode("utf-8"), error=CameraFormatError)
    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
    ]
    qvecs = rotmat_to_quat(np.stack([c.R for c in cameras]))
    for image_id, (camera, cid, qvec) in enumerate(zip(cameras, ids, qvecs), start=1):
        pose = " ".join(repr(float(v)) for v in (*qvec, *camera.t))
        lines += [f"{image_id} {pose} {cid} {camera.name}", ""]
    write_atomic(sparse_dir / "images.txt", ("\n".join(lines) + "\n").encode("utf-8"), error=CameraFormatError)
    if not (sparse_dir / "points3D.txt").exists():
        write_atomic(sparse_dir / "points3D.txt", b"# 3D point list (empty)\n", error=CameraFormatError)


def write_colmap_binary(sparse_dir: PathLike, cameras: Sequence[Camera]) -> None:
    """Write ``cameras`` as a COLMAP binary model (see :func:`write_colmap_text`)."""
    sparse_dir = Path(sparse_dir)
    _check_writable(sparse_dir, cameras)
    intrinsics, ids = _shared_intrinsics(cameras)
    chunks = [struct.pack("<Q", len(intrinsics))]
    for cid, (w, h, fx, fy, cx, cy) in enumerate(intrinsics, start=1):
        chunks.append(struct.pack("<iiQQ4d", cid, 1, w, h, fx, fy, cx, cy))
    write_atomic(sparse_dir / "cameras.bin", b"".join(chunks), error=CameraFormatError)
    chunks = [struct.pack("<Q", len(cameras))]
    qvecs = rotmat_to_quat(np.stack([c.R for c in cameras]))
    for image_id, (camera, cid, qvec) in enumerate(zip(cameras, ids, qvecs), start=1):
        chunks.append(struct.pack("<i7di", image_id, *qvec, *camera.t, cid))
        chunks.append(camera.name.encode("utf-8") + b"\0" + struct.pack("<Q", 0))
    write_atomic(sparse_dir / "images.bin", b"".join(chunks), error=CameraFormatError)
    if not (sparse_dir / "points3D.bin").exists():
        write_atomic(sparse_dir / "points3D.bin", struct.pack("<Q", 0), error=CameraFormatError)
