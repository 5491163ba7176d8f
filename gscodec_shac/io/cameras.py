"""Cameras from any supported capture file or folder: :func:`load_cameras`.

The formats have one module each, all returning ``list[Camera]``
(:class:`gscodec_shac.camera.Camera`):

* Inria 3DGS ``cameras.json`` (:mod:`.inria_cameras`);
* COLMAP sparse models, text and binary (:mod:`.colmap`);
* NeRF-synthetic ``transforms_*.json`` (:mod:`.nerf`);
* LLFF / Mip-NeRF 360 ``poses_bounds.npy`` (:mod:`.llff`).

Every unusable input raises :class:`CameraFormatError` with one sentence naming
the file and the problem.
"""

from __future__ import annotations

import os
from pathlib import Path

from gscodec_shac.camera import Camera
from gscodec_shac.errors import CameraFormatError
from gscodec_shac.io.colmap import read_colmap
from gscodec_shac.io.common import load_json
from gscodec_shac.io.inria_cameras import read_inria_cameras
from gscodec_shac.io.llff import read_llff_poses
from gscodec_shac.io.nerf import read_nerf_transforms

PathLike = str | os.PathLike

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
        data = load_json(path, "camera JSON")
        if isinstance(data, list):
            return read_inria_cameras(path, image_dir)
        if isinstance(data, dict) and "frames" in data:
            return read_nerf_transforms(path, image_dir)
        raise CameraFormatError(
            f"{path}: JSON is neither an Inria cameras.json (a list) nor NeRF transforms (with 'frames')"
        )
    raise CameraFormatError(f"{path}: unrecognised camera file (expected {_LOOKED_FOR})")
