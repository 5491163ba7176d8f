"""Prune by importance, then recover: distil the pruned model to the original's renders.

Importance pruning (:mod:`gscodec_shac.codec.importance`) drops the Gaussians that add least to
the rendered views, but the Gaussians kept were trained next to the ones dropped: lego's most important
45% measure 37.7 dB against the uncompressed model's renders on its held-out views, and 46.9 dB
after 200 steps of this recovery (docs/rate_control.md, "Pruning with recovery"). Post-training codecs
(LightGaussian, POTR) therefore fine-tune what they keep. Here the targets are not photos but the
*original model's renders* from the same views, so a scene needs no photos, only views (its
cameras, or orbit views when it has none), and the result approaches the model being compressed
rather than drifting towards the photos.

The fine-tune is the trainer's step (:class:`~gscodec_shac.train.trainer.Trainer`: render, ``0.8 L1
+ 0.2 D-SSIM``, backward through the CPU rasteriser, Adam) with every SH degree active from the
first step and no densification, pruning or opacity reset. The learning rates are a fine-tune's,
not a training's from scratch: positions from ``4.8e-5 x extent`` (the reference starts at
``1.6e-4``) decayed tenfold; opacity and scales at 0.3x and 0.5x the reference's
(Adam moves every parameter by about its rate each step, which at the reference's rates kept the
recovery from settling: bonsai's 45% restored 40.6 dB on its held-out views with them, 43.0 dB
with these; the chair's 47.7 and 48.1 dB; docs/rate_control.md, "Pruning with recovery"). For the
same reason every rate but the positions' decays tenfold over the last quarter of the steps. Seeded:
the same inputs give the same model.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from gscodec_shac.camera import Camera, spread_views
from gscodec_shac.errors import ValidationError
from gscodec_shac.gaussians import GaussianCloud

#: The views the recovery renders its targets from: at most this many, at most this wide.
MAX_VIEWS = 200
MAX_WIDTH = 800
#: The fine-tune's learning rates where they differ from the trainer's (the reference's): positions
#: (times the views' extent) from 4.8e-5 to 4.8e-6 (reference 1.6e-4 to 1.6e-6); opacity and scales
#: at 0.3x and 0.5x the reference's 0.05 and 5e-3; over the last quarter of the steps every rate but the
#: positions' decays tenfold, so that the fine-tune settles (at 400 steps, 45% kept: bonsai 43.40 ->
#: 44.86 dB, the chair 49.07 -> 49.50 dB; docs/rate_control.md, "400 recovery steps instead of 200").
#: ``prune_and_recover(learning_rates=...)`` overrides them.
LEARNING_RATES = {"lr_means": 4.8e-5, "lr_means_final": 4.8e-6, "lr_opacity": 0.015, "lr_scales": 2.5e-3,
                  "lr_decay_start": 0.75, "lr_decay_final": 0.1}
#: Fine-tuning steps. 400 since 2026-11-29 (200 before): at 45% kept, held-out views against the
#: uncompressed model, bonsai 42.98 -> 43.40 dB and the chair 48.13 -> 49.07 dB (600 steps, three times
#: the 200 steps' fine-tuning: 43.80 and 49.81 dB); docs/rate_control.md, "400 recovery steps instead of 200".
DEFAULT_ITERATIONS = 400


@dataclass
class Recovery:
    """A pruned and recovered cloud and what it took."""

    cloud: GaussianCloud
    kept: int
    dropped: int
    iterations: int
    views: int
    seconds: float
    #: mean PSNR (dB) of the pruned model against the original's renders on the recovery views,
    #: before and after the fine-tune (each measured on the same views the fine-tune saw)
    psnr_pruned: float = float("nan")
    psnr_recovered: float = float("nan")
    timings: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        def db(value: float) -> float | None:  # None when not measured (valid JSON)
            return round(value, 3) if math.isfinite(value) else None

        return {"kept": self.kept, "dropped": self.dropped, "iterations": self.iterations, "views": self.views,
                "seconds": round(self.seconds, 2), "psnr_pruned": db(self.psnr_pruned),
                "psnr_recovered": db(self.psnr_recovered)}


def check_settings(keep_share: float, iterations: int, learning_rates: Mapping[str, float] | None = None) -> None:
    """One clear error for a keep share outside (0, 1], a negative iteration count or a learning rate
    that is not a positive number of the trainer's (``lr_means``, ``lr_opacity``, ...)."""
    from dataclasses import fields

    from gscodec_shac.train.trainer import TrainConfig

    if not (isinstance(keep_share, (int, float)) and math.isfinite(keep_share) and 0.0 < keep_share <= 1.0):
        raise ValidationError(f"the keep share must lie in (0, 1], got {keep_share!r}")
    if not (isinstance(iterations, int) and iterations >= 0):
        raise ValidationError(f"the recovery iterations must be an integer >= 0, got {iterations!r}")
    names = sorted(f.name for f in fields(TrainConfig) if f.name.startswith("lr_"))
    for name, value in (learning_rates or {}).items():
        if name not in names:
            raise ValidationError(f"unknown learning rate {name!r}; the trainer's are {', '.join(names)}")
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValidationError(f"the learning rate {name} must be a positive number, got {value!r}")


def recovery_views(cloud: GaussianCloud, cameras: Sequence[Camera] | None) -> list[Camera]:
    """The views pruning is ranked on and the fine-tune renders: the cameras (at most
    :data:`MAX_VIEWS`, evenly spread, at most :data:`MAX_WIDTH` wide), else the importance's orbit views."""
    from gscodec_shac.codec.importance import importance_views

    if cameras:
        return spread_views(cameras, MAX_VIEWS, MAX_WIDTH)
    return importance_views(cloud, None)


class _Targets:
    """The original's renders, stored as float16 (half the memory; errors ~60 dB below the signal),
    handed to the trainer as float32 one view at a time."""

    def __init__(self, images: list[np.ndarray]) -> None:
        self.images = [np.asarray(image, dtype=np.float16) for image in images]

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, index: int) -> np.ndarray:
        return self.images[index].astype(np.float32)


def _mean_psnr(cloud: GaussianCloud, views: Sequence[Camera], targets: _Targets, background: np.ndarray) -> float:
    """Mean over ``views`` of each view's PSNR against its target (:func:`gscodec_shac.metrics.mse`; at most 120 dB)."""
    from gscodec_shac.metrics import mse
    from gscodec_shac.render import Renderer

    renderer = Renderer(cloud)
    errors = [mse(renderer.render(view, background=background).image, targets[index])
              for index, view in enumerate(views)]
    return float(np.mean([-10.0 * math.log10(max(error, 1e-12)) for error in errors]))


def prune_and_recover(
    cloud: GaussianCloud,
    cameras: Sequence[Camera] | None = None,
    *,
    keep_share: float,
    iterations: int = DEFAULT_ITERATIONS,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    seed: int = 0,
    measure: bool = True,
    progress: bool = False,
    learning_rates: Mapping[str, float] | None = None,
) -> Recovery:
    """Keep the most important ``keep_share`` of ``cloud`` (ranked on ``cameras``, else orbit views)
    and fine-tune the kept Gaussians for ``iterations`` steps towards the original's renders.

    ``measure``: also render the pruned and the recovered model on the views (their PSNR against
    the original, :attr:`Recovery.psnr_pruned` / ``psnr_recovered``). ``learning_rates``: the
    trainer's ``lr_*`` settings to use instead of :data:`LEARNING_RATES` and the trainer's defaults.
    """
    from tqdm import tqdm

    from gscodec_shac.codec.importance import gaussian_importance, keep_count, most_important_counts
    from gscodec_shac.render import Renderer
    from gscodec_shac.render.renderer import parse_background

    check_settings(keep_share, iterations, learning_rates)
    rates = {**LEARNING_RATES, **(learning_rates or {})}
    tic = time.perf_counter()
    bg = parse_background(background)
    views = recovery_views(cloud, cameras)
    original = Renderer(cloud)
    timings: dict[str, float] = {}
    importance = gaussian_importance(cloud, views, renderer=original)
    rows = most_important_counts(importance, [keep_count(cloud.num_gaussians, keep_share)])[0]
    pruned = cloud.select(rows)
    timings["importance"] = time.perf_counter() - tic
    if iterations == 0:
        return Recovery(pruned, rows.size, cloud.num_gaussians - rows.size, 0, len(views),
                        time.perf_counter() - tic, timings=timings)
    targets = _Targets([original.render(view, background=bg).image for view in views])
    del original
    timings["targets"] = time.perf_counter() - tic - timings["importance"]
    before = _mean_psnr(pruned, views, targets, bg) if measure else float("nan")
    recovered = _fine_tune(pruned, views, targets, bg, iterations, seed, rates, progress, tqdm)
    timings["fine_tune"] = time.perf_counter() - tic - sum(timings.values())
    after = _mean_psnr(recovered, views, targets, bg) if measure else float("nan")
    return Recovery(recovered, rows.size, cloud.num_gaussians - rows.size, iterations, len(views),
                    time.perf_counter() - tic, before, after, timings)


def _fine_tune(pruned: GaussianCloud, views: list[Camera], targets: _Targets, background: np.ndarray,
               iterations: int, seed: int, rates: Mapping[str, float], progress: bool, tqdm: Any) -> GaussianCloud:
    """``iterations`` trainer steps on ``pruned`` towards ``targets`` (see the module docstring)."""
    from gscodec_shac.train.data import Capture, camera_extent
    from gscodec_shac.train.model import GaussianModel
    from gscodec_shac.train.trainer import Trainer, TrainConfig

    params = {"means": pruned.means, "scales": pruned.scales, "quats": pruned.quats,
              "opacities": pruned.opacities, "sh_dc": pruned.sh_dc, "sh_rest": pruned.sh_rest}
    model = GaussianModel(params, pruned.sh_degree)
    empty = np.zeros((0, 3))
    capture = Capture("recover", "views", list(views), [], targets, [], empty, empty,  # type: ignore[arg-type]
                      np.asarray(background, dtype=np.float64), camera_extent(views)[1])
    never = 1 << 40
    config = TrainConfig(iterations=iterations, sh_degree=pruned.sh_degree, seed=seed, **rates,
                         sh_interval=1, densify_until=0, opacity_reset_interval=never,
                         checkpoint_every=never, log_every=never)
    trainer = Trainer(capture, config, model=model)
    trainer.active_degree = pruned.sh_degree  # the model is trained: every degree from the first step
    for _ in tqdm(range(iterations), desc="recover", unit="step", disable=not progress, leave=False):
        trainer.step()
    return model.to_cloud()
