"""What plain ``gscodec-shac encode IN OUT.gsc`` uses, chosen from the measured RD of the shared
scenes (docs/formats.md, "The default encode").

The rate point is ``shac_ladder:rp5``. The SH stage is SHAC-PCA at 99% energy retention,
except for a model whose SH rows are already a palette (at most :data:`PALETTE_SIZE`
distinct rows and fewer than half the Gaussians, as SOG stores them): there vq-pca
(k-means codebook of that size, its codebook coded with SHAC-PCA) keeps the palette almost
exactly for fewer bytes. On bonsai, kacy and plant rp5 + PCA was the lowest ladder point
both smaller than SPZ (splat-transform) from the same model and at least as close to the
uncompressed model (rp4 fell below SPZ's PSNR on plant); on playbot (a SOG) rp5 + PCA was
larger than the SOG and 0.3 dB below SPZ, rp5 + vq-pca smaller than both and above SPZ.
The paper's points stay one flag away (``-r paper_table3:rp2``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

DEFAULT_RATE_POINT = "shac_ladder:rp5"
DEFAULT_SH_STAGE = "pca"
DEFAULT_STAGE_PARAMS: dict[str, Any] = {"energy_retention": 0.99}
#: The codebook size of vq-pca, and the most distinct SH rows a model may have to count as a palette.
PALETTE_SIZE = 65536


def is_sh_palette(cloud: Any) -> bool:
    """True when ``cloud``'s SH rows take at most :data:`PALETTE_SIZE` distinct values, fewer than half
    the Gaussians (a SOG-style palette)."""
    n = cloud.num_gaussians
    if cloud.sh_degree == 0 or n < 2 * PALETTE_SIZE:
        return False
    rows = np.ascontiguousarray(cloud.sh_rest.reshape(n, -1))
    return len(np.unique(rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))))) <= PALETTE_SIZE


def choose_default_sh(cloud: Any) -> tuple[str, dict[str, Any]]:
    """The default SH stage and its parameters for ``cloud`` (see the module docstring)."""
    if is_sh_palette(cloud):
        return "vq-pca", {"n_clusters": PALETTE_SIZE}
    return DEFAULT_SH_STAGE, dict(DEFAULT_STAGE_PARAMS)


def describe_default(stage: str | None = None) -> str:
    """``shac_ladder:rp5 + SHAC-PCA (ER 0.99)``: the default in words (``stage``: the one chosen)."""
    if stage == "vq-pca":
        return f"{DEFAULT_RATE_POINT} + vq-pca (the input's SH is a palette)"
    return f"{DEFAULT_RATE_POINT} + SHAC-PCA (ER {DEFAULT_STAGE_PARAMS['energy_retention']:g})"
