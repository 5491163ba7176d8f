"""Render-loss fine-tuning of SHAC-LST with the geometry fixed (paper eq. 33, 36-37, Sec. VI-B2).

What is trained: the per-Gaussian subset ``S`` (N x d, eq. 32), the structured transform ``T``
(the blocks ``t_l``, eq. 33-34, or an ablation variant of :class:`LSTModule`) and, unless
frozen, the DC coefficients. Means, scales, rotations and opacities stay as they are, so every
view is rendered through the sparse colour path of :mod:`gscodec_shac.train.colour_path`.
The objective is eq. (37)::

    L = 0.8 L1(image, target) + 0.2 (1 - SSIM(image, target)) + lambda_t L_T     (eq. 36)

with ``lambda_t = 5e-3``, one random training view per step (shuffled epochs, seeded), Adam
(eps 1e-15) with ``S`` at the reference SH-rest rate 1.25e-4, DC at 2.5e-3 and ``T`` on the
Sec. VI-B2 schedule (linear warm-up to 2.5e-3 over the first 5 % of steps, cosine to 2.5e-5),
all via :func:`~gscodec_shac.shac.lst_torch.lst_param_groups` /
:func:`~gscodec_shac.shac.lst_torch.make_lst_optimizer`.

Starting point (``init="posthoc"``): the post-hoc ridge fit :meth:`ShacLST.fit` (optionally
with ``refit_subset`` rounds of alternating least squares for ``S``). This is *not* the paper's
training-integrated setting, where ``S`` and ``T`` (zero-initialised) are learnt together with
the geometry from the start; ``init="module"`` starts from the module's own initialisation
(e.g. T = 0) with ``S`` = the subset columns of the pretrained model.

Targets: ground-truth images (``targets="images"``, resized with ``cv2.INTER_AREA``), or the
original model's renders from the same cameras (``"original"``; computed through the colour
path, which equals the rasteriser's image), or explicit arrays.

Outputs (:meth:`LstFinetuner.save_outputs`):

* a standard Inria PLY with the full SH ``[DC | S T]`` (any 3DGS viewer opens it);
* the compact form ``<name>.lst.npz`` (:func:`save_compact`): ``subset`` S (N, d) float32,
  ``sh_dc`` (N, 3), the geometry (``means``, ``scales``, ``quats``, ``opacities``), ``lst_state``
  (the bytes of the :class:`ShacLST` stage state: the blocks of T, float32) and a JSON ``meta``.
  ``S T`` rebuilds the PLY's SH bit for bit, and S equals the PLY's subset columns, so the
  codec's ``lst`` stage built from ``lst_state`` (``ShacLST.from_state``) returns exactly this
  ``S`` from the PLY (:func:`load_finetuned`).

Checkpoints (``torch.save``, written atomically): S, DC, T's state, Adam and scheduler state,
the step, the loss log and a fingerprint of the run; resuming checks the fingerprint and
continues bit-identically (the view order is a fixed function of the seed).
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

import numpy as np
import torch

from gscodec_shac import sh_index
from gscodec_shac.atomic import write_atomic
from gscodec_shac.camera import Camera
from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.shac.base import StageState
from gscodec_shac.shac.lst import DEFAULT_RIDGE, ShacLST
from gscodec_shac.shac.lst_torch import (
    DC_LR,
    SH_REST_LR,
    T_LR_PEAK,
    LSTConfig,
    LSTModule,
    lst_param_groups,
    make_lst_optimizer,
)
from gscodec_shac.train.colour_path import (
    DEFAULT_CACHE_BYTES,
    ViewCache,
    ViewData,
    render_cloud_view,
    render_view,
    resolve_dtype,
)
from gscodec_shac.train.losses import LAMBDA_DSSIM, l1, ssim

PathLike = str | os.PathLike

COMPACT_FORMAT = "gscodec-shac/lst-finetuned"
COMPACT_VERSION = 1
CHECKPOINT_FORMAT = "gscodec-shac/lst-finetune-checkpoint"
CHECKPOINT_VERSION = 1
INITS = ("posthoc", "module")
TARGET_KINDS = ("auto", "images", "original")
#: LST operators that are linear maps without bias (A~ = S T, eq. 33).
LINEAR_OPERATORS = ("matrix", "vector")
LOG_FIELDS = ("step", "view", "loss", "l1", "ssim", "l_t", "lr_t", "lr_s", "wall_s", "cpu_s", "cache_miss")


class FinetuneError(GscodecError):
    """A fine-tuning input, checkpoint or output file is unusable."""


# ----------------------------------------------------------------------------- config
@dataclass(frozen=True)
class FinetuneConfig:
    """Settings of one fine-tuning run (defaults: the paper's values, Sec. V-B3 / VI-B2).

    ``lst`` selects the SHAC-LST variant (``None``: the paper's model for the cloud's degree;
    ``lambda_t`` lives there). ``init``: ``"posthoc"`` (ridge fit, matrix operator with joint
    RGB only) or ``"module"``. ``dtype``: ``"float32"`` (training) or ``"float64"`` (checks).
    ``cache_bytes``: budget of the per-view weight cache. ``threads``: torch threads while
    :meth:`LstFinetuner.run` / :meth:`~LstFinetuner.mean_loss` work (restored afterwards;
    ``None`` = leave torch's setting). One thread is the default because on a shared 2-core
    machine two threads made a small-scene step 30x slower (0.47 s vs 0.014 s, measured):
    each parallel region waits for a descheduled second thread.
    """

    steps: int = 3000
    seed: int = 0
    lst: LSTConfig | None = None
    init: str = "posthoc"
    ridge: float = DEFAULT_RIDGE
    refit_subset: int = 0
    train_dc: bool = True
    sh_rest_lr: float = SH_REST_LR
    dc_lr: float = DC_LR
    t_lr: float = T_LR_PEAK
    lambda_dssim: float = LAMBDA_DSSIM
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    dtype: str = "float32"
    cache_bytes: int = DEFAULT_CACHE_BYTES
    threads: int | None = 1

    def __post_init__(self) -> None:
        if isinstance(self.steps, bool) or not isinstance(self.steps, (int, np.integer)) or self.steps < 1:
            raise ValidationError(f"steps must be a positive integer, got {self.steps!r}")
        if self.init not in INITS:
            raise ValidationError(f"init must be one of {', '.join(map(repr, INITS))}, got {self.init!r}")
        for name in ("sh_rest_lr", "dc_lr", "t_lr"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValidationError(f"{name} must be a finite number >= 0, got {value!r}")
        if not 0.0 <= self.lambda_dssim <= 1.0:
            raise ValidationError(f"lambda_dssim must lie in [0, 1], got {self.lambda_dssim!r}")
        resolve_dtype(self.dtype)
        if self.threads is not None and (isinstance(self.threads, bool) or int(self.threads) != self.threads or self.threads < 1):
            raise ValidationError(f"threads must be a positive integer or None, got {self.threads!r}")
        if len(self.background) != 3:
            raise ValidationError(f"background must be three numbers, got {self.background!r}")
        object.__setattr__(self, "background", tuple(float(v) for v in self.background))

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["lst"] = self.lst.as_dict() if self.lst is not None else None
        out["background"] = list(self.background)
        return out


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run a block with ``n`` torch threads (``None``: unchanged), restoring the old count."""
    if n is None:
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def view_schedule(n_views: int, steps: int, seed: int) -> np.ndarray:
    """The view of every step: back-to-back random permutations of the views (seeded)."""
    if n_views < 1:
        raise ValidationError("fine-tuning needs at least one training view")
    rng = np.random.default_rng(seed)
    epochs = -(-steps // n_views)
    return np.concatenate([rng.permutation(n_views) for _ in range(epochs)])[:steps]


# ----------------------------------------------------------------------------- results
@dataclass
class FinetuneResult:
    """What :meth:`LstFinetuner.run` did (this session) and the loss log of the whole run."""

    steps: int
    start_step: int
    resumed: bool
    wall_seconds: float
    prefetch_seconds: float
    step_seconds_median: float | None
    step_cpu_seconds_median: float | None
    log: list[dict[str, Any]] = field(default_factory=list)
    cache: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        losses = [row["loss"] for row in self.log]
        tail = max(1, len(losses) // 10)
        return {
            "steps": self.steps,
            "start_step": self.start_step,
            "resumed": self.resumed,
            "wall_seconds": round(self.wall_seconds, 3),
            "prefetch_seconds": round(self.prefetch_seconds, 3),
            "step_seconds_median": self.step_seconds_median,
            "step_cpu_seconds_median": self.step_cpu_seconds_median,
            "loss_first": losses[0] if losses else None,
            "loss_last_10pct_mean": float(np.mean(losses[-tail:])) if losses else None,
            "cache": self.cache,
        }


# ----------------------------------------------------------------------------- trainer
class LstFinetuner:
    """Fine-tunes SHAC-LST (S, T, DC) of ``cloud`` on ``cameras`` with the 3DGS render loss.

    ``targets``: ``"auto"`` (ground-truth images when every camera has ``image_path``, else the
    original model's renders), ``"images"``, ``"original"`` or a sequence of (H, W, 3) arrays
    in [0, 1], one per camera.
    """

    def __init__(
        self,
        cloud: GaussianCloud,
        cameras: Sequence[Camera],
        *,
        targets: str | Sequence[np.ndarray] = "auto",
        config: FinetuneConfig | None = None,
    ) -> None:
        self.config = config = config or FinetuneConfig()
        if not isinstance(cloud, GaussianCloud):
            raise FinetuneError(f"fine-tuning needs a GaussianCloud, got {type(cloud).__name__}")
        if cloud.sh_degree < 2:
            raise FinetuneError(
                f"SHAC-LST fine-tuning needs SH degree 2-4, but the model has SH degree {cloud.sh_degree}"
            )
        self.cameras = list(cameras)
        if not self.cameras:
            raise FinetuneError("fine-tuning needs at least one training camera")
        self.cloud = cloud
        self.np_dtype, self.dtype = resolve_dtype(config.dtype)
        lst = config.lst or LSTConfig(degree=cloud.sh_degree)
        if lst.degree != cloud.sh_degree:
            raise FinetuneError(f"the LST config is for SH degree {lst.degree}, the model has degree {cloud.sh_degree}")
        self.lst_config = lst
        self.target_kind = self._target_kind(targets)
        self._explicit_targets = None if isinstance(targets, str) else list(targets)
        if self._explicit_targets is not None and len(self._explicit_targets) != len(self.cameras):
            raise FinetuneError(f"got {len(self._explicit_targets)} target images for {len(self.cameras)} cameras")

        # --- parameters: post-hoc (or module) initialisation
        ac = cloud.ac_matrix()
        self.module = LSTModule(lst)
        if config.init == "posthoc":
            if lst.operator != "matrix" or lst.rgb != "joint":
                raise FinetuneError(
                    "the post-hoc initialisation needs the matrix operator with joint RGB; "
                    f"use init='module' for operator={lst.operator!r}, rgb={lst.rgb!r}"
                )
            stage = ShacLST(
                degree=lst.degree, subset=lst.subset, structure=lst.structure,
                ridge=config.ridge, refit_subset=config.refit_subset,
            ).fit(ac)
            subset0 = stage.transform(ac)
            self.module.load_blocks(stage.blocks_)
        else:
            subset0 = ac[:, self.module.layout.subset_columns]
        self.module.to(self.dtype)
        self.subset = torch.nn.Parameter(torch.tensor(np.asarray(subset0, dtype=np.float64), dtype=self.dtype))
        self.dc = torch.nn.Parameter(
            torch.tensor(cloud.sh_dc.astype(np.float64), dtype=self.dtype), requires_grad=config.train_dc
        )
        groups = lst_param_groups(
            self.module, [self.subset], [self.dc] if config.train_dc else [],
            sh_rest_lr=config.sh_rest_lr, dc_lr=config.dc_lr, t_lr=config.t_lr,
        )
        self.optimizer, self.scheduler = make_lst_optimizer(groups, config.steps)
        self.background = torch.tensor(config.background, dtype=self.dtype)
        self.schedule = view_schedule(len(self.cameras), config.steps, config.seed)
        self.step_index = 0
        self.log: list[dict[str, Any]] = []
        self.cache = ViewCache(
            cloud, self.cameras, dtype=self.dtype, max_bytes=config.cache_bytes, target=self._target
        )

    # ------------------------------------------------------------------ targets
    def _target_kind(self, targets: str | Sequence[np.ndarray]) -> str:
        if not isinstance(targets, str):
            return "given"
        if targets not in TARGET_KINDS:
            raise FinetuneError(f"targets must be one of {', '.join(TARGET_KINDS)} or a list of images, got {targets!r}")
        with_images = [c.image_path is not None for c in self.cameras]
        if targets == "images" and not all(with_images):
            missing = next(c.name for c in self.cameras if c.image_path is None)
            raise FinetuneError(f"camera {missing!r} has no ground-truth image (give the image folder)")
        if targets == "auto":
            return "images" if all(with_images) else "original"
        return targets

    def _target(self, i: int, view: ViewData) -> np.ndarray:
        camera = self.cameras[i]
        if self.target_kind == "given":
            image = np.asarray(self._explicit_targets[i], dtype=np.float32)
        elif self.target_kind == "images":
            from gscodec_shac.metrics import load_image

            image = load_image(camera.image_path, background=self.config.background, size=(camera.width, camera.height))
        else:
            image = render_cloud_view(view, self.cloud, self.config.background)
        return image

    # ------------------------------------------------------------------ forward
    def ac_rows(self, index: torch.Tensor) -> torch.Tensor:
        """``A~`` (eq. 33) of the Gaussians in ``index``, differentiable in S and T.

        The matrix and vector operators are linear without bias, so ``T = module(I_d)`` and
        ``A~ = S T`` is one small matrix product (the same values as ``module(S)``, cheaper);
        the linear (bias) and MLP operators run the module itself.
        """
        if self.lst_config.operator in LINEAR_OPERATORS:
            eye = torch.eye(self.module.d, dtype=self.dtype)
            return self.subset[index] @ self.module(eye)
        return self.module(self.subset[index])

    def render(self, view: ViewData) -> torch.Tensor:
        """(H, W, 3) image of ``view`` with the current S, T, DC (differentiable)."""
        idx = view.index
        return render_view(view, self.dc[idx], self.ac_rows(idx), self.background)

    def loss(self, view: ViewData) -> tuple[torch.Tensor, dict[str, float]]:
        """Eq. (37): (1 - l) L1 + l (1 - SSIM) + lambda_t L_T, and its parts."""
        if view.target is None:
            raise FinetuneError(f"view {view.camera.name!r} has no target image")
        image = self.render(view)
        target = view.target.to(self.dtype)
        lam = self.config.lambda_dssim
        l1_value = l1(image, target)
        ssim_value = ssim(image, target)
        reg = self.module.regularization()
        total = (1.0 - lam) * l1_value + lam * (1.0 - ssim_value) + self.lst_config.lambda_t * reg
        return total, {"l1": float(l1_value.detach()), "ssim": float(ssim_value.detach()), "l_t": float(reg.detach())}

    @torch.no_grad()
    def mean_loss(self, views: Iterable[int] | None = None) -> float:
        """Mean eq. (37) loss over camera indices (all by default), without updating anything."""
        indices = range(len(self.cameras)) if views is None else views
        with torch_threads(self.config.threads):
            values = [float(self.loss(self.cache[i])[0]) for i in indices]
        return float(np.mean(values))

    def step(self) -> dict[str, Any]:
        """One Adam step on the scheduled view; returns its log row."""
        if self.step_index >= self.config.steps:
            raise FinetuneError(f"the run is complete ({self.config.steps} steps)")
        with torch_threads(self.config.threads):
            return self._step()

    def _step(self) -> dict[str, Any]:
        i = int(self.schedule[self.step_index])
        miss = i not in self.cache
        wall0, cpu0 = time.perf_counter(), time.process_time()
        view = self.cache[i]
        lr_t = self._group_lr("lst_T")
        lr_s = self._group_lr("sh_subset")
        self.optimizer.zero_grad(set_to_none=True)
        total, parts = self.loss(view)
        total.backward()
        self.optimizer.step()
        self.scheduler.step()
        row = {
            "step": self.step_index, "view": self.cameras[i].name, "loss": float(total.detach()), **parts,
            "lr_t": lr_t, "lr_s": lr_s, "wall_s": time.perf_counter() - wall0, "cpu_s": time.process_time() - cpu0,
            "cache_miss": int(miss),
        }
        self.log.append(row)
        self.step_index += 1
        return row

    def _group_lr(self, name: str) -> float:
        return float(next(g["lr"] for g in self.optimizer.param_groups if g.get("name") == name))

    # ------------------------------------------------------------------ run
    def prefetch(self, progress: bool = False) -> float:
        """Build every view now when they all fit the cache budget; returns the seconds spent."""
        from tqdm import tqdm

        start = time.perf_counter()
        if len(self.cameras) and self.cache.n_cached == 0:
            self.cache[0]
        if not self.cache.fits_all():
            return time.perf_counter() - start
        for i in tqdm(range(len(self.cameras)), desc="views", unit="view", disable=not progress, leave=False):
            self.cache[i]
        return time.perf_counter() - start

    def run(
        self,
        *,
        progress: bool = True,
        checkpoint: PathLike | None = None,
        checkpoint_every: int = 500,
        resume: bool = False,
        log_path: PathLike | None = None,
        prefetch: bool = True,
        stop_at: int | None = None,
    ) -> FinetuneResult:
        """Train to ``config.steps`` (or ``stop_at``), checkpointing every ``checkpoint_every`` steps.

        With ``resume`` and an existing ``checkpoint`` the run continues from it (its
        fingerprint must match). The loss log goes to ``log_path`` (CSV) at every checkpoint
        and at the end.
        """
        with torch_threads(self.config.threads):
            return self._run(progress, checkpoint, checkpoint_every, resume, log_path, prefetch, stop_at)

    def _run(
        self, progress: bool, checkpoint: PathLike | None, checkpoint_every: int, resume: bool,
        log_path: PathLike | None, prefetch: bool, stop_at: int | None,
    ) -> FinetuneResult:
        from tqdm import tqdm

        if checkpoint_every < 1:
            raise FinetuneError(f"checkpoint_every must be at least 1, got {checkpoint_every}")
        resumed = False
        if resume:
            if checkpoint is None:
                raise FinetuneError("resuming needs a checkpoint path")
            if Path(checkpoint).exists():
                self.load_checkpoint(checkpoint)
                resumed = True
        start_step = self.step_index
        end = self.config.steps if stop_at is None else min(self.config.steps, int(stop_at))
        wall0 = time.perf_counter()
        prefetch_seconds = self.prefetch(progress) if prefetch and end > start_step else 0.0
        walls: list[float] = []
        cpus: list[float] = []
        bar = tqdm(total=end, initial=start_step, desc="lst-finetune", unit="step", disable=not progress)
        try:
            while self.step_index < end:
                row = self._step()
                walls.append(row["wall_s"])
                cpus.append(row["cpu_s"])
                bar.update(1)
                if self.step_index % 10 == 0 or self.step_index == end:
                    bar.set_postfix(loss=f"{row['loss']:.4f}", refresh=False)
                if checkpoint is not None and (self.step_index % checkpoint_every == 0 or self.step_index == end):
                    self.save_checkpoint(checkpoint)
                    if log_path is not None:
                        write_log(log_path, self.log)
        finally:
            bar.close()
        if log_path is not None:
            write_log(log_path, self.log)
        return FinetuneResult(
            steps=self.step_index,
            start_step=start_step,
            resumed=resumed,
            wall_seconds=time.perf_counter() - wall0,
            prefetch_seconds=prefetch_seconds,
            step_seconds_median=float(np.median(walls)) if walls else None,
            step_cpu_seconds_median=float(np.median(cpus)) if cpus else None,
            log=list(self.log),
            cache=self.cache.stats.as_dict(),
        )

    # ------------------------------------------------------------------ checkpoints
    def fingerprint(self) -> dict[str, Any]:
        """What must match for a checkpoint to continue this run exactly."""
        return {
            "n_gaussians": self.cloud.num_gaussians,
            "sh_degree": self.cloud.sh_degree,
            "config": json.loads(json.dumps(
                {k: v for k, v in self.config.as_dict().items() if k not in ("cache_bytes", "threads")} | {"lst": self.lst_config.as_dict()}
            )),
            "cameras": [c.name for c in self.cameras],
            "targets": self.target_kind,
        }

    def state_dict(self) -> dict[str, Any]:
        return {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "step": self.step_index,
            "fingerprint": self.fingerprint(),
            "subset": self.subset.detach().clone(),
            "dc": self.dc.detach().clone(),
            "module": self.module.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "log": self.log,
        }

    def save_checkpoint(self, path: PathLike) -> Path:
        """Write a checkpoint atomically (temporary file, then rename)."""
        buffer = io.BytesIO()
        torch.save(self.state_dict(), buffer)
        return write_atomic(Path(path), buffer.getvalue(), error=FinetuneError)

    def load_checkpoint(self, path: PathLike) -> None:
        """Continue from a checkpoint of the same run (fingerprint checked)."""
        path = Path(path)
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except FileNotFoundError:
            raise FinetuneError(f"{path}: no such checkpoint") from None
        except Exception as exc:  # noqa: BLE001 - any unreadable file is a user-facing error
            raise FinetuneError(f"{path}: not a readable fine-tuning checkpoint ({type(exc).__name__})") from None
        if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
            raise FinetuneError(f"{path}: not a gscodec-shac LST fine-tuning checkpoint")
        if state.get("version") != CHECKPOINT_VERSION:
            raise FinetuneError(f"{path}: checkpoint version {state.get('version')} is not supported")
        mine, theirs = self.fingerprint(), state.get("fingerprint", {})
        if mine != theirs:
            differing = _differences(mine, theirs) or ["its contents"]
            raise FinetuneError(
                f"{path}: the checkpoint belongs to a different run (differs in {', '.join(differing)}); "
                "remove it or start without --resume"
            )
        with torch.no_grad():
            self.subset.copy_(state["subset"])
            self.dc.copy_(state["dc"])
        self.module.load_state_dict(state["module"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.step_index = int(state["step"])
        self.log = list(state["log"])

    # ------------------------------------------------------------------ outputs
    def to_stage(self) -> ShacLST:
        """The fitted numpy stage with the learnt blocks (matrix operator only)."""
        if self.lst_config.operator != "matrix":
            raise FinetuneError(
                f"only the matrix operator has a compact SHAC-LST form, not {self.lst_config.operator!r}"
            )
        return self.module.to_stage()

    def subset_float32(self) -> np.ndarray:
        return self.subset.detach().numpy().astype(np.float32)

    def finetuned_ac(self) -> np.ndarray:
        """(N, K') float32 AC matrix ``S T`` (through the numpy stage for the matrix operator,
        so it is exactly what the codec's decoder rebuilds)."""
        if self.lst_config.operator == "matrix":
            return self.to_stage().inverse_transform(self.subset_float32())
        with torch.no_grad():
            return self.module(self.subset).numpy().astype(np.float32)

    def finetuned_cloud(self) -> GaussianCloud:
        """The cloud with full SH ``[DC | S T]`` (geometry and extra properties unchanged)."""
        return self.cloud.replace(
            sh_dc=self.dc.detach().numpy().astype(np.float32),
            sh_rest=sh_index.sh_rest_from_ac(self.finetuned_ac()),
        )

    def save_outputs(self, ply_path: PathLike, compact_path: PathLike | None = None, meta: dict | None = None) -> tuple[Path, Path | None]:
        """Write the full-SH PLY and (matrix operator) the compact ``.lst.npz``; both atomically."""
        from gscodec_shac.io.ply import write_ply

        ply_path = Path(ply_path)
        cloud = self.finetuned_cloud()
        compact = None
        if self.lst_config.operator == "matrix":
            compact = Path(compact_path) if compact_path is not None else compact_path_for(ply_path)
            info = {"steps": self.step_index, "config": self.fingerprint()["config"], "targets": self.target_kind}
            save_compact(compact, cloud, self.subset_float32(), self.to_stage(), meta=info | (meta or {}))
        write_ply(ply_path, cloud)
        return ply_path, compact


def _differences(a: dict, b: dict, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two nested dicts."""
    out = []
    for key in sorted(set(a) | set(b)):
        va, vb = a.get(key), b.get(key)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += _differences(va, vb, f"{prefix}{key}.")
        elif va != vb:
            out.append(f"{prefix}{key}")
    return out


def finetune_lst(
    cloud: GaussianCloud,
    cameras: Sequence[Camera],
    *,
    targets: str | Sequence[np.ndarray] = "auto",
    config: FinetuneConfig | None = None,
    progress: bool = True,
    checkpoint: PathLike | None = None,
    checkpoint_every: int = 500,
    resume: bool = False,
    log_path: PathLike | None = None,
) -> tuple[LstFinetuner, FinetuneResult]:
    """Build a :class:`LstFinetuner` and run it; returns both (the trainer holds S, T, DC)."""
    tuner = LstFinetuner(cloud, cameras, targets=targets, config=config)
    result = tuner.run(progress=progress, checkpoint=checkpoint, checkpoint_every=checkpoint_every,
                       resume=resume, log_path=log_path)
    return tuner, result


# ----------------------------------------------------------------------------- files
def compact_path_for(ply_path: PathLike) -> Path:
    """``scene.ply`` -> ``scene.lst.npz`` (the compact S + T form beside the PLY)."""
    path = Path(ply_path)
    return path.with_name(path.stem + ".lst.npz") if path.suffix.lower() == ".ply" else path.with_name(path.name + ".lst.npz")


def checkpoint_path_for(ply_path: PathLike) -> Path:
    path = Path(ply_path)
    return path.with_name((path.stem if path.suffix.lower() == ".ply" else path.name) + ".ckpt.pt")


def log_path_for(ply_path: PathLike) -> Path:
    path = Path(ply_path)
    return path.with_name((path.stem if path.suffix.lower() == ".ply" else path.name) + ".log.csv")


def summary_path_for(ply_path: PathLike) -> Path:
    path = Path(ply_path)
    return path.with_name((path.stem if path.suffix.lower() == ".ply" else path.name) + ".finetune.json")


def write_log(path: PathLike, rows: Sequence[dict[str, Any]]) -> Path:
    """The loss log as CSV (one row per step, columns ``LOG_FIELDS``), written atomically."""
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=LOG_FIELDS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (f"{v:.7g}" if isinstance(v, float) else v) for k, v in row.items()})
    return write_atomic(Path(path), text.getvalue().encode(), error=FinetuneError)


def save_compact(path: PathLike, cloud: GaussianCloud, subset: np.ndarray, stage: ShacLST, meta: dict | None = None) -> Path:
    """Write the compact SHAC-LST form (see module docstring) atomically.

    ``cloud`` supplies geometry and DC; ``subset`` (N, d) and ``stage`` must rebuild its AC
    matrix exactly (checked).
    """
    subset = np.ascontiguousarray(subset, dtype=np.float32)
    layout = stage._fitted_layout()
    if subset.shape != (cloud.num_gaussians, layout.d):
        raise FinetuneError(f"subset must have shape ({cloud.num_gaussians}, {layout.d}), got {subset.shape}")
    if not np.array_equal(stage.inverse_transform(subset), cloud.ac_matrix()):
        raise FinetuneError("the subset and T do not rebuild the cloud's SH exactly; refusing to write the compact form")
    info = {
        "format": COMPACT_FORMAT, "version": COMPACT_VERSION, "n_gaussians": cloud.num_gaussians,
        "sh_degree": layout.degree, "d": layout.d, "p_t": stage.n_params, "side_bytes": stage.state().nbytes(),
    } | (meta or {})
    arrays = {
        "subset": subset,
        "sh_dc": cloud.sh_dc,
        "means": cloud.means,
        "scales": cloud.scales,
        "quats": cloud.quats,
        "opacities": cloud.opacities,
        "lst_state": np.frombuffer(stage.state().to_bytes(), dtype=np.uint8),
        "meta": np.frombuffer(json.dumps(info).encode(), dtype=np.uint8),
    }
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return write_atomic(Path(path), buffer.getvalue(), error=FinetuneError)


def load_finetuned(path: PathLike) -> tuple[GaussianCloud, ShacLST]:
    """``(cloud with full SH, ShacLST)`` from a compact ``.lst.npz`` or the PLY beside one.

    From the ``.npz`` the cloud is rebuilt (geometry, DC and ``S T``); from a ``.ply`` the
    PLY is read and checked to hold exactly ``[DC | S T]`` of its ``.lst.npz``. Either way
    ``stage.transform(cloud.ac_matrix())`` is the fine-tuned S and
    ``stage.inverse_transform(S)`` the cloud's AC matrix, bit for bit.
    """
    path = Path(path)
    ply_cloud = None
    if path.suffix.lower() == ".ply":
        from gscodec_shac.io.ply import read_ply

        ply_cloud = read_ply(path)
        path = compact_path_for(path)
    if not path.is_file():
        raise FinetuneError(f"{path}: no such compact SHAC-LST file")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError) as exc:
        raise FinetuneError(f"{path}: not a readable .npz file ({exc})") from None
    needed = ("subset", "sh_dc", "means", "scales", "quats", "opacities", "lst_state", "meta")
    missing = [k for k in needed if k not in arrays]
    if missing:
        raise FinetuneError(f"{path}: not a compact SHAC-LST file (missing {', '.join(missing)})")
    try:
        meta = json.loads(arrays["meta"].tobytes())
    except ValueError:
        raise FinetuneError(f"{path}: unreadable metadata") from None
    if meta.get("format") != COMPACT_FORMAT or meta.get("version") != COMPACT_VERSION:
        raise FinetuneError(f"{path}: not a compact SHAC-LST file of version {COMPACT_VERSION}")
    stage = ShacLST.from_state(StageState.from_bytes(arrays["lst_state"].tobytes()))
    subset = arrays["subset"]
    try:
        ac = stage.inverse_transform(subset)
    except ValidationError as exc:
        raise FinetuneError(f"{path}: subset does not fit the stored T ({exc})") from None
    if ply_cloud is not None:
        if ply_cloud.num_gaussians != subset.shape[0] or not (
            np.array_equal(ply_cloud.ac_matrix(), ac) and np.array_equal(ply_cloud.sh_dc, arrays["sh_dc"])
        ):
            raise FinetuneError(f"{path}: does not match the SH of the PLY beside it")
        return ply_cloud, stage
    try:
        cloud = GaussianCloud(
            means=arrays["means"], scales=arrays["scales"], quats=arrays["quats"], opacities=arrays["opacities"],
            sh_dc=arrays["sh_dc"], sh_rest=sh_index.sh_rest_from_ac(ac),
        )
    except ValidationError as exc:
        raise FinetuneError(f"{path}: inconsistent arrays ({exc})") from None
    return cloud, stage

