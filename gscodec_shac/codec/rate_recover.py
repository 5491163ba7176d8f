"""Rate control over the model and its pruned-and-recovered versions (``encode --recover``).

Importance pruning inside the controller (:mod:`.importance`, ``prune.keep_share``) drops
Gaussians and codes the rest as they were trained: next to the ones dropped. Recovering them
first (:func:`gscodec_shac.train.recover.prune_and_recover`: keep the most important share, then
fine-tune the kept ones towards the model's own renders) makes a smaller model that renders
nearly like the whole one: lego's most important 45% measure 37.7 dB against the model's renders
on its held-out views pruned alone, 46.9 dB recovered. Which source codes best depends on the
target: a small file gains from the smaller model, a large one is limited by what the recovery
could not restore.

:class:`RecoveringController` therefore fits one :class:`~.rate_control.RateController` on the
model and one on each recovered version, encodes them at the target and keeps the file that
measures best against the *model's* renders (a size or bits-per-Gaussian target: the highest
PSNR; a PSNR target: the smallest file at least as good as the model's own). The model is coded
first; a recovered version whose own PSNR on the judges (its ceiling: coding only adds error) does
not pass the model's file cannot win and is not coded, and its controller is fitted only when a
target first codes it. The judges
are the controller's own views and :data:`JUDGE_VIEWS` more of the cameras, at their resolution
up to :data:`JUDGE_WIDTH` wide (the controller's are 192 wide: too coarse to tell the sources
apart, which differ in their finest detail). The recovery never sees those views: it is ranked
and fine-tuned on the other cameras (or on orbit views when there are none; the judges are then
the controller's orbit views).

A PSNR target is met as the controller meets it, on its own views: the model's file is the
controller's answer, and a recovered source's file replaces it only when it is smaller, at least
as good on the judges (which measure lower than the controller's coarse views: lego's plain 38 dB
file measured 37.86 dB on them) and meets the target on the controller's views too. Each
recovered source's controller is given the target its coding may still spend: the target's MSE
minus what the recovery left on the controller's views (MSEs of independent errors add); a
source that already misses the target is not tried.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Sequence

import numpy as np

from gscodec_shac.camera import Camera, spread_views
from gscodec_shac.codec.rate_control import (
    TEMPLATE,
    Outcome,
    RateController,
    Target,
    TargetUnreachableError,
    _decoded,
    _psnr,
)
from gscodec_shac.codec.rate_points import RatePoint
from gscodec_shac.gaussians import GaussianCloud

#: Shares of the Gaussians kept by the recovered sources (the most important ones). 45% only: a 60%
#: source won none of the 24 targets of lego, bonsai and the chair at 30-170 bits/G and 38-44 dB, the
#: 45% source every target up to 55 bits/G (docs/rate_control.md, "Pruning with recovery").
RECOVER_SHARES = (0.45,)
#: Cameras the sources are judged on beside the controller's views, and their largest width.
JUDGE_VIEWS = 12
JUDGE_WIDTH = 800


@dataclass
class Source:
    """One source the controller codes: the model (``share`` 1, no recovery) or a recovered version."""

    share: float
    controller: RateController | None  # a recovered source's is fitted when a target first codes it
    recovery: Any = None  # gscodec_shac.train.recover.Recovery
    #: PSNR (dB) of the source against the model on the judges (inf for the model itself)
    psnr: float = math.inf
    #: the same on the controller's views, which a PSNR target is measured on
    controller_psnr: float = math.inf


class _Coded(NamedTuple):
    """One source's file at a target and its PSNR against the model on the judges and on the controller's views."""

    source: Source
    outcome: Outcome
    judged: float
    on_controller_views: float

    @property
    def bytes(self) -> int:
        return self.outcome.stream.total_bytes()


@dataclass
class RecoveringController:
    """The rate controller on ``cloud`` and on its recovered versions; :meth:`encode` keeps the best file.

    ``controller_options`` go to every :class:`RateController` (``up``, ``background``, ``workers``, ...).
    """

    cloud: GaussianCloud
    template: str | RatePoint = TEMPLATE
    views: Sequence[Camera] | None = None
    shares: Sequence[float] = RECOVER_SHARES
    iterations: int | None = None
    seed: int = 0
    controller_options: dict[str, Any] = field(default_factory=dict)
    sources_: list[Source] = field(default_factory=list, init=False)
    seconds_: dict[str, float] = field(default_factory=dict, init=False)
    #: the views the sources are judged on and the model's renders of them
    judges_: list[Camera] = field(default_factory=list, init=False)
    _references: list[np.ndarray] = field(default_factory=list, init=False, repr=False)

    @property
    def steps(self) -> int:
        """The recovery's fine-tuning steps: ``iterations``, else the recovery's default."""
        from gscodec_shac.train.recover import DEFAULT_ITERATIONS

        return DEFAULT_ITERATIONS if self.iterations is None else self.iterations

    def fit(self) -> "RecoveringController":
        from gscodec_shac.train.recover import check_settings, prune_and_recover

        iterations = self.steps
        for share in self.shares:
            check_settings(share, iterations)
        tic = time.perf_counter()
        base = RateController(self.cloud, self.template, self.views, **self.controller_options).fit()
        self.sources_ = [Source(1.0, base)]
        self.seconds_["fit_model"] = time.perf_counter() - tic
        self.judges_ = self._judges(base)
        judged = {view.name for view in self.judges_}
        training = [view for view in self.views or () if view.name not in judged] or None
        self._references = self._renders(self.cloud)
        for share in self.shares:
            tic = time.perf_counter()
            recovery = prune_and_recover(self.cloud, training, keep_share=share, iterations=iterations,
                                         background=self._background, seed=self.seed, measure=False,
                                         progress=bool(self.controller_options.get("progress")))
            self.seconds_[f"recover_{share:g}"] = time.perf_counter() - tic
            self.sources_.append(Source(share, None, recovery, self._psnr(recovery.cloud),
                                        _psnr(base._rendered_mse(recovery.cloud))))
        return self

    def _controller(self, source: Source) -> RateController:
        """``source``'s rate controller, fitted on its first use."""
        if source.controller is None:
            tic = time.perf_counter()
            source.controller = RateController(source.recovery.cloud, self.template, self.views,
                                               **self.controller_options).fit()
            self.seconds_[f"fit_{source.share:g}"] = time.perf_counter() - tic
        return source.controller

    @property
    def _background(self) -> Sequence[float]:
        """The scene's render background, as the controllers are given it."""
        return self.controller_options.get("background", (0.0, 0.0, 0.0))

    def _judges(self, base: RateController) -> list[Camera]:
        """The controller's views and :data:`JUDGE_VIEWS` more cameras, at most :data:`JUDGE_WIDTH` wide."""
        if not self.views:
            return list(base.views)
        names = {view.name for view in base.views} | {view.name for view in spread_views(self.views, JUDGE_VIEWS)}
        return spread_views([view for view in self.views if view.name in names], len(names), JUDGE_WIDTH)

    def _renders(self, cloud: GaussianCloud) -> list[np.ndarray]:
        from gscodec_shac.render import Renderer

        renderer = Renderer(cloud)
        return [renderer.render(view, background=self._background).image for view in self.judges_]

    def _psnr(self, cloud: GaussianCloud) -> float:
        """Mean-MSE PSNR of ``cloud`` against the model on the judges."""
        images = self._renders(cloud)
        return _psnr(float(np.mean([np.mean((image - ref) ** 2) for image, ref in zip(images, self._references)])))

    def encode(self, target: Target) -> Outcome:
        """Encode every source at ``target``; the best file measured against the model (module docstring)."""
        if not self.sources_:
            self.fit()
        base = self._controller(self.sources_[0])
        tried: list[_Coded] = []
        rows: list[dict[str, Any]] = []
        for source in self.sources_:
            wanted = self._source_target(source, target)
            row: dict[str, Any] = {"keep": source.share}
            if source.recovery is not None:
                row.update(source_psnr=round(source.psnr, 3), source_psnr_controller_views=round(source.controller_psnr, 3))
            rows.append(row)
            if wanted is None:
                row["skipped"] = "the recovered model alone misses the target"
                continue
            model = _model_file(tried)
            if source.recovery is not None and model is not None and source.psnr <= model.judged:
                row["skipped"] = (f"the recovered model alone measures {source.psnr:.2f} dB on the judges, "
                                  f"the model's file {model.judged:.2f} dB")
                continue
            controller = self._controller(source)
            try:
                outcome = controller.encode(wanted)
            except TargetUnreachableError as exc:
                row["skipped"] = str(exc)
                continue
            decoded = _decoded(outcome.stream, controller.workers)
            coded = _Coded(source, outcome, self._psnr(decoded), _psnr(base._rendered_mse(decoded)))
            row.update(bytes=coded.bytes, measured_psnr=round(coded.judged, 3),
                       psnr_controller_views=round(coded.on_controller_views, 3))
            tried.append(coded)
        if not tried:
            raise TargetUnreachableError(f"no source reached {target.describe()}: "
                                         + "; ".join(f"keep {r['keep']:g}: {r['skipped']}" for r in rows))
        best = self._best(tried, target)
        outcome, source = best.outcome, best.source
        outcome.measured_psnr = best.on_controller_views  # against the model, as a plain target reports it
        outcome.recovery = {"keep": source.share, "iterations": source.recovery.iterations if source.recovery else 0,
                            "steps": self.steps,
                            "judged_psnr": round(best.judged, 3), "judges": len(self.judges_), "sources": rows,
                            "seconds": {step: round(value, 2) for step, value in self.seconds_.items()}}
        return outcome

    def _source_target(self, source: Source, target: Target) -> Target | None:
        """The target ``source``'s controller is given: a PSNR target less what its recovery lost."""
        if target.kind != "psnr" or source.recovery is None:
            return target
        left = 10.0 ** (-target.value / 10.0) - 10.0 ** (-source.controller_psnr / 10.0)
        return Target("psnr", _psnr(left)) if left > 0 else None

    @staticmethod
    def _best(tried: list[_Coded], target: Target) -> _Coded:
        if target.kind == "bytes":  # the best quality; on a tie the smaller file
            return max(tried, key=lambda c: (c.judged, -c.bytes))
        model = _model_file(tried)
        bar = model.judged if model else target.value  # the model's file on the judges (its controller met the target)
        # the smallest file at least as good as the model's on the judges that also meets the target where
        # the controller measures it (the PSNR reported), as the model's file does
        meeting = [c for c in tried if c.judged >= bar
                   and (c.source.recovery is None or c.on_controller_views >= target.value)]
        if meeting:
            return min(meeting, key=lambda c: c.bytes)
        return max(tried, key=lambda c: c.judged)


def _model_file(tried: list[_Coded]) -> _Coded | None:
    """The model's own file among the coded ones (None when its controller could not reach the target)."""
    return next((c for c in tried if c.source.recovery is None), None)
