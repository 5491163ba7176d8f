"""Compile (or load from numba's on-disk cache) every kernel of the renderer up front: :func:`warmup`."""

from __future__ import annotations

import time

import numpy as np

from gscodec_shac.camera import look_at
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.render.key_sort import sort_depth_keys
from gscodec_shac.render.renderer import Renderer
from gscodec_shac.render.variants import FrameVariants


def warmup() -> float:
    """Render a tiny scene (image, depth, weights, contributions), then reach the kernels such a render
    does not: the radix depth sort (numpy sorts short key arrays) and the moved-row merge of the rate
    controller's calibration renders. Returns the seconds it took."""
    start = time.perf_counter()
    rng = np.random.default_rng(0)
    n = 8
    cloud = GaussianCloud(
        means=rng.normal(0.0, 0.3, (n, 3)), scales=np.full((n, 3), -2.0), quats=rng.normal(size=(n, 4)),
        opacities=np.full(n, 2.0), sh_dc=rng.normal(size=(n, 3)), sh_rest=rng.normal(0, 0.1, (n, 15, 3)),
    )
    camera = look_at("warmup", np.array([0.0, -3.0, 0.5]), np.zeros(3), np.array([0.0, 0.0, 1.0]), 24, 20, 30.0)
    renderer = Renderer(cloud)
    renderer.render(camera, depth=True)
    renderer.weights(camera)
    renderer.contributions(camera)
    sort_depth_keys(np.arange(64, 0, -1, dtype=np.uint64) << np.uint64(32), min_radix=0)
    rows = np.arange(2)
    moved = cloud.select(rows)
    FrameVariants(renderer, camera, moved_rows=rows.size).moved(rows, Renderer(moved.replace(means=moved.means + 0.05)))
    return time.perf_counter() - start
