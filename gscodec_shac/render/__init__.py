"""CPU rasteriser for 3D Gaussian Splatting with the math of the reference CUDA rasteriser.

Public API::

    from gscodec_shac.render import Renderer, render, render_views, render_weights, warmup

    result = render(cloud, camera, background=(0, 0, 0))   # RenderResult: image, alpha, depth, counts
    renderer = Renderer(cloud)                             # caches covariances / opacities
    images = [renderer.render(cam).image for cam in cameras]
    W, T = render_weights(cloud, camera)                   # image = W @ colours + T * background

Modules: :mod:`.projection` (EWA projection, pixel convention), :mod:`.shading` (SH colours),
:mod:`.binning` (depth sort + tile lists), :mod:`.raster` (per-pixel blending),
:mod:`.renderer` (the API), :mod:`.kernel_warmup` (every kernel compiled up front),
:mod:`.reference` (a dense every-pixel-every-Gaussian version for tests), :mod:`.output` (PNG
writing). Kernels are numba-compiled with ``cache=True``; the first call in a fresh environment
compiles them (:func:`warmup` does it up front).

Importing this package sets ``OMP_WAIT_POLICY=PASSIVE`` unless the variable is already set
(:mod:`gscodec_shac.openmp`): numba's OpenMP threads then sleep between the renderer's parallel regions.
"""

import gscodec_shac.openmp  # noqa: F401

from gscodec_shac.render.output import save_png, to_uint8  # noqa: E402
from gscodec_shac.render.projection import BLOCK  # noqa: E402
from gscodec_shac.render.renderer import (  # noqa: E402
    Frame,
    Renderer,
    RenderResult,
    gaussian_colors,
    render,
    render_views,
    render_weights,
)
from gscodec_shac.render.kernel_warmup import warmup  # noqa: E402

__all__ = [
    "BLOCK",
    "Frame",
    "RenderResult",
    "Renderer",
    "gaussian_colors",
    "render",
    "render_views",
    "render_weights",
    "save_png",
    "to_uint8",
    "warmup",
]
