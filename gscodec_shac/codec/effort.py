"""How much analysis x265 spends on a scene: the full one for small scenes, the preset's for big ones.

x265's full analysis (RD level 6, :data:`.grid.hevc.FULL_ANALYSIS_PARAMS`) codes bonsai's and the chair's
attribute streams 2-3.7% smaller at equal sample PSNR, for 1.3-3.5x x265's CPU (docs/benchmarks.md,
"The full x265 analysis for small scenes"). The encode takes 2.2x (bonsai, 75k Gaussians: 3.2 -> 7.2 s)
to 2.8x (a 150k synthetic scene: 5.9 -> 16.5 s) as long, so only scenes of up to
:data:`FULL_ANALYSIS_MAX_GAUSSIANS` Gaussians get it; the 1-6M Gaussians of a real capture keep the
preset's analysis. The choice is by the whole scene, so the rate controller's probes
(subsets of it) are analysed as its encodes are (:func:`with_scene_analysis`). A rate point or a caller
that sets the hevc option ``analysis`` itself keeps it.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from gscodec_shac.codec.rate_points import AttributeSpec, RatePoint

#: The hevc codec's ``analysis`` option: the preset's analysis (the long frames streams narrowed, see
#: :data:`.grid.hevc.LONG_STREAM_PARAMS`), or the full one (:data:`.grid.hevc.FULL_ANALYSIS_PARAMS` added
#: to every lossy stream).
ANALYSES = ("preset", "full")
#: Scenes up to this many (input) Gaussians get x265's full analysis.
FULL_ANALYSIS_MAX_GAUSSIANS = 100_000


def scene_analysis(n_gaussians: int) -> str:
    """The hevc ``analysis`` option for a scene of ``n_gaussians``: ``"full"`` when small, else ``"preset"``."""
    return "full" if n_gaussians <= FULL_ANALYSIS_MAX_GAUSSIANS else "preset"


def with_analysis(spec: AttributeSpec, analysis: str) -> AttributeSpec:
    """``spec`` with x265's ``analysis`` when it is a lossy hevc attribute that sets none itself, else ``spec``."""
    if spec.codec != "hevc" or spec.lossless or "analysis" in spec.options:
        return spec
    return dataclasses.replace(spec, options={**spec.options, "analysis": analysis})


def with_scene_analysis(point: RatePoint, n_gaussians: int) -> RatePoint:
    """``point`` with the scene's ``analysis`` set on every lossy hevc attribute that has none, so that
    encodes of parts of the scene (the rate controller's probes) are analysed as the whole scene is."""
    analysis = scene_analysis(n_gaussians)
    attributes = {name: with_analysis(spec, analysis) for name, spec in point.attributes.items()}
    return dataclasses.replace(point, attributes=attributes)
