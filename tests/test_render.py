"""The CPU rasteriser against the dense reference, culling, blending semantics, weights, CLI."""

from __future__ import annotations

import numpy as np
import pytest

from gscodec_shac import sh
from gscodec_shac.camera import Camera, look_at
from gscodec_shac.errors import ValidationError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.render import Renderer, render, render_views, render_weights, warmup
from gscodec_shac.render.reference import render_reference
from gscodec_shac.render.shading import view_colors

TOL = 1e-4


def random_cloud(rng: np.random.Generator, n: int, degree: int, *, spread: float = 1.0) -> GaussianCloud:
    """Anisotropic, rotated, overlapping Gaussians around the origin with mixed opacities."""
    k = (degree + 1) ** 2 - 1
    return GaussianCloud(
        means=rng.uniform(-spread, spread, (n, 3)),
        scales=np.log(rng.uniform(0.02, 0.35, (n, 3))),
        quats=rng.normal(size=(n, 4)),
        opacities=rng.normal(0.5, 2.5, n),
        sh_dc=rng.normal(0.0, 1.0, (n, 3)),
        sh_rest=rng.normal(0.0, 0.3, (n, k, 3)),
    )


def off_centre_camera(name: str, eye, width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> Camera:
    base = look_at(name, eye, np.zeros(3), np.array([0.0, 0.0, 1.0]), width, height, fx)
    return Camera(name, width, height, fx, fy, cx, cy, base.R, base.t)


def cameras() -> list[Camera]:
    up = np.array([0.0, 0.0, 1.0])
    return [
        look_at("centred", np.array([0.3, -3.5, 0.8]), np.zeros(3), up, 48, 40, 45.0),
        off_centre_camera("off_centre", np.array([2.8, 1.5, 1.2]), 37, 29, 30.0, 34.0, 11.3, 19.7),
        off_centre_camera("wide_fov_close", np.array([-1.2, -1.6, 0.4]), 33, 50, 14.0, 15.5, 20.0, 22.5),
    ]


def single(means, *, log_scale=-3.0, opacity_logit=4.0, dc=(1.0, 0.5, 0.2)) -> GaussianCloud:
    means = np.atleast_2d(np.asarray(means, dtype=np.float64))
    n = means.shape[0]
    return GaussianCloud(
        means=means, scales=np.full((n, 3), log_scale), quats=np.tile([1.0, 0, 0, 0], (n, 1)),
        opacities=np.full(n, opacity_logit), sh_dc=np.tile(dc, (n, 1)), sh_rest=np.zeros((n, 0, 3)),
    )


def axis_camera(width: int = 33, height: int = 33, focal: float = 40.0) -> Camera:
    """At the origin looking along +z (identity pose)."""
    return Camera("axis", width, height, focal, focal, width / 2.0, height / 2.0, np.eye(3), np.zeros(3))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_fast_renderer_matches_dense_reference(degree):
    rng = np.random.default_rng(degree)
    cloud = random_cloud(rng, 160, degree)
    renderer = Renderer(cloud)
    background = (0.2, 0.4, 0.9)
    for camera in cameras():
        fast = renderer.render(camera, background=background)
        ref = render_reference(cloud, camera, background=background)
        assert fast.image.shape == (camera.height, camera.width, 3)
        assert fast.n_rendered > 20  # the scene is really seen
        assert np.abs(fast.image - ref.image).max() < TOL, camera.name
        assert np.abs(fast.alpha - ref.alpha).max() < TOL, camera.name


def test_dense_reference_and_fast_agree_on_a_crowded_occluding_scene():
    rng = np.random.default_rng(11)
    cloud = random_cloud(rng, 400, 3, spread=0.7)  # many overlapping layers: early stop matters
    cloud = cloud.replace(opacities=rng.normal(3.0, 1.5, cloud.num_gaussians))
    camera = cameras()[0]
    fast = render(cloud, camera)
    ref = render_reference(cloud, camera)
    assert (ref.trans < 1e-3).mean() > 0.2  # a fifth of the pixels run into the early stop
    assert np.abs(fast.image - ref.image).max() < TOL


def test_gaussians_behind_camera_or_outside_frustum_do_not_draw():
    camera = axis_camera()
    background = (0.25, 0.5, 0.75)
    cloud = single([[0.0, 0.0, -2.0], [0.0, 0.0, 0.1], [50.0, 0.0, 2.0], [0.0, -40.0, 2.0]], log_scale=-2.0)
    result = render(cloud, camera, background=background)
    assert result.n_rendered == 0
    assert np.array_equal(result.image, np.broadcast_to(np.float32(background), result.image.shape))
    assert not result.alpha.any()


def test_background_shows_where_nothing_is():
    camera = axis_camera(width=65, height=49)
    background = (0.1, 0.9, 0.3)
    result = render(single([0.0, 0.0, 3.0], log_scale=-4.0), camera, background=background)
    assert result.n_rendered == 1
    assert np.allclose(result.image[0, 0], background, atol=0) and result.alpha[0, 0] == 0
    centre = result.image[24, 32]
    assert result.alpha[24, 32] > 0.9 and not np.allclose(centre, background, atol=0.05)


def test_alpha_cap_and_early_stop_before_accumulating():
    colours = [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 1.0, 1.0)]
    opacities = [0.999, 0.98, 0.99, 0.01]
    cloud = GaussianCloud(
        means=[[0.0, 0.0, z] for z in (2.0, 2.5, 3.0, 3.5)],  # on the optical axis: pixel (16, 16)
        scales=np.full((4, 3), np.log(0.2)), quats=np.tile([1.0, 0, 0, 0], (4, 1)),
        opacities=np.log(np.array(opacities) / (1 - np.array(opacities))),
        sh_dc=sh.rgb_to_sh_dc(np.array(colours)), sh_rest=np.zeros((4, 0, 3)),
    )
    background = np.array([0.3, 0.6, 0.9])
    # alpha 0.99 (capped) -> T 0.01; alpha 0.98 -> T 2e-4; the third would leave T 2e-6 < 1e-4,
    # so the pixel stops without it, and the fourth (which would keep T above 1e-4) is skipped too.
    expected = 0.99 * np.array(colours[0]) + 0.98 * 0.01 * np.array(colours[1]) + 2e-4 * background
    camera = axis_camera()
    fast = render(cloud, camera, background=background)
    ref = render_reference(cloud, camera, background=background)
    assert np.abs(fast.image[16, 16] - expected).max() < 1e-5
    assert np.abs(ref.image[16, 16] - expected).max() < 1e-5
    assert np.abs(fast.image - ref.image).max() < TOL


def test_render_weights_reproduce_the_image_exactly():
    rng = np.random.default_rng(5)
    cloud = random_cloud(rng, 200, 3, spread=0.6)
    camera = cameras()[1]
    background = np.array([0.7, 0.2, 0.5])
    weights, trans = render_weights(cloud, camera)
    assert weights.shape == (camera.width * camera.height, cloud.num_gaussians)
    colours = sh.eval_sh(cloud.sh_coefficients(), cloud.means - camera.center)  # independent colours
    image = (weights @ colours + trans[:, None] * background).reshape(camera.height, camera.width, 3)
    fast = render(cloud, camera, background=background)
    assert np.abs(image - fast.image).max() < 1e-5
    ref = render_reference(cloud, camera, background=background, return_weights=True)
    assert np.abs(weights.toarray() - ref.weights).max() < 1e-7
    assert np.abs(trans - ref.trans).max() < 1e-7
    assert np.allclose(weights.sum(axis=1).A1, 1.0 - trans)  # sum of alpha_i T_i telescopes


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_colour_kernel_matches_eval_sh(degree):
    rng = np.random.default_rng(20 + degree)
    cloud = random_cloud(rng, 300, degree)
    center = np.array([0.4, -2.0, 0.7])
    fast = view_colors(cloud.means, cloud.sh_dc, cloud.sh_rest, center)
    slow = sh.eval_sh(cloud.sh_coefficients(), cloud.means - center)
    assert np.abs(fast - slow).max() < 1e-9


def test_pixel_convention_off_centre_principal_point():
    camera = off_centre_camera("pp", np.array([0.0, -4.0, 0.0]), 64, 48, 55.0, 60.0, 20.25, 30.75)
    point = np.array([0.31, 0.2, -0.17])
    uv, _ = camera.project(point[None])
    result = render(single(point, log_scale=-4.5), camera)
    row, col = np.unravel_index(np.argmax(result.alpha), result.alpha.shape)
    # the pixel whose centre (i + 0.5, j + 0.5) is nearest to the projection
    assert (col, row) == tuple(np.floor(uv[0]).astype(int))


def test_renderer_reuse_across_cameras_and_sizes():
    rng = np.random.default_rng(3)
    cloud = random_cloud(rng, 150, 2)
    renderer = Renderer(cloud)
    cams = cameras()
    first = [renderer.render(c).image for c in cams]
    again = [renderer.render(c).image for c in reversed(cams)][::-1]
    for a, b, c in zip(first, again, cams):
        assert np.array_equal(a, b)
        assert np.array_equal(a, render(cloud, c).image)


def test_depth_of_an_opaque_gaussian():
    result = render(single([0.0, 0.0, 2.5], log_scale=-1.5, opacity_logit=8.0), axis_camera(), depth=True)
    assert result.depth is not None and abs(result.depth[16, 16] - 2.5) < 1e-5
    assert np.all(result.depth[result.alpha == 0] == 0.0)


def test_user_mistakes_raise_validation_errors():
    cloud = single([0.0, 0.0, 2.0])
    with pytest.raises(ValidationError, match="background"):
        render(cloud, axis_camera(), background=(0.0, 1.0))
    with pytest.raises(ValidationError, match="Camera"):
        render(cloud, "not a camera")  # type: ignore[arg-type]


def test_render_views_returns_images_or_writes_pngs(tmp_path):
    import cv2

    cloud = random_cloud(np.random.default_rng(1), 80, 1)
    cams = cameras()[:2]
    images = render_views(cloud, cams, progress=False)
    assert [im.shape for im in images] == [(c.height, c.width, 3) for c in cams]
    paths = render_views(cloud, cams, tmp_path / "pngs", progress=False)
    assert [p.name for p in paths] == ["centred.png", "off_centre.png"]
    png = cv2.imread(str(paths[0]), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint8 and png.shape == (40, 48, 3)
    expected = np.clip(images[0], 0, 1)[:, :, ::-1] * 255
    assert np.abs(png - expected).max() <= 0.5 + 1e-3


def test_views_that_share_a_name_get_separate_pngs(tmp_path):
    """NeRF-synthetic train and test views are both called r_0: neither PNG may overwrite the other."""
    from dataclasses import replace

    from gscodec_shac.render.output import png_names

    cloud = random_cloud(np.random.default_rng(2), 60, 0)
    first, second = cameras()[:2]
    same_name = [replace(first, name="r_0"), replace(second, name="r_0"), replace(first, name="r_1.png")]
    paths = render_views(cloud, same_name, tmp_path, progress=False)
    assert [p.name for p in paths] == ["r_0.png", "r_0_00001.png", "r_1.png"]
    assert len(list(tmp_path.glob("*.png"))) == 3
    assert png_names(["a", "a", "a", "b"]) == ["a.png", "a_00001.png", "a_00002.png", "b.png"]


def test_warmup_reports_seconds():
    assert warmup() >= 0.0


def test_cli_render_writes_pngs(tmp_path, small_scene, capsys):
    import cv2

    from gscodec_shac.cli import main
    from gscodec_shac.io.inria_cameras import write_inria_cameras
    from gscodec_shac.io.ply import write_ply

    ply = tmp_path / "scene.ply"
    write_ply(ply, small_scene.cloud)
    write_inria_cameras(tmp_path / "cameras.json", small_scene.cameras)
    out = tmp_path / "renders"
    args = ["render", str(ply), "--cameras", str(tmp_path / "cameras.json"), "--every", "3",
            "--width", "40", "--background", "1,1,1", "--out", str(out), "--quiet"]
    assert main(args) == 0
    pngs = sorted(out.glob("*.png"))
    assert len(pngs) == 3  # 8 cameras, every 3rd
    assert cv2.imread(str(pngs[0])).shape == (30, 40, 3)
    assert main(["render", str(ply), "--orbit-views", "2", "--scale", "0.1", "--out", str(out / "orbit"),
                 "--quiet"]) == 0
    assert len(list((out / "orbit").glob("*.png"))) == 2
    assert main(["render", str(ply), "--out", str(out), "--background", "2,0,0"]) == 2
    assert "background" in capsys.readouterr().err


@pytest.mark.shared_data
def test_bonsai_test_views_reproduce_the_trainers_psnr():
    """An independent exact 3DGS renderer measured these per-view PSNRs on the same model."""
    import json

    from gscodec_shac.camera import test_split
    from gscodec_shac.io.cameras import load_cameras
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.metrics import load_image, psnr
    from tests.conftest import shared_scene

    scene = shared_scene("bonsai_cpu_sh3")
    images = shared_scene("mipnerf360_bonsai", "images")
    expected = json.loads((scene / "train_summary.json").read_text())["test_psnr_list"]
    _, test = test_split(load_cameras(scene / "cameras.json", images))
    renderer = Renderer(read_ply(scene / "point_cloud.ply"))
    for index in (0, 9, 29):  # the worst, a middle and the best view
        camera = test[index]
        truth = load_image(camera.image_path, size=(camera.width, camera.height))
        assert abs(psnr(renderer.render(camera).image, truth) - expected[index]) < 1e-3


def test_a_renderer_given_the_covariances_renders_the_same_images():
    """The rate controller renders variants of a cloud (other colours, opacities, positions, a subset)
    with the 3D covariances of the whole cloud's renderer: the images are the ones computed afresh."""
    rng = np.random.default_rng(7)
    cloud = random_cloud(rng, 300, 2)
    whole = Renderer(cloud)
    keep = np.sort(rng.choice(300, 170, replace=False))
    moved = cloud.replace(means=cloud.means + 0.01, opacities=cloud.opacities - 0.3)
    for variant, covariances in ((cloud.select(keep), whole.cov3[keep]), (moved, whole.cov3)):
        given = Renderer(variant, covariances=covariances)
        fresh = Renderer(variant)
        for camera in cameras():
            assert np.array_equal(given.render(camera).image, fresh.render(camera).image)
    with pytest.raises(ValidationError, match="covariances have shape"):
        Renderer(cloud, covariances=whole.cov3[:10])


def test_variants_from_one_prepared_frame_render_as_a_fresh_renderer():
    """The rate controller renders subsets (pruning), recoloured clouds (SH of some rows as decoded)
    and recoloured subsets (pruning with the DC-only bar's AC zeroed) from the whole cloud's prepared frame (gscodec_shac/render/variants.py): only the blend runs
    again, and the images equal a fresh renderer's of the variant bit for bit, for every kind of
    camera, over a non-black background, also after other variants were rendered from the frame."""
    from gscodec_shac.render.variants import FrameVariants

    rng = np.random.default_rng(11)
    cloud = random_cloud(rng, 400, 3)
    cloud = cloud.replace(means=np.concatenate([cloud.means[:-20], cloud.means[:20]]))  # equal depths: ties by row
    whole = Renderer(cloud)
    keep = np.sort(rng.choice(400, 230, replace=False))
    rows = rng.choice(400, 90, replace=False)  # any order, as the probe's decoded rows come
    new_dc, new_rest = cloud.sh_dc.copy(), cloud.sh_rest.copy()
    new_dc[rows] += rng.normal(0.0, 0.2, (90, 3))
    new_rest[rows] += rng.normal(0.0, 0.1, (90, 15, 3))
    recoloured = cloud.replace(sh_dc=new_dc, sh_rest=new_rest)
    sh_dc, sh_rest = recoloured.sh_dc[rows], recoloured.sh_rest[rows]
    background = (0.2, 0.9, 1.0)
    for camera in cameras():
        frame = FrameVariants(whole, camera, background)
        for _ in range(2):  # the frame is left as it was by every variant
            assert np.array_equal(frame.image(), render(cloud, camera, background=background).image)
            pruned = frame.subset(keep)
            assert np.array_equal(pruned, render(cloud.select(keep), camera, background=background).image)
            mask = np.zeros(400, dtype=bool)
            mask[keep] = True
            assert np.array_equal(frame.subset(mask), pruned)
            image = frame.recoloured(rows, sh_dc, sh_rest)
            assert np.array_equal(image, render(recoloured, camera, background=background).image)
            assert not np.array_equal(image, frame.image())
            both = frame.variant(keep=mask, rows=rows, sh_dc=sh_dc, sh_rest=sh_rest)  # recoloured, then pruned
            assert np.array_equal(both, render(recoloured.select(keep), camera, background=background).image)
            assert not np.array_equal(both, pruned)


def test_blend_schedule_deals_every_tile_once_and_gives_the_same_pixels_for_any_worker_count(monkeypatch):
    """The blend deals the tiles to one worker per thread, the longest lists first to the least loaded
    worker (gscodec_shac/render/raster.py, tile_schedule): every tile goes to exactly one worker, the
    loads are balanced, and since each tile is blended alone the image, the weights and the importance
    totals are the same with 1, 2, 3 and 8 workers."""
    from gscodec_shac.render import raster

    lengths = np.array([0, 500, 3, 3, 900, 0, 40, 41, 7, 600])
    tile_start = np.concatenate([[0], np.cumsum(lengths)])
    tiles, worker_start = raster.tile_schedule(tile_start, 2)
    assert np.array_equal(np.sort(tiles), np.arange(10)) and worker_start[-1] == 10
    loads = [np.sum(lengths[tiles[a:b]] + raster.TILE_COST) for a, b in zip(worker_start[:-1], worker_start[1:])]
    assert max(loads) - min(loads) <= 500 + raster.TILE_COST  # LPT: within the largest tile left after the first
    assert all(np.all(np.diff(tiles[a:b]) > 0) for a, b in zip(worker_start[:-1], worker_start[1:]))
    assert raster.tile_schedule(tile_start, 64)[1].size == 11  # no more workers than tiles

    cloud = random_cloud(np.random.default_rng(5), 600, 3)
    camera = look_at("wide", np.array([0.2, -3.0, 0.6]), np.zeros(3), np.array([0.0, 0.0, 1.0]), 160, 112, 50.0)
    outputs = []
    schedule = raster.tile_schedule
    for workers in (1, 2, 3, 8):
        monkeypatch.setattr(raster, "tile_schedule", lambda start, threads, only=None, workers=workers: schedule(start, workers, only))
        renderer = Renderer(cloud)
        weights, trans = renderer.weights(camera)
        outputs.append((renderer.render(camera, background=(0.3, 0.1, 0.7)).image, weights.toarray(), trans,
                        renderer.contributions(camera)))
    assert outputs[0][0].any()
    for other in outputs[1:]:
        assert all(np.array_equal(a, b) for a, b in zip(outputs[0], other))
