"""A compact 3DGS trainer on the CPU: the reference recipe with full SH or SHAC-LST.

Per iteration (the reference ``train.py`` loop): pick a training view (a shuffled stack, refilled
when empty), raise the active SH degree every ``sh_interval`` steps, render with
:class:`~gscodec_shac.render.backward.DiffRenderer`, loss ``0.8 L1 + 0.2 D-SSIM``
(:func:`gscodec_shac.train.fastloss.render_loss_and_grad`, numerically
:func:`gscodec_shac.train.losses.render_loss`, with its image gradient), backward through the
numba rasteriser, one Adam step (eps 1e-15), then density control.

**Learning rates** (reference 3DGS): means ``1.6e-4 x extent`` decayed exponentially to
``1.6e-6 x extent`` over the run; SH DC ``2.5e-3``; SH rest (and the LST subset ``S``, as the
paper's Sec. VI-B2) ``2.5e-3 / 20``; opacity ``0.05`` (the original 3DGS release; newer
releases use 0.025: ``opacity_lr``); scales ``5e-3``; rotations ``1e-3``. LST's ``T``:
:func:`~gscodec_shac.shac.lst_torch.t_learning_rate` (warm-up to 2.5e-3 over 5% of the steps,
cosine to 2.5e-5) and the eq. (36) regulariser with ``lambda_t = 5e-3`` (eq. 37).

**Short runs.** The reference schedule is written for 30,000 iterations. With ``s =
iterations / 30000`` every interval is scaled by ``s`` (rounded, at least 1): SH degree up every
``1000 s`` steps; densification from ``500 s`` to ``15000 s`` every ``100 s`` steps with an
opacity reset every ``3000 s``; MCMC refinement from ``500 s`` to ``25000 s`` every ``100 s``.
The learning-rate schedules run over the actual iteration count. Any interval can be set
explicitly in :class:`TrainConfig`.

**Strategies.** ``"default"``: the reference's clone/split/prune + opacity reset
(:mod:`.densify`), optionally capped by ``max_gaussians``. ``"mcmc"``: a fixed budget
(:mod:`.mcmc`): N grows to exactly ``max_gaussians`` (the growth per refinement step is at
least 5% and large enough to reach the cap by 60% of the refinement window) and dead Gaussians
are relocated, so runs compared at equal N really have equal N.

**Checkpoints** (``checkpoint.npz``) hold every parameter, Adam moment, ``T``, the density
statistics, the active SH degree, the view stack and the random generator state: a resumed run
continues bit-identically (the raster backward reduces in a fixed order).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Callable

import numpy as np

import gscodec_shac.render  # noqa: F401  (sets OMP_WAIT_POLICY before torch loads OpenMP)
import torch  # noqa: E402

from gscodec_shac import sh_index
from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.render.backward import DiffRenderer
from gscodec_shac.shac.lst_torch import LAMBDA_T, LSTConfig, t_learning_rate
from gscodec_shac.train import densify as dens
from gscodec_shac.train import mcmc
from gscodec_shac.train.data import Capture
from gscodec_shac.train.fastloss import render_loss_and_grad
from gscodec_shac.train.losses import LAMBDA_DSSIM
from gscodec_shac.train.model import GaussianModel

REFERENCE_ITERATIONS = 30_000
CHECKPOINT_NAME = "checkpoint.npz"
CHECKPOINT_VERSION = 1


class TrainError(GscodecError):
    """A training setting or checkpoint is unusable."""


@dataclass
class TrainConfig:
    """Every setting of a run (defaults = the reference recipe; ``None`` = scaled, see module)."""

    iterations: int = 30_000
    sh: str = "full"
    sh_degree: int = 3
    strategy: str = "default"
    max_gaussians: int | None = None
    seed: int = 0
    init_opacity: float = 0.1
    lambda_dssim: float = LAMBDA_DSSIM
    lambda_t: float = LAMBDA_T
    # SHAC-LST variant (paper Sec. VII-E, Tables VII-IX; defaults = the paper's model)
    lst_subset: str = "lowest"
    lst_operator: str = "matrix"
    lst_structure: str = "block"
    lst_rgb: str = "joint"
    lst_init: str = "zero"
    # learning rates
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20.0
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    #: the factor every learning rate but the positions' decays to over the run, exponentially (1: constant,
    #: as the reference trains; the recovery's fine-tune decays them over its last quarter,
    #: gscodec_shac.train.recover.LEARNING_RATES)
    lr_decay_final: float = 1.0
    #: the share of the run before that decay starts (0: from the first step)
    lr_decay_start: float = 0.0
    # schedule (None = reference value scaled by iterations / 30000)
    sh_interval: int | None = None
    densify_from: int | None = None
    densify_until: int | None = None
    densify_interval: int | None = None
    opacity_reset_interval: int | None = None
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    min_opacity: float = 0.005
    # MCMC
    refine_from: int | None = None
    refine_until: int | None = None
    refine_every: int | None = None
    mcmc_growth: float = 0.05
    noise_lr: float = 5e5
    opacity_reg: float = 0.01
    scale_reg: float = 0.01
    # bookkeeping
    checkpoint_every: int = 500
    log_every: int = 100

    def validate(self) -> None:
        if self.iterations < 1:
            raise TrainError(f"--iterations must be at least 1, got {self.iterations}")
        if self.sh not in ("full", "lst"):
            raise TrainError(f"--sh must be 'full' or 'lst', got {self.sh!r}")
        if not 0 <= self.sh_degree <= 3:
            raise TrainError(f"--sh-degree must be 0-3, got {self.sh_degree}")
        if self.sh == "lst" and self.sh_degree < 2:
            raise TrainError("--sh lst needs --sh-degree 2 or 3")
        if not (math.isfinite(self.lr_decay_final) and 0 < self.lr_decay_final <= 1):
            raise TrainError(f"lr_decay_final must lie in (0, 1], got {self.lr_decay_final}")
        if not (math.isfinite(self.lr_decay_start) and 0 <= self.lr_decay_start < 1):
            raise TrainError(f"lr_decay_start must lie in [0, 1), got {self.lr_decay_start}")
        if not (math.isfinite(self.lambda_t) and self.lambda_t >= 0):
            raise TrainError(f"--lambda-t must be a number >= 0, got {self.lambda_t}")
        if self.sh == "lst":
            try:
                self.lst_config()
            except ValidationError as exc:
                raise TrainError(f"SHAC-LST variant: {exc}") from None
        if self.strategy not in ("default", "mcmc"):
            raise TrainError(f"--strategy must be 'default' or 'mcmc', got {self.strategy!r}")
        if self.strategy == "mcmc" and not self.max_gaussians:
            raise TrainError("--strategy mcmc needs --max-gaussians (the fixed budget)")
        if self.max_gaussians is not None and self.max_gaussians < 1:
            raise TrainError(f"--max-gaussians must be positive, got {self.max_gaussians}")
        if not 0.0 < self.init_opacity < 1.0:
            raise TrainError(f"the initial opacity must lie in (0, 1), got {self.init_opacity}")

    def scaled(self, value: int | None, reference: int) -> int:
        """``value`` or ``reference x iterations / 30000`` rounded (at least 1 for intervals)."""
        if value is not None:
            return int(value)
        return int(round(reference * self.iterations / REFERENCE_ITERATIONS))

    def resolved(self) -> dict[str, int]:
        """The schedule in iterations after scaling."""
        return {
            "sh_interval": max(1, self.scaled(self.sh_interval, 1000)),
            "densify_from": self.scaled(self.densify_from, 500),
            "densify_until": self.scaled(self.densify_until, 15_000),
            "densify_interval": max(1, self.scaled(self.densify_interval, 100)),
            "opacity_reset_interval": max(1, self.scaled(self.opacity_reset_interval, 3000)),
            "refine_from": self.scaled(self.refine_from, 500),
            "refine_until": self.scaled(self.refine_until, 25_000),
            "refine_every": max(1, self.scaled(self.refine_every, 100)),
        }

    def lst_config(self) -> LSTConfig:
        """The :class:`LSTConfig` of an ``sh="lst"`` run (variant and ``lambda_t``)."""
        return LSTConfig(
            degree=self.sh_degree, subset=self.lst_subset, operator=self.lst_operator,
            structure=self.lst_structure, rgb=self.lst_rgb, init=self.lst_init, lambda_t=self.lambda_t,
        )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "TrainConfig":
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})


def log_linear(start: float, end: float, t: float) -> float:
    """``exp((1 - t) log start + t log end)`` with ``t`` clipped to [0, 1]: the schedules' exponential decay."""
    t = min(1.0, max(0.0, t))
    return math.exp((1.0 - t) * math.log(start) + t * math.log(end))


def decay_factor(config: TrainConfig, iteration: int) -> float:
    """Exponential decay from 1 to ``lr_decay_final`` over the run after its first ``lr_decay_start``
    share (1 throughout by default)."""
    start = config.lr_decay_start
    return log_linear(1.0, config.lr_decay_final, (iteration / config.iterations - start) / (1.0 - start))


def means_lr(config: TrainConfig, extent: float, iteration: int) -> float:
    """Exponential decay from ``lr_means`` to ``lr_means_final`` (x extent) over the run."""
    return log_linear(config.lr_means * extent, config.lr_means_final * extent, iteration / config.iterations)


@dataclass
class StepInfo:
    iteration: int
    loss: float
    psnr: float
    num_gaussians: int
    sh_degree: int
    seconds: float
    phases: dict[str, float] = field(default_factory=dict)


class Trainer:
    """Trains a :class:`GaussianModel` on a :class:`Capture` (see the module docstring)."""

    def __init__(self, capture: Capture, config: TrainConfig, *, model: GaussianModel | None = None) -> None:
        config.validate()
        self.capture = capture
        self.config = config
        self.schedule = config.resolved()
        self.rng = np.random.default_rng(config.seed)
        if model is None:
            lst_config = config.lst_config() if config.sh == "lst" else None
            if lst_config is not None and lst_config.operator in ("linear", "mlp"):
                torch.manual_seed(config.seed)  # torch's default init of the linear / hidden MLP layers
            model = GaussianModel.from_points(
                capture.points, capture.colors, config.sh_degree, config.sh, config.init_opacity, config.lambda_t,
                lst_config,
            )
            if config.max_gaussians is not None and model.num_gaussians > config.max_gaussians:
                keep = np.sort(self.rng.choice(model.num_gaussians, config.max_gaussians, replace=False))
                model.select(keep)
        self.model = model
        self.stats = dens.DensifyStats.zeros(model.num_gaussians)
        self.iteration = 0
        self.active_degree = 0
        self.view_stack: list[int] = []
        self.renderer = DiffRenderer()
        self.elapsed = 0.0
        self.log: list[dict[str, Any]] = []
        self.events: list[dict[str, Any]] = []
        self._mcmc_growth = self._growth_rate()

    # ------------------------------------------------------------------ schedule helpers
    def _growth_rate(self) -> float:
        c, s = self.config, self.schedule
        if c.strategy != "mcmc":
            return 0.0
        steps = max(1, int(0.6 * max(0, s["refine_until"] - s["refine_from"]) / s["refine_every"]))
        n0 = max(1, self.model.num_gaussians)
        needed = (c.max_gaussians / n0) ** (1.0 / steps) - 1.0 if c.max_gaussians > n0 else 0.0
        return max(c.mcmc_growth, needed)

    def learning_rates(self, iteration: int) -> dict[str, float]:
        c = self.config
        d = decay_factor(c, iteration)
        rates = {
            "means": means_lr(c, self.capture.extent, iteration), "scales": c.lr_scales * d, "quats": c.lr_quats * d,
            "opacities": c.lr_opacity * d, "sh_dc": c.lr_sh_dc * d, "sh_rest": c.lr_sh_rest * d,
            "sh_subset": c.lr_sh_rest * d,
        }
        return rates

    def _next_view(self) -> int:
        if not self.view_stack:
            self.view_stack = list(range(len(self.capture.train_cameras)))
        return self.view_stack.pop(int(self.rng.integers(len(self.view_stack))))

    # ------------------------------------------------------------------ one iteration
    def step(self) -> StepInfo:
        """Run iteration ``self.iteration + 1``."""
        start = time.perf_counter()
        c, s, model = self.config, self.schedule, self.model
        it = self.iteration + 1
        if it % s["sh_interval"] == 0 and self.active_degree < model.sh_degree:
            self.active_degree += 1
        view = self._next_view()
        camera = self.capture.train_cameras[view]
        n = model.num_gaussians
        n_active = sh_index.num_rest_coeffs(self.active_degree)
        phases: dict[str, float] = {}

        t0 = time.perf_counter()
        p = model.params
        subset_t = ac_t = None
        if model.sh_mode == "lst":
            subset_t = torch.from_numpy(p["sh_subset"]).requires_grad_(True)
            ac_t = model.lst(subset_t)
            rest = sh_index.sh_rest_from_ac(ac_t.detach().numpy())[:, :n_active]
        else:
            rest = p["sh_rest"][:, :n_active]
        state = self.renderer.forward(
            p["means"], p["scales"], p["quats"], p["opacities"], p["sh_dc"], rest, camera, self.capture.background
        )
        t1 = time.perf_counter()
        truth = self.capture.train_images[view]
        loss, dl_dimage = render_loss_and_grad(state.image, truth, c.lambda_dssim, dtype=np.float32)
        mse = float(np.mean((np.clip(state.image, 0.0, 1.0) - truth) ** 2))
        t2 = time.perf_counter()
        grads = self.renderer.backward(state, dl_dimage, dtype=np.float32)
        t3 = time.perf_counter()

        g: dict[str, np.ndarray] = {
            "means": grads.means, "scales": grads.log_scales, "quats": grads.quats,
            "opacities": grads.logits, "sh_dc": grads.sh_dc,
        }
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
        if c.strategy == "mcmc":
            reg, g_op, g_sc = mcmc.regularizer_grads(model, c.opacity_reg, c.scale_reg)
            loss += reg
            g["opacities"] = g["opacities"] + g_op
            g["scales"] = g["scales"] + g_sc
        if c.strategy == "default" and it < s["densify_until"]:
            self.stats.update(grads.means2d_ndc_norm, grads.radii)

        lrs = self.learning_rates(it)
        lst_lr = t_learning_rate(it - 1, c.iterations) if model.sh_mode == "lst" else None
        columns = {"sh_rest": 3 * n_active} if model.sh_mode == "full" else None
        model.adam_step(g, lrs, lst_lr, columns)
        t4 = time.perf_counter()
        self._density_control(it, lrs["means"])
        t5 = time.perf_counter()
        phases.update(forward=t1 - t0, loss=t2 - t1, backward=t3 - t2, optimizer=t4 - t3, density=t5 - t4)
        self.iteration = it
        seconds = time.perf_counter() - start
        self.elapsed += seconds
        psnr = -10.0 * math.log10(max(mse, 1e-12))
        return StepInfo(it, loss, psnr, model.num_gaussians, self.active_degree, seconds, phases)

    def _density_control(self, it: int, lr_means: float) -> None:
        c, s, model = self.config, self.schedule, self.model
        if c.strategy == "default":
            if it < s["densify_until"]:
                if it > s["densify_from"] and it % s["densify_interval"] == 0:
                    size = 20 if it > s["opacity_reset_interval"] else None
                    result = dens.densify_and_prune(
                        model, self.stats, grad_threshold=c.densify_grad_threshold, extent=self.capture.extent,
                        percent_dense=c.percent_dense, min_opacity=c.min_opacity, max_screen_size=size,
                        rng=self.rng, max_gaussians=c.max_gaussians,
                    )
                    self.events.append({"it": it, "cloned": result.cloned, "split": result.split,
                                        "pruned": result.pruned, "n": model.num_gaussians})
                white = bool(np.all(self.capture.background == 1.0))
                if it % s["opacity_reset_interval"] == 0 or (white and it == s["densify_from"]):
                    dens.reset_opacity(model)
                    self.events.append({"it": it, "opacity_reset": True})
        else:
            if s["refine_from"] <= it < s["refine_until"] and it % s["refine_every"] == 0:
                moved = mcmc.relocate(model, self.rng, c.min_opacity)
                added = mcmc.grow(model, self.rng, c.max_gaussians, self._mcmc_growth)
                self.events.append({"it": it, "relocated": moved, "added": added, "n": model.num_gaussians})
            mcmc.inject_noise(model, lr_means, self.rng, c.noise_lr)

    # ------------------------------------------------------------------ loop
    def train(
        self,
        *,
        time_budget: float | None = None,
        out_dir: Path | None = None,
        progress: bool = True,
        callback: Callable[[StepInfo], None] | None = None,
    ) -> bool:
        """Train until ``config.iterations`` (True) or until ``time_budget`` seconds of this call
        have passed (False). Checkpoints go to ``out_dir`` every ``checkpoint_every`` steps and
        at the end."""
        from tqdm import tqdm

        c = self.config
        began = time.perf_counter()
        bar = tqdm(total=c.iterations, initial=self.iteration, desc="train", unit="it", disable=not progress,
                   dynamic_ncols=True, mininterval=2.0)
        recent: list[StepInfo] = []
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
                    entry = self._log_entry(recent)
                    self.log.append(entry)
                    recent = []
                    bar.set_postfix(loss=f"{entry['loss']:.4f}", psnr=f"{entry['psnr']:.2f}", n=entry["n"],
                                    deg=entry["deg"], s_it=f"{entry['s_per_it']:.3f}")
                    if not progress:
                        print(json.dumps(entry), flush=True)
                if out_dir is not None and info.iteration % c.checkpoint_every == 0:
                    self.save_checkpoint(Path(out_dir) / CHECKPOINT_NAME)
        finally:
            bar.close()
        if out_dir is not None:
            self.save_checkpoint(Path(out_dir) / CHECKPOINT_NAME)
        return self.iteration >= c.iterations

    def _log_entry(self, recent: list[StepInfo]) -> dict[str, Any]:
        last = recent[-1]
        phases = {k: float(np.median([r.phases.get(k, 0.0) for r in recent])) for k in last.phases}
        return {
            "it": last.iteration, "loss": float(np.mean([r.loss for r in recent])),
            "psnr": float(np.mean([r.psnr for r in recent])), "n": last.num_gaussians, "deg": last.sh_degree,
            "s_per_it": float(np.median([r.seconds for r in recent])), "elapsed": self.elapsed, "phases": phases,
        }

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, split: str = "test", progress: bool = False) -> dict[str, Any]:
        """PSNR / SSIM of every view of ``split`` ("test" or "train") with the standard renderer."""
        from tqdm import tqdm

        from gscodec_shac.metrics import psnr, ssim
        from gscodec_shac.render import Renderer

        cams = self.capture.test_cameras if split == "test" else self.capture.train_cameras
        images = self.capture.test_images if split == "test" else self.capture.train_images
        renderer = Renderer(export_cloud(self.model)[0])
        views = []
        for cam, truth in tqdm(list(zip(cams, images)), desc=f"eval {split}", disable=not progress, leave=False):
            image = renderer.render(cam, background=self.capture.background).image
            views.append({"name": cam.name, "psnr": psnr(image, truth), "ssim": ssim(image, truth)})
        mean = {k: float(np.mean([v[k] for v in views])) if views else float("nan") for k in ("psnr", "ssim")}
        return {"split": split, "views": views, "mean_psnr": mean["psnr"], "mean_ssim": mean["ssim"]}

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self, path: Path) -> Path:
        """Write every piece of training state atomically (``np.savez``)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = {
            "version": CHECKPOINT_VERSION, "iteration": self.iteration, "active_degree": self.active_degree,
            "view_stack": self.view_stack, "rng": self.rng.bit_generator.state, "elapsed": self.elapsed,
            "config": self.config.to_dict(), "model": self.model.meta(), "log": self.log, "events": self.events,
            "growth": self._mcmc_growth, "capture": self.capture.name,
        }
        arrays = dict(self.model.state_arrays())
        arrays.update({"stats/grad_accum": self.stats.grad_accum, "stats/denom": self.stats.denom,
                       "stats/max_radii": self.stats.max_radii})
        from gscodec_shac.atomic import atomic_output

        with atomic_output(path) as handle:
            np.savez(handle, meta=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8), **arrays)
        return path

    @classmethod
    def from_checkpoint(cls, capture: Capture, path: Path) -> "Trainer":
        """A trainer in exactly the state saved by :meth:`save_checkpoint`."""
        path = Path(path)
        if not path.is_file():
            raise TrainError(f"{path}: no checkpoint to resume from")
        try:
            with np.load(path) as data:
                arrays = {k: data[k] for k in data.files}
            meta = json.loads(arrays.pop("meta").tobytes().decode())
        except (OSError, ValueError, KeyError) as exc:
            raise TrainError(f"{path}: not a readable training checkpoint ({exc})") from None
        if meta.get("version") != CHECKPOINT_VERSION:
            raise TrainError(f"{path}: checkpoint version {meta.get('version')} is not supported")
        if meta.get("capture") not in (None, capture.name):
            raise TrainError(f"{path}: the checkpoint was trained on {meta['capture']!r}, not on {capture.name!r}")
        config = TrainConfig.from_dict(meta["config"])
        model = GaussianModel.from_state(meta["model"], arrays)
        trainer = cls(capture, config, model=model)
        trainer.stats = dens.DensifyStats(
            arrays["stats/grad_accum"].copy(), arrays["stats/denom"].copy(), arrays["stats/max_radii"].copy()
        )
        trainer.iteration = int(meta["iteration"])
        trainer.active_degree = int(meta["active_degree"])
        trainer.view_stack = [int(v) for v in meta["view_stack"]]
        trainer.rng.bit_generator.state = meta["rng"]
        trainer.elapsed = float(meta["elapsed"])
        trainer.log = list(meta.get("log", []))
        trainer.events = list(meta.get("events", []))
        trainer._mcmc_growth = float(meta.get("growth", trainer._mcmc_growth))
        return trainer


def model_sizes(model: GaussianModel) -> dict[str, Any]:
    """Sizes as the paper counts them: float32 MB of the stored model and SH floats per Gaussian."""
    n = model.num_gaussians
    floats = model.stored_floats()
    return {
        "num_gaussians": n,
        "sh_floats_per_gaussian": model.sh_floats_per_gaussian(),
        "sh_ac_dims": model.sh_floats_per_gaussian() - 3,
        "transform_params": model.lst.n_params if model.lst is not None else 0,
        "size_mb": floats * 4 / 1e6,
        "full_ply_mb": n * (11 + 3 * sh_index.num_coeffs(model.sh_degree)) * 4 / 1e6,
    }


def export_cloud(model: GaussianModel):
    """``(cloud, stage or None)``: the model as a full-SH :class:`GaussianCloud`; for SHAC-LST the
    AC matrix is ``ShacLST.inverse_transform(S)`` so that the compact form rebuilds it exactly
    (the ablation operators vector/linear/mlp of Table VIII have no stage: ``S T`` by the module)."""
    from gscodec_shac.gaussians import GaussianCloud

    p = model.params
    stage = None
    if model.sh_mode == "lst" and model.lst.config.operator != "matrix":
        rest = model.sh_rest()  # linear / MLP / vector ablation operators: no compact stage form
    elif model.sh_mode == "lst":
        stage = model.lst_stage()
        rest = sh_index.sh_rest_from_ac(stage.inverse_transform(p["sh_subset"]))
    else:
        rest = p["sh_rest"]
    cloud = GaussianCloud(means=p["means"], scales=p["scales"], quats=p["quats"], opacities=p["opacities"],
                          sh_dc=p["sh_dc"], sh_rest=np.ascontiguousarray(rest))
    return cloud, stage


def write_outputs(
    trainer: Trainer, out_dir: Path, *, evaluate: bool = True, extra: dict[str, Any] | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Write ``point_cloud.ply`` (full SH), ``point_cloud.lst.npz`` (LST: the compact S + T form
    of :func:`gscodec_shac.train.finetune.save_compact`), ``cameras.json`` (Inria, every view at
    the training size), ``cameras_test.json`` (the held-out views only: what an RD sweep of the
    model evaluates, unambiguous also where train and test views share names, as in
    NeRF-synthetic) and ``metrics.json`` (per-test-view PSNR / SSIM and their means, sizes,
    schedule, timings); returns the metrics."""
    from gscodec_shac.io.inria_cameras import write_inria_cameras
    from gscodec_shac.io.ply import write_ply
    from gscodec_shac.metrics import psnr, ssim
    from gscodec_shac.render import Renderer

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cloud, stage = export_cloud(trainer.model)
    ply = out_dir / "point_cloud.ply"
    write_ply(ply, cloud)
    files = {"ply": ply.name}
    if stage is not None:
        from gscodec_shac.train.finetune import compact_path_for, save_compact

        compact = compact_path_for(ply)
        save_compact(compact, cloud, trainer.model.params["sh_subset"], stage,
                     {"source": "gscodec-shac train", "iterations": trainer.iteration})
        files["compact"] = compact.name
    write_inria_cameras(out_dir / "cameras.json", trainer.capture.all_cameras)
    write_inria_cameras(out_dir / "cameras_test.json", trainer.capture.test_cameras)
    files.update(cameras="cameras.json", test_cameras="cameras_test.json")
    c = trainer.config
    metrics: dict[str, Any] = {
        "capture": trainer.capture.name,
        "method": method_label(trainer.model),
        "complete": trainer.iteration >= c.iterations,
        "iterations_done": trainer.iteration,
        "train_seconds": trainer.elapsed,
        "seconds_per_iteration": trainer.elapsed / max(1, trainer.iteration),
        "width": trainer.capture.train_cameras[0].width,
        "height": trainer.capture.train_cameras[0].height,
        "n_train_views": len(trainer.capture.train_cameras),
        "n_test_views": len(trainer.capture.test_cameras),
        "sizes": model_sizes(trainer.model),
        "config": c.to_dict(),
        "schedule": trainer.schedule,
        "capture_info": trainer.capture.info,
        "files": files,
    }
    if evaluate:
        start = time.perf_counter()
        renderer = Renderer(cloud)
        views = []
        from tqdm import tqdm

        pairs = list(zip(trainer.capture.test_cameras, trainer.capture.test_images))
        for cam, truth in tqdm(pairs, desc="test views", disable=not progress, leave=False):
            image = renderer.render(cam, background=trainer.capture.background).image
            views.append({"name": cam.name, "psnr": psnr(image, truth), "ssim": ssim(image, truth)})
        metrics["test"] = {
            "views": views,
            "mean_psnr": float(np.mean([v["psnr"] for v in views])) if views else None,
            "mean_ssim": float(np.mean([v["ssim"] for v in views])) if views else None,
        }
        metrics["eval_seconds"] = time.perf_counter() - start
    metrics.update(extra or {})
    metrics["log"] = trainer.log
    metrics["events"] = trainer.events[-200:]
    from gscodec_shac.atomic import write_atomic

    write_atomic(out_dir / "metrics.json", json.dumps(metrics, indent=1))
    return metrics


def method_label(model: GaussianModel) -> str:
    """The paper's "{method}-L{degree}-D{AC dims}" label (Table II)."""
    if model.sh_mode == "lst":
        label = f"SHAC-LST-L{model.sh_degree}-D{model.params['sh_subset'].shape[1]}"
        c, paper = model.lst.config, LSTConfig(degree=model.sh_degree)
        changed = [f"{k}={v}" for k, v in c.as_dict().items() if k not in ("degree", "lambda_t") and v != getattr(paper, k)]
        if c.lambda_t != paper.lambda_t:
            changed.append(f"lambda_t={c.lambda_t:g}")
        return label + (f" ({', '.join(changed)})" if changed else "")
    return f"Train-L{model.sh_degree}-D{3 * sh_index.num_rest_coeffs(model.sh_degree)}"
