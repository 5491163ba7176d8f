"""Deformable 3DGS on the CPU: canonical Gaussians + deformation MLP (:mod:`gscodec_shac.deform`).

Per iteration (the reference Deformable-3D-Gaussians loop, batch 1): pick a training frame
(shuffled stack), raise the active SH degree every ``sh_interval`` steps; during the static
warm-up (``warm_up`` steps) render the canonical Gaussians; afterwards query the network at the
frame's ``time`` for every Gaussian and render the deformed Gaussians with the numba rasteriser
(:class:`~gscodec_shac.render.backward.DiffRenderer`). The rasteriser's gradients w.r.t. the
deformed means, log-scales and quaternions are pushed through
:func:`~gscodec_shac.deform.deform_tensors` by torch autograd (chain rule) into the canonical
parameters and the network weights. Loss ``0.8 L1 + 0.2 D-SSIM``. Gaussians: Adam (numba, eps
1e-15) with the reference's rates (means ``1.6e-4 x 5`` decayed log-linearly to ``1.6e-6 x 5``
over 75% of the run, the reference's 30k of 40k; SH DC 2.5e-3, rest /20; opacity 0.05; scales
5e-3; rotations 1e-3); network: torch Adam (eps 1e-15), ``8e-4`` decayed log-linearly to
``1.6e-6`` over the run. Density control as the static trainer (:mod:`.densify`), statistics from
the deformed Gaussians' screen-space gradients.

**Short runs.** The reference schedule is written for 40,000 iterations (warm-up 3000, SH degree up
every 1000, densify from 500 to 15,000 every 100, opacity reset every 3000); with
``s = iterations / 40000`` every interval is scaled by ``s`` unless set explicitly.

Checkpoints: ``checkpoint.npz`` (Gaussians, Adam moments, statistics, schedule state, RNG) plus
``deform_checkpoint.pt`` (network + its Adam state); a resumed run continues where it stopped.
"""

from __future__ import annotations

import io
import json
import math
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

import gscodec_shac.render  # noqa: F401  (sets OMP_WAIT_POLICY before torch loads OpenMP)
import torch  # noqa: E402

from gscodec_shac import sh_index
from gscodec_shac.camera import Camera
from gscodec_shac.deform import DeformArch, DeformNetwork, DynamicModel, deform_tensors, save_dynamic_model
from gscodec_shac.errors import GscodecError
from gscodec_shac.render.backward import DiffRenderer
from gscodec_shac.shac.lst_torch import LAMBDA_T, t_learning_rate
from gscodec_shac.train import densify as dens
from gscodec_shac.train.fastloss import render_loss_and_grad
from gscodec_shac.train.losses import LAMBDA_DSSIM
from gscodec_shac.train.model import GaussianModel
from gscodec_shac.train.trainer import log_linear

REFERENCE_ITERATIONS = 40_000
CHECKPOINT_NAME = "checkpoint.npz"
DEFORM_CHECKPOINT_NAME = "deform_checkpoint.pt"
CHECKPOINT_VERSION = 1
NERF_CUBE = 1.3


class DynamicTrainError(GscodecError):
    """A dynamic-training setting, scene or checkpoint is unusable."""


@dataclass
class DynamicCapture:
    """Frames of a D-NeRF scene with their times and ground-truth images (float32 (H, W, 3))."""

    name: str
    train_cameras: list[Camera]
    train_times: list[float]
    train_images: list[np.ndarray]
    test_cameras: list[Camera]
    test_times: list[float]
    test_images: list[np.ndarray]
    background: np.ndarray
    extent: float
    info: dict = field(default_factory=dict)


def load_dnerf_capture(
    root: str | Path, *, resolution_scale: float = 0.5, background: Sequence[float] = (0.0, 0.0, 0.0),
    progress: bool = False,
) -> DynamicCapture:
    """Read a D-NeRF scene for training: RGBA composited over ``background`` (black as the reference's
    default), resized by ``resolution_scale`` with ``INTER_AREA``."""
    from gscodec_shac.io.dnerf import read_dnerf_scene
    from gscodec_shac.train.data import camera_extent, load_images

    root = Path(root)
    bg = np.asarray(background, dtype=np.float64).reshape(3)
    splits = read_dnerf_scene(root, resolution_scale)
    train, test = splits["train"], splits["test"]
    if not train:
        raise DynamicTrainError(f"{root}: no training frames")
    train_cams = [f.camera for f in train]
    test_cams = [f.camera for f in test]
    _, extent = camera_extent(train_cams)
    return DynamicCapture(
        name=root.name, train_cameras=train_cams, train_times=[f.time for f in train],
        train_images=load_images(train_cams, bg, progress=progress, desc="train images"),
        test_cameras=test_cams, test_times=[f.time for f in test],
        test_images=load_images(test_cams, bg, progress=progress, desc="test images"),
        background=bg, extent=extent, info={"root": str(root), "resolution_scale": resolution_scale},
    )


@dataclass
class DynamicConfig:
    """Every setting of a dynamic run (defaults: the reference; ``None`` = scaled by iterations/40000)."""

    iterations: int = 40_000
    sh: str = "full"
    sh_degree: int = 3
    max_gaussians: int | None = None
    init_points: int = 100_000
    init_opacity: float = 0.1
    seed: int = 0
    lambda_dssim: float = LAMBDA_DSSIM
    lambda_t: float = LAMBDA_T
    # network
    depth: int = 8
    width: int = 256
    # learning rates
    spatial_lr_scale: float = 5.0
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    means_decay_fraction: float = 0.75
    lr_deform: float = 8e-4
    lr_deform_final: float = 1.6e-6
    #: Quantisation-aware training: the last ``network_grid_fraction`` of the iterations see the
    #: network's matrices on the grid ``encode --network-bits network_bits`` codes (None: off).
    network_bits: int | None = None
    network_grid_fraction: float = 0.1
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20.0
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    # schedule
    warm_up: int | None = None
    sh_interval: int | None = None
    densify_from: int | None = None
    densify_until: int | None = None
    densify_interval: int | None = None
    opacity_reset_interval: int | None = None
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    min_opacity: float = 0.005
    checkpoint_every: int = 500
    log_every: int = 100

    def validate(self) -> None:
        if self.iterations < 1:
            raise DynamicTrainError(f"--iterations must be at least 1, got {self.iterations}")
        if self.sh not in ("full", "lst"):
            raise DynamicTrainError(f"--sh must be 'full' or 'lst', got {self.sh!r}")
        if not 0 <= self.sh_degree <= 3 or (self.sh == "lst" and self.sh_degree < 2):
            raise DynamicTrainError(f"--sh-degree must be 0-3 (2-3 with --sh lst), got {self.sh_degree}")
        if self.max_gaussians is not None and self.max_gaussians < 1:
            raise DynamicTrainError(f"--max-gaussians must be positive, got {self.max_gaussians}")
        if self.init_points < 1:
            raise DynamicTrainError(f"--init-points must be positive, got {self.init_points}")
        if self.depth < 2 or self.width < 1:
            raise DynamicTrainError(f"--net-depth must be >= 2 and --net-width >= 1, got {self.depth}/{self.width}")
        if not 0.0 < self.lr_deform_final <= self.lr_deform:
            raise DynamicTrainError(f"--deform-lr-final must be in (0, {self.lr_deform:g}], got {self.lr_deform_final:g}")
        if self.network_bits is not None and not 2 <= self.network_bits <= 8:
            raise DynamicTrainError(f"--network-bits must be 2-8 (the coded grid to train against), got {self.network_bits}")
        if not 0.0 < self.network_grid_fraction <= 1.0:
            raise DynamicTrainError(f"the quantisation-aware share of the iterations must be in (0, 1], "
                                    f"got {self.network_grid_fraction:g}")
        for key, value in self.resolved().items():
            if value < 0:
                raise DynamicTrainError(f"schedule value {key} must be >= 0, got {value}")

    def scaled(self, value: int | None, reference: int) -> int:
        if value is not None:
            return int(value)
        return int(round(reference * self.iterations / REFERENCE_ITERATIONS))

    def resolved(self) -> dict[str, int]:
        return {
            "warm_up": self.scaled(self.warm_up, 3000),
            "sh_interval": max(1, self.scaled(self.sh_interval, 1000)),
            "densify_from": self.scaled(self.densify_from, 500),
            "densify_until": self.scaled(self.densify_until, 15_000),
            "densify_interval": max(1, self.scaled(self.densify_interval, 100)),
            "opacity_reset_interval": max(1, self.scaled(self.opacity_reset_interval, 3000)),
        }

    def arch(self) -> DeformArch:
        return DeformArch(depth=self.depth, width=self.width)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "DynamicConfig":
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})


def initial_model(capture: DynamicCapture, config: DynamicConfig, rng: np.random.Generator) -> GaussianModel:
    """The reference's D-NeRF initialisation: uniform random points in [-1.3, 1.3]^3, opacity 0.1;
    colours: the median training pixel they project to (the reference draws random dark colours)."""
    from gscodec_shac.train.data import project_colors

    points = rng.uniform(-NERF_CUBE, NERF_CUBE, (config.init_points, 3))
    colors = np.clip(project_colors(points, capture.train_cameras, capture.train_images), 0.0, 1.0)
    model = GaussianModel.from_points(points, colors, config.sh_degree, config.sh, config.init_opacity,
                                      config.lambda_t)
    if config.max_gaussians is not None and model.num_gaussians > config.max_gaussians:
        model.select(np.sort(rng.choice(model.num_gaussians, config.max_gaussians, replace=False)))
    return model


@dataclass
class DynStep:
    iteration: int
    loss: float
    psnr: float
    num_gaussians: int
    sh_degree: int
    seconds: float
    phases: dict[str, float] = field(default_factory=dict)


class DynamicTrainer:
    """Trains canonical Gaussians + deformation network on a :class:`DynamicCapture`."""

    def __init__(
        self, capture: DynamicCapture, config: DynamicConfig, *, model: GaussianModel | None = None,
        net: DeformNetwork | None = None,
    ) -> None:
        config.validate()
        self.capture = capture
        self.config = config
        self.schedule = config.resolved()
        self.rng = np.random.default_rng(config.seed)
        torch.manual_seed(config.seed)
        self.model = model if model is not None else initial_model(capture, config, self.rng)
        self.net = net if net is not None else DeformNetwork(config.arch())
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=config.lr_deform, eps=1e-15)
        self.stats = dens.DensifyStats.zeros(self.model.num_gaussians)
        self.iteration = 0
        self.active_degree = 0
        self.view_stack: list[int] = []
        self.renderer = DiffRenderer()
        self.elapsed = 0.0
        self.log: list[dict[str, Any]] = []
        self.events: list[dict[str, Any]] = []

    # ------------------------------------------------------------------ schedule
    def learning_rates(self, it: int) -> dict[str, float]:
        c = self.config
        decay = max(1.0, c.means_decay_fraction * c.iterations)
        means = log_linear(c.lr_means * c.spatial_lr_scale, c.lr_means_final * c.spatial_lr_scale, it / decay)
        return {"means": means, "scales": c.lr_scales, "quats": c.lr_quats, "opacities": c.lr_opacity,
                "sh_dc": c.lr_sh_dc, "sh_rest": c.lr_sh_rest, "sh_subset": c.lr_sh_rest,
                "deform": log_linear(c.lr_deform, c.lr_deform_final, it / c.iterations)}

    def _next_view(self) -> int:
        if not self.view_stack:
            self.view_stack = list(range(len(self.capture.train_cameras)))
        return self.view_stack.pop(int(self.rng.integers(len(self.view_stack))))

    def deforming(self, it: int) -> bool:
        return it > self.schedule["warm_up"]

    def network_grid(self, it: int) -> dict[str, int] | None:
        """The per-matrix bits the network trains against at iteration ``it`` (quantisation-aware
        phase: the last ``network_grid_fraction`` of the run, once the network is in use), else None."""
        c = self.config
        if c.network_bits is None or not self.deforming(it):
            return None
        if it <= c.iterations - round(c.network_grid_fraction * c.iterations):
            return None
        from gscodec_shac.codec.deformation import encoder_grid

        return encoder_grid(self.net.arch, c.network_bits)

    # ------------------------------------------------------------------ one iteration
    def step(self) -> DynStep:
        start = time.perf_counter()
        c, s, model = self.config, self.schedule, self.model
        it = self.iteration + 1
        if it % s["sh_interval"] == 0 and self.active_degree < model.sh_degree:
            self.active_degree += 1
        view = self._next_view()
        camera = self.capture.train_cameras[view]
        t_frame = self.capture.train_times[view]
        n = model.num_gaussians
        n_active = sh_index.num_rest_coeffs(self.active_degree)
        p = model.params
        t0 = time.perf_counter()
        subset_t = ac_t = None
        if model.sh_mode == "lst":
            subset_t = torch.from_numpy(p["sh_subset"]).requires_grad_(True)
            ac_t = model.lst(subset_t)
            rest = sh_index.sh_rest_from_ac(ac_t.detach().numpy())[:, :n_active]
        else:
            rest = p["sh_rest"][:, :n_active]
        deform = self.deforming(it)
        self.net.grid_bits = self.network_grid(it)
        if deform:
            scales_t = torch.from_numpy(p["scales"]).requires_grad_(True)
            quats_t = torch.from_numpy(p["quats"]).requires_grad_(True)
            d_means, d_scales, d_quats = deform_tensors(self.net, torch.from_numpy(p["means"]), scales_t, quats_t,
                                                        t_frame)
            arrays = [np.ascontiguousarray(x.detach().numpy()) for x in (d_means, d_scales, d_quats)]
        else:
            arrays = [p["means"], p["scales"], p["quats"]]
        t1 = time.perf_counter()
        state = self.renderer.forward(arrays[0], arrays[1], arrays[2], p["opacities"], p["sh_dc"], rest, camera,
                                      self.capture.background)
        t2 = time.perf_counter()
        truth = self.capture.train_images[view]
        loss, dl_dimage = render_loss_and_grad(state.image, truth, c.lambda_dssim, dtype=np.float32)
        mse = float(np.mean((np.clip(state.image, 0.0, 1.0) - truth) ** 2))
        grads = self.renderer.backward(state, dl_dimage, dtype=np.float32)
        t3 = time.perf_counter()
        g: dict[str, np.ndarray] = {"means": grads.means, "opacities": grads.logits, "sh_dc": grads.sh_dc}
        lrs = self.learning_rates(it)
        if deform:
            self.optimizer.zero_grad(set_to_none=True)
            torch.autograd.backward(
                [d_means, d_scales, d_quats],
                [torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
                 for a in (grads.means, grads.log_scales, grads.quats)],
            )
            g["scales"] = scales_t.grad.numpy()
            g["quats"] = quats_t.grad.numpy()
            for group in self.optimizer.param_groups:
                group["lr"] = lrs["deform"]
            self.optimizer.step()
        else:
            g["scales"] = grads.log_scales
            g["quats"] = grads.quats
        if model.sh_mode == "lst":
            g_ac = np.zeros((n, ac_t.shape[1]), dtype=np.float32)
            g_ac[:, : 3 * n_active] = grads.sh_rest.reshape(n, -1)
            ac_t.backward(torch.from_numpy(g_ac))
            penalty = model.lst.penalty()
            penalty.backward()
            loss += float(penalty.detach())
            g["sh_subset"] = subset_t.grad.numpy()
        else:
            g["sh_rest"] = grads.sh_rest
        if it < s["densify_until"]:
            self.stats.update(grads.means2d_ndc_norm, grads.radii)
        lst_lr = t_learning_rate(it - 1, c.iterations) if model.sh_mode == "lst" else None
        columns = {"sh_rest": 3 * n_active} if model.sh_mode == "full" else None
        model.adam_step(g, lrs, lst_lr, columns)
        t4 = time.perf_counter()
        self._density_control(it)
        t5 = time.perf_counter()
        self.iteration = it
        seconds = time.perf_counter() - start
        self.elapsed += seconds
        phases = {"deform": t1 - t0, "render_forward": t2 - t1, "loss_backward": t3 - t2, "optimizer": t4 - t3,
                  "density": t5 - t4}
        return DynStep(it, loss, -10.0 * math.log10(max(mse, 1e-12)), model.num_gaussians, self.active_degree,
                       seconds, phases)

    def _density_control(self, it: int) -> None:
        c, s, model = self.config, self.schedule, self.model
        if it >= s["densify_until"]:
            return
        if it > s["densify_from"] and it % s["densify_interval"] == 0:
            size = 20 if it > s["opacity_reset_interval"] else None
            result = dens.densify_and_prune(
                model, self.stats, grad_threshold=c.densify_grad_threshold, extent=self.capture.extent,
                percent_dense=c.percent_dense, min_opacity=c.min_opacity, max_screen_size=size, rng=self.rng,
                max_gaussians=c.max_gaussians,
            )
            self.events.append({"it": it, "cloned": result.cloned, "split": result.split, "pruned": result.pruned,
                                "n": model.num_gaussians})
        white = bool(np.all(self.capture.background == 1.0))
        if it % s["opacity_reset_interval"] == 0 or (white and it == s["densify_from"]):
            dens.reset_opacity(model)
            self.events.append({"it": it, "opacity_reset": True})

    # ------------------------------------------------------------------ loop
    def train(
        self, *, time_budget: float | None = None, out_dir: Path | None = None, progress: bool = True,
        callback: Callable[[DynStep], None] | None = None,
    ) -> bool:
        """Train until ``iterations`` (True) or ``time_budget`` seconds of this call (False)."""
        from tqdm import tqdm

        c = self.config
        began = time.perf_counter()
        bar = tqdm(total=c.iterations, initial=self.iteration, desc="train-dynamic", unit="it",
                   disable=not progress, dynamic_ncols=True, mininterval=2.0)
        recent: list[DynStep] = []
        try:
            while self.iteration < c.iterations:
                if time_budget is not None and time.perf_counter() - began >= time_budget:
                    break
                info = self.step()
                recent.append(info)
                bar.update(1)
                if callback is not None:
                    callback(info)
                if info.iteration % c.log_every == 0 or info.iteration == c.iterations:
                    last = recent[-1]
                    entry = {
                        "it": last.iteration, "loss": float(np.mean([r.loss for r in recent])),
                        "psnr": float(np.mean([r.psnr for r in recent])), "n": last.num_gaussians,
                        "deg": last.sh_degree, "s_per_it": float(np.median([r.seconds for r in recent])),
                        "elapsed": self.elapsed,
                        "phases": {k: float(np.median([r.phases[k] for r in recent])) for k in last.phases},
                    }
                    self.log.append(entry)
                    recent = []
                    bar.set_postfix(loss=f"{entry['loss']:.4f}", psnr=f"{entry['psnr']:.2f}", n=entry["n"],
                                    s_it=f"{entry['s_per_it']:.3f}")
                    if not progress:
                        print(json.dumps(entry), flush=True)
                if out_dir is not None and info.iteration % c.checkpoint_every == 0:
                    self.save_checkpoint(Path(out_dir))
        finally:
            bar.close()
        if out_dir is not None:
            self.save_checkpoint(Path(out_dir))
        return self.iteration >= c.iterations

    # ------------------------------------------------------------------ model / evaluation
    def dynamic_model(self) -> tuple[DynamicModel, Any]:
        """``(DynamicModel, LST stage or None)``: canonical full-SH cloud + a copy of the network."""
        from gscodec_shac.train.trainer import export_cloud

        cloud, stage = export_cloud(self.model)
        net = DeformNetwork(self.net.arch)
        net.load_weights(self.net.weights())
        if not self.deforming(self.iteration):
            # still in the warm-up: the network is not in use yet; store it as the identity
            with torch.no_grad():
                for head in (net.head_xyz, net.head_rot, net.head_scale):
                    head.weight.zero_()
                    head.bias.zero_()
        grid = self.network_grid(self.iteration)
        if grid is not None:  # the network the last iterations trained: its weights on the coded grid
            net.snap_to_grid(grid)
        return DynamicModel(cloud, net), stage

    def evaluate(self, progress: bool = False) -> dict[str, Any]:
        return evaluate_dynamic(self.dynamic_model()[0], self.capture, progress=progress)

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self, out_dir: Path) -> Path:
        from gscodec_shac.atomic import atomic_output, write_atomic

        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        meta = {
            "version": CHECKPOINT_VERSION, "iteration": self.iteration, "active_degree": self.active_degree,
            "view_stack": self.view_stack, "rng": self.rng.bit_generator.state, "elapsed": self.elapsed,
            "config": self.config.to_dict(), "model": self.model.meta(), "log": self.log,
            "events": self.events[-500:], "capture": self.capture.name,
        }
        arrays = dict(self.model.state_arrays())
        arrays.update({"stats/grad_accum": self.stats.grad_accum, "stats/denom": self.stats.denom,
                       "stats/max_radii": self.stats.max_radii})
        buffer = io.BytesIO()
        torch.save({"net": self.net.state_dict(), "optimizer": self.optimizer.state_dict(),
                    "torch_rng": torch.get_rng_state()}, buffer)
        write_atomic(out_dir / DEFORM_CHECKPOINT_NAME, buffer.getvalue())
        with atomic_output(out_dir / CHECKPOINT_NAME) as handle:
            np.savez(handle, meta=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8), **arrays)
        return out_dir / CHECKPOINT_NAME

    @classmethod
    def from_checkpoint(cls, capture: DynamicCapture, out_dir: Path) -> "DynamicTrainer":
        out_dir = Path(out_dir)
        path, deform_path = out_dir / CHECKPOINT_NAME, out_dir / DEFORM_CHECKPOINT_NAME
        if not path.is_file() or not deform_path.is_file():
            raise DynamicTrainError(f"{out_dir}: no dynamic training checkpoint to resume from")
        try:
            with np.load(path) as data:
                arrays = {k: data[k] for k in data.files}
            meta = json.loads(arrays.pop("meta").tobytes().decode())
            saved = torch.load(deform_path, weights_only=True)
        except (OSError, ValueError, KeyError, RuntimeError) as exc:
            raise DynamicTrainError(f"{out_dir}: not a readable dynamic checkpoint ({exc})") from None
        if meta.get("version") != CHECKPOINT_VERSION:
            raise DynamicTrainError(f"{path}: checkpoint version {meta.get('version')} is not supported")
        if meta.get("capture") not in (None, capture.name):
            raise DynamicTrainError(f"{path}: trained on {meta['capture']!r}, not on {capture.name!r}")
        config = DynamicConfig.from_dict(meta["config"])
        model = GaussianModel.from_state(meta["model"], arrays)
        net = DeformNetwork(config.arch())
        net.load_state_dict(saved["net"])
        trainer = cls(capture, config, model=model, net=net)
        trainer.optimizer.load_state_dict(saved["optimizer"])
        torch.set_rng_state(saved["torch_rng"])
        trainer.stats = dens.DensifyStats(arrays["stats/grad_accum"].copy(), arrays["stats/denom"].copy(),
                                          arrays["stats/max_radii"].copy())
        trainer.iteration = int(meta["iteration"])
        trainer.active_degree = int(meta["active_degree"])
        trainer.view_stack = [int(v) for v in meta["view_stack"]]
        trainer.rng.bit_generator.state = meta["rng"]
        trainer.elapsed = float(meta["elapsed"])
        trainer.log = list(meta.get("log", []))
        trainer.events = list(meta.get("events", []))
        return trainer


def evaluate_dynamic(
    model: DynamicModel, capture: DynamicCapture, *, progress: bool = False
) -> dict[str, Any]:
    """Per test frame (rendered at its own time): PSNR and SSIM against the composited ground truth;
    the means are the arithmetic means of the per-image values (as the reference's metrics.py)."""
    from tqdm import tqdm

    from gscodec_shac.metrics import psnr, ssim
    from gscodec_shac.render import Renderer

    views = []
    frames = list(zip(capture.test_cameras, capture.test_times, capture.test_images))
    for cam, t, truth in tqdm(frames, desc="test frames", disable=not progress, leave=False):
        image = Renderer(model.at(t)).render(cam, background=capture.background).image
        views.append({"name": cam.name, "time": t, "psnr": psnr(image, truth), "ssim": ssim(image, truth)})
    return {
        "views": views,
        "mean_psnr": float(np.mean([v["psnr"] for v in views])) if views else None,
        "mean_ssim": float(np.mean([v["ssim"] for v in views])) if views else None,
    }


def write_dynamic_outputs(
    trainer: DynamicTrainer, out_dir: Path, *, evaluate: bool = True, extra: dict[str, Any] | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """The model directory (``point_cloud.ply``, ``deformation.npz``, ``deformation.json``;
    ``point_cloud.lst.npz`` for SHAC-LST) and ``metrics.json``; returns the metrics."""
    from gscodec_shac.atomic import write_atomic

    out_dir = Path(out_dir)
    model, stage = trainer.dynamic_model()
    c = trainer.config
    save_dynamic_model(out_dir, model, {"source": "gscodec-shac train-dynamic", "iterations": trainer.iteration})
    if stage is not None:
        from gscodec_shac.train.finetune import compact_path_for, save_compact

        save_compact(compact_path_for(out_dir / "point_cloud.ply"), model.cloud, trainer.model.params["sh_subset"],
                     stage, {"source": "gscodec-shac train-dynamic", "iterations": trainer.iteration})
    n = trainer.model.num_gaussians
    metrics: dict[str, Any] = {
        "capture": trainer.capture.name, "complete": trainer.iteration >= c.iterations,
        "iterations_done": trainer.iteration, "train_seconds": trainer.elapsed,
        "seconds_per_iteration": trainer.elapsed / max(1, trainer.iteration),
        "width": trainer.capture.train_cameras[0].width, "height": trainer.capture.train_cameras[0].height,
        "n_train_views": len(trainer.capture.train_cameras), "n_test_views": len(trainer.capture.test_cameras),
        "background": trainer.capture.background.tolist(), "num_gaussians": n,
        "network_params": model.net.n_params, "arch": model.arch.to_dict(),
        "sizes": {"canonical_mb": n * (11 + 3 * sh_index.num_coeffs(trainer.model.sh_degree)) * 4 / 1e6,
                  "network_mb": model.net.n_params * 4 / 1e6},
        "config": c.to_dict(), "schedule": trainer.schedule,
    }
    metrics["sizes"]["total_mb"] = metrics["sizes"]["canonical_mb"] + metrics["sizes"]["network_mb"]
    if evaluate:
        start = time.perf_counter()
        metrics["test"] = evaluate_dynamic(model, trainer.capture, progress=progress)
        metrics["eval_seconds"] = time.perf_counter() - start
    metrics.update(extra or {})
    metrics["log"] = trainer.log
    metrics["events"] = trainer.events[-200:]
    write_atomic(out_dir / "metrics.json", json.dumps(metrics, indent=1))
    return metrics
