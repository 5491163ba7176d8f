"""NeRF-synthetic / instant-ngp ``transforms*.json``: :func:`read_nerf_transforms`.

A JSON object with shared intrinsics (``camera_angle_x``, ``fl_x``, ``w``, ...) and a
list of ``frames``, each with a ``file_path`` and a camera-to-world ``transform_matrix``
in the OpenGL/Blender convention (camera y up, z backward).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from gscodec_shac.camera import (
    Camera,
    finite_float,
    float_array,
    from_camera_to_world,
    positive_int,
    strip_image_extension,
)
from gscodec_shac.errors import CameraFormatError
from gscodec_shac.io.common import find_image, image_size, load_json, require_key

PathLike = str | os.PathLike

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
    data = load_json(path, "transforms")
    if not isinstance(data, dict):
        raise CameraFormatError(f"{path}: not a NeRF transforms file (expected a JSON object with 'frames')")
    frames = require_key(data, "frames", path, "the file")
    if not isinstance(frames, list) or not frames:
        raise CameraFormatError(f"{path}: 'frames' is empty or not a list")
    base = Path(image_dir) if image_dir is not None else path.parent
    size: tuple[int, int] | None = None
    cameras = []
    for index, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise CameraFormatError(f"{path}: frame {index} is not a JSON object")
        where = f"frame {index}"
        file_path = str(require_key(frame, "file_path", path, where))
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
    found = find_image(base / relative.parent, relative.name)
    if found is None and str(relative.parent) not in ("", "."):
        found = find_image(base, relative.name)
    return found


def _first_image_size(path: Path, image_path: Path | None, file_path: str) -> tuple[int, int]:
    if image_path is None:
        raise CameraFormatError(
            f"{path}: has no 'w'/'h' keys and its first image {file_path!r} was not found to read the size from"
        )
    return image_size(image_path)


def _nerf_camera(frame: dict, params: dict, image_path: Path | None, file_path: str) -> Camera:
    """One frame's camera; errors are prefixed with the file and frame by the caller."""
    name = strip_image_extension(Path(file_path).name)
    width = positive_int(params["w"], "w", name)
    height = positive_int(params["h"], "h", name)
    if "fl_x" in params:
        fx = finite_float(params["fl_x"], "fl_x", name)
    elif "camera_angle_x" in params:
        fx = 0.5 * width / math.tan(0.5 * _angle(params["camera_angle_x"], "camera_angle_x", name))
    else:
        raise CameraFormatError("there is neither a 'camera_angle_x' nor an 'fl_x' key")
    if "fl_y" in params:
        fy = finite_float(params["fl_y"], "fl_y", name)
    elif "camera_angle_y" in params:
        fy = 0.5 * height / math.tan(0.5 * _angle(params["camera_angle_y"], "camera_angle_y", name))
    else:
        fy = fx
    cx = params.get("cx", width / 2.0)
    cy = params.get("cy", height / 2.0)
    if "transform_matrix" not in frame:
        raise CameraFormatError("there is no 'transform_matrix' key")
    matrix = np.array(frame["transform_matrix"], dtype=object)
    if matrix.shape not in ((4, 4), (3, 4)):
        raise CameraFormatError(f"transform_matrix has shape {matrix.shape}, expected 4x4 or 3x4")
    c2w = float_array(matrix[:3].tolist(), (3, 4), "transform_matrix", name)
    rotation = c2w[:, :3] @ _OPENGL_TO_OPENCV  # flip the camera y and z axes
    return from_camera_to_world(name, width, height, fx, fy, cx, cy, rotation, c2w[:, 3], image_path)


def _angle(value: object, key: str, name: str) -> float:
    """A field of view in radians, strictly between 0 and pi."""
    angle = finite_float(value, key, name)
    if not 0.0 < angle < math.pi:
        raise CameraFormatError(f"camera {name!r}: {key} {angle} is not a field of view in (0, pi) radians")
    return angle
