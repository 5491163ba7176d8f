"""The renderer's depth sort (gscodec_shac.render.key_sort): the same keys as numpy's sort, and the same images."""

from __future__ import annotations

import numpy as np
import pytest

from gscodec_shac.render import Renderer
from gscodec_shac.render import key_sort
from gscodec_shac.render.projection import NO_KEY
from gscodec_shac.synthetic import make_synthetic_scene


def _keys(depths: np.ndarray) -> np.ndarray:
    """Projection-style keys: float32 depth bits in the high word, the index in the low one."""
    bits = depths.astype(np.float32).view(np.uint32).astype(np.uint64)
    return (bits << np.uint64(32)) | np.arange(depths.size, dtype=np.uint64)


def _sorted(keys: np.ndarray) -> np.ndarray:
    out = keys.copy()
    key_sort.sort_depth_keys(out)
    return out


@pytest.mark.parametrize("n", [key_sort.MIN_RADIX, 100_003])
def test_radix_sort_equals_numpy_sort_with_ties_and_culled_keys(n):
    rng = np.random.default_rng(n)
    depths = rng.uniform(0.2, 80.0, n)
    depths[rng.random(n) < 0.1] = 3.0  # equal depths: the index decides, as in a full sort
    keys = _keys(depths)
    keys[rng.random(n) < 0.2] = NO_KEY  # culled Gaussians sort last
    assert np.array_equal(_sorted(keys), np.sort(keys))


@pytest.mark.parametrize("low, high", [(1.0, 1.9), (1.0, 1.0 + 1e-6), (0.01, 1e6)])
def test_radix_sort_skips_constant_digits_and_still_sorts(low, high):
    # depths within one octave leave the top digits constant (passes skipped, so an even or odd
    # number of passes runs and the result must come back to the caller's array either way)
    rng = np.random.default_rng(1)
    keys = _keys(rng.uniform(low, high, 50_000))
    assert np.array_equal(_sorted(keys), np.sort(keys))


def test_small_arrays_take_numpys_sort():
    keys = _keys(np.array([3.0, 1.0, 2.0]))
    assert np.array_equal(_sorted(keys), np.sort(keys))


def test_images_are_those_of_numpys_sort(monkeypatch):
    scene = make_synthetic_scene(40_000, seed=4, n_cameras=2, width=96, height=72)
    cloud, views = scene.cloud, scene.cameras
    assert cloud.num_gaussians >= key_sort.MIN_RADIX
    radix = [Renderer(cloud).render(v).image for v in views]
    monkeypatch.setattr(key_sort, "MIN_RADIX", 10 ** 9)  # every sort by numpy
    plain = [Renderer(cloud).render(v).image for v in views]
    assert all(np.array_equal(a, b) for a, b in zip(radix, plain))
