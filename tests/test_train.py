"""The CPU trainer: loss and Adam against torch, density control bookkeeping, MCMC relocation,
re-learning a synthetic capture, bit-identical resume, data loading and the ``train`` CLI."""

from __future__ import annotations

import gscodec_shac.render  # noqa: F401  (before torch: sets OMP_WAIT_POLICY)

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from gscodec_shac.cli import main
from gscodec_shac.io.inria_cameras import write_inria_cameras
from gscodec_shac.render.output import save_png
from gscodec_shac.sh import C0
from gscodec_shac.train import densify as dens
from gscodec_shac.train import mcmc
from gscodec_shac.train.data import (
    CaptureError,
    load_capture,
    read_colmap_points,
    synthetic_capture,
)
from gscodec_shac.train.fastloss import render_loss_and_grad
from gscodec_shac.train.losses import render_loss
from gscodec_shac.train.model import GaussianModel, adam_update
from gscodec_shac.train.trainer import TrainConfig, Trainer, TrainError, export_cloud


@pytest.fixture(scope="module")
def tiny_capture():
    """600 synthetic Gaussians seen by 16 orbit cameras at 48x36 (2 held out), 400 noisy init points."""
    return synthetic_capture(600, n_cameras=16, width=48, height=36, init_points=400, init_noise=0.02, seed=3)


# --------------------------------------------------------------------------- loss and Adam
def test_numba_loss_equals_the_torch_loss() -> None:
    rng = np.random.default_rng(0)
    image = rng.random((21, 34, 3)) * 1.2 - 0.1
    target = rng.random((21, 34, 3))
    tensor = torch.tensor(image, requires_grad=True)
    expected = render_loss(tensor, torch.tensor(target))
    expected.backward()
    loss, grad = render_loss_and_grad(image, target)
    assert abs(loss - expected.item()) < 1e-12
    assert np.abs(grad - tensor.grad.numpy()).max() < 1e-15 + 1e-9 * np.abs(tensor.grad.numpy()).max()


def test_adam_equals_torch_adam() -> None:
    rng = np.random.default_rng(1)
    start = rng.normal(size=(50, 4)).astype(np.float32)
    grads = [rng.normal(size=(50, 4)).astype(np.float32) * (0.1 ** i) for i in range(4)]
    param = torch.nn.Parameter(torch.tensor(start))
    opt = torch.optim.Adam([param], lr=3e-3, eps=1e-15)
    ours, m, v = start.copy(), np.zeros_like(start), np.zeros_like(start)
    for step, g in enumerate(grads, 1):
        param.grad = torch.tensor(g)
        opt.step()
        adam_update(ours, g, m, v, 3e-3, step)
    assert np.allclose(ours, param.detach().numpy(), rtol=1e-6, atol=1e-7)
    assert not np.allclose(ours, start)


def test_adam_column_limit_leaves_other_columns() -> None:
    p = np.ones((5, 4, 3), np.float32)
    m, v = np.zeros_like(p), np.zeros_like(p)
    adam_update(p, np.ones((5, 6), np.float32), m, v, 0.1, 1, columns=6)
    assert np.all(p.reshape(5, -1)[:, :6] < 1.0) and np.all(p.reshape(5, -1)[:, 6:] == 1.0)


# --------------------------------------------------------------------------- density control
def _model(sh: str, n: int = 60, seed: int = 0) -> GaussianModel:
    rng = np.random.default_rng(seed)
    model = GaussianModel.from_points(rng.uniform(-1, 1, (n, 3)), rng.random((n, 3)), 3, sh)
    model.params["scales"][:] = np.log(rng.uniform(0.002, 0.1, (n, 1)))  # small and large ones
    model.params["opacities"][:] = rng.normal(0.0, 2.0, n)
    key = "sh_subset" if sh == "lst" else "sh_rest"
    model.params[key][:] = rng.normal(size=model.params[key].shape)
    model.params["means"][:, 0] = np.arange(n)  # row identity for the checks (x = original row)
    for k in model.names:  # recognisable Adam moments: m = row id + 1
        model.exp_avg[k][:] = (np.arange(n) + 1).reshape((n,) + (1,) * (model.exp_avg[k].ndim - 1))
        model.exp_avg_sq[k][:] = 1.0
    return model


@pytest.mark.parametrize("sh", ["full", "lst"])
def test_densify_clones_splits_and_prunes_every_array_alike(sh: str) -> None:
    model = _model(sh)
    n = model.num_gaussians
    before = {k: v.copy() for k, v in model.params.items()}
    stats = dens.DensifyStats.zeros(n)
    stats.update(np.where(np.arange(n) % 3 == 0, 1e-3, 1e-5), np.full(n, 5, np.int32))
    extent = 2.0
    opacity = 1 / (1 + np.exp(-before["opacities"].astype(np.float64)))
    max_scale = np.exp(before["scales"].astype(np.float64)).max(1)
    candidates = np.arange(n) % 3 == 0
    clone = candidates & (max_scale <= 0.01 * extent)
    split = candidates & ~clone
    result = dens.densify_and_prune(model, stats, grad_threshold=2e-4, extent=extent, percent_dense=0.01,
                                    min_opacity=0.005, max_screen_size=None, rng=np.random.default_rng(0))
    assert (result.cloned, result.split) == (clone.sum(), split.sum())
    n_new = model.num_gaussians
    for store in (model.params, model.exp_avg, model.exp_avg_sq):
        assert all(store[k].shape[0] == n_new for k in model.names)
    assert stats.grad_accum.shape == (n_new,) and stats.denom.sum() == 0
    key = "sh_subset" if sh == "lst" else "sh_rest"
    survivors = int(np.count_nonzero(~split & (opacity >= 0.005)))
    assert result.pruned == np.count_nonzero(opacity < 0.005) + np.count_nonzero(clone & (opacity < 0.005)) + 2 * (
        np.count_nonzero(split & (opacity < 0.005))) - np.count_nonzero(split & (opacity < 0.005))
    old = model.params["means"][:survivors, 0].astype(int)  # survivors keep their order and moments
    assert np.all(np.diff(old) > 0) and not np.any(split[old])
    assert np.array_equal(model.exp_avg["means"][:survivors, 0], old + 1)
    assert np.array_equal(model.params[key][:survivors], before[key][old])
    new = slice(survivors, None)
    assert np.all(model.exp_avg[key][new] == 0) and np.all(model.exp_avg_sq["quats"][new] == 0)
    # clones: exact copies (x coordinate = source row); split children: source's S/SH, scales / 1.6
    sources = np.flatnonzero(clone)
    kept_clones = [s for s in sources if opacity[s] >= 0.005]
    cloned_rows = model.params["means"][survivors:survivors + len(kept_clones), 0].astype(int)
    assert np.array_equal(cloned_rows, kept_clones)
    assert np.array_equal(model.params[key][survivors:survivors + len(kept_clones)], before[key][kept_clones])
    children = model.params["scales"][survivors + len(kept_clones):]
    split_sources = [s for s in np.flatnonzero(split) if opacity[s] >= 0.005]
    expected = np.log(np.exp(before["scales"][split_sources].astype(np.float64)) / 1.6)
    assert np.allclose(children, np.concatenate([expected, expected]), atol=1e-6)
    assert np.all(1 / (1 + np.exp(-model.params["opacities"].astype(np.float64))) >= 0.005)


def test_densify_respects_the_cap_and_opacity_reset() -> None:
    model = _model("full")
    n = model.num_gaussians
    stats = dens.DensifyStats.zeros(n)
    stats.update(np.full(n, 1e-3), np.ones(n, np.int32))
    model.params["opacities"][:] = 3.0
    dens.densify_and_prune(model, stats, grad_threshold=2e-4, extent=2.0, percent_dense=0.01, min_opacity=0.005,
                           max_screen_size=None, rng=np.random.default_rng(0), max_gaussians=n + 7)
    assert model.num_gaussians == n + 7
    dens.reset_opacity(model)
    assert np.all(1 / (1 + np.exp(-model.params["opacities"].astype(np.float64))) <= 0.01 + 1e-6)
    assert not np.any(model.exp_avg["opacities"]) and np.any(model.exp_avg["means"])


# --------------------------------------------------------------------------- MCMC
def test_relocation_formula() -> None:
    o = np.array([0.3, 0.8, 0.05])
    new_o, factor = mcmc.relocation_update(o, np.ones(3, int))
    assert np.allclose(new_o, o) and np.allclose(factor, 1.0)
    new_o, factor = mcmc.relocation_update(o, np.full(3, 2))
    on = 1 - np.sqrt(1 - o)
    assert np.allclose(new_o, on)
    assert np.allclose(factor, o / (2 * on - on**2 / math.sqrt(2)))


@pytest.mark.parametrize("sh", ["full", "lst"])
def test_mcmc_relocates_dead_gaussians_and_grows_to_the_cap(sh: str) -> None:
    model = _model(sh, n=40)
    model.params["opacities"][:10] = -8.0  # dead
    model.params["opacities"][10:] = 1.0
    key = "sh_subset" if sh == "lst" else "sh_rest"
    moved = mcmc.relocate(model, np.random.default_rng(0))
    assert moved == 10 and model.num_gaussians == 40
    source_rows = model.params["means"][:10, 0].astype(int)
    assert np.all(source_rows >= 10)  # dead rows now hold copies of live ones ...
    assert np.array_equal(model.params[key][:10], model.params[key][source_rows])  # ... S / SH rows included
    assert np.all(model.params["opacities"][source_rows] < 1.0)  # the sources' opacity was shared out
    assert not np.any(model.exp_avg["means"][:10]) and not np.any(model.exp_avg["means"][source_rows])
    added = mcmc.grow(model, np.random.default_rng(1), cap=47, growth=0.5)
    assert added == 7 and model.num_gaussians == 47
    for store in (model.params, model.exp_avg, model.exp_avg_sq):
        assert all(store[k].shape[0] == 47 for k in model.names)


# --------------------------------------------------------------------------- training
def _psnr(trainer: Trainer) -> float:
    return trainer.evaluate("test")["mean_psnr"]


@pytest.mark.parametrize("sh", ["full", "lst"])
def test_short_run_relearns_a_synthetic_capture(tiny_capture, sh: str) -> None:
    config = TrainConfig(iterations=300, sh=sh, strategy="mcmc", max_gaussians=900, log_every=1000)
    trainer = Trainer(tiny_capture, config)
    start = _psnr(trainer)
    trainer.train(progress=False)
    end = _psnr(trainer)
    assert trainer.model.num_gaussians == 900
    assert end > 27.0 and end > start + 8.0, (start, end)
    if sh == "lst":
        cloud, stage = export_cloud(trainer.model)
        assert np.abs(stage.transform_matrix()).max() > 0  # T was learnt
        assert np.array_equal(stage.inverse_transform(trainer.model.params["sh_subset"]), cloud.ac_matrix())


@pytest.mark.parametrize("strategy,sh", [("default", "full"), ("mcmc", "lst")])
def test_resume_continues_bit_identically(tiny_capture, tmp_path: Path, strategy: str, sh: str) -> None:
    config = TrainConfig(iterations=60, sh=sh, strategy=strategy, max_gaussians=700 if strategy == "mcmc" else None,
                         densify_from=5, densify_until=50, densify_interval=10, opacity_reset_interval=30,
                         sh_interval=15,
                         refine_from=5, refine_every=10, log_every=1000)
    straight = Trainer(tiny_capture, config)
    straight.train(progress=False)
    first = Trainer(tiny_capture, config)
    first.train(progress=False, time_budget=0.0)  # stops at once
    assert first.iteration == 0
    while first.iteration < 33:
        first.step()
    first.save_checkpoint(tmp_path / "checkpoint.npz")
    resumed = Trainer.from_checkpoint(tiny_capture, tmp_path / "checkpoint.npz")
    assert resumed.iteration == 33
    resumed.train(progress=False)
    assert straight.events and any("opacity_reset" in e or "added" in e for e in straight.events)
    a, b = straight.model.state_arrays(), resumed.model.state_arrays()
    assert a.keys() == b.keys()
    for key in a:
        assert np.array_equal(a[key], b[key]), key
    assert straight.model.step == resumed.model.step == 60


@pytest.mark.parametrize("variant", [
    {"lst_operator": "mlp"}, {"lst_operator": "linear", "lst_init": "identity"}, {"lst_operator": "vector"},
    {"lst_subset": "highest", "lst_structure": "dense"}, {"lst_rgb": "separate"}, {"lambda_t": 0.0},
])
def test_lst_variants_train_and_resume_bit_identically(tiny_capture, tmp_path: Path, variant: dict) -> None:
    """Every Sec. VII-E variant learns its operator, and checkpoints hold every operator weight."""
    config = TrainConfig(iterations=24, sh="lst", strategy="mcmc", max_gaussians=500, sh_interval=2,
                         refine_from=5, refine_every=10, log_every=1000, **variant)
    straight = Trainer(tiny_capture, config)
    before = {k: v.detach().clone() for k, v in straight.model.lst_parameters().items()}
    straight.train(progress=False)
    assert straight.model.lst.config.as_dict() == config.lst_config().as_dict()
    changed = [k for k, v in straight.model.lst_parameters().items() if not torch.equal(v.detach(), before[k])]
    assert changed, "the operator was not trained"
    first = Trainer(tiny_capture, config)
    while first.iteration < 11:
        first.step()
    first.save_checkpoint(tmp_path / "checkpoint.npz")
    resumed = Trainer.from_checkpoint(tiny_capture, tmp_path / "checkpoint.npz")
    assert resumed.model.lst.config == straight.model.lst.config
    resumed.train(progress=False)
    a, b = straight.model.state_arrays(), resumed.model.state_arrays()
    assert a.keys() == b.keys() and any(k.startswith("lst/") for k in a)
    for key in a:
        assert np.array_equal(a[key], b[key]), key
    cloud, stage = export_cloud(straight.model)
    assert (stage is None) == (config.lst_operator != "matrix")
    assert np.allclose(cloud.sh_rest, straight.model.sh_rest(), atol=1e-5)


def test_lst_variant_choices_match_the_module() -> None:
    from gscodec_shac.commands import _options
    from gscodec_shac.shac import lst_torch
    from gscodec_shac.shac.lst import STRUCTURES, SUBSET_STRATEGIES

    assert set(_options.LST_SUBSETS) == set(SUBSET_STRATEGIES)
    assert set(_options.LST_OPERATORS) == set(lst_torch.OPERATORS)
    assert set(_options.LST_STRUCTURES) == set(STRUCTURES)
    assert set(_options.LST_RGB) == set(lst_torch.RGB_MODES)
    assert set(_options.LST_INITS) == set(lst_torch.INITS)


def test_bad_settings_raise(tiny_capture) -> None:
    with pytest.raises(TrainError, match="max-gaussians"):
        Trainer(tiny_capture, TrainConfig(iterations=10, strategy="mcmc"))
    with pytest.raises(TrainError, match="degree 2 or 3"):
        Trainer(tiny_capture, TrainConfig(iterations=10, sh="lst", sh_degree=1))
    with pytest.raises(TrainError, match="mlp operator has no identity"):
        Trainer(tiny_capture, TrainConfig(iterations=10, sh="lst", lst_operator="mlp", lst_init="identity"))
    with pytest.raises(TrainError, match="lambda-t"):
        Trainer(tiny_capture, TrainConfig(iterations=10, sh="lst", lambda_t=-1.0))
    with pytest.raises(CaptureError):
        load_capture("/nonexistent/capture")
    with pytest.raises(TrainError, match="lr_decay_final"):
        Trainer(tiny_capture, TrainConfig(iterations=10, lr_decay_final=0.0))
    with pytest.raises(TrainError, match="lr_decay_start"):
        Trainer(tiny_capture, TrainConfig(iterations=10, lr_decay_start=1.0))


def test_lr_decay_final_decays_every_rate_but_the_positions(tiny_capture) -> None:
    constant = Trainer(tiny_capture, TrainConfig(iterations=100))
    decaying = Trainer(tiny_capture, TrainConfig(iterations=100, lr_decay_final=0.01))
    assert constant.learning_rates(0) == decaying.learning_rates(0)
    assert constant.learning_rates(100) == constant.learning_rates(0) | {"means": constant.learning_rates(100)["means"]}
    start, middle, end = (decaying.learning_rates(it) for it in (0, 50, 100))
    for name in ("scales", "quats", "opacities", "sh_dc", "sh_rest"):
        assert end[name] == pytest.approx(0.01 * start[name]) and middle[name] == pytest.approx(0.1 * start[name])
    assert end["means"] == constant.learning_rates(100)["means"]  # the positions keep their own schedule
    late = Trainer(tiny_capture, TrainConfig(iterations=100, lr_decay_final=0.01, lr_decay_start=0.5))
    assert late.learning_rates(50) == constant.learning_rates(50)  # no decay before half the run
    assert late.learning_rates(75)["scales"] == pytest.approx(0.1 * start["scales"])
    assert late.learning_rates(100)["opacities"] == pytest.approx(0.01 * start["opacities"])


# --------------------------------------------------------------------------- data and CLI
def _write_capture(root: Path, capture) -> None:
    """An Inria-style capture folder: cameras.json, images/<name>.png, input.ply."""
    import plyfile

    (root / "images").mkdir(parents=True)
    cams = capture.train_cameras + capture.test_cameras
    for cam, image in zip(cams, capture.train_images + capture.test_images):
        save_png(root / "images" / f"{cam.name}.png", image)
    write_inria_cameras(root / "cameras.json", [c.resized(c.width * 2, c.height * 2) for c in cams])  # full-res
    rgb = (np.clip(capture.colors, 0, 1) * 255).astype(np.uint8)
    vertex = np.empty(len(capture.points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"),
                                                   ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, k in enumerate("xyz"):
        vertex[k] = capture.points[:, i]
    vertex["red"], vertex["green"], vertex["blue"] = rgb.T
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(str(root / "input.ply"))


def test_capture_with_an_undecodable_image_is_a_capture_error(tiny_capture, tmp_path: Path) -> None:
    root = tmp_path / "capture"
    _write_capture(root, tiny_capture)
    for png in (root / "images").glob("*.png"):
        png.write_bytes(b"not a png")
    with pytest.raises(CaptureError, match=r"\.png: cannot be decoded as an image"):
        load_capture(root)  # the image size is read before any pixels


def test_cli_trains_resumes_and_writes_outputs(tiny_capture, tmp_path: Path, capsys) -> None:
    root = tmp_path / "capture"
    _write_capture(root, tiny_capture)
    out = tmp_path / "out"
    args = ["train", str(root), str(out), "--sh", "lst", "--iterations", "12", "--max-gaussians", "450", "--quiet"]
    assert main(args + ["--time-budget", "1e-9"]) == 0  # stops before the first step, checkpoint written
    assert main(args) == 2
    assert "--resume" in capsys.readouterr().err
    assert main(args + ["--resume"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["complete"] and metrics["iterations_done"] == 12
    assert metrics["method"] == "SHAC-LST-L3-D21" and metrics["sizes"]["num_gaussians"] == 450
    assert len(metrics["test"]["views"]) == 2 and metrics["n_train_views"] == 14  # every 8th held out
    assert (metrics["width"], metrics["height"]) == (48, 36)  # cameras resized to the image files
    for name in ("point_cloud.ply", "point_cloud.lst.npz", "cameras.json", "checkpoint.npz", "run.json"):
        assert (out / name).is_file(), name
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.train.finetune import load_finetuned

    cloud, stage = load_finetuned(out / "point_cloud.ply")
    assert cloud.num_gaussians == 450 and cloud.sh_degree == 3 and stage.n_params == 306
    assert read_ply(out / "point_cloud.ply").num_gaussians == 450
    assert len(json.loads((out / "cameras.json").read_text())) == 16
    held_out = [view["name"] for view in metrics["test"]["views"]]
    assert [c["img_name"] for c in json.loads((out / "cameras_test.json").read_text())] == held_out


def test_nerf_capture_is_composited_on_white_and_resized(tmp_path: Path) -> None:
    import cv2

    root = tmp_path / "nerf"
    (root / "train").mkdir(parents=True)
    (root / "test").mkdir()
    frames = {"train": [], "test": []}
    for split, count in (("train", 3), ("test", 1)):
        for i in range(count):
            rgba = np.zeros((16, 16, 4), np.uint8)
            rgba[4:12, 4:12] = (0, 0, 255, 255)  # an opaque red square (BGR) on transparent black
            cv2.imwrite(str(root / split / f"r_{i}.png"), rgba)
            angle = 2 * math.pi * i / 3
            c2w = [[math.cos(angle), 0, math.sin(angle), 4 * math.sin(angle)], [0, 1, 0, 0],
                   [-math.sin(angle), 0, math.cos(angle), 4 * math.cos(angle)], [0, 0, 0, 1]]
            frames[split].append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w})
    for split in frames:
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames[split]}))
    capture = load_capture(root, width=8, init="random")
    assert capture.kind == "nerf" and len(capture.train_cameras) == 3 and len(capture.test_cameras) == 1
    assert capture.train_images[0].shape == (8, 8, 3)
    assert np.allclose(capture.train_images[0][0, 0], 1.0)  # transparent -> white background
    assert np.allclose(capture.train_images[0][3, 3], (1.0, 0.0, 0.0))
    assert np.array_equal(capture.background, np.ones(3)) and capture.points.shape == (100_000, 3)


def test_colmap_points_binary_and_text(tmp_path: Path) -> None:
    import struct

    sparse = tmp_path / "bin"
    sparse.mkdir()
    data = struct.pack("<Q", 2)
    data += struct.pack("<QdddBBBdQ", 1, 1.0, 2.0, 3.0, 255, 0, 0, 0.5, 2) + struct.pack("<iiii", 1, 2, 3, 4)
    data += struct.pack("<QdddBBBdQ", 2, -1.0, 0.0, 1.0, 0, 0, 255, 0.5, 0)
    (sparse / "points3D.bin").write_bytes(data)
    xyz, rgb = read_colmap_points(sparse)
    assert np.array_equal(xyz, [[1, 2, 3], [-1, 0, 1]]) and np.array_equal(rgb, [[1, 0, 0], [0, 0, 1]])
    text = tmp_path / "txt"
    text.mkdir()
    (text / "points3D.txt").write_text("# comment\n7 0.5 0.25 1 10 20 30 0.1 1 2\n")
    xyz, rgb = read_colmap_points(text)
    assert np.allclose(xyz, [[0.5, 0.25, 1.0]]) and np.allclose(rgb * 255, [[10, 20, 30]])


def test_initialisation_follows_the_reference(tiny_capture) -> None:
    model = GaussianModel.from_points(tiny_capture.points, tiny_capture.colors, 3, "full")
    assert np.allclose(1 / (1 + np.exp(-model.params["opacities"].astype(np.float64))), 0.1, atol=1e-6)
    assert np.allclose(model.params["sh_dc"] * C0 + 0.5, tiny_capture.colors, atol=1e-6)
    assert np.all(model.params["quats"] == [1, 0, 0, 0]) and not np.any(model.params["sh_rest"])
    scales = model.params["scales"]
    assert np.all(scales[:, 0] == scales[:, 1]) and np.all(scales[:, 1] == scales[:, 2])
