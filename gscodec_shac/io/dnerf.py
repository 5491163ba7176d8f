"""D-NeRF scenes: ``transforms_{train,val,test}.json`` whose frames carry a ``time``.

The files are NeRF-synthetic transforms (:func:`gscodec_shac.io.nerf.read_nerf_transforms`
reads the cameras) plus one number per frame, ``time`` in [0, 1], the instant the frame shows.
:func:`read_dnerf_frames` returns ``(camera, time)`` pairs in file order and refuses, with
one message naming the file and frame, a frame without a finite ``time``, a frame whose
image file is absent, and images of different sizes within a split.
:func:`read_dnerf_scene` reads the train and test splits (``val`` is not used, as the
reference) and resizes the cameras by ``resolution_scale``. Images are read by the trainer
(:mod:`gscodec_shac.train.dynamic`), RGBA composited over its background (black by default).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

from gscodec_shac.camera import Camera
from gscodec_shac.errors import CameraFormatError
from gscodec_shac.io.common import image_size, load_json
from gscodec_shac.io.nerf import read_nerf_transforms

PathLike = str | os.PathLike


@dataclass(frozen=True)
class DnerfFrame:
    """One frame of a D-NeRF split: its camera (with the image path) and its time."""

    camera: Camera
    time: float


def is_dnerf_scene(root: PathLike) -> bool:
    """True when ``root/transforms_train.json`` exists and its first frame has a ``time``."""
    path = Path(root) / "transforms_train.json"
    if not path.is_file():
        return False
    try:
        data = load_json(path, "D-NeRF transforms")
        return isinstance(data, dict) and bool(data.get("frames")) and "time" in data["frames"][0]
    except (CameraFormatError, TypeError, KeyError, IndexError):
        return False


def read_dnerf_frames(path: PathLike, *, check_sizes: bool = True) -> list[DnerfFrame]:
    """The frames of one ``transforms_*.json`` (see the module docstring)."""
    path = Path(path)
    cameras = read_nerf_transforms(path)
    frames_json = load_json(path, "D-NeRF transforms")["frames"]
    out: list[DnerfFrame] = []
    size: tuple[int, int] | None = None
    for index, (camera, frame) in enumerate(zip(cameras, frames_json)):
        where = f"{path}: frame {index} ({frame.get('file_path', '?')!r})"
        if "time" not in frame:
            raise CameraFormatError(f"{where} has no 'time' key (a D-NeRF frame needs the instant it shows)")
        value = frame["time"]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
            raise CameraFormatError(f"{where}: 'time' must be a finite number, got {value!r}")
        if camera.image_path is None:
            raise CameraFormatError(f"{where}: the image file is absent")
        if check_sizes:
            this = image_size(camera.image_path)
            if size is None:
                size = this
            elif this != size:
                raise CameraFormatError(
                    f"{where}: image {camera.image_path.name} is {this[0]}x{this[1]}, the split's first image is "
                    f"{size[0]}x{size[1]} (all frames must have one size)"
                )
            if (camera.width, camera.height) != this:
                camera = camera.resized(*this)
        out.append(DnerfFrame(camera, float(value)))
    return out


def read_dnerf_scene(
    root: PathLike, resolution_scale: float = 1.0, splits: tuple[str, ...] = ("train", "test")
) -> dict[str, list[DnerfFrame]]:
    """``{split: frames}`` with cameras scaled by ``resolution_scale`` (0.5 = 400x400 for D-NeRF)."""
    root = Path(root)
    if not root.is_dir():
        raise CameraFormatError(f"{root}: no such D-NeRF scene folder")
    if not (math.isfinite(resolution_scale) and resolution_scale > 0):
        raise CameraFormatError(f"--resolution-scale must be a positive number, got {resolution_scale}")
    out: dict[str, list[DnerfFrame]] = {}
    for split in splits:
        frames = read_dnerf_frames(root / f"transforms_{split}.json")
        scaled = []
        for f in frames:
            w = max(1, round(f.camera.width * resolution_scale))
            h = max(1, round(f.camera.height * resolution_scale))
            scaled.append(DnerfFrame(f.camera.resized(w, h), f.time))
        out[split] = scaled
    return out


def read_dnerf_cameras(path: PathLike) -> list[DnerfFrame]:
    """Frames of a transforms file for rendering: images need not exist (their size comes from the first
    one found or from ``w``/``h``); ``time`` is still required."""
    path = Path(path)
    cameras = read_nerf_transforms(path)
    frames_json = load_json(path, "D-NeRF transforms")["frames"]
    out = []
    for index, (camera, frame) in enumerate(zip(cameras, frames_json)):
        value = frame.get("time")
        if value is None:
            raise CameraFormatError(f"{path}: frame {index} has no 'time' key; pass --time")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
            raise CameraFormatError(f"{path}: frame {index}: 'time' must be a finite number, got {value!r}")
        out.append(DnerfFrame(camera, float(value)))
    return out
