"""Rate control (SHAC-auto): the best quality at a size, or the smallest file at a quality.

The template rate point (``rate_points/shac_auto.yaml``) fixes the containers and the SH
stage; for each scene and target the controller chooses seven settings: the opacity below
which Gaussians are pruned, the position bits (set coding) and the QPs of opacity,
rotation, scale, DC and the water-filled SHAC-PCA features (whose base QP also picks the
rank M, :mod:`.allocation`; chosen in quarter steps since version 17). A template with SH
stage ``none`` codes every AC coefficient instead, on its ``sh_ac`` degree ladder, whose first
QP takes the place of the base QP (the controller without an SH stage,
:func:`gscodec_shac.rd.methods.template_without_sh`).

The attributes are coded independently, so both the size and, for small errors, the
rendered mean squared error are sums over attributes. The controller therefore models
each attribute on its own:

* **rate** ``R_a(x)`` and **attribute error** ``e_a(x)``: real encodes and decodes of a
  *probe* (a sample of the cloud made of a few runs along its Morton order, so it keeps
  the neighbourhoods the grid codecs exploit, plus the Gaussians holding each coded
  channel's extremes, so its quantiser ranges are the whole cloud's) at a handful of QPs,
  all attributes at once, scaled to the whole cloud and interpolated (PCHIP in the log
  domain) between probe QPs; the water-filled SH features' rate is summed over the
  features kept at each base QP, each at its own QP; position bits are measured exactly
  on the whole cloud (set coding is cheap);
* **render sensitivity** ``k_a``: the rendered MSE per unit attribute MSE, from renders of
  the cloud with that attribute of the probe's Gaussians as the codec decoded it (QP 30),
  on a few views (the scene's cameras, else orbit views), against renders of the
  uncompressed cloud, weighed by how visible the probe's Gaussians are where that is clearly
  off (version 11); a PSNR target rescales it per attribute by its first encode's renders
  (version 12);
* **pruning**: the rendered MSE of the cloud without its Gaussians below each opacity
  threshold, or without all but its most important ones (:mod:`.importance`, at each share of
  :data:`IMPORTANCE_SHARES`), by exact renders; pruning keeps a share ``f`` of the Gaussians and scales every
  attribute's bytes by ``f`` (positions: their gaps grow, ``+log2(1/f)`` bits each) times what a
  Gaussian that stays costs against an average one (version 14: a size target measures it on the
  probe, :meth:`RateController._probe_at`; the Gaussians pruned are cheaper than the rest).

The predicted rendered error is ``D = sum_a k_a e_a(x_a)`` (PSNR against the uncompressed
model, images in [0, 1]). A Lagrangian search (per attribute ``min R_a + lambda D_a``)
traces the lower convex hull of (size, D) and picks the point meeting the middle of the
target's window; one real encode confirms it, and the controller corrects its models with
what the encode measured and re-encodes until the target is met (at most ``max_encodes``,
:data:`MAX_ENCODES` by default; unchanged chunks are taken from a cache): a size within 3% under it (each
attribute's bytes as measured), a PSNR within 0.3 dB above it (the prediction error,
measured minus predicted PSNR, interpolated between the encodes so far, brackets the
next plan on the hull of the QPs). A size target whose plan keeps enough Gaussians is coded in the
template's importance tiers, and since version 23 its tiered file is kept only when it renders at least
as well as the plan's one-grid prediction; else the target is searched again in one grid and the file
that renders better lands. ``Outcome.trials`` records the predicted and measured
bytes and PSNR of every encode. A size target is never exceeded, nor a PSNR target
undershot; a target outside the reachable range raises :class:`TargetUnreachableError`
naming the reachable limit.
"""

from __future__ import annotations

import dataclasses
import math
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from tqdm.auto import tqdm

from gscodec_shac.camera import Camera, orbit_views, spread_views
from gscodec_shac.codec import quantize as qz
from gscodec_shac.codec.allocation import BASE_QP_STEP, MAX_QP, waterfill_qps, whole_base_equivalent
from gscodec_shac.codec import parameter_sets
from gscodec_shac.codec.attributes import coded_attributes
from gscodec_shac.codec.container import Bitstream
from gscodec_shac.codec.decoder import Decoder
from gscodec_shac.codec.effort import with_scene_analysis
from gscodec_shac.codec.encoder import Encoder, position_set_cache_key
from gscodec_shac.codec.importance import (gaussian_importance, importance_views, keep_count,
                                           most_important_counts)
from gscodec_shac.codec.pchip import pchip
from gscodec_shac.codec.positions import encode_sorted_codes, morton_encode, set_order
from gscodec_shac.codec.rate_points import RatePoint, load_rate_point
from gscodec_shac.codec.rate_sh_degree import (DC_ONLY_BARS, RATIO_QPS, DcOnlyChoice, cloud_energy, fit_choices,
                                                kept_flags, whole_cloud_flags)
from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac import limits
from gscodec_shac.limits import default_workers
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.shac.base import STAGES, ShStage, make_stage
from gscodec_shac.shac.view_metric import cloud_view_metric, metric_applies

#: The template rate point of SHAC-auto.
TEMPLATE = "shac_auto:template"
#: Bumped when the controller's choices change for the same input (RD sweeps key their rows on it).
#: Version 8 (the PSNR target's chain, docs/rate_control.md) kept the constant at 7; 9 is the size
#: target's fill of the first plan and its SH-keeping corrections (:data:`FINE_BAND`); 10 compares a
#: PSNR target's single steps with the start's bytes as the corrected models predict them now; 11 weighs
#: the probe's rendered error by how visible its Gaussians are (:meth:`RateController._probe_visibility`);
#: 12 rescales a PSNR target's models by the renders of its first encode (:meth:`RateController._rescale_models`);
#: 13 codes the probe at a size target's first plan and plans again (:meth:`RateController._probe_at`);
#: 14 also codes the probe pruned as that plan prunes and scales the pruned plans' bytes by what a kept
#: Gaussian costs there (:meth:`RateController._prune_factor`), up to :data:`PLAN_PROBES` times; 15 is version 14
#: on the template's 12-bit samples (``rate_points/shac_auto.yaml``: at QP 0 the 10-bit rounding was part of the error);
#: 16 also probes again when the plan after a probe moved the SH features' base QP off the QPs coded
#: (:meth:`RateController._sh_measured`); 17 chooses the water-filled SH features' base QP in quarter steps
#: (:meth:`RateController._choices`), reads their error model at the whole-base equivalent of a fractional base
#: (:func:`.allocation.whole_base_equivalent`) and counts their probe feature by feature; 18 fits SHAC-PCA in the
#: view metric of the caller's cameras (:meth:`RateController._sh_metric`, :mod:`gscodec_shac.shac.view_metric`);
#: 19 codes the rotation as a rotation vector (the template's ``rotation: {form: vector}``, format 2.4) and
#: counts the file's HEVC parameter-set table (:mod:`.parameter_sets`) with its header; its PSNR search
#: ignores a bigger encode below the target as a bracket and lets the slope reach 4 (:data:`PSNR_SLOPES`);
#: 20 lets a target take up to 8 encodes (:data:`MAX_ENCODES`, 6 before); 21 codes the plans in the template's
#: importance tiers (:mod:`.tiers`, format 2.6), its models and probes staying those of one grid; 22 with the
#: tiers' DC-only Gaussians chosen over all of them and their QP offsets scaled by the scene's importance
#: (the template's ``tiers.spread: importance``, :func:`.tiers.importance_spread`); 23 keeps a size target's tiered
#: file only when it renders at least as well as its plan's one-grid prediction, else searches the target again
#: in one grid and keeps the file that renders better (:meth:`RateController._checked_tiers`).
VERSION = 23
#: The QP attributes the controller sets (``sh`` is the water-filled features' base QP).
QP_ATTRIBUTES = ("opacity", "rotation", "scale", "sh_dc", "sh")
#: QPs at which the probe is encoded; the models interpolate between them (and extrapolate).
PROBE_QPS = (6, 18, 30, 42)
#: Candidate position bits (set coding).
POSITION_BITS = tuple(range(9, 17))
#: Candidate opacity thresholds below which Gaussians are pruned (rate-point ``prune.min_opacity``).
PRUNE_THRESHOLDS = (0.0, 0.005, 0.01, 0.02, 0.05)
#: Candidate shares of the Gaussians kept by render-based importance (rate-point ``prune.keep_share``).
IMPORTANCE_SHARES = (0.8, 0.6, 0.45, 0.3)
#: The fewest Gaussians a plan keeps for the template's importance tiers to code it (version 21): measured
#: to win at 36,500-75,000 kept (docs/rate_control.md, "Controller version 21: importance tiers"), to lose
#: on a 2,000-Gaussian synthetic scene (2.3 dB at equal size: each tier's header, positions set and 30-40
#: HEVC streams weigh there) and to gain nothing on the chair's 28,118; since version 22 the tiers save 2-3%
#: there (docs/rate_control.md, "Tiers below 30,000 kept Gaussians"), not yet taken.
TIER_MIN_GAUSSIANS = 30_000
#: A size target codes the probe at its plan (and pruned as the plan prunes) and plans again at most
#: this many times, again only when the new plan prunes in a way not yet measured (version 14) or puts
#: the SH features' base QP where the probe has not coded them (version 16; 2 probes then let the chair's
#: 40 and 55 bits/G plans end on an unmeasured pruning: -1.0 and -0.7 dB).
PLAN_PROBES = 3
#: Bounds of the measured cost of a kept Gaussian against an average one (:meth:`RateController._prune_factor`).
PRUNE_FACTOR_BOUNDS = (0.5, 3.0)
#: A probe holds this many Gaussians (all of a smaller cloud), whatever the cloud's size (up to
#: version 5: 1/16 of a cloud above 320,000 Gaussians), ...
PROBE_MIN = 20_000
#: ... in this many runs along the Morton order.
PROBE_RUNS = 4
#: The probe QP whose decoded errors measure the render sensitivities.
SENSITIVITY_QP = 30
#: Views (and their width) the render sensitivities are measured on.
CALIBRATION_VIEWS = 6
CALIBRATION_WIDTH = 192
#: At most this many encodes per target (version 20; 6 before). Only a PSNR target has needed more than
#: 2 on the shared scenes: bonsai's 38 dB target ran out of its 6 at 38.75 dB, where plans of 449k and
#: 466k bytes measured 37.86 and 38.75 dB, and its 7th encode lands (38.01 dB, a 2.8% smaller file).
#: The later encodes re-code a few chunks each (the grid and the others come from the cache).
MAX_ENCODES = 8
#: A size target is met when the file is within this share under it ...
SIZE_TOLERANCE = 0.03
#: After an encode this close to a size target (a share of it), the next moves keep the SH features'
#: base QP: a step of it re-codes every water-filled SH chunk and moves the file by about the
#: window's width, where the other attributes' steps re-code one chunk each (version 9) ...
FINE_BAND = 0.08
#: ... unless that costs more than this many dB of predicted PSNR against moving every QP (at high
#: rates the other attributes' steps can cost dB where one SH step costs little: chair at 220 bits/G).
FINE_PSNR_COST = 0.05
#: ... a PSNR target when the measured PSNR is within this many dB above it.
PSNR_WINDOW = 0.3
#: Bounds of the slope of measured against predicted PSNR between the encodes on either side of
#: a PSNR target's window, and the spread of predictions (dB) it needs (:meth:`RateController._next_for_quality`;
#: the upper bound 1.5 up to version 18: bonsai's 38 dB chain measured 3.7).
PSNR_SLOPES = (0.25, 4.0)
PSNR_SLOPE_SPREAD = 0.1
#: A PSNR target rescales each attribute model by the renders of its first encode (version 12) by a
#: factor within these bounds, those models that hold at least this share of the plan's error.
RESCALE_BOUNDS = (0.1, 10.0)
RESCALE_SHARE = 0.05
#: ... when that encode measured within this many dB of the window's middle (a factor measured at one
#: QP mix holds near it: snowmiku's 45 dB target, first encoded at 48.63 dB, ended in a 3.7% bigger file).
RESCALE_WITHIN = 2.0
#: The probe's visibility against the whole cloud's (:meth:`RateController._probe_visibility`) is taken as 1
#: inside this band (the proxy's own scatter on the trained scenes) ...
VISIBILITY_BAND = (0.8, 1.25)
#: ... and clipped to these bounds outside it.
VISIBILITY_BOUNDS = (0.25, 4.0)


class TargetUnreachableError(GscodecError):
    """A rate-control target lies outside what the codec can reach on this scene."""


@dataclass(frozen=True)
class Target:
    """``bytes`` (an upper bound) or ``psnr`` (a lower bound, dB against the uncompressed model)."""

    kind: str
    value: float

    def describe(self) -> str:
        return f"{self.value:,.0f} bytes" if self.kind == "bytes" else f"{self.value:.2f} dB PSNR"


def parse_size(text: str) -> float:
    """``"2.5MB"`` -> 2.5e6 bytes (:func:`gscodec_shac.limits.parse_size`), a ValidationError otherwise."""
    try:
        return float(limits.parse_size(text))
    except ValueError as exc:
        raise ValidationError(f"size {exc}") from None


def make_target(n_gaussians: int, size: str | None = None, bpg: float | None = None,
                psnr: float | None = None) -> Target:
    """The one target given: a size (``"2.5MB"``), bits per Gaussian, or a PSNR in dB."""
    given = [v is not None for v in (size, bpg, psnr)]
    if sum(given) != 1:
        raise ValidationError("give exactly one of a target size, a target bits per Gaussian or a target PSNR")
    if size is not None:
        return Target("bytes", parse_size(size))
    if bpg is not None:
        if not (math.isfinite(bpg) and bpg > 0):
            raise ValidationError(f"target bits per Gaussian must be positive, got {bpg}")
        return Target("bytes", bpg * n_gaussians / 8.0)
    if not (math.isfinite(psnr) and 0 < psnr < 200):
        raise ValidationError(f"target PSNR must be a number of dB in (0, 200), got {psnr}")
    return Target("psnr", float(psnr))


# ------------------------------------------------------------------ models
@dataclass
class AttributeModel:
    """Predicted bytes and rendered MSE of one attribute at each of its ``choices``."""

    name: str
    choices: np.ndarray
    bytes: np.ndarray
    mse: np.ndarray

    def best_choices(self, lams: np.ndarray) -> np.ndarray:
        """The choice minimising ``bytes + lam * mse`` for each of ``lams``."""
        return self.choices[np.argmin(self.bytes[:, None] + lams[None, :] * self.mse[:, None], axis=0)]


@dataclass
class Plan:
    """The chosen settings, what the models predict for them and the rate point that codes them
    (built from the settings when first asked for: a hull holds thousands of plans, one is coded)."""

    settings: dict[str, int]
    predicted_bytes: float
    predicted_mse: float
    point_of: Callable[[dict[str, int]], RatePoint] = field(repr=False, compare=False)
    _point: RatePoint | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def rate_point(self) -> RatePoint:
        if self._point is None:
            self._point = self.point_of(self.settings)
        return self._point

    @property
    def predicted_psnr(self) -> float:
        return _psnr(self.predicted_mse)


@dataclass
class Outcome:
    """A rate-controlled encode: the stream, its plan and what the controller measured."""

    stream: Bitstream
    plan: Plan
    target: Target
    encodes: int
    seconds: dict[str, float] = field(default_factory=dict)
    measured_psnr: float | None = None
    #: One row per real encode: predicted and measured bytes and PSNR (the models' prediction error).
    trials: list[dict[str, float]] = field(default_factory=list)
    #: The probe's visibility the render sensitivities were weighed by (1: not weighed; version 11).
    probe_visibility: float = 1.0
    #: With ``--recover`` (:mod:`.rate_recover`): the source kept (its keep share) and every source's result.
    recovery: dict[str, Any] | None = None

    def summary(self) -> dict[str, Any]:
        """What ``encode --json`` and the header report about the choice."""
        out = {
            "target": {"kind": self.target.kind, "value": self.target.value},
            "settings": {**{k: v for k, v in self.plan.settings.items() if k not in ("prune", "dc_only")},
                         **self.plan.rate_point.prune_json(),
                         **({"dc_only_energy": self.plan.rate_point.dc_only_energy}
                            if self.plan.rate_point.dc_only_energy > 0 else {})},
            "predicted_bytes": round(self.plan.predicted_bytes),
            "predicted_psnr": round(self.plan.predicted_psnr, 3),
            "encodes": self.encodes,
            "seconds": {k: round(v, 3) for k, v in self.seconds.items()},
            "probe_visibility": round(self.probe_visibility, 3),
        }
        if self.measured_psnr is not None:
            out["measured_psnr"] = round(self.measured_psnr, 3)
        if self.trials:
            out["trials"] = [{k: round(v, 3) for k, v in row.items()} for row in self.trials]
        if self.recovery is not None:
            out["recovery"] = self.recovery
        tiers = (self.stream.header.get("rate_point") or {}).get("tiers")
        if tiers:  # the plan coded in the template's importance tiers (version 21)
            out["tiers"] = tiers
        return out


@dataclass
class _Encoded:
    """One of a target's real encodes: its stream, plan, PSNR on the controller's views (None: not
    measured yet) and its row in the target's trials."""

    stream: Bitstream
    plan: Plan
    measured: float | None
    trial: int


# -------------------------------------------------------------- controller
class RateController:
    """Choose the settings of ``template`` that meet a target on ``cloud`` (see module docstring).

    ``views``: cameras to judge quality from (default: orbit views around the cloud, with
    ``up`` as the world up axis), rendered over ``background`` (the scene's: a white
    background weighs errors differently from a black one). ``workers``/``progress`` as for :class:`Encoder`.
    Call :meth:`fit` once, then :meth:`encode` (or :meth:`plan`) for any number of targets.
    """

    def __init__(
        self,
        cloud: GaussianCloud,
        template: str | RatePoint = TEMPLATE,
        views: Sequence[Camera] | None = None,
        *,
        up: Sequence[float] = (0.0, 0.0, 1.0),
        background: Sequence[float] = (0.0, 0.0, 0.0),
        codec_options: dict[str, Any] | None = None,
        workers: int | None = None,
        progress: bool = False,
        max_encodes: int = MAX_ENCODES,
        importance_shares: Sequence[float] = IMPORTANCE_SHARES,
        view_metric: bool = True,
    ) -> None:
        # every encode of the scene, the probes of its subsets too, gets the whole scene's x265 analysis
        point = with_scene_analysis(load_rate_point(template).with_overrides(codec_options=codec_options),
                                    cloud.num_gaussians)
        if not point.positions_as_set or point.attributes["sh_features"].allocation != "waterfill":
            raise ValidationError(f"rate control needs a template with set-coded positions and water-filled SH "
                                  f"features (like {TEMPLATE}); {point.name} has not")
        if cloud.num_gaussians < 2:
            raise ValidationError("rate control needs at least 2 Gaussians")
        self.cloud = cloud
        #: the template's importance tiers (:mod:`.tiers`; version 21): the models and probes are of one
        #: grid; the real encodes split the plan's Gaussians into the tiers
        self.tiers = point.tiers
        self.template = dataclasses.replace(point, tiers=None)
        self.views = list(views) if views else orbit_views(cloud.means, CALIBRATION_VIEWS, CALIBRATION_WIDTH, up=up)
        self.views = _calibration_views(self.views)
        # importance from the other cameras, so the pruning error is measured on views it was not ranked on
        judged = {view.name for view in self.views}
        self.importance_shares = tuple(importance_shares)
        self.importance_views = importance_views(
            cloud, [v for v in views if v.name not in judged] or views if views else None, up=up) \
            if self.importance_shares or self.tiers is not None else []
        self.importance_: np.ndarray | None = None
        #: the caller's cameras: SHAC-PCA is fitted in their view metric (version 18, :meth:`_sh_metric`);
        #: None without cameras (orbit views are the controller's guess, not where the scene is seen from)
        self.metric_cameras: list[Camera] | None = list(views) if views and view_metric else None
        self.background = tuple(float(v) for v in background)
        self.workers = workers
        self.progress = progress
        self.max_encodes = max_encodes
        self.models_: dict[str, AttributeModel] = {}
        #: (rate-point prune settings, share of Gaussians kept, rendered MSE of pruning) per candidate
        self.prune_: list[tuple[dict[str, float], float, float]] = [(_prune(), 1.0, 0.0)]
        self._prune_masks: list[np.ndarray | None] = [None]  # the Gaussians each pruning choice keeps
        #: per pruning choice measured on the probe: each attribute's bytes per kept Gaussian against
        #: the unpruned probe's per Gaussian (version 14; one size target's, like :attr:`_exact`)
        self._prune_factors: dict[int, dict[str, float]] = {}
        #: the DC-only energy bars the controller chooses between (:mod:`.rate_sh_degree`), bar 0 first
        self.dc_only_: list[DcOnlyChoice] = [DcOnlyChoice(0.0)]
        self.overhead_: float = 0.0
        self.stage_: ShStage | None = None
        #: the rate-point attribute the ``sh`` QP sets: the water-filled features, or the AC coefficients
        #: of a template without an SH stage (stage ``none``: its degree ladder moves with the base QP)
        self.sh_attribute = STAGES.get(point.sh_stage).rate_attribute
        self.seconds_: dict[str, float] = {}
        self._cache: dict = {}
        self._references: list[np.ndarray] = []
        self._covariances: np.ndarray | None = None  # the cloud's 3D covariances (for renders of its variants)
        self._exact: dict[str, dict[int, float]] = {}
        self._last_order: np.ndarray | None = None  # source rows of the last encode's decoded rows
        self._probe_decoded: tuple[np.ndarray, GaussianCloud] | None = None  # (rows, decoded) at SENSITIVITY_QP
        self._sh_points: dict[int, dict[int, float]] = {}  # SH feature (-1: side information) -> {QP: bytes}
        self._sh_ranges: np.ndarray | None = None  # the whole cloud's range of each SH feature
        #: the fitted stage's features of every row (``stage_.transform``), given to the trial encodes
        self._stage_features: np.ndarray | None = None
        self._probe_rows: np.ndarray | None = None  # the probe's rows of the cloud
        #: the chunk cache of the probe's encodes (:meth:`_probe_encoder`): its placement, features and the
        #: chunks of settings coded before are not coded again (the same bytes)
        self._probe_cache: dict = {}
        self._probe_rates: dict[str, dict[int, float]] = {}  # QP attribute -> {probe QP: bytes, whole cloud}
        #: the rendered MSE of each attribute of the probe as decoded (the sensitivities' numerators)
        self.rendered_mse_: dict[str, float] = {}
        #: the probe's mean importance over the whole cloud's (:meth:`_probe_visibility`)
        self.probe_visibility_: float = 1.0

    # -------------------------------------------------------------- fit
    def fit(self) -> "RateController":
        """Measure the per-attribute models (probe encodes, position bits, render sensitivities)."""
        tic = time.perf_counter()
        cloud = self.cloud
        # the exact position bits (LZMA and sorts, which release the GIL) are coded beside the probe
        with ThreadPoolExecutor(self.workers or default_workers()) as pool:
            coded = _position_set_jobs(pool, cloud)
            if cloud.sh_degree > 0:
                from threadpoolctl import threadpool_limits

                # one BLAS thread, as in the encoder: the position jobs run beside it (a 1M profile at
                # load 6-8 spent 12 s in this fit, which takes 0.15 s alone; the same bytes)
                with threadpool_limits(1, user_api="blas"):
                    self.stage_ = fitted_stage(self.template, cloud, self._sh_metric())
            probes = len(PROBE_QPS)
            attributes = len(QP_ATTRIBUTES) - (0 if self.stage_ is not None else 1)
            renders = 1 + attributes + 1 + len(PRUNE_THRESHOLDS) - 1 + len(self.importance_shares) \
                + (len(DC_ONLY_BARS) - 1)  # references, perturbed attributes, positions, pruning, DC-only bars
            with tqdm(total=probes + renders, desc="rate control: calibrate", unit="step", disable=not self.progress,
                      leave=False) as bar:
                sh_values = self._sh_values()  # the whole cloud's SH features, once: the probe's extremes, ranges
                sh_ranges = None if sh_values is None else np.ptp(sh_values, axis=0)
                rows = _probe_rows(cloud)
                if rows.size < cloud.num_gaussians:
                    rows = np.union1d(rows, _extreme_rows(cloud, sh_values, self.template.rotation_form))
                sh_values = None
                self._probe_rows, self._sh_ranges, self._probe_cache = rows, sh_ranges, {}
                rates, errors, overhead = self._probe(rows, bar)
                self.seconds_["probe"] = time.perf_counter() - tic
                tic = time.perf_counter()
                # the DC-only bars' probe encodes (x265 in worker processes) run beside the calibration's renders
                dc_only_probes = pool.submit(self._dc_only_probe_sizes, rows, rates) if self._dc_only_applies(rates) \
                    else None
                sensitivity = self._calibrate(errors, bar)
                self.dc_only_ = self._fit_dc_only(rates, *(dc_only_probes.result() if dc_only_probes else ({}, {})),
                                                  bar=bar)
                self.seconds_["calibrate"] = time.perf_counter() - tic
            self.models_["positions"] = self._position_model(coded, sensitivity["positions"])
        self._probe_rates = {name: dict(zip(PROBE_QPS, map(float, rates[name]))) for name in rates}
        for name in rates:
            grid = self._choices(name)
            error_at = grid if name != "sh" or not self._waterfilled else \
                whole_base_equivalent(self._sh_ranges, self.stage_.feature_weights(), grid)
            self.models_[name] = AttributeModel(
                name, grid, self._rate_curve(name, grid), sensitivity[name] * _interpolate_log(PROBE_QPS, errors[name], error_at))
        self.overhead_ = overhead
        return self

    def _sh_metric(self) -> np.ndarray | None:
        """Version 18: the error metric of the AC coefficients as the caller's cameras see them
        (:func:`~gscodec_shac.shac.view_metric.view_metric`) when the template's SH stage takes one
        (joint-RGB SHAC-PCA over the AC); None otherwise."""
        if self.metric_cameras is None or self.cloud.sh_degree == 0 or \
                not metric_applies(self.template.sh_stage, self.template.sh_params):
            return None
        return cloud_view_metric(self.cloud, self.metric_cameras)

    def _choices(self, name: str) -> np.ndarray:
        """The settings QP attribute ``name`` chooses from: QPs 0-51, the water-filled SH features' base QP
        in steps of :data:`.allocation.BASE_QP_STEP` (version 17: a whole step of the base moves every
        feature's QP at once; on bonsai near 44 dB one step, 20 -> 21, moved the file by -1.1 dB and -3.3%
        of its bytes, wider than a PSNR target's window, and the quarter steps between land inside it)."""
        if name == "sh" and self._waterfilled:
            return np.arange(0.0, MAX_QP + BASE_QP_STEP / 2, BASE_QP_STEP)
        return np.arange(0, MAX_QP + 1)

    def _rate_curve(self, name: str, grid: np.ndarray) -> np.ndarray:
        """Bytes of QP attribute ``name`` at each QP of ``grid`` from the probe's encodes (:attr:`_probe_rates`,
        with a size target's encodes at its plans, :meth:`_probe_at`); the water-filled SH features' from
        :attr:`_sh_points` (:meth:`_sh_rates`)."""
        if name == "sh" and self._waterfilled:
            return self._sh_rates(grid, self._sh_ranges)
        points = self._probe_rates[name]
        qps = sorted(points)
        return _interpolate_log(qps, np.array([points[q] for q in qps]), grid)

    def _prune_candidates(self, renderer: Any = None) -> list[tuple[dict[str, float], np.ndarray]]:
        """Rate-point prune settings and the Gaussians kept (a mask) for each opacity threshold that prunes
        something (at most 80%) and each importance share (``renderer``: one of the cloud, for the
        importance renders)."""
        opacity = self.cloud.activated_opacities()
        n = self.cloud.num_gaussians
        out: list[tuple[dict[str, float], np.ndarray]] = []
        for threshold in PRUNE_THRESHOLDS[1:]:
            keep = opacity >= threshold
            if 0.2 <= np.count_nonzero(keep) / n < 1.0:
                out.append((_prune(min_opacity=threshold), keep))
        if self.importance_shares or self.tiers is not None:  # the tiers split by importance too
            tic = time.perf_counter()
            self.importance_ = gaussian_importance(self.cloud, self.importance_views, renderer=renderer,
                                                   progress=self.progress)
            # part of ``calibrate``: a scene's cameras (up to 512) can make it most of the fit
            self.seconds_["importance"] = time.perf_counter() - tic
        counts = [keep_count(n, share) for share in self.importance_shares]
        for share, rows in zip(self.importance_shares, most_important_counts(self.importance_, counts)):
            if rows.size < n:
                keep = np.zeros(n, dtype=np.bool_)
                keep[rows] = True
                out.append((_prune(keep_share=share), keep))
        return out

    def _calibrate(self, errors: dict[str, np.ndarray], bar: Any = None) -> dict[str, float]:
        """The render sensitivities (:meth:`_sensitivities`) and the pruning candidates' rendered MSE
        (:attr:`prune_`), against renders of the uncompressed cloud (:attr:`_references`).

        The variants that keep every Gaussian's geometry, the pruned subsets, the clouds with the
        probe's DC or SH features as decoded and the pruned subsets with the DC-only bars' AC
        zeroed (:meth:`_zeroings`), are rendered view by view from one prepared frame of
        the cloud (:class:`~gscodec_shac.render.variants.FrameVariants`: only the per-pixel blend runs
        again, the images are those of fresh renders); the others by renders of their own."""
        from gscodec_shac.render import Renderer
        from gscodec_shac.render.variants import FrameVariants

        renderer = Renderer(self.cloud)
        self._covariances = renderer.cov3
        candidates = self._prune_candidates(renderer)
        rows, decoded = self._probe_decoded
        probe = self.cloud.select(rows)
        recolours, variant = {}, None
        for name in ("sh_dc", "sh"):
            if name in errors:
                variant = _with_decoded(probe, name, np.arange(rows.size), decoded)
                recolours[name] = (variant.sh_dc, variant.sh_rest)
        # the other attributes move the probe's Gaussians: only the tiles those touch blend again
        moved = self._moved_parts(probe, rows, decoded, [name for name in errors if name not in recolours]) \
            if rows.size < self.cloud.num_gaussians else {}
        probe = variant = None
        zeroings = self._zeroings(candidates, errors)
        no_ac = np.zeros((max((z.size for _, z in zeroings.values()), default=0), *self.cloud.sh_rest.shape[1:]),
                         dtype=self.cloud.sh_rest.dtype)
        self._references = []
        per_view: dict[Any, list] = {key: [] for key in [*recolours, *moved, *range(len(candidates)), *zeroings]}
        for view in self.views:
            frame = FrameVariants(renderer, view, self.background, moved_rows=rows.size if moved else 0)
            reference = frame.image()
            self._references.append(reference)
            for name, (sh_dc, sh_rest) in recolours.items():
                per_view[name].append(np.mean((frame.recoloured(rows, sh_dc, sh_rest) - reference) ** 2))
            for name, (ascending, part) in moved.items():
                per_view[name].append(np.mean((frame.moved(ascending, part, reference) - reference) ** 2))
            for index, (_, keep) in enumerate(candidates):
                per_view[index].append(np.mean((frame.subset(keep) - reference) ** 2))
            for key, (keep, zero) in zeroings.items():
                image = frame.variant(keep=keep, rows=zero, sh_dc=self.cloud.sh_dc[zero], sh_rest=no_ac[:zero.size])
                per_view[key].append(np.mean((image - reference) ** 2))
        renderer = frame = no_ac = None
        self._zeroed_mse = {key: float(np.mean(per_view[key])) for key in zeroings}
        if bar is not None:
            bar.update(1 + len(PRUNE_THRESHOLDS) - 1 + len(self.importance_shares))
        n = self.cloud.num_gaussians
        self.prune_ = [(_prune(), 1.0, 0.0)] + [
            (settings, int(np.count_nonzero(keep)) / n, float(np.mean(per_view[i])))
            for i, (settings, keep) in enumerate(candidates)]
        self._prune_masks = [None] + [keep for _, keep in candidates]
        self.rendered_mse_ = {name: float(np.mean(per_view[name])) for name in [*recolours, *moved]}
        return self._sensitivities(errors, self.rendered_mse_, bar)

    @staticmethod
    def _moved_parts(probe: GaussianCloud, rows: np.ndarray, decoded: GaussianCloud,
                     names: Sequence[str]) -> dict[str, tuple[np.ndarray, Any]]:
        """Per attribute of ``names``: the probe's ``rows`` in ascending order and a renderer of the probe's
        Gaussians in that order with that attribute as ``decoded`` (row for row with ``rows``), for
        :meth:`~gscodec_shac.render.variants.FrameVariants.moved` (the same images as renders of the whole
        cloud with those rows replaced, :meth:`_rendered_with_decoded`)."""
        from gscodec_shac.render import Renderer

        ascending = np.argsort(rows, kind="stable")
        everything = np.arange(rows.size)
        return {name: (rows[ascending], Renderer(_with_decoded(probe, name, everything, decoded).select(ascending)))
                for name in names}

    def _dc_only_applies(self, names: Any) -> bool:
        """Whether the DC-only bars are a choice: an SH attribute among ``names`` whose stage codes the DC
        apart, and a template that does not set its own DC-only Gaussians."""
        return "sh" in names and self.stage_ is not None and not self.stage_.uses_dc and not self.template.dc_only

    def _zeroings(self, candidates: list[tuple[dict[str, float], np.ndarray]],
                  names: Any) -> dict[tuple[float, int], tuple[np.ndarray | None, np.ndarray]]:
        """Per DC-only bar and pruning choice (0: none, ``i + 1``: ``candidates[i]``), the Gaussians kept
        (a mask, None for all) and those of them the bar leaves DC-only, flagged among the kept ones
        (:func:`.rate_sh_degree.kept_flags`); empty when the bars are no choice."""
        if not self._dc_only_applies(names):
            return {}
        energy = cloud_energy(self.cloud)
        order = np.argsort(energy, kind="stable")  # once for every pruning choice
        kept = [None] + [keep for _, keep in candidates]
        everything = np.arange(self.cloud.num_gaussians)
        return {(value, j): (keep, kept_flags(energy, everything if keep is None else np.flatnonzero(keep), value,
                                              order))
                for value in DC_ONLY_BARS if value > 0 for j, keep in enumerate(kept)}

    def _dc_only_probe_sizes(self, rows: np.ndarray, rates: dict[str, np.ndarray]
                             ) -> tuple[dict[float, np.ndarray], dict[tuple[float, int], float]]:
        """Each DC-only bar's flags over the whole cloud (:func:`.rate_sh_degree.whole_cloud_flags`) and
        the SH bytes (scaled to the whole cloud) of the probe of ``rows`` under each bar that flags
        something, at each of :data:`RATIO_QPS`: what :func:`.rate_sh_degree.fit_choices` measures,
        the encodes one after the other (beside the calibration's renders)."""
        probe = self.cloud.select(rows)
        scale = self.cloud.num_gaussians / probe.num_gaussians
        flags = {value: whole_cloud_flags(self.cloud, value) for value in DC_ONLY_BARS if value > 0}
        out = {}
        for value, flagged in flags.items():
            if not flagged.any():
                continue
            for qp in RATIO_QPS:
                point = self._rate_point({a: qp for a in rates} | {"positions": 16}).with_overrides(dc_only_energy=value)
                sizes = self._probe_encoder(point).encode(probe).attribute_sizes()
                out[(value, qp)] = _scaled_probe_bytes(sizes, "sh", scale)
        return flags, out

    def _fit_dc_only(self, rates: dict[str, np.ndarray], flags: dict[float, np.ndarray],
                     sizes: dict[tuple[float, int], float], bar: Any = None) -> list[DcOnlyChoice]:
        """The DC-only energy bars to choose between, measured (:func:`.rate_sh_degree.fit_choices`) from
        the bars' ``flags`` and probe encodes ``sizes`` (:meth:`_dc_only_probe_sizes`), with the zeroing
        errors rendered by :meth:`_calibrate`; bar 0 alone when they are no choice (:meth:`_dc_only_applies`)."""
        if not self._dc_only_applies(rates):
            return [DcOnlyChoice(0.0)]

        def zeroing_errors(value: float) -> tuple[float, ...]:
            return tuple(max(self._zeroed_mse[(value, j)] - prune_mse, 0.0)
                         for j, (_, _, prune_mse) in enumerate(self.prune_))

        without = {qp: float(rates["sh"][PROBE_QPS.index(qp)]) for qp in RATIO_QPS}  # the probe's own encodes
        return fit_choices(without, flags, sizes, zeroing_errors, bar=bar)

    def _dc_factor(self, settings: dict[str, int], name: str) -> float:
        """The factor of attribute ``name``'s bytes under the settings' DC-only bar."""
        return float(self.dc_only_[settings.get("dc_only", 0)].bytes_factor(settings[name])) if name == "sh" else 1.0

    def _dc_models(self, dc: int) -> dict[str, AttributeModel]:
        """The attribute models under DC-only choice ``dc`` (the SH bytes scaled by its factor)."""
        models = dict(self.models_)
        if dc and "sh" in models:
            sh = models["sh"]
            models["sh"] = AttributeModel(sh.name, sh.choices, sh.bytes * self.dc_only_[dc].bytes_factor(sh.choices),
                                          sh.mse)
        return models

    def _probe(self, rows: np.ndarray, bar: Any = None) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], float]:
        """Per attribute, bytes (scaled to the whole cloud) and attribute MSE at each probe QP of the
        probe made of ``rows`` (``bar``: a progress bar advanced once per probe)."""
        self._sh_points = {}
        probe = self.cloud.select(rows)
        scale = self.cloud.num_gaussians / probe.num_gaussians
        names = [a for a in QP_ATTRIBUTES if a != "sh" or self.stage_ is not None]
        rates = {a: np.zeros(len(PROBE_QPS)) for a in names}
        errors = {a: np.zeros(len(PROBE_QPS)) for a in names}
        overhead = 0.0
        for i, qp in enumerate(PROBE_QPS):
            point = self._rate_point({a: qp for a in names} | {"positions": 16})
            encoder = self._probe_encoder(point)
            stream = encoder.encode(probe)
            decoded = _decoded(stream, self.workers)
            source = probe.select(encoder.order_)
            sizes = stream.attribute_sizes()
            for a in names:
                rates[a][i] = _scaled_probe_bytes(sizes, a, scale)
                errors[a][i] = _attribute_mse(a, source, decoded, point.color == "ycbcr")
            if qp == SENSITIVITY_QP:
                self._probe_decoded = (rows[encoder.order_], decoded)
            if "sh" in names and self._waterfilled:
                self._record_sh_chunks(stream, scale)
            # the header and the HEVC parameter-set table (codec/parameter_sets.py): a file's fixed bytes
            overhead = max(overhead, sizes.get("header", 0) + sizes.get(parameter_sets.CHUNK, 0))
            if bar is not None:
                bar.update(1)
        return rates, errors, overhead

    @property
    def _waterfilled(self) -> bool:
        """Whether the ``sh`` QP is the base QP of water-filled features (else of the AC degree ladder)."""
        return self.sh_attribute == "sh_features"

    def _sh_values(self) -> np.ndarray | None:
        """The whole cloud's SH features as the encoder quantises them (YCbCr triplets where it applies);
        the stage's own features are kept (:attr:`_stage_features`)."""
        if self.stage_ is None:
            return None
        ac = self.cloud.ac_matrix()
        features = np.asarray(self.stage_.transform(np.concatenate([self.cloud.sh_dc, ac], axis=1)
                                                    if self.stage_.uses_dc else ac))
        self._stage_features = features  # the trial encodes gather theirs from these
        if self.template.color == "ycbcr" and self.stage_.ycbcr_applies(features.shape[1]):
            features = qz.triplets_to_ycbcr(features)
        return features

    def _record_sh_chunks(self, stream: Bitstream, scale: float) -> None:
        """Remember each SH feature's bytes (scaled to the whole cloud) at the QP a probe coded it with;
        a chunk of several features (equal QPs) is shared equally among them."""
        for name in stream.header["attributes"]["sh"]["chunks"]:
            chunk = stream.chunk(name)
            start, stop = chunk.meta["channels"]
            for feature in range(start, stop):
                self._sh_points.setdefault(feature, {})[int(chunk.meta["qp"])] = \
                    scale * len(chunk.data) / (stop - start)
        self._sh_points.setdefault(-1, {})[int(stream.header["sh"]["features"])] = \
            float(stream.attribute_sizes().get("sh_state", 0))

    def _sh_rates(self, grid: np.ndarray, ranges: np.ndarray) -> np.ndarray:
        """Bytes of the water-filled SH features (value ``ranges`` per feature) at each base QP of
        ``grid``: the sum over the features kept of each one's bytes at its own QP (interpolated
        between the probe's), plus the stage's side information (interpolated in the number kept).
        Water-filling drops features as the base QP rises, which one curve over the base QP would
        smear between the probe's QPs."""
        weights = self.stage_.feature_weights()
        curves: dict[int, np.ndarray] = {}
        for feature, points in sorted(self._sh_points.items()):
            if feature >= 0 and points:
                qps = sorted(points)
                curves[feature] = _interpolate_log(qps, np.array([points[q] for q in qps]), np.arange(0, 52))
        # a feature the probe never kept (only below its lowest QP) costs what the last measured one
        # before it does (the first measured one when none comes before it)
        curve_of = [curves.get(f, curves[max((k for k in curves if k <= f), default=min(curves))])
                    for f in range(ranges.size)] if curves else []
        state = sorted(self._sh_points.get(-1, {}).items())
        out = np.zeros(grid.size)
        for i, base in enumerate(grid):
            qps = waterfill_qps(ranges, weights, float(base))
            out[i] = sum(curve_of[f][q] for f, q in enumerate(qps))
            if state:
                out[i] += float(np.interp(len(qps), [k for k, _ in state], [v for _, v in state]))
        return out

    def _sensitivities(self, errors: dict[str, np.ndarray], rendered: dict[str, float],
                       bar: Any = None) -> dict[str, float]:
        """Rendered MSE per unit attribute MSE: renders of the cloud with one attribute of the probe's
        Gaussians replaced by what the codec decoded at :data:`SENSITIVITY_QP` (its errors are
        correlated along the grid, as in a real encode, where independent noise of the same size
        renders less error), divided by that error spread over the whole cloud and weighted by the
        probe's visibility (:meth:`_probe_visibility`; ``rendered``: the rendered MSE of the attributes
        already rendered; ``bar``: a progress bar advanced once per attribute)."""
        middle = PROBE_QPS.index(SENSITIVITY_QP)
        rows, decoded = self._probe_decoded
        share = rows.size / self.cloud.num_gaussians
        self.probe_visibility_ = self._probe_visibility(rows)
        out = {}
        for name, mse in errors.items():
            # the probe's error spread over the whole cloud, as visible as the probe's Gaussians (version 11)
            error = max(float(mse[middle]), 1e-12) * share * self.probe_visibility_
            if name not in rendered:
                rendered[name] = self._rendered_with_decoded(name, rows, decoded)
            out[name] = rendered[name] / error
            if bar is not None:
                bar.update(1)
        bits = 12
        moved = _quantised_positions(self.cloud, bits)
        step_mse = _position_step_mse(self.cloud, bits)
        out["positions"] = self._rendered_mse(moved, slice(None)) / step_mse
        if bar is not None:
            bar.update(1)
        return out

    def _probe_visibility(self, rows: np.ndarray) -> float:
        """How much more the probe's Gaussians (``rows``) show than the cloud's on average: their mean
        importance over the whole cloud's (summed blending weight per pixel,
        :func:`.importance.gaussian_importance`: the pruning's, else on the controller's views), within
        :data:`VISIBILITY_BOUNDS`; 1 when the probe is the whole cloud or the ratio lies inside
        :data:`VISIBILITY_BAND`.

        The probe is a few runs along the Morton order, so a few places in the scene. Where those show
        more than the average Gaussian, every render sensitivity came out too high by as much (version 10
        and before): on synthetic 250k the probe's rows rendered 1.5-1.8x the error per Gaussian of the
        whole cloud under the same encode, where their mean importance is 1.45x the cloud's, and the
        first plan of a 52 dB target measured 2.4 dB above its prediction (docs/rate_control.md,
        "Controller version 11"). The proxy is rough: it weighs blending weights, not rendered errors,
        on the pruning's views. On the trained scenes it reads 0.87-1.10, within the first plans' own
        scatter, and taking it there made bonsai's PSNR-target files 2-3% bigger; so a ratio inside
        :data:`VISIBILITY_BAND` counts as 1."""
        if rows.size >= self.cloud.num_gaussians:
            return 1.0
        importance = self.importance_
        if importance is None:
            importance = gaussian_importance(self.cloud, self.views)
        whole, probe = float(np.mean(importance)), float(np.mean(importance[rows]))
        if not (whole > 0 and probe > 0):  # nothing visible on these views: no evidence either way
            return 1.0
        ratio = probe / whole
        if VISIBILITY_BAND[0] <= ratio <= VISIBILITY_BAND[1]:
            return 1.0
        return min(max(ratio, VISIBILITY_BOUNDS[0]), VISIBILITY_BOUNDS[1])

    def _position_model(self, coded: dict[int, Future], sensitivity: float) -> AttributeModel:
        """Exact set-coding bytes per bit depth (``coded``: :func:`_position_set_jobs`); rendered MSE
        from the quantisation step. The unpruned cloud's chunks are kept for the trial encodes."""
        chunks = {bits: job.result() for bits, job in coded.items()}
        for bits, data in chunks.items():
            key = position_set_cache_key(self._rate_point({"positions": bits}), bits)
            self._cache[key] = data
        sizes = [len(chunks[bits]) for bits in POSITION_BITS]
        mses = [sensitivity * _position_step_mse(self.cloud, bits) for bits in POSITION_BITS]
        return AttributeModel("positions", np.array(POSITION_BITS), np.array(sizes, float), np.array(mses))

    def _rendered_with_decoded(self, name: str, rows: np.ndarray, decoded: GaussianCloud) -> float:
        """Rendered MSE of the cloud with attribute ``name`` of its ``rows`` as ``decoded`` (row for row)."""
        same_shapes = None if name in ("rotation", "scale") else slice(None)  # else the covariances stay
        return self._rendered_mse(_with_decoded(self.cloud, name, rows, decoded), same_shapes)

    def _rendered_mse(self, cloud: GaussianCloud, rows: np.ndarray | slice | None = None) -> float:
        """Rendered MSE of ``cloud`` against the references; ``rows``: ``cloud``'s rows of :attr:`cloud` when
        their scales and rotations are the same (their 3D covariances are then taken, not recomputed)."""
        from gscodec_shac.render import Renderer

        covariances = None if rows is None or self._covariances is None else self._covariances[rows]
        renderer = Renderer(cloud, covariances=covariances)
        return float(np.mean([np.mean((renderer.render(v, background=self.background).image - ref) ** 2)
                              for v, ref in zip(self.views, self._references)]))

    # ------------------------------------------------------------- plan
    def plan(self, target: Target) -> Plan:
        """The settings the models pick for ``target`` (models corrected by the last encode's measurements)."""
        if not self.models_:
            raise ValidationError("call fit() before plan()")
        hull = self._hull()
        if target.kind == "bytes":
            feasible = [p for p in hull if p.predicted_bytes <= target.value]
            if not feasible:
                smallest = min(p.predicted_bytes for p in hull)
                raise TargetUnreachableError(
                    f"target {target.describe()} is below the smallest file this scene can be coded into "
                    f"(about {smallest:,.0f} bytes, {8 * smallest / self.cloud.num_gaussians:.1f} bits/Gaussian)")
            return min(feasible, key=lambda p: (p.predicted_mse, p.predicted_bytes))
        wanted = 10.0 ** (-target.value / 10.0)
        feasible = [p for p in hull if p.predicted_mse <= wanted]
        if not feasible:
            best = max(p.predicted_psnr for p in hull)
            raise TargetUnreachableError(
                f"target {target.describe()} is above the best quality this codec reaches on this scene "
                f"(about {best:.2f} dB against the uncompressed model)")
        return min(feasible, key=lambda p: (p.predicted_bytes, p.predicted_mse))

    def _hull(self) -> list[Plan]:
        """Plans along the lower convex hull of (bytes, rendered MSE): one per Lagrange multiplier,
        pruning choice and DC-only bar (pruning scales every attribute's bytes by the share kept)."""
        plans: dict[tuple, Plan] = {}
        memo: dict[tuple, float] = {}  # the attributes' bytes and MSE per setting, shared by the hull's plans
        model = self.models_["positions"]
        lams = np.geomspace(1e-3, 1e15, 400)
        for index, (_, kept, _) in enumerate(self.prune_):
            position_bytes = np.array([self._position_bytes(int(b), index) for b in model.choices])
            positions = dataclasses.replace(model, bytes=position_bytes).best_choices(lams)
            for dc in range(len(self.dc_only_)):
                models = self._dc_models(dc)
                # each attribute's choice at every multiplier at once
                chosen = {name: m.best_choices(lams / (kept * self._prune_factor(index, name)))
                          for name, m in models.items() if name != "positions"}
                for i in range(lams.size):
                    settings = {name: _setting(choices[i]) for name, choices in chosen.items()}
                    settings["positions"] = int(positions[i])
                    settings["prune"] = index
                    settings["dc_only"] = dc
                    key = tuple(sorted(settings.items()))
                    if key not in plans:
                        plans[key] = self._predict(settings, memo)
        return list(plans.values())

    def _predict(self, settings: dict[str, int], memo: dict[tuple, float] | None = None) -> Plan:
        """Bytes and rendered MSE the models predict for ``settings``, corrected by the encodes so far
        (``memo``: each attribute's bytes and MSE per setting, kept across the plans of one hull)."""
        prune = settings.get("prune", 0)
        _, kept, prune_mse = self.prune_[prune]
        dc_choice = settings.get("dc_only", 0)
        dc = self.dc_only_[dc_choice]
        memo = {} if memo is None else memo

        def attribute_bytes(name: str) -> float:
            key = (name, settings[name], prune, dc_choice)
            if key not in memo:
                memo[key] = self._attribute_bytes(settings, name)
            return memo[key]

        def attribute_mse(name: str, model: AttributeModel) -> float:
            key = (name, settings[name])
            if key not in memo:
                memo[key] = model.mse[np.searchsorted(model.choices, settings[name])]
            return memo[key]

        size = self._overhead_bytes() + self._position_bytes(settings["positions"], prune) + kept * dc.flag_bytes + sum(
            attribute_bytes(name) for name in self.models_ if name != "positions")
        mse = prune_mse + dc.zeroing(prune) + sum(attribute_mse(n, m) for n, m in self.models_.items())
        return Plan(settings, size, mse, self._rate_point)

    def _attribute_bytes(self, settings: dict[str, int], name: str) -> float:
        """The bytes :meth:`_predict` counts for attribute ``name`` under ``settings``: after the pruning's
        share kept and the DC-only bar (the positions: :meth:`_position_bytes`)."""
        prune = settings.get("prune", 0)
        if name == "positions":
            return self._position_bytes(settings["positions"], prune)
        return self._kept_factor(settings, name) * self._bytes(name, settings[name])

    def _kept_factor(self, settings: dict[str, int], name: str) -> float:
        """What the pruning and DC-only bar of ``settings`` make of QP attribute ``name``'s unpruned bytes:
        the share kept times a kept Gaussian's cost (:meth:`_prune_factor`) times the DC-only factor."""
        prune = settings.get("prune", 0)
        return self.prune_[prune][1] * self._prune_factor(prune, name) * self._dc_factor(settings, name)

    def _prune_factor(self, prune: int, name: str) -> float:
        """Bytes per kept Gaussian of QP attribute ``name`` under pruning choice ``prune``, against the
        unpruned cloud's per Gaussian (version 14): measured on the probe (:meth:`_probe_at`), else
        interpolated in the share kept between no pruning (1) and the choices measured, constant past
        them; 1 before any is measured.

        A pruned cloud's Gaussians each cost more: on the chair (50k), with the 32% below opacity 0.02
        gone, a kept Gaussian's SH cost 1.35x an average one (DC 1.30x, rotation 1.18x; removing a
        random 32%: 1.16x, 1.04x, 1.03x). The faint Gaussians are cheap, and a sparser grid codes
        worse; the factor levels off at 1.2-1.5 (docs/rate_control.md, "Controller version 14";
        ``scripts/prune_cost.py``)."""
        if prune == 0 or name == "positions" or not self._prune_factors:
            return 1.0
        if prune in self._prune_factors:
            return self._prune_factors[prune].get(name, 1.0)
        measured = sorted((self.prune_[i][1], factors.get(name, 1.0)) for i, factors in self._prune_factors.items())
        shares = [share for share, _ in measured] + [1.0]
        return float(np.interp(self.prune_[prune][1], shares, [factor for _, factor in measured] + [1.0]))

    def _position_bytes(self, bits: int, prune: int) -> float:
        """Set-coded positions at ``bits`` after pruning: measured, else the unpruned size scaled by the
        share kept plus the gaps' growth (log2(1/kept) bits each)."""
        exact = self._exact.get("positions", {})
        if bits in exact:
            return exact[bits]
        model = self.models_["positions"]
        kept = self.prune_[prune][1]
        full = model.bytes[np.searchsorted(model.choices, bits)]
        return kept * (full + self.cloud.num_gaussians * math.log2(1.0 / kept) / 8.0)

    def _bytes(self, name: str, choice: int) -> float:
        """One attribute's bytes at ``choice``: measured when an encode coded it so (the bytes of a chunk
        depend only on its planes and settings), else the model scaled by the measured/modelled ratio
        of the nearest measured choices (interpolated in the log domain)."""
        model = self.models_[name]
        modelled = model.bytes[np.searchsorted(model.choices, choice)]
        exact = self._exact.get(name, {})
        if choice in exact:
            return exact[choice]
        if not exact:
            return modelled
        known = sorted(exact)
        ratios = [np.log(exact[k] / max(model.bytes[np.searchsorted(model.choices, k)], 1e-9)) for k in known]
        return modelled * float(np.exp(np.interp(choice, known, ratios)))

    def _overhead_bytes(self) -> float:
        return self._exact.get("overhead", {}).get(0, self.overhead_)

    def _learn(self, plan: Plan, stream: Bitstream) -> None:
        """Remember what each attribute of ``plan``'s encode cost (the positions fix the grid: their
        setting is the same for every later plan of this target)."""
        sizes = _model_sizes(stream)
        for name in self.models_:
            if sizes.get(name, 0) > 0:  # kept unpruned-equivalent, without a DC-only bar; positions as measured
                scale = 1.0 if name == "positions" else 1.0 / self._kept_factor(plan.settings, name)
                self._exact.setdefault(name, {})[plan.settings[name]] = float(sizes[name]) * scale
        coded = sum(sizes.get(name, 0) for name in self.models_) + sizes.get("sh_dc_only", 0)  # the flags: modelled
        self._exact["overhead"] = {0: float(stream.total_bytes() - coded)}

    def _rate_point(self, settings: dict[str, int]) -> RatePoint:
        """The template with ``settings`` (position bits and QPs) filled in."""
        point = self.template
        attributes = dict(point.attributes)
        for name, value in settings.items():
            if name in ("prune", "dc_only"):
                continue
            key = self.sh_attribute if name == "sh" else name
            field_name = "bits" if name == "positions" else "qp"
            qp = attributes[key].qp
            if field_name == "qp" and isinstance(qp, tuple):  # a degree ladder: its first QP moves, the steps stay
                value = tuple(min(51, int(value) + q - qp[0]) for q in qp)
            attributes[key] = dataclasses.replace(attributes[key], **{field_name: value if isinstance(value, tuple)
                                                                      else _setting(value)})
        return dataclasses.replace(point, attributes=attributes, name=f"{point.name}+auto",
                                   **self.prune_[settings.get("prune", 0)][0],
                                   **self.dc_only_[settings.get("dc_only", 0)].rate_point_fields())

    # ----------------------------------------------------------- encode
    def encode(self, target: Target) -> Outcome:
        """Plan, encode, correct and re-encode until the target is met (see module docstring).

        After the first encode the position bits and the pruning stay fixed (changing them
        re-sorts the grid, so no coded chunk could be reused). A size target moves the QPs by
        single steps, the cheapest error per byte first, with the rate model scaled by what the
        encodes measured; a PSNR target walks a chain of single QP steps from the smallest file
        above its window, the PSNR estimated from the encodes (:meth:`_next_for_quality`), with each
        attribute's error model rescaled by what its first encode rendered (:meth:`_rescale_models`;
        the fitted models are back when the target is done).
        """
        if not self.models_:
            self.fit()
        # a PSNR target rescales the models for itself (version 12), a size target adds rate points (13, 14)
        fitted = (dict(self.models_), {name: dict(points) for name, points in self._probe_rates.items()},
                  {feature: dict(points) for feature, points in self._sh_points.items()})
        self._prune_factors = {}
        try:
            return self._encode_to(target)
        finally:
            self.models_, self._probe_rates, self._sh_points = fitted
            self._prune_factors = {}

    def _encode_to(self, target: Target) -> Outcome:
        """:meth:`encode` with the models fitted."""
        tic = time.perf_counter()
        self._exact = {}  # bytes measured per attribute and setting
        self.seconds_.pop("plan_probe", None)  # an earlier target's
        plan: Plan = self._first_plan(target)
        first_plan_bytes = plan.predicted_bytes
        for _ in range(PLAN_PROBES if target.kind == "bytes" else 0):  # versions 13, 14 and 16
            if not self._probe_at(plan):
                break
            plan = self._first_plan(target)
            self.seconds_["plan_probe"] = time.perf_counter() - tic
            if plan.settings.get("prune", 0) in (0, *self._prune_factors) and self._sh_measured(plan):
                break
        trials: list[dict[str, float]] = []
        bar = tqdm(total=self.max_encodes, desc="rate control: encode", unit="encode", disable=not self.progress,
                   leave=False)
        if target.kind == "bytes":
            best = self._checked_tiers(self._search_size(plan, target, trials, bar), plan, target, trials, bar)
        else:
            best = self._search_psnr(plan, target, trials, bar)
        bar.close()
        if trials and "plan_probe" in self.seconds_:
            trials[0]["first_plan_bytes"] = first_plan_bytes  # predicted before the probe at its QPs
        self.seconds_["encode"] = time.perf_counter() - tic
        if best is None:
            raise TargetUnreachableError(f"no encode met {target.describe()} in {len(trials)} tries")
        measured = best.measured if best.measured is not None else self.measured_psnr(best.stream)
        return Outcome(best.stream, best.plan, target, len(trials), dict(self.seconds_), measured, trials,
                       self.probe_visibility_)

    def _trial(self, plan: Plan, target: Target, expected: float, trials: list[dict[str, float]],
               bar: Any, *, one_grid: bool = False) -> Bitstream:
        """One real encode of ``plan`` (in one grid when ``one_grid``, else as :meth:`_tiered` says), recorded in
        ``trials`` (predicted and measured bytes, chunks coded)."""
        cached = set(self._cache)
        tiered = self._tiered(plan, target, one_grid=one_grid)
        stream = self._encode(plan, target, one_grid=one_grid)
        bar.update(1)
        trials.append({"predicted_bytes": plan.predicted_bytes, "bytes": stream.total_bytes(),
                       "model_psnr": plan.predicted_psnr, "predicted_psnr": expected,
                       "chunks": len(stream.chunks), "chunks_coded": _coded_chunks(set(self._cache) - cached),
                       "tiered": float(tiered)})
        self._learn(plan, stream)
        return stream

    def _search_size(self, plan: Plan, target: Target, trials: list[dict[str, float]], bar: Any, *,
                     one_grid: bool = False) -> _Encoded | None:
        """Encode from ``plan`` (every plan in one grid when ``one_grid``) until a file lands within
        :data:`SIZE_TOLERANCE` under the size target (or the encodes run out); the biggest file under the target."""
        tried: set[tuple] = set()
        best: _Encoded | None = None
        current: Plan | None = plan
        while current is not None and len(trials) < self.max_encodes and _key(current) not in tried:
            tried.add(_key(current))
            started = time.perf_counter()
            stream = self._trial(current, target, plan.predicted_psnr, trials, bar, one_grid=one_grid)
            size = stream.total_bytes()
            if size <= target.value and (best is None or size > best.stream.total_bytes()):
                best = _Encoded(stream, current, None, len(trials) - 1)
            if (1 - SIZE_TOLERANCE) * target.value <= size <= target.value:
                current = None
            else:
                current = self._next_for_size(current, size, target, tried)
            trials[-1]["seconds"] = time.perf_counter() - started
        return best

    def _checked_tiers(self, best: _Encoded | None, start: Plan, target: Target, trials: list[dict[str, float]],
                       bar: Any) -> _Encoded | None:
        """Version 23: a size target's file coded in tiers is kept when it renders on the controller's views at
        least as well as its plan's one-grid models predict; else the target is searched again in one grid
        from ``start`` (the same first plan, the rate corrections of the tiered encodes dropped) and of the two
        files, each the biggest under the target, the one that renders better is kept. On bonsai, the chair
        and snowmiku every tiered file of SHAC-auto rendered 0.9-5.2 dB above that prediction; on the
        500,000-Gaussian playbot the tiers lost up to 4.1 dB to one grid with files 0.6-5.9 dB below it
        (docs/rate_control.md, "Controller version 23"). Checking the first tiered encode instead saves an
        encode or two there, but compares the one-grid file with a smaller tiered one: tried, not kept."""
        if best is None or not self._tiered(best.plan, target):
            return best
        if not self._falls_short(best, trials) or len(trials) >= self.max_encodes:
            return best
        self._exact = {}
        one_grid = self._search_size(start, target, trials, bar, one_grid=True)
        if one_grid is None:
            return best
        self._measure(one_grid, trials)
        return one_grid if one_grid.measured > best.measured else best

    def _falls_short(self, encoded: _Encoded, trials: list[dict[str, float]]) -> bool:
        """Whether ``encoded`` renders below its plan's one-grid prediction on the controller's views."""
        self._measure(encoded, trials)
        return encoded.measured < encoded.plan.predicted_psnr

    def _measure(self, encoded: _Encoded, trials: list[dict[str, float]]) -> None:
        """``encoded``'s PSNR on the controller's views, recorded in its trial too."""
        encoded.measured = self.measured_psnr(encoded.stream)
        trials[encoded.trial]["measured_psnr"] = encoded.measured

    def _search_psnr(self, plan: Plan, target: Target, trials: list[dict[str, float]], bar: Any
                     ) -> _Encoded | None:
        """Encode from ``plan`` until the smallest file measured within :data:`PSNR_WINDOW` above the PSNR
        target lands (or the encodes run out): a regula falsi along a chain of single QP steps
        (:meth:`_next_for_quality`), the models rescaled by the first encode's renders when it came near."""
        tried: set[tuple] = set()
        best: _Encoded | None = None
        measured_plans: list[tuple[Plan, int, float]] = []  # (plan, bytes, measured PSNR)
        current: Plan | None = plan
        expected = plan.predicted_psnr  # the PSNR the controller expects of the plan it encodes
        while current is not None and len(trials) < self.max_encodes and _key(current) not in tried:
            tried.add(_key(current))
            started = time.perf_counter()
            stream = self._trial(current, target, expected, trials, bar)
            size = stream.total_bytes()
            decoded = _decoded(stream, self.workers)
            measured = _psnr(self._rendered_mse(decoded))
            trials[-1]["measured_psnr"] = measured
            measured_plans.append((current, size, measured))
            if measured >= target.value and (best is None or size < best.stream.total_bytes()):
                best = _Encoded(stream, current, measured, len(trials) - 1)
            if best is not None and best.measured <= target.value + PSNR_WINDOW:  # the smallest file that meets it lands
                current = None
            else:
                if len(trials) == 1 and abs(measured - target.value - PSNR_WINDOW / 2) <= RESCALE_WITHIN:
                    # the models, by what the first encode rendered, when it came near enough
                    trials[-1]["rescaled"] = self._rescale_models(current, decoded)
                current, expected = self._next_for_quality(target, measured_plans, tried) or (None, math.nan)
            decoded = None
            trials[-1]["seconds"] = time.perf_counter() - started
        return best

    def _first_plan(self, target: Target) -> Plan:
        """The hull's plan for ``target``, aimed at the middle of its window when it can; for a size,
        the bytes between that hull point and the next are spent by single QP steps (:meth:`_adjust`;
        version 9: the hull's points can lie 10% apart, wider than the window)."""
        middle = target.value + PSNR_WINDOW / 2 if target.kind == "psnr" else target.value * (1 - SIZE_TOLERANCE / 2)
        try:
            plan = self.plan(Target(target.kind, middle))
        except TargetUnreachableError:
            return self.plan(target)
        if target.kind == "bytes":
            plan = self._adjust(plan, limit=middle) or plan
        return plan

    def _next_for_size(self, plan: Plan, size: int, target: Target, tried: set[tuple]) -> Plan | None:
        """The next plan after an encode of ``size`` bytes missed a size target's window: single QP
        steps from ``plan`` with the corrected rate model (:meth:`_adjust`), keeping the SH features'
        base QP when the encode came within :data:`FINE_BAND` of the target, that reaches an untried
        plan and its predicted PSNR is within :data:`FINE_PSNR_COST` of the plan with every QP free
        (each step then re-codes one attribute's chunks, not every SH chunk)."""
        limit = target.value * (1 - SIZE_TOLERANCE / 2)
        free = self._adjust(plan, limit=limit)
        if abs(size - target.value) <= FINE_BAND * target.value:
            fine = self._adjust(plan, limit=limit, frozen=("sh",))
            if fine is not None and _key(fine) not in tried and (
                    free is None or fine.predicted_psnr >= free.predicted_psnr - FINE_PSNR_COST):
                return fine
        return free

    def _encode(self, plan: Plan, target: Target, *, one_grid: bool = False) -> Bitstream:
        """One real encode of ``plan``; the header records the target (the settings are in its rate point)."""
        point = plan.rate_point if not self._tiered(plan, target, one_grid=one_grid) else \
            dataclasses.replace(plan.rate_point, tiers=self.tiers)
        encoder = Encoder(point, sh_stage=self.stage_, fit_stage=False, workers=self.workers,
                          progress=self.progress, chunk_cache=self._cache, importance=self.importance_,
                          stage_features=self._stage_features)
        stream = encoder.encode(self.cloud)
        self._last_order = encoder.order_
        stream.header["rate_control"] = {"target": {"kind": target.kind, "value": target.value},
                                         "template": self.template.name}
        return stream

    def _tiered(self, plan: Plan, target: Target, *, one_grid: bool = False) -> bool:
        """Whether ``plan`` is coded in the template's importance tiers: for a size target, when its pruning
        keeps at least :data:`TIER_MIN_GAUSSIANS` (below that each tier's own headers, positions set and
        streams cost more than its QPs save; the pruning of a target's plans stays that of its first encode).
        A PSNR target is coded in one grid: its search steps along the one-grid models, and in tiers plans
        of about the same size measured up to 0.5 dB apart (bonsai's 35 dB target ended 0.27 dB above its
        window after 8 encodes; docs/rate_control.md, "Controller version 21: importance tiers"). Tried again
        with version 22's tiers: 14 of 15 targets landed with 4-12% smaller files, bonsai's 44 dB did not
        (plans 1% apart in size measured 42.6-46.5 dB; "Controller version 22"). With ``one_grid`` never: a size
        target searched again in one grid after its tiers fell short (version 23, :meth:`_checked_tiers`)."""
        if self.tiers is None or target.kind != "bytes" or one_grid:
            return False
        share = self.prune_[plan.settings.get("prune", 0)][1]
        return share * self.cloud.num_gaussians >= TIER_MIN_GAUSSIANS

    def _next_for_quality(self, target: Target, measured: Sequence[tuple[Plan, int, float]],
                          tried: set[tuple]) -> tuple[Plan, float] | None:
        """The next plan for a PSNR target and its estimated PSNR: a regula falsi along one chain of
        single QP steps.

        The chain starts at the smallest measured file above the window (or, when every encode fell
        short, at the encode nearest the target from below) and walks :meth:`_step` by :meth:`_step`
        towards the other side. Along it the PSNR is estimated from the start's measured PSNR and the
        models' change, scaled by the slope between the start and the encode nearest the window on
        the other side (1 until one exists): the plans along one chain differ from its start by
        single steps that all lower (or raise) the quality, where the rendered PSNR follows the
        models far better than between two plans of other QP mixes (two plans of about the same size
        can differ by 0.3 dB, the window's width). The cheapest untried plan estimated to reach the
        window's middle is next (else the best estimated); None when the chain holds no untried plan.
        An encode below the target with more bytes than the start (another QP mix, 0.9 dB lower at the
        same size on bonsai) bounds nothing along the chain: without it the chain walks on (version 19;
        with it every encode moved by one step, and bonsai's 35 and 38 dB targets ran out of encodes)."""
        top, aim = target.value + PSNR_WINDOW, target.value + PSNR_WINDOW / 2
        above = [(psnr, plan, size) for plan, size, psnr in measured if psnr > top]
        below = [(psnr, plan, size) for plan, size, psnr in measured if psnr < target.value]
        cheaper = bool(above)
        if cheaper:
            start_psnr, start, start_size = min(above, key=lambda r: r[2])
            other = max(below, key=lambda r: r[0]) if below else None
            if other is not None and other[2] >= start_size:  # version 19: no bracket along the chain
                other = None  # a bigger file of another QP mix fell short: the chain walks on from the start
        else:
            start_psnr, start, _ = max(below, key=lambda r: r[0])
            other = None  # nothing measured above the window
        # the start as the corrected rate models predict it now, like the plans around it (version 10: a
        # plan's own bytes date from before its encode; bonsai's 37.5 dB first plan, predicted at 395,002
        # bytes, coded 483,227, and every single step looked dearer than it: none was tried)
        start = self._predict(start.settings)
        slope = 1.0
        other_psnr = self._predict(other[1].settings).predicted_psnr if other is not None else math.nan
        if other is not None and abs(start.predicted_psnr - other_psnr) >= PSNR_SLOPE_SPREAD:
            slope = (start_psnr - other[0]) / (start.predicted_psnr - other_psnr)
            slope = min(max(slope, PSNR_SLOPES[0]), PSNR_SLOPES[1])
        stop = other[2] if other is not None else (0.0 if cheaper else math.inf)
        moves = self._chain(start, cheaper=cheaper, stop=stop) + [  # and every single step from the start
            p for p in self._single_steps(start) if (p.predicted_bytes < start.predicted_bytes) == cheaper]
        moves = [p for p in moves if _key(p) not in tried]
        if not moves:
            return None
        estimate = {id(p): start_psnr + slope * (p.predicted_psnr - start.predicted_psnr) for p in moves}
        reaching = [p for p in moves if estimate[id(p)] >= aim]
        if reaching:
            chosen = min(reaching, key=lambda p: (p.predicted_bytes, -estimate[id(p)]))
        else:
            chosen = max(moves, key=lambda p: (estimate[id(p)], -p.predicted_bytes))
        return chosen, estimate[id(chosen)]

    def _single_steps(self, plan: Plan) -> list[Plan]:
        """Every plan one QP step of one attribute away from ``plan``: the finest moves between two
        encodes (the :meth:`_step` chain takes only the best move per byte, which can jump over the
        window when the encodes are a few hundred bytes apart, as on a 2,000-Gaussian cloud)."""
        out = []
        for name, model in self.models_.items():
            if name == "positions":
                continue
            i = int(np.searchsorted(model.choices, plan.settings[name]))
            out += [self._predict({**plan.settings, name: _setting(model.choices[j])})
                    for j in (i - 1, i + 1) if 0 <= j < model.choices.size]
        return out

    def _chain(self, plan: Plan, *, cheaper: bool, stop: float, steps: int = 64) -> list[Plan]:
        """Plans one :meth:`_step` apart from ``plan`` (fewer bytes when ``cheaper``) until the
        predicted bytes pass ``stop`` (or after ``steps`` steps)."""
        out: list[Plan] = []
        current: Plan | None = plan  # a step is predicted from the settings alone
        for _ in range(steps):
            current = self._step(current, cheaper=cheaper)
            if current is None:
                break
            out.append(current)
            if (current.predicted_bytes <= stop) if cheaper else (current.predicted_bytes >= stop):
                break
        return out

    def _adjust(self, plan: Plan, *, limit: float, frozen: Sequence[str] = ()) -> Plan | None:
        """The QPs moved step by step (position bits and the ``frozen`` attributes fixed) until the
        corrected prediction is within ``limit`` bytes, as closely as possible from below."""
        current = self._predict(plan.settings)
        while current.predicted_bytes > limit:  # too big
            step = self._step(current, cheaper=True, frozen=frozen)
            if step is None:
                return None
            current = step
        while True:  # spend what is left
            step = self._step(current, cheaper=False, limit=limit, frozen=frozen)
            if step is None:
                return current
            current = step

    def _step(self, plan: Plan, *, cheaper: bool, limit: float = math.inf, frozen: Sequence[str] = ()) -> Plan | None:
        """One QP step of one attribute (not of the ``frozen`` ones): the least error added per byte
        saved (``cheaper``), or the most error removed per byte spent; only steps whose prediction
        stays within ``limit`` bytes."""
        moves = []
        for name, model in self.models_.items():
            if name == "positions" or name in frozen:
                continue
            i = int(np.searchsorted(model.choices, plan.settings[name]))
            j = i + (1 if cheaper else -1)  # a higher QP costs fewer bytes
            if not 0 <= j < model.choices.size:
                continue
            d_bytes = self._bytes(name, _setting(model.choices[j])) - self._bytes(name, _setting(model.choices[i]))
            d_mse = model.mse[j] - model.mse[i]
            if d_bytes != 0 and (d_bytes < 0) == cheaper:
                moves.append((d_mse / abs(d_bytes), name, _setting(model.choices[j])))
        for _, name, value in sorted(moves):
            step = self._predict({**plan.settings, name: value})
            if step.predicted_bytes <= limit:
                return step
        return None

    def _probe_at(self, plan: Plan) -> bool:
        """Version 13: encode the probe at ``plan``'s QPs and add what each QP attribute's chunks cost there
        (scaled to the whole cloud; the water-filled SH features' each at its own QP) to its rate curve;
        version 14: when ``plan`` prunes in a way not yet measured, also encode the probe's Gaussians that
        pruning keeps at the same QPs, and keep each attribute's bytes per kept Gaussian against the
        unpruned probe's per Gaussian (:meth:`_prune_factor`). False, changing nothing, when the probe
        is the whole cloud (its encode would be the first trial).

        The probe codes each attribute at QPs 6, 18, 30 and 42 only; between them the curves are
        interpolated, and where a rate falls steeply that is far off. On synthetic 1M the first plan of
        a 100 bits/G target put scale at QP 34, where the curve between QPs 30 and 42 gave 0.65 of the
        bytes the whole cloud's scale then cost, and the probe itself coded there 1.03 of them; the
        file came out 2% over the target and took a second encode (docs/rate_control.md, "Controller
        version 13"). Used by size targets, whose models :meth:`encode` restores afterwards."""
        rows = self._probe_rows
        if rows is None or rows.size >= self.cloud.num_gaussians:
            return False
        names = list(self._probe_rates)
        point = self._rate_point({name: plan.settings[name] for name in names} | {"positions": 16})
        sizes = self._probe_sizes(rows, point, record_sh="sh" in names and self._waterfilled)
        scale = self.cloud.num_gaussians / rows.size
        prune = plan.settings.get("prune", 0)
        if prune and prune not in self._prune_factors:
            kept_rows = rows[self._prune_masks[prune][rows]]
            if kept_rows.size:
                pruned = self._probe_sizes(kept_rows, point, record_sh=False, cached=False)
                self._prune_factors[prune] = {
                    name: float(np.clip((pruned.get(name, 0) / kept_rows.size) / max(sizes.get(name, 0) / rows.size, 1e-9),
                                        *PRUNE_FACTOR_BOUNDS)) for name in names}
        for name in names:
            self._probe_rates[name][plan.settings[name]] = _scaled_probe_bytes(sizes, name, scale)
            model = self.models_[name]
            self.models_[name] = AttributeModel(name, model.choices, self._rate_curve(name, model.choices), model.mse)
        return True

    def _sh_measured(self, plan: Plan) -> bool:
        """Whether the probe has coded the SH at ``plan``'s base QP (version 16). Between the probe's QPs the
        features' curves over-predict their bytes by 4-11% in sum (PCHIP in log, where a feature's rate falls
        ever faster towards the QP that drops it; bonsai, the chair, snowmiku, synthetic 250k), so a plan that
        moved off the QP probed lands under a size target (synthetic 250k at 100 bits/G: the first plan's
        base QP 18 was a probe QP, the plan after it took 19 and came out 5.2% under, outside the window).

        Water-filled features count one by one (version 17): the SH is measured when the probe has coded
        every feature the plan keeps at the QP the plan gives it. For a whole base that is the base itself;
        a quarter step gives each feature the QP of one of the whole bases around it (synthetic 1M at
        100 bits/G: after probes at 16.25 and 17, the plan at 17.25 has every feature at its QP of base 17
        or of 18, a probe QP; counted by its base alone, it was probed a third time)."""
        if "sh" not in plan.settings:
            return True
        if not self._waterfilled:
            return plan.settings["sh"] in self._probe_rates.get("sh", {})
        qps = waterfill_qps(self._sh_ranges, self.stage_.feature_weights(), float(plan.settings["sh"]))
        return all(qp in self._sh_points.get(feature, {}) for feature, qp in enumerate(qps))

    def _probe_sizes(self, rows: np.ndarray, point: RatePoint, *, record_sh: bool, cached: bool = True
                     ) -> dict[str, int]:
        """The attribute sizes of the cloud's ``rows`` coded at ``point``; with ``record_sh`` each
        water-filled SH feature's bytes (scaled to the whole cloud) join its rate points. ``cached``
        only when ``rows`` are the probe's (:meth:`_probe_encoder`)."""
        stream = self._probe_encoder(point, cached=cached).encode(self.cloud.select(rows))
        if record_sh:
            self._record_sh_chunks(stream, self.cloud.num_gaussians / rows.size)
        return stream.attribute_sizes()

    def _probe_encoder(self, point: RatePoint, *, cached: bool = True) -> Encoder:
        """An encoder of the probe at ``point`` with the fitted stage; ``cached``: sharing
        :attr:`_probe_cache` (only for the probe's own rows: the cache keeps one cloud's placement).

        The DC-only bars' probes are coded at probe QPs, so only their SH chunks are new; a size target's
        plan probes take the placement, the SH features, the 16-bit positions and any chunk whose QP an
        earlier probe coded. Synthetic 250k at 100 bits/G, the same file: the plan probes 2.38 -> 1.62 s and
        the calibration, beside which the DC-only probes run, 5.86 -> 5.20 s (medians of three runs;
        docs/benchmarks.md, "The probe's chunk cache")."""
        return Encoder(point, sh_stage=self.stage_, fit_stage=False, workers=self.workers,
                       chunk_cache=self._probe_cache if cached else None)

    def _rescale_models(self, plan: Plan, decoded: GaussianCloud) -> int:
        """Rescale each QP attribute's rendered-error model by what the first encode of a PSNR target
        rendered, when it measured within :data:`RESCALE_WITHIN` of the window's middle (version 12):
        the whole cloud with only that attribute as ``decoded`` (the encode of ``plan``), against the
        model at the plan's QP. The probe's render sensitivities are estimated
        on a few places of the scene and can be off by 2-4x per attribute, differently for each
        (bonsai 0.74-1.71, snowmiku 1.7-3.7 at 40 dB); the search then walks with each attribute's own
        error. Attributes holding under :data:`RESCALE_SHARE` of the plan's predicted error are not
        rendered (a 1M cloud's render set costs about a second), and the SH features are left alone
        under a DC-only bar (their render holds its zeroing). Returns how many attributes were rescaled."""
        order = self._last_order
        count = 0
        for name in QP_ATTRIBUTES:
            model = self.models_.get(name)
            if model is None or (name == "sh" and plan.settings.get("dc_only", 0)):
                continue
            predicted = float(model.mse[np.searchsorted(model.choices, plan.settings[name])])
            if predicted < RESCALE_SHARE * plan.predicted_mse:  # even 2x off, it moves the PSNR by < 0.2 dB
                continue
            rendered = self._rendered_with_decoded(name, order, decoded)
            if predicted <= 0 or rendered <= 0:
                continue
            factor = min(max(rendered / predicted, RESCALE_BOUNDS[0]), RESCALE_BOUNDS[1])
            self.models_[name] = AttributeModel(name, model.choices, model.bytes, model.mse * factor)
            count += 1
        return count

    def measured_psnr(self, stream: Bitstream) -> float:
        """PSNR of the decoded stream against the uncompressed model on the controller's views."""
        decoded = _decoded(stream, self.workers)
        return _psnr(self._rendered_mse(decoded))


# ------------------------------------------------------------------ helpers
def fitted_stage(point: RatePoint, cloud: GaussianCloud, metric: np.ndarray | None = None) -> ShStage:
    """``point``'s SH stage fitted once on the whole ``cloud`` (its DC too where the stage codes it), as
    every encode of the rate controller uses it; ``metric``: the AC columns' error metric a SHAC-PCA
    stage is fitted in (:meth:`ShacPCA.set_metric`)."""
    stage = make_stage(point.sh_stage, **point.sh_params)
    if metric is not None:
        stage.set_metric(metric)
    if stage.uses_positions:  # pca-spatial: its regions (each encode keeps the labels of its rows)
        stage.set_positions(cloud.means)
    ac = cloud.ac_matrix()
    return stage.fit(np.concatenate([cloud.sh_dc, ac], axis=1) if stage.uses_dc else ac)


def _setting(value: Any) -> int | float:
    """A choice as a rate-point value: an int when whole (QPs, position bits), else a fractional
    water-filling base QP (a float)."""
    value = float(value)
    return int(value) if value.is_integer() else value


def _scaled_probe_bytes(sizes: dict[str, int], name: str, scale: float) -> float:
    """A probe encode's bytes of attribute ``name`` (``sizes``: its attribute sizes) scaled to the whole
    cloud by ``scale``; the SH stage's side information counts once with the SH features."""
    return scale * sizes.get(name, 0) + (sizes.get("sh_state", 0) if name == "sh" else 0)


def _model_sizes(stream: Bitstream) -> dict[str, int]:
    """Bytes per modelled attribute; the SH stage's side information counts with the SH features
    (water-filling sets how many components it stores)."""
    sizes = dict(stream.attribute_sizes())
    sizes["sh"] = sizes.get("sh", 0) + sizes.pop("sh_state", 0)
    return sizes


def _coded_chunks(keys: set) -> int:
    """How many of the chunk cache's new ``keys`` are coded chunks (not placements or SH features)."""
    return sum(1 for key in keys if key[0] != "__work__" or key[1].startswith("positions-"))


def _prune(min_opacity: float = 0.0, keep_share: float = 1.0) -> dict[str, float]:
    """One pruning candidate as rate-point fields (the other kind of pruning off)."""
    return {"min_opacity": min_opacity, "keep_share": keep_share}


def _key(plan: Plan) -> tuple:
    return tuple(sorted(plan.settings.items()))


def _decoded(stream: Bitstream, workers: int | None) -> GaussianCloud:
    """``stream`` decoded on one BLAS thread: the SH inverse transform's float32 product then has
    the same last bits whatever the machine's core count (docs/reliability.md), and so do the
    errors the controller measures and its choices."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1, user_api="blas"):
        return Decoder(workers=workers).decode(stream.to_bytes())


def _psnr(mse: float) -> float:
    return 10.0 * math.log10(1.0 / max(mse, 1e-20))


def _calibration_views(views: list[Camera]) -> list[Camera]:
    """At most :data:`CALIBRATION_VIEWS` views, evenly spread, at most :data:`CALIBRATION_WIDTH` wide."""
    return spread_views(views, CALIBRATION_VIEWS, CALIBRATION_WIDTH)


def _probe_rows(cloud: GaussianCloud) -> np.ndarray:
    """Rows of a few runs of the cloud along its Morton order (all of a small cloud), ascending."""
    n = cloud.num_gaussians
    size = min(n, PROBE_MIN)
    if size == n:
        return np.arange(n)
    values = qz.log_transform(cloud.means)
    order = set_order(qz.Quantizer.fit(values, 16).quantize(values))
    run = size // PROBE_RUNS
    starts = np.linspace(0, n - run, PROBE_RUNS).round().astype(np.int64)
    rows = np.concatenate([order[s : s + run] for s in starts])
    return np.sort(rows)


def _interpolate_log(xs: Sequence[float], ys: np.ndarray, grid: np.ndarray,
                     inner: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """Monotone piecewise-cubic (PCHIP) in log(y) (y floored at a tiny value) between the points,
    extended along the end segments (one point: a constant). A rate falls faster towards the QP at
    which the codec stops coding detail than one straight segment in log(y) between probes says.
    ``inner(xs, logs, grid)``: another curve between three points or more (``scripts/rate_curve_check.py``)."""
    inner = inner or pchip
    xs = np.asarray(xs, dtype=np.float64)
    logs = np.log(np.maximum(np.asarray(ys, dtype=np.float64), 1e-12))
    grid = np.asarray(grid, dtype=np.float64)
    if xs.size == 1:
        return np.full(grid.shape, float(np.exp(logs[0])))
    out = inner(xs, logs, np.clip(grid, xs[0], xs[-1])) if xs.size > 2 else np.interp(grid, xs, logs)
    low, high = grid < xs[0], grid > xs[-1]
    out[low] = logs[0] + (grid[low] - xs[0]) * (logs[1] - logs[0]) / (xs[1] - xs[0])
    out[high] = logs[-1] + (grid[high] - xs[-1]) * (logs[-1] - logs[-2]) / (xs[-1] - xs[-2])
    return np.exp(out)


def _attribute_mse(name: str, source: GaussianCloud, decoded: GaussianCloud, ycbcr: bool) -> float:
    """Mean squared error of one attribute in the domain it is coded in."""
    if name == "opacity":
        a, b = source.opacities, decoded.opacities
    elif name == "scale":
        a, b = source.scales, decoded.scales
    elif name == "rotation":  # q and -q are one rotation: the nearer sign (a rotation vector may decode to w < 0)
        a, b = qz.canonical_quaternions(source.quats), np.asarray(decoded.quats, np.float64)
        b = np.where(np.sum(a * b, axis=1, keepdims=True) < 0, -b, b)
    elif name == "sh_dc":
        a, b = (qz.triplets_to_ycbcr(source.sh_dc), qz.triplets_to_ycbcr(decoded.sh_dc)) if ycbcr \
            else (source.sh_dc, decoded.sh_dc)
    else:
        a, b = source.ac_matrix(), decoded.ac_matrix()
    return float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))


def _extreme_rows(cloud: GaussianCloud, sh_values: np.ndarray | None, rotation_form: str) -> np.ndarray:
    """The rows holding each coded channel's minimum and maximum (``sh_values``: the SH features as
    coded; the rotation in ``rotation_form``): with them a probe's quantiser ranges, and so its steps and
    water-filled QPs, are the whole cloud's (a quantiser spans its data's range)."""
    columns = [attribute.forward(cloud, False) for name, attribute in coded_attributes(rotation_form).items()
               if name not in ("positions", "sh_dc")]
    columns.append(cloud.sh_dc)
    columns.append(qz.triplets_to_ycbcr(cloud.sh_dc))
    if sh_values is not None:
        columns.append(sh_values)
    rows = [_first_extremes(v) for v in columns]
    return np.unique(np.concatenate(rows))


def _first_extremes(values: np.ndarray) -> np.ndarray:
    """Each column's first row holding its minimum, then each column's first row holding its maximum:
    ``np.argmin`` and ``np.argmax`` along axis 0 for finite values (a cloud's are), by a comparison with
    the column extremes, which numpy runs along the rows (a third of argmin's time on a 1M x 45 array)."""
    values = np.asarray(values)
    return np.concatenate([(values == values.min(axis=0)).argmax(axis=0),
                           (values == values.max(axis=0)).argmax(axis=0)])


def _with_decoded(cloud: GaussianCloud, name: str, rows: np.ndarray, decoded: GaussianCloud) -> GaussianCloud:
    """``cloud`` with one attribute of ``rows`` replaced by the codec's decoded values (``decoded``'s rows
    in the same order)."""
    if name == "sh":
        ac = cloud.ac_matrix().copy()
        ac[rows] = decoded.ac_matrix()
        return cloud.with_ac_matrix(ac)
    field_name = {"opacity": "opacities", "scale": "scales", "rotation": "quats", "sh_dc": "sh_dc"}[name]
    values = getattr(cloud, field_name).copy()
    values[rows] = getattr(decoded, field_name)
    return cloud.replace(**{field_name: values})


def _position_set_jobs(pool: ThreadPoolExecutor, cloud: GaussianCloud) -> dict[int, Future]:
    """The set-coded position chunk of the whole cloud at each of :data:`POSITION_BITS`, submitted to
    ``pool`` (the bytes an unpruned encode codes: the sorted Morton codes of the quantised log-positions)."""
    values = qz.log_transform(cloud.means)

    def coded(bits: int) -> bytes:
        quantizer = qz.Quantizer.fit(values, bits)
        return encode_sorted_codes(np.sort(morton_encode(quantizer.quantize(values))))

    return {bits: pool.submit(coded, bits) for bits in sorted(POSITION_BITS, reverse=True)}  # dearest first


def _quantised_positions(cloud: GaussianCloud, bits: int) -> GaussianCloud:
    values = qz.log_transform(cloud.means)
    quantizer = qz.Quantizer.fit(values, bits)
    return cloud.replace(means=qz.inverse_log_transform(quantizer.dequantize(quantizer.quantize(values))))


def _position_step_mse(cloud: GaussianCloud, bits: int) -> float:
    """Mean squared quantisation error of the log-positions at ``bits`` bits (uniform: step^2 / 12)."""
    values = qz.log_transform(cloud.means)
    steps = np.ptp(values, axis=0) / ((1 << bits) - 1)
    return float(np.mean(steps**2) / 12.0)
