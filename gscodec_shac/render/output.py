"""Writing rendered images: 8-bit PNGs of images clipped to [0, 1]."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from gscodec_shac.atomic import write_atomic
from gscodec_shac.errors import GscodecError

_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Float image -> uint8, clipped to [0, 1] and rounded to the nearest level."""
    return (np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def save_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write an (H, W, 3) RGB float image as an 8-bit PNG (clipped); returns the path."""
    import cv2

    path = Path(path)
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise GscodecError(f"{path}: expected an (H, W, 3) RGB image, got shape {image.shape}")
    ok, encoded = cv2.imencode(".png", to_uint8(image)[:, :, ::-1])
    if not ok:
        raise GscodecError(f"{path}: could not encode the PNG")
    return write_atomic(path, encoded.tobytes())


def png_name(camera_name: str, index: int) -> str:
    """A safe file name for a view: the camera name without an image extension, else the index."""
    stem = Path(camera_name).stem if Path(camera_name).suffix.lower() in {".png", ".jpg", ".jpeg"} else camera_name
    stem = _UNSAFE.sub("_", stem).strip("._")
    return f"{stem or f'view_{index:05d}'}.png"


def png_names(camera_names: list[str]) -> list[str]:
    """:func:`png_name` for every view, made unique: a name seen before gets its index appended
    (NeRF-synthetic train and test views share names such as ``r_0``; no view overwrites another)."""
    names, used = [], set()
    for index, camera_name in enumerate(camera_names):
        name = png_name(camera_name, index)
        if name in used:
            name = f"{name[:-4]}_{index:05d}.png"
        used.add(name)
        names.append(name)
    return names
