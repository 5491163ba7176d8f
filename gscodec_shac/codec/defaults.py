"""What plain ``gscodec-shac encode IN OUT.gsc`` uses: SHAC-PCA on the ``shac_ladder`` rate point
chosen from the measured RD of the shared scenes (docs/formats.md, "The default encode").

``shac_ladder:rp5`` with SHAC-PCA at 99% energy retention was the lowest ladder point that is
both smaller than SPZ (splat-transform) from the same model and at least as close to the
uncompressed model on all four shared scenes (bonsai, kacy, plant, playbot); rp4 was smaller
but below SPZ's PSNR on plant. The paper's points stay one flag away (``-r paper_table3:rp2``).
"""

from __future__ import annotations

DEFAULT_RATE_POINT = "shac_ladder:rp5"
DEFAULT_SH_STAGE = "pca"
DEFAULT_STAGE_PARAMS = {"energy_retention": 0.99}


def describe_default() -> str:
    """``shac_ladder:rp5 + SHAC-PCA (ER 0.99)``: the default in words."""
    return f"{DEFAULT_RATE_POINT} + SHAC-PCA (ER {DEFAULT_STAGE_PARAMS['energy_retention']:g})"
