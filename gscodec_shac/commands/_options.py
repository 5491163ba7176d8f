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
