"""Deployed formats through PlayCanvas ``splat-transform`` (npm): SPZ and SOG, and conversions.

The tool is found, in order, at ``$GSCODEC_SHAC_SPLAT_TRANSFORM`` (a path), as
``splat-transform`` on ``PATH``, or in the npm cache folder
``$GSCODEC_SHAC_NPM_PREFIX`` (default ``~/.cache/gscodec-shac/npm``), where it is
installed, outside any repository, with::

    npm install --prefix ~/.cache/gscodec-shac/npm @playcanvas/splat-transform

It needs ``node`` (18+). The sweep never installs it; without it the SPZ/SOG runs are
recorded as skipped with that command as the reason. SOG is written on the CPU
(``-g cpu``); reading back to PLY uses the same tool, so the decoded model is what a
PlayCanvas viewer would show.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import zipfile
from pathlib import Path

from gscodec_shac.errors import CodecUnavailableError, GscodecError

PACKAGE = "@playcanvas/splat-transform"
INSTALL_HINT = f"npm install --prefix ~/.cache/gscodec-shac/npm {PACKAGE}"

#: SOG bundle members -> our attribute names (``sh0`` holds DC colour and opacity).
SOG_MEMBERS = {"means": "positions", "quats": "rotation", "scales": "scale", "sh0": "sh_dc+opacity",
               "shN": "sh", "meta": "header"}


class ExternalToolError(GscodecError):
    """splat-transform ran but failed."""


def npm_prefix() -> Path:
    return Path(os.environ.get("GSCODEC_SHAC_NPM_PREFIX", Path.home() / ".cache" / "gscodec-shac" / "npm"))


def find_splat_transform() -> Path | None:
    """The ``splat-transform`` executable, or None."""
    explicit = os.environ.get("GSCODEC_SHAC_SPLAT_TRANSFORM")
    if explicit:
        return Path(explicit) if Path(explicit).is_file() else None
    on_path = shutil.which("splat-transform")
    if on_path:
        return Path(on_path)
    cached = npm_prefix() / "node_modules" / ".bin" / "splat-transform"
    return cached if cached.exists() else None


def unavailable_reason() -> str | None:
    """Why SPZ/SOG cannot run here, or None when they can."""
    if shutil.which("node") is None:
        return "node is not installed (SPZ/SOG need node 18+ and " + PACKAGE + ")"
    if find_splat_transform() is None:
        return f"{PACKAGE} is not installed; install it with: {INSTALL_HINT}"
    return None


def require_splat_transform() -> Path:
    reason = unavailable_reason()
    if reason is not None:
        raise CodecUnavailableError(reason)
    return find_splat_transform()  # type: ignore[return-value]


def splat_transform(*args: str | os.PathLike, timeout: float = 3600.0) -> str:
    """Run ``splat-transform -w -q ARGS``; returns stdout, raises :class:`ExternalToolError` on failure."""
    tool = require_splat_transform()
    command = [str(tool), "-w", "-q", *(str(a) for a in args)]
    try:
        result = subprocess.run(command, capture_output=True, text=True, timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        raise ExternalToolError(f"splat-transform timed out after {timeout:.0f} s: {' '.join(command[1:])}") from None
    if result.returncode != 0:
        tail = (result.stderr or result.stdout).strip().splitlines()[-1:] or ["no output"]
        raise ExternalToolError(f"splat-transform failed ({result.returncode}): {tail[0][:300]}")
    return result.stdout


def tool_version() -> str | None:
    tool = find_splat_transform()
    if tool is None:
        return None
    try:
        out = subprocess.run([str(tool), "--version"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return None
    return (out.stdout or out.stderr).strip().splitlines()[0] if (out.stdout or out.stderr).strip() else None


def convert_to_ply(source: str | os.PathLike, target: str | os.PathLike) -> Path:
    """Any input splat-transform reads (meta.json, .sog, .spz, .splat, ...) -> an Inria PLY."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    splat_transform(source, target)
    if not target.is_file():
        raise ExternalToolError(f"splat-transform wrote no {target}")
    return target


def encode_spz(ply: str | os.PathLike, out: str | os.PathLike, version: int = 4) -> Path:
    """PLY -> Niantic SPZ (``--spz-version``)."""
    splat_transform("--spz-version", str(version), ply, out)
    return Path(out)


def encode_sog(ply: str | os.PathLike, out: str | os.PathLike, iterations: int = 10, workers: int = 1) -> Path:
    """PLY -> bundled PlayCanvas SOG (``.sog``) on the CPU (``-g cpu``)."""
    splat_transform("-g", "cpu", "-i", str(iterations), "--max-workers", str(workers), ply, out)
    return Path(out)


#: Finite stand-in for an infinite opacity logit (8-bit alpha 0 or 255): sigmoid(20) = 1 - 2e-9.
OPACITY_LOGIT_LIMIT = 20.0


def read_decoded_ply(path: str | os.PathLike):
    """``(cloud, n_clamped)``: a PLY written by splat-transform, infinite opacity logits clamped.

    SPZ stores opacity as 8-bit alpha, so fully opaque (255) or transparent (0) Gaussians
    come back with logits of +-inf; they are set to +-:data:`OPACITY_LOGIT_LIMIT`, which
    renders the same. Any other non-finite value is an error.
    """
    import numpy as np
    from plyfile import PlyData

    from gscodec_shac.io.ply import read_ply

    data = PlyData.read(str(path), mmap=False)  # not memory-mapped: the file may be rewritten below
    vertex = data["vertex"].data
    clamped = 0
    if "opacity" in (vertex.dtype.names or ()):
        opacity = vertex["opacity"]
        infinite = np.isinf(opacity)
        clamped = int(infinite.sum())
        if clamped:
            vertex["opacity"] = np.where(infinite, np.sign(opacity) * OPACITY_LOGIT_LIMIT, opacity)
            data.write(str(path))
    return read_ply(path), clamped


def sog_member_sizes(path: str | os.PathLike) -> dict[str, int]:
    """Compressed bytes per attribute of a bundled ``.sog`` (a zip of WebP planes and meta.json)."""
    sizes: dict[str, int] = {}
    with zipfile.ZipFile(path) as bundle:
        for info in bundle.infolist():
            stem = Path(info.filename).stem.split("_")[0]
            name = SOG_MEMBERS.get(stem, "other")
            sizes[name] = sizes.get(name, 0) + info.compress_size
    total = Path(path).stat().st_size
    sizes["container"] = total - sum(sizes.values())
    return sizes
