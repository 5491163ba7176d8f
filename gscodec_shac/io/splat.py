"""Read and write antimatter15 ``.splat`` files.

Layout: no header; one 32-byte little-endian record per Gaussian::

    position  3 x float32
    scale     3 x float32, linear (exp of the log-scale)
    colour    4 x u8: R, G, B = (0.5 + SH_C0 * f_dc) * 255, A = sigmoid(opacity) * 255
    rotation  4 x u8: w, x, y, z of the unit quaternion * 128 + 128

What .splat loses: all SH above the DC term (the writer notes the degree dropped), 8-bit
colour (DC clipped to the displayable [0, 1]) and alpha, rotations to ~1/128 per
component, extra properties; positions and scales are float32 and kept. Alpha 0 or 255
reads as an infinite logit, clamped with a note; a zero scale reads as a tiny one.
Records are written in the cloud's order (antimatter15's converter sorts by size x
opacity; viewers do not need it).
"""

from __future__ import annotations

import os

import numpy as np

from gscodec_shac.atomic import write_atomic
from gscodec_shac.errors import ModelFormatError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.bounded import READ_COPIES, check_memory, cloud_bytes, read_file
from gscodec_shac.io.model_common import (
    SH_C0, check_rows, logits_from_alpha, note, sigmoid, to_uint8, unit_quats, zero_sh_rest,
)
from gscodec_shac.limits import MAX_GAUSSIANS, memory_budget

RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])
#: The smallest linear scale a reader accepts; zero scales become this.
MIN_SCALE = 1e-12


def read_splat(path: str | os.PathLike) -> GaussianCloud:
    """Read a ``.splat`` file into a :class:`GaussianCloud` (SH degree 0)."""
    data = read_file(path, memory_budget(), ".splat")
    if len(data) % RECORD.itemsize:
        raise ModelFormatError(f"{path}: not a .splat file ({len(data):,} bytes is not a multiple of 32)")
    if len(data) // RECORD.itemsize > MAX_GAUSSIANS:
        raise ModelFormatError(f"{path}: {len(data) // RECORD.itemsize:,} records (at most {MAX_GAUSSIANS:,} Gaussians)")
    check_memory(str(path), READ_COPIES * cloud_bytes(len(data) // RECORD.itemsize, 0), "reading the records")
    records = np.frombuffer(data, dtype=RECORD)
    n = records.shape[0]
    check_rows(path, n, ".splat file")
    means, scale = records["position"], records["scale"].astype(np.float64)
    for name, values in (("positions", means), ("scales", scale)):
        bad = int(np.sum(~np.isfinite(values)))
        if bad:
            raise ModelFormatError(f"{path}: {bad:,} {name} value(s) are NaN or infinite")
    if np.any(scale < 0):
        raise ModelFormatError(f"{path}: {int(np.sum(scale < 0)):,} scale value(s) are negative")
    tiny = int(np.sum(scale < MIN_SCALE))
    if tiny:
        note(f"{path}: {tiny:,} scale value(s) below {MIN_SCALE:g} (zero) read as {MIN_SCALE:g}")
    rgba = records["rgba"].astype(np.float64) / 255.0
    quats = (records["rotation"].astype(np.float64) - 128.0) / 128.0
    return GaussianCloud(
        means=np.array(means, dtype=np.float32),
        scales=np.log(np.maximum(scale, MIN_SCALE)),
        quats=unit_quats(quats),
        opacities=logits_from_alpha(rgba[:, 3], path),
        sh_dc=(rgba[:, :3] - 0.5) / SH_C0,
        sh_rest=zero_sh_rest(n),
    )


def write_splat(path: str | os.PathLike, cloud: GaussianCloud) -> None:
    """Write ``cloud`` as a ``.splat`` file (DC colour only), atomically."""
    n = cloud.num_gaussians
    if cloud.sh_degree:
        note(f"{path}: .splat holds no SH; the degree-{cloud.sh_degree} AC coefficients are dropped")
    if cloud.extra:
        note(f"{path}: .splat has no place for extra properties; dropped {', '.join(cloud.extra)}")
    scales = np.exp(cloud.scales.astype(np.float64))
    if np.any(scales > np.finfo(np.float32).max):
        raise ModelFormatError(f"{path}: log-scales above {np.log(np.finfo(np.float32).max):.1f} overflow float32")
    records = np.empty(n, dtype=RECORD)
    records["position"] = cloud.means
    records["scale"] = scales
    records["rgba"][:, :3] = to_uint8((0.5 + SH_C0 * cloud.sh_dc.astype(np.float64)) * 255.0)
    records["rgba"][:, 3] = to_uint8(sigmoid(cloud.opacities) * 255.0)
    records["rotation"] = to_uint8(unit_quats(cloud.quats) * 128.0 + 128.0)
    write_atomic(path, records.tobytes(), error=ModelFormatError)
