"""Option parsing shared by several commands (not a command itself: the leading underscore
keeps it out of the CLI's command discovery)."""

from __future__ import annotations

import math

from gscodec_shac.errors import GscodecError


def comma_floats(text: str, what: str, count: int = 3) -> list[float]:
    """``"a,b,c"`` -> ``[a, b, c]``: exactly ``count`` finite numbers, else one clear error."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise GscodecError(f"{what} must be {count} comma-separated numbers, got {text!r}")
    return values


def resize_cameras(cameras: list, scale: float | None, width: int | None) -> list:
    """Cameras scaled by ``--scale`` or resized to ``--width`` (aspect kept), else unchanged."""
    if scale is not None:
        if not (math.isfinite(scale) and scale > 0):
            raise GscodecError(f"--scale must be a positive number, got {scale}")
        return [c.scaled(scale) for c in cameras]
    if width is not None:
        if width < 1:
            raise GscodecError(f"--width must be a positive integer, got {width}")
        return [c.resized(width, max(1, round(width * c.height / c.width))) for c in cameras]
    return cameras


def add_force(parser) -> None:
    """``--force``: replace existing outputs (inputs are never written over, even with it)."""
    parser.add_argument("--force", action="store_true",
                        help="replace existing output files (an input is never overwritten, even with --force)")


def check_results_folder(out, force: bool) -> None:
    """A sweep's output folder: absent, empty, or one a sweep wrote (it resumes there); anything
    else (a file, a folder of other files) is refused unless ``--force``."""
    from pathlib import Path

    from gscodec_shac.errors import OutputError

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: the output folder is a file")
    if out.is_dir() and any(out.iterdir()) and not force and not (
        (out / "sweep.json").is_file() or (out / "runs.jsonl").is_file()
    ):
        raise OutputError(f"{out}: the folder holds files but no sweep results (sweep.json); choose another "
                          "--out or pass --force")
