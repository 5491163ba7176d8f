"""LLFF / Mip-NeRF 360 ``poses_bounds.npy``: :func:`read_llff_poses`.

An (N, 17) array: per image a 3x5 matrix ``[R | center | (H, W, f)]`` (camera-to-world,
columns [down, right, back]) and the near/far bounds, in sorted image-name order.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from gscodec_shac.camera import IMAGE_EXTENSIONS, Camera, from_camera_to_world
from gscodec_shac.errors import CameraFormatError
from gscodec_shac.io.common import image_size, require_file

PathLike = str | os.PathLike


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
    require_file(path, "poses_bounds.npy")
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
                from_camera_to_world(
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
