"""A cloud with a few rows moved, rendered from the cloud's prepared frame (gscodec_shac.render.moved):
the same images as fresh renders, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from gscodec_shac.render import Renderer
from gscodec_shac.render.variants import FrameVariants
from gscodec_shac.synthetic import make_synthetic_scene


@pytest.fixture(scope="module")
def scene():
    return make_synthetic_scene(3_000, seed=7, n_cameras=3, width=80, height=60)


def _moved(cloud, rows, rng, what):
    """``cloud`` with ``what`` of its ``rows`` changed (as a decoded attribute would be)."""
    changes = {}
    if "means" in what:
        changes["means"] = cloud.means.copy()
        changes["means"][rows] += rng.normal(0.0, 0.05, (rows.size, 3)).astype(np.float32)
    if "scales" in what:
        changes["scales"] = cloud.scales.copy()
        changes["scales"][rows] += rng.normal(0.0, 0.3, (rows.size, 3)).astype(np.float32)
    if "quats" in what:
        changes["quats"] = cloud.quats.copy()
        changes["quats"][rows] += rng.normal(0.0, 0.2, (rows.size, 4)).astype(np.float32)
    if "opacities" in what:
        changes["opacities"] = cloud.opacities.copy()
        changes["opacities"][rows] += rng.normal(0.0, 1.5, rows.size).astype(np.float32)
    return cloud.replace(**changes)


@pytest.mark.parametrize("what", [("scales",), ("quats",), ("opacities",), ("means", "scales", "quats", "opacities")])
@pytest.mark.parametrize("share", [0.0, 0.02, 0.3, 1.0])
@pytest.mark.parametrize("reserve", [False, True])
def test_moved_rows_render_as_a_fresh_renderer(scene, what, share, reserve):
    rng = np.random.default_rng(3)
    cloud = scene.cloud
    rows = np.flatnonzero(rng.random(cloud.num_gaussians) < share)
    moved = _moved(cloud, rows, rng, what)
    part = Renderer(moved.select(rows))
    renderer = Renderer(cloud)
    for background in ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)):
        for camera in scene.cameras:
            variants = FrameVariants(renderer, camera, background, moved_rows=rows.size if reserve else 0)
            image = variants.moved(rows, part)
            fresh = Renderer(moved).render(camera, background=background).image
            assert np.array_equal(image, fresh)


def test_a_run_of_rows_moves_only_the_tiles_it_touches(scene):
    """A run along the cloud (as the rate controller's probe is) changes a part of the image only,
    and the rest is the cloud's own image."""
    rng = np.random.default_rng(5)
    cloud = scene.cloud
    rows = np.arange(1000, 1100)
    moved = _moved(cloud, rows, rng, ("scales", "quats"))
    camera = scene.cameras[0]
    variants = FrameVariants(Renderer(cloud), camera)
    reference = variants.image()
    image = variants.moved(rows, Renderer(moved.select(rows)), reference)
    assert np.array_equal(image, Renderer(moved).render(camera).image)
    changed = np.any(image != reference, axis=2)
    assert 0 < np.count_nonzero(changed) < changed.size


def test_the_part_must_hold_one_gaussian_per_row_in_row_order(scene):
    cloud = scene.cloud
    variants = FrameVariants(Renderer(cloud), scene.cameras[0])
    with pytest.raises(ValueError, match="moved Gaussians"):
        variants.moved(np.arange(10), Renderer(cloud.select(np.arange(5))))
    with pytest.raises(ValueError, match="ascending"):
        variants.moved(np.array([3, 1, 2]), Renderer(cloud.select(np.array([3, 1, 2]))))


def test_a_schedule_of_some_tiles_deals_each_of_them_once():
    from gscodec_shac.render import raster

    lengths = np.array([0, 500, 3, 3, 900, 0, 40, 41, 7, 600])
    tile_start = np.concatenate([[0], np.cumsum(lengths)])
    for only in (np.array([1, 4, 9]), np.array([5]), np.array([], dtype=np.int64)):
        tiles, worker_start = raster.tile_schedule(tile_start, 2, only)
        assert np.array_equal(np.sort(tiles), only) and worker_start[-1] == only.size


def test_reserved_rows_take_the_moved_parameter_rows_without_a_copy_of_the_frames(scene):
    cloud = scene.cloud
    renderer = Renderer(cloud)
    rows = np.arange(cloud.num_gaussians)  # every Gaussian moved: no culled rows leave room
    part_pack = np.ones((rows.size, renderer._workspace().pack.shape[1]))
    plain = FrameVariants(renderer, scene.cameras[0]).pack_with(part_pack)
    assert not np.shares_memory(plain, renderer._workspace().pack)
    variants = FrameVariants(renderer, scene.cameras[0], moved_rows=rows.size)
    reserved = variants.pack_with(part_pack)
    assert np.shares_memory(reserved, renderer._workspace().pack)
    assert np.array_equal(reserved, plain)


def test_a_frames_parameter_rows_hold_no_stale_memory():
    """The packs' padding column is zero, not what the allocator's last owner left there (a frame's
    rows then compare equal wherever they are packed: the test above failed on a reused heap block)."""
    from gscodec_shac.render.projection import PACK_WIDTH

    small = make_synthetic_scene(200, seed=3, n_cameras=1, width=48, height=32)
    for _ in range(3):
        junk = np.full((small.cloud.num_gaussians, PACK_WIDTH), np.nan)
        del junk  # a block of this size, full of NaN, back to the allocator
        renderer = Renderer(small.cloud)
        frame = renderer.prepare(small.cameras[0])
        assert frame.bins.pack.shape[0] > 0
        assert np.all(frame.bins.pack[:, PACK_WIDTH - 1] == 0)
        assert np.all(renderer._workspace().pack_n[:, PACK_WIDTH - 1] == 0)
