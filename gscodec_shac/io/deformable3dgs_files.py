"""Where a Deformable-3DGS output folder keeps an iteration's files (no torch; see :mod:`.deformable3dgs`).

``OUT/point_cloud/iteration_N/point_cloud.ply`` and ``OUT/deform/iteration_N/deform.pth``;
``OUT`` means the newest ``N`` of ``point_cloud/``, ``OUT/point_cloud/iteration_N`` (or
``OUT/deform/iteration_N``) that ``N``.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from gscodec_shac.errors import ModelFormatError
from gscodec_shac.io.bounded import member_path

PathLike = str | os.PathLike
PLY_DIR, DEFORM_DIR = "point_cloud", "deform"
PLY_NAME, DEFORM_NAME = "point_cloud.ply", "deform.pth"
_ITERATION = re.compile(r"iteration_(\d+)")


def _iteration(path: Path) -> int | None:
    match = _ITERATION.fullmatch(path.name)
    return int(match.group(1)) if match else None


def locate(path: PathLike) -> tuple[Path, int | None] | None:
    """``(output root, named iteration or None)`` when ``path`` is a Deformable-3DGS output folder
    (one holding ``point_cloud/`` and ``deform/``) or one of its ``iteration_N`` folders; else None."""
    path = Path(path)
    if not path.is_dir():
        return None
    if (path / PLY_DIR).is_dir() and (path / DEFORM_DIR).is_dir():
        return path, None
    number = _iteration(path)
    root = path.parent.parent
    if number is not None and path.parent.name in (PLY_DIR, DEFORM_DIR) and (root / PLY_DIR).is_dir() \
            and (root / DEFORM_DIR).is_dir():
        return root, number
    return None


def is_deformable_output(path: PathLike) -> bool:
    """True for a Deformable-3DGS output folder or one of its ``iteration_N`` folders (no torch needed)."""
    return locate(path) is not None


def iteration_files(path: PathLike) -> tuple[Path, Path, int]:
    """``(point_cloud.ply, deform.pth, N)`` of the chosen iteration (see the module docstring)."""
    found = locate(path)
    if found is None:
        raise ModelFormatError(f"{path}: not a Deformable-3DGS output folder (no {PLY_DIR}/ and {DEFORM_DIR}/)")
    root, number = found
    if number is None:
        saved = sorted(n for n in map(_iteration, (root / PLY_DIR).iterdir())
                       if n is not None and (root / PLY_DIR / f"iteration_{n}" / PLY_NAME).is_file())
        if not saved:
            raise ModelFormatError(f"{root}: no {PLY_DIR}/iteration_N/{PLY_NAME} (nothing saved yet?)")
        number = saved[-1]
    # a file that is a symlink leaving the folder is refused, as in our model directories
    ply = member_path(root, f"{PLY_DIR}/iteration_{number}/{PLY_NAME}", str(root))
    pth = member_path(root, f"{DEFORM_DIR}/iteration_{number}/{DEFORM_NAME}", str(root))
    for file in (ply, pth):
        if not file.is_file():
            have = sorted(n for n in map(_iteration, file.parent.parent.iterdir()) if n is not None)
            raise ModelFormatError(f"{root}: iteration {number} has no {file.relative_to(root)} "
                                   f"(saved iterations there: {have or 'none'})")
    return ply, pth, number
