"""Inria 3DGS ``cameras.json``: :func:`read_inria_cameras`, :func:`write_inria_cameras`.

A JSON list with one object per view: ``img_name``, ``width``, ``height``,
``position`` (the camera centre), ``rotation`` (camera-to-world), ``fx``, ``fy``;
the principal point is the image centre. Entries are written by
:meth:`Camera.to_inria_dict <gscodec_shac.camera.Camera.to_inria_dict>`.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Sequence

from gscodec_shac.camera import Camera, from_camera_to_world, positive_int
from gscodec_shac.atomic import write_atomic
from gscodec_shac.errors import CameraFormatError
from gscodec_shac.io.common import find_image, load_json, require_key

PathLike = str | os.PathLike

_INRIA_KEYS = ("img_name", "width", "height", "position", "rotation", "fx", "fy")


def read_inria_cameras(path: PathLike, image_dir: PathLike | None = None) -> list[Camera]:
    """Read an Inria 3DGS ``cameras.json`` (file order is kept).

    ``rotation`` is camera-to-world and ``position`` the camera centre; the
    principal point is the image centre. With ``image_dir``, ``image_path`` is
    ``image_dir / img_name`` plus the extension found on disk, or None.
    """
    path = Path(path)
    data = load_json(path, "cameras.json")
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
        values = {key: require_key(entry, key, path, where) for key in _INRIA_KEYS}
        name = str(values["img_name"])
        try:
            width = positive_int(values["width"], "width", name)
            height = positive_int(values["height"], "height", name)
            cameras.append(
                from_camera_to_world(
                    name, width, height, values["fx"], values["fy"], width / 2.0, height / 2.0,
                    values["rotation"], values["position"], find_image(directory, name),
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
    write_atomic(path, json.dumps(entries).encode("utf-8"), error=CameraFormatError)
