"""SHAC-LST render-loss fine-tuning: the colour path against the rasterisers, gradients against
finite differences, training, checkpoints, variants, outputs and the CLI (tiny scenes)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from gscodec_shac.cli import main as cli_main
from gscodec_shac.io.inria_cameras import write_inria_cameras
from gscodec_shac.io.ply import read_ply, write_ply
from gscodec_shac.render import Renderer
from gscodec_shac.render.reference import render_reference
from gscodec_shac.shac.base import StageState, stage_from_state
from gscodec_shac.shac.lst_torch import LSTConfig
from gscodec_shac.train.colour_path import ViewCache, blend, build_view, render_cloud_view
from gscodec_shac.train.finetune import (
    FinetuneConfig,
    FinetuneError,
    LstFinetuner,
    compact_path_for,
    load_finetuned,
    view_schedule,
)
from gscodec_shac.train.losses import render_loss

BG = (0.2, 0.3, 0.4)


@pytest.fixture(scope="module")
def scene():
    from gscodec_shac.synthetic import make_synthetic_scene

    return make_synthetic_scene(1_500, seed=3, n_cameras=8, width=64, height=48)


def tuner_for(scene, steps: int = 10, dtype: str = "float64", **kwargs) -> LstFinetuner:
    config = FinetuneConfig(steps=steps, dtype=dtype, **kwargs)
    return LstFinetuner(scene.cloud, scene.cameras[:6], targets="original", config=config)


# ----------------------------------------------------------------------------- colour path
def test_colour_path_image_equals_rasteriser_and_dense_reference(scene):
    renderer = Renderer(scene.cloud)
    for camera in scene.cameras[:3]:
        view = build_view(renderer, camera, dtype="float64")
        image = render_cloud_view(view, scene.cloud, BG)
        raster = renderer.render(camera, background=BG).image
        dense = render_reference(scene.cloud, camera, background=BG, return_weights=True)
        assert view.n_used > 50 and view.nnz > view.n_pixels
        assert np.abs(image - raster).max() < 1e-5
        assert np.abs(image - dense.image).max() < 1e-5
        assert np.abs(view.weights_dense(scene.cloud.num_gaussians) - dense.weights).max() < 1e-6
        assert np.abs(view.trans.numpy() - dense.trans).max() < 1e-6
        # only Gaussians that reach a pixel are kept, and all of them
        assert set(view.index.numpy()) == set(np.flatnonzero(np.abs(dense.weights).sum(axis=0) > 0))


def test_colour_path_float32_matches_float64(scene):
    renderer = Renderer(scene.cloud)
    a = render_cloud_view(build_view(renderer, scene.cameras[0], dtype="float64"), scene.cloud, BG)
    b = render_cloud_view(build_view(renderer, scene.cameras[0], dtype="float32"), scene.cloud, BG)
    assert np.abs(a - b).max() < 1e-5


def test_blend_gradient_is_the_transposed_weights(scene):
    view = build_view(Renderer(scene.cloud), scene.cameras[1], dtype="float64")
    colours = torch.rand(view.n_used, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c: blend(view, c), (colours,), fast_mode=True, rtol=1e-6, atol=1e-9)


def test_loss_gradient_in_colours_matches_finite_differences(scene):
    """d(loss)/d(colour) by autograd against central differences of the same loss."""
    view = build_view(Renderer(scene.cloud), scene.cameras[2], dtype="float64")
    rng = np.random.default_rng(0)
    target = torch.from_numpy(rng.uniform(0, 1, (*view.shape, 3)))
    colours0 = torch.from_numpy(rng.uniform(0.1, 0.9, (view.n_used, 3)))

    def loss(c: torch.Tensor) -> torch.Tensor:
        image = (blend(view, c) + view.trans[:, None] * torch.tensor(BG, dtype=torch.float64)).reshape(*view.shape, 3)
        return render_loss(image, target)

    colours = colours0.clone().requires_grad_(True)
    loss(colours).backward()
    grad = colours.grad
    assert grad.abs().max() > 0
    eps = 1e-6
    with torch.no_grad():
        for _ in range(4):  # random directions
            v = torch.from_numpy(rng.normal(size=colours0.shape))
            fd = (loss(colours0 + eps * v) - loss(colours0 - eps * v)) / (2 * eps)
            assert float(fd) == pytest.approx(float((grad * v).sum()), rel=1e-5, abs=1e-9)
        for i in np.argsort(-grad.abs().sum(dim=1).numpy())[:3]:  # single coordinates with the largest gradient
            e = torch.zeros_like(colours0)
            e[i, 0] = 1.0
            fd = (loss(colours0 + eps * e) - loss(colours0 - eps * e)) / (2 * eps)
            assert float(fd) == pytest.approx(float(grad[i, 0]), rel=1e-4, abs=1e-9)


def test_gradients_in_s_t_dc_match_finite_differences(scene):
    """The chain S, T, DC -> SH -> colours -> image -> loss by autograd, against central
    differences of (a) the same float64 colour-path loss and (b) the loss of images from the
    real rasteriser rendering the PLY-precision cloud ``[DC | S T]`` (float32 SH and image:
    a looser tolerance)."""
    tuner = tuner_for(scene)
    view = tuner.cache[0]
    rng = np.random.default_rng(1)
    target = torch.from_numpy(rng.uniform(0, 1, (*view.shape, 3)))

    def path_loss() -> float:
        with torch.no_grad():
            return float(render_loss(tuner.render(view), target))

    def raster_loss() -> float:
        image = Renderer(tuner.finetuned_cloud()).render(view.camera).image.astype(np.float64)
        return float(render_loss(torch.from_numpy(image), target))

    def central(loss, param, v, eps) -> float:
        base = param.detach().clone()
        values = []
        for sign in (1.0, -1.0):
            with torch.no_grad():
                param.copy_(base + sign * eps * v)
            values.append(loss())
        with torch.no_grad():
            param.copy_(base)
        return (values[0] - values[1]) / (2 * eps)

    tuner.optimizer.zero_grad()
    render_loss(tuner.render(view), target).backward()
    params = {"subset": tuner.subset, "dc": tuner.dc, **{f"T.{k}": w for k, w in tuner.module.weights.items()}}
    for name, param in params.items():
        v = torch.from_numpy(rng.normal(size=param.shape))
        analytic = float((param.grad * v).sum())
        assert analytic != 0.0, name
        assert central(path_loss, param, v, 1e-6) == pytest.approx(analytic, rel=1e-5), name
        assert central(raster_loss, param, v, 3e-4) == pytest.approx(analytic, rel=1e-2), name


# ----------------------------------------------------------------------------- training
def test_view_schedule_is_seeded_epochs_of_permutations():
    a = view_schedule(5, 12, seed=4)
    assert np.array_equal(a, view_schedule(5, 12, seed=4))
    assert not np.array_equal(a, view_schedule(5, 12, seed=5))
    assert sorted(a[:5]) == list(range(5)) and sorted(a[5:10]) == list(range(5))


def test_orbit_views_surround_the_scene_and_look_at_its_centre(scene):
    from gscodec_shac.camera import orbit_views

    views = orbit_views(scene.cloud.means, 9, 40)
    centre = np.median(scene.cloud.means.astype(np.float64), axis=0)
    assert [v.name for v in views] == [f"orbit_{i:03d}" for i in range(9)]
    assert all((v.width, v.height) == (40, 30) for v in views)
    for v in views:  # the centre projects to the principal point
        uv, depth = v.project(centre[None])
        assert depth[0] > 0 and np.allclose(uv[0], (v.cx, v.cy), atol=1e-6)
    heights = sorted({round(float(v.center[2] - centre[2]), 6) for v in views})
    assert len(heights) == 3  # three elevation rings


def test_finetuning_lowers_the_loss(scene):
    tuner = tuner_for(scene, steps=40, dtype="float32")
    before = tuner.mean_loss()
    result = tuner.run(progress=False)
    after = tuner.mean_loss()
    assert result.steps == 40 and len(result.log) == 40
    assert after < 0.9 * before
    assert all(np.isfinite(row["loss"]) for row in result.log)


def test_checkpoint_resume_equals_uninterrupted_run(scene, tmp_path):
    whole = tuner_for(scene, steps=12)
    whole.run(progress=False)

    ckpt = tmp_path / "run.ckpt.pt"
    first = tuner_for(scene, steps=12)
    first.run(progress=False, checkpoint=ckpt, checkpoint_every=5, stop_at=7)
    assert first.step_index == 7
    resumed = tuner_for(scene, steps=12)
    result = resumed.run(progress=False, checkpoint=ckpt, resume=True, log_path=tmp_path / "log.csv")
    assert result.resumed and result.start_step == 7 and resumed.step_index == 12

    assert torch.equal(whole.subset, resumed.subset)
    assert torch.equal(whole.dc, resumed.dc)
    for key, value in whole.module.state_dict().items():
        assert torch.equal(value, resumed.module.state_dict()[key]), key
    assert [r["loss"] for r in whole.log] == [r["loss"] for r in resumed.log]
    assert len((tmp_path / "log.csv").read_text().splitlines()) == 13

    other = tuner_for(scene, steps=12, seed=1)
    with pytest.raises(FinetuneError, match="different run"):
        other.load_checkpoint(ckpt)


VARIANTS = [
    dict(),
    dict(rgb="separate"),
    dict(structure="dense"),
    dict(structure="dense", rgb="separate"),
    dict(init="identity"),
    dict(subset="highest"),
    dict(operator="vector"),
    dict(operator="vector", init="identity"),
    dict(operator="linear"),
    dict(operator="mlp"),
]


@pytest.mark.parametrize("variant", VARIANTS, ids=lambda v: "-".join(f"{k}={x}" for k, x in v.items()) or "paper")
def test_every_lst_variant_trains_through_the_render_loss(scene, variant):
    torch.manual_seed(0)
    config = LSTConfig(degree=3, **variant)
    tuner = tuner_for(scene, steps=20, dtype="float32", lst=config, init="module")
    s0 = tuner.subset.detach().clone()
    t0 = [p.detach().clone() for p in tuner.module.parameters()]
    rows = [tuner.step(), tuner.step()]  # step 0 has T's warm-up rate 0; step 1 its peak
    assert all(np.isfinite(r["loss"]) for r in rows)
    assert not torch.equal(s0, tuner.subset)
    assert any(not torch.equal(a, b) for a, b in zip(t0, tuner.module.parameters()))
    assert tuner.finetuned_ac().shape == scene.cloud.ac_matrix().shape


def test_posthoc_start_reproduces_the_posthoc_fit(scene):
    from gscodec_shac.shac.lst import ShacLST

    tuner = tuner_for(scene, refit_subset=3)
    stage = ShacLST(refit_subset=3).fit(scene.cloud.ac_matrix())
    expected = stage.inverse_transform(stage.transform(scene.cloud.ac_matrix()))
    assert np.allclose(tuner.finetuned_ac(), expected, atol=1e-6)


def test_posthoc_start_needs_the_joint_matrix_operator(scene):
    with pytest.raises(FinetuneError, match="init='module'"):
        tuner_for(scene, lst=LSTConfig(operator="vector"))


def test_image_targets_are_ground_truth_files_at_camera_size(scene, tmp_path):
    from gscodec_shac.metrics import load_image, psnr
    from gscodec_shac.render import save_png

    cameras = []
    for i, camera in enumerate(scene.cameras[:2]):  # "photos" at twice the resolution
        big = camera.resized(2 * camera.width, 2 * camera.height)
        path = save_png(tmp_path / f"{i}.png", Renderer(scene.cloud).render(big).image)
        cameras.append(camera.with_image_path(path))
    tuner = LstFinetuner(scene.cloud, cameras, config=FinetuneConfig(steps=2))
    assert tuner.target_kind == "images"
    view = tuner.cache[1]
    assert np.array_equal(view.target.numpy(), load_image(cameras[1].image_path, size=(64, 48)))
    assert psnr(view.target.numpy(), render_cloud_view(view, scene.cloud)) > 20
    assert tuner.run(progress=False).steps == 2


def test_images_target_needs_image_paths(scene):
    with pytest.raises(FinetuneError, match="no ground-truth image"):
        LstFinetuner(scene.cloud, scene.cameras[:2], targets="images", config=FinetuneConfig(steps=2))


def test_view_cache_budget_evicts_and_rebuilds_identically(scene):
    cache = ViewCache(scene.cloud, scene.cameras[:3], dtype="float64", max_bytes=1)
    first = cache[0].values.copy()
    cache[1], cache[2]
    assert cache.n_cached == 1 and cache.stats.evictions == 2
    assert np.array_equal(cache[0].values, first) and cache.stats.misses == 4


# ----------------------------------------------------------------------------- outputs
def test_outputs_reload_and_compact_form_reproduces_the_ply_exactly(scene, tmp_path):
    tuner = tuner_for(scene, steps=3, dtype="float32")
    tuner.run(progress=False)
    ply, compact = tuner.save_outputs(tmp_path / "ft.ply")
    assert compact == compact_path_for(ply) == tmp_path / "ft.lst.npz"

    from_ply = read_ply(ply)
    cloud, stage = load_finetuned(compact)
    assert np.array_equal(cloud.sh_rest, from_ply.sh_rest)
    assert np.array_equal(cloud.sh_dc, from_ply.sh_dc)
    for name in ("means", "scales", "quats", "opacities"):
        assert np.array_equal(getattr(cloud, name), getattr(from_ply, name))
    # the codec path: S from the PLY and the stage state alone, then back to the full SH
    codec_stage = stage_from_state(StageState.from_bytes(stage.state().to_bytes()))
    subset = codec_stage.transform(from_ply.ac_matrix())
    assert np.array_equal(subset, tuner.subset_float32())
    assert np.array_equal(codec_stage.inverse_transform(subset), from_ply.ac_matrix())
    # fine-tuning changed the SH, and only the SH
    assert not np.array_equal(from_ply.sh_rest, scene.cloud.sh_rest)
    assert np.array_equal(from_ply.means, scene.cloud.means)

    cloud_ply, _ = load_finetuned(ply)
    assert np.array_equal(cloud_ply.sh_rest, from_ply.sh_rest)
    write_ply(tmp_path / "other.ply", scene.cloud)
    compact.rename(tmp_path / "other.lst.npz")
    with pytest.raises(FinetuneError, match="does not match"):
        load_finetuned(tmp_path / "other.ply")
    (tmp_path / "junk.lst.npz").write_bytes(b"not an npz")
    with pytest.raises(FinetuneError):
        load_finetuned(tmp_path / "junk.lst.npz")


# ----------------------------------------------------------------------------- CLI
def test_cli_missing_cameras_is_one_line_error(scene, tmp_path, capsys):
    write_ply(tmp_path / "in.ply", scene.cloud)
    code = cli_main(["lst-finetune", str(tmp_path / "in.ply"), str(tmp_path / "out.ply"),
                     "--cameras", str(tmp_path / "missing.json"), "--steps", "2"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: ") and len(err.strip().splitlines()) == 1
    assert "missing.json" in err
    code = cli_main(["lst-finetune", str(tmp_path / "in.ply"), str(tmp_path / "out.ply"), "--steps", "2"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: ") and "--cameras" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out.ply").exists()


def test_cli_runs_resumes_and_writes_outputs(scene, tmp_path):
    write_ply(tmp_path / "in.ply", scene.cloud)
    write_inria_cameras(tmp_path / "cameras.json", scene.cameras)
    base = [sys.executable, "-m", "gscodec_shac", "lst-finetune", str(tmp_path / "in.ply"), str(tmp_path / "out.ply"),
            "--cameras", str(tmp_path / "cameras.json"), "--steps", "4", "--width", "48", "--quiet"]
    done = subprocess.run(base, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert len(done.stdout.strip().splitlines()) == 1 and "4 steps on 7 views" in done.stdout
    for suffix in (".ply", ".lst.npz", ".ckpt.pt", ".log.csv", ".finetune.json"):
        assert (tmp_path / f"out{suffix}").is_file(), suffix
    cloud, _ = load_finetuned(tmp_path / "out.ply")
    assert cloud.num_gaussians == scene.cloud.num_gaussians
    again = subprocess.run(base + ["--resume"], capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and "resumed at step 4" in again.stdout


def test_cli_trains_an_ablation_variant_and_refuses_a_posthoc_start_for_it(scene, tmp_path, capsys):
    write_ply(tmp_path / "in.ply", scene.cloud)
    write_inria_cameras(tmp_path / "cameras.json", scene.cameras)
    base = ["lst-finetune", str(tmp_path / "in.ply"), str(tmp_path / "out.ply"), "--cameras",
            str(tmp_path / "cameras.json"), "--steps", "3", "--width", "32", "--quiet", "--lst-operator", "mlp"]
    assert cli_main(base) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "--start module" in err and not (tmp_path / "out.ply").exists()
    assert cli_main(base + ["--start", "module"]) == 0
    summary = json.loads((tmp_path / "out.finetune.json").read_text())
    assert summary["config"]["lst"]["operator"] == "mlp" and summary["compact"] is None
    assert summary["side_bytes"] > 4 * 300 and (tmp_path / "out.ply").is_file()
    assert not (tmp_path / "out.lst.npz").exists()
