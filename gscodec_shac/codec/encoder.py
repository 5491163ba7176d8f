"""The encoder: a :class:`GaussianCloud` -> a ``.gsc`` :class:`Bitstream`.

One call of :meth:`Encoder.encode` runs, in order::

    prune -> sort onto an (H, W) grid (layout.py) -> SH stage (shac/) -> per-attribute
    transform (attributes.py) -> per-channel quantiser (quantize.py) -> (C, H, W) planes
    -> grid codec (grid/) in threads -> chunks + header (container.py)

A chunk is a run of an attribute's channels that share a QP (and, for 9-16 bit lossless
data in the ``split8`` layout, one of its two 8-bit halves). The SH stage says how its
features are coded (``feature_kind``, ``rate_attribute``, ``feature_degrees``): the
encoder never tests a stage's name. The decoded cloud is in grid order.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import heapq
import itertools
import json
import threading
import time
import zlib
from concurrent.futures import Future, wait
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

import gscodec_shac
import gscodec_shac.openmp  # noqa: F401  (numba's OpenMP threads sleep between the sort's parallel regions)
from gscodec_shac.camera import Camera
from gscodec_shac.codec import quantize as qz
from gscodec_shac.codec import parameter_sets
from gscodec_shac.codec import sh_degree as degrees
from gscodec_shac.codec import tiers
from gscodec_shac.codec.allocation import waterfill_qps
from gscodec_shac.codec.attributes import (ATTRIBUTES, ROTATION_VECTOR_FEATURE, SH_FEATURES_TRANSFORM,
                                          coded_attributes)
from gscodec_shac.codec.container import Bitstream
from gscodec_shac.codec.effort import scene_analysis, with_analysis
from gscodec_shac.codec.grid.base import GridCodec, get_codec
from gscodec_shac.codec.importance import gaussian_importance, importance_views, keep_count, most_important
from gscodec_shac.codec.layout import (
    GridOrder,
    check_grid,
    kept_rows,
    placement_view,
    plan_grid,
    plan_positions_grid,
    planes,
    qp_runs,
)
from gscodec_shac.codec.positions import encode_sorted_codes, morton_encode
from gscodec_shac.codec.rate_points import AttributeSpec, RatePoint, load_rate_point
from gscodec_shac.errors import ValidationError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.limits import default_workers
from gscodec_shac.progress import optional_bar
from gscodec_shac.row_blocks import GatheredRows
from gscodec_shac.shac.base import ShStage, make_stage
from gscodec_shac.shac.view_metric import metric_applies


@dataclass
class _Job:
    """One chunk being coded: the chunk-table entry it will get and its pieces of work running in
    the scheduler (or its bytes, from the chunk cache)."""

    name: str
    meta: dict[str, Any]
    parts: list[Future] = field(default_factory=list)
    join: Callable[[list[bytes]], bytes] | None = None
    key: tuple | None = None
    data: bytes | None = None

    def result(self, scheduler: _Scheduler) -> bytes:
        """The chunk's bytes; the caller's thread runs pending pieces meanwhile."""
        if self.data is None:
            scheduler.work_until(self.parts)
            self.data = self.join([part.result() for part in self.parts])  # type: ignore[misc]
            self.parts = []
        return self.data


class _Scheduler:
    """Runs submitted work in ``workers`` threads, the costliest pending piece first.

    ``workers - 1`` threads start with the first piece; the caller's thread is the last worker
    once it waits for results (:meth:`work_until`), so at most ``workers`` pieces run at once
    (as many x265 instances in memory as before) and the SH pieces, queued after the SH stage
    is fitted, start as soon as they are queued. The encoder submits each chunk's pieces
    (:meth:`GridCodec.encode_parts`) as soon as its planes exist, so the other attributes are
    coded while the SH stage is fitted. A piece's output does not depend on when or in which
    thread it runs, so neither do the bytes.
    """

    def __init__(self, workers: int) -> None:
        self.threads = max(1, workers) - 1
        self._pending: list[tuple[int, int, Callable[[], Any], Future]] = []
        self._wake = threading.Condition()
        self._started: list[threading.Thread] = []
        self._closed = False
        self._tickets = itertools.count()

    def submit(self, cost: int, work: Callable[[], Any]) -> Future:
        """Queue ``work`` (costlier first; equal costs in submission order)."""
        future: Future = Future()
        with self._wake:
            heapq.heappush(self._pending, (-int(cost), next(self._tickets), work, future))
            if len(self._started) < self.threads:
                thread = threading.Thread(target=self._run, name="gscodec-encode", daemon=True)
                self._started.append(thread)
                thread.start()
            self._wake.notify()
        return future

    def _next(self, block: bool) -> tuple | None:
        with self._wake:
            while block and not self._pending and not self._closed:
                self._wake.wait()
            return heapq.heappop(self._pending) if self._pending else None

    @staticmethod
    def _execute(item: tuple) -> None:
        *_, work, future = item
        if future.set_running_or_notify_cancel():
            try:
                future.set_result(work())
            except BaseException as exc:  # re-raised in the caller by future.result()
                future.set_exception(exc)

    def _run(self) -> None:
        while (item := self._next(block=True)) is not None:
            self._execute(item)
            del item

    def work_until(self, futures: list[Future]) -> None:
        """Run pending pieces in this thread until ``futures`` are done (waiting once none is pending)."""
        while not all(future.done() for future in futures):
            item = self._next(block=False)
            if item is None:
                wait(futures)
                return
            self._execute(item)
            del item

    def close(self) -> None:
        """Drop the pieces not started, let the running ones finish and join the threads."""
        with self._wake:
            for *_, future in self._pending:
                future.cancel()
            self._pending = []
            self._closed = True
            self._wake.notify_all()
        for thread in self._started:
            thread.join()


class Encoder:
    """Encode clouds with one rate point and the caller's overrides of it.

    ``sh_stage``: a stage name (fitted on each cloud) or a :class:`ShStage` instance;
    with ``fit_stage=False`` an instance is used as already fitted (e.g. SHAC-LST's
    trained T). ``sh_params`` go to the stage; ``sort`` and ``seed`` override the rate
    point's sorting; ``codec_options`` are merged into every lossy attribute's codec
    options (e.g. ``{"preset": "veryfast"}``). All overrides are applied here, once,
    and the resolved rate point is :attr:`rate_point` (recorded in the header).
    ``workers`` threads code the chunks (the bytes do not depend on it). ``chunk_cache``
    (a dict shared by several encoders of the same cloud, e.g. the rate controller's trials)
    keeps coded chunks by their planes and settings, so a chunk whose input did not change
    is not coded again. ``views`` (cameras) or ``importance`` (one value per input Gaussian) serve
    importance pruning (rate point ``prune.keep_share``, :mod:`.importance`): without either it is
    measured on orbit views. ``stage_features``: a fitted ``sh_stage``'s features of every row of the
    cloud :meth:`encode` is given (what ``sh_stage.transform`` returns for them, e.g. the rate
    controller's, which it computed for its probe): they are gathered instead of computed again.
    ``dc_only_rows``: a caller's choice of the DC-only Gaussians, one bool per input row (the importance
    tiers choose them over all their rows at once), used instead of the rate point's bar. After
    :meth:`encode`, ``order_`` holds the input row of each decoded Gaussian and
    ``timings_`` the seconds per step.
    """

    def __init__(
        self,
        rate_point: str | Path | RatePoint,
        sh_stage: str | ShStage | None = None,
        sort: str | None = None,
        *,
        sh_params: Mapping[str, Any] | None = None,
        seed: int | None = None,
        codec_options: Mapping[str, Any] | None = None,
        fit_stage: bool = True,
        progress: bool = False,
        workers: int | None = None,
        chunk_cache: dict | None = None,
        views: Sequence[Camera] | None = None,
        importance: np.ndarray | None = None,
        sh_metric: np.ndarray | None = None,
        stage_features: np.ndarray | None = None,
        dc_only_rows: np.ndarray | None = None,
    ) -> None:
        self._stage_instance = sh_stage if isinstance(sh_stage, ShStage) else None
        name = self._stage_instance.name if self._stage_instance is not None else sh_stage
        self.rate_point = load_rate_point(rate_point).with_overrides(
            sh_stage=name, sh_params=sh_params, sort_method=sort, seed=seed, codec_options=codec_options
        )
        self.fit_stage = fit_stage
        self.progress = progress
        self.workers = workers or default_workers()
        self.order_: np.ndarray | None = None
        self.timings_: dict[str, float] = {}
        self._codecs: dict[tuple, tuple[GridCodec, int]] = {}
        self._jobs: list[_Job] = []
        self._chunk_cache = chunk_cache
        self._work_key: str | None = None
        self.views = list(views) if views else None
        self.importance = importance
        #: the AC columns' error metric a fitted SHAC-PCA stage is fitted in (:mod:`gscodec_shac.shac.view_metric`)
        self.sh_metric = sh_metric
        self.stage_features = stage_features
        self.dc_only_rows = dc_only_rows
        self._measured: tuple[GaussianCloud, np.ndarray] | None = None
        self._dc_only: np.ndarray | None = None
        self._dc_only_shape: tuple[int, int] = (0, 0)
        self._analysis = "preset"  # x265's analysis for lossy hevc attributes without their own (set per encode)
        #: what tells this encoder's cached placement and features apart from another's of the same settings
        #: (an importance tier's encoder: its tier, :meth:`_encode_tiers`)
        self._tag = ""

    # ---------------------------------------------------------------- main
    def grid_order(self, cloud: GaussianCloud) -> GridOrder:
        """The grid placement :meth:`encode` computes for ``cloud`` (after pruning), to reuse it."""
        return self._plan(placement_view(cloud, self.kept_rows(cloud)))

    def _plan(self, work: GaussianCloud) -> GridOrder:
        rp = self.rate_point
        if rp.positions_as_set:
            return plan_positions_grid(work, rp.attributes["positions"].bits, rp.sort.multiple)
        return plan_grid(work, rp.sort, self.progress)

    def encode(self, cloud: GaussianCloud, grid: GridOrder | None = None, *, release_input: bool = False) -> Bitstream:
        """Compress ``cloud`` into a :class:`Bitstream` (deterministic for equal input).

        ``grid``: a placement from :meth:`grid_order` for the same cloud and settings,
        to sort once for many encodes (the bytes are the same). ``release_input``: the
        caller gives ``cloud`` up; it is emptied (:meth:`GaussianCloud.take`) and its arrays
        are freed once the SH features exist, so the coding holds no copy of the model.
        """
        rp = self.rate_point
        n_input, sh_degree = cloud.num_gaussians, cloud.sh_degree
        for name, given in (("stage_features", self.stage_features), ("dc_only_rows", self.dc_only_rows)):
            if given is not None and len(given) != n_input:
                raise ValueError(f"{name} has {len(given)} rows for a cloud of {n_input:,} Gaussians")
        if rp.tiers is not None:
            return self._encode_tiers(cloud)
        if release_input:
            cloud = cloud.take()
        self._codecs, self._jobs, self.timings_ = {}, [], {}
        self._analysis = scene_analysis(n_input)
        # With a shared cache (the rate controller's trials), the placement, the SH features and
        # the position set of equal pruning and sorting settings are computed once.
        self._work_key = _work_key(rp) + self._tag if self._chunk_cache is not None and grid is None else None
        with self._timed("sort"):
            kept, grid, cells, grid_cloud = self._cached("grid", lambda: self._placement(cloud, grid))
            self.order_ = kept[grid.order[cells]]
        # the AC matrix is read in grid order, a block of rows at a time; with release_input the
        # model's other arrays are freed now (the grid-order cloud has its own), the AC matrix after the stage
        ac = GatheredRows(cloud.ac_matrix(), self.order_) if sh_degree else None
        dc_only_weight = self._dc_only_weight(cloud, self.order_) if sh_degree else None
        cloud = None
        if release_input:
            self._measured = None  # the importance measurement holds the model too
        stage = self._make_stage(sh_degree)
        stream = Bitstream()
        n = grid_cloud.num_gaussians
        padding = grid.padding
        if padding == "mask":  # empty cells inside the grid: store which cells are occupied
            packed, raw_size = grid.mask_chunk()
            stream.add_chunk("grid_mask", packed, attribute="grid", encoding="zlib", raw_size=raw_size)
        cell_rows = grid.cell_rows(cells)
        ycbcr = rp.color == "ycbcr"
        attributes: dict[str, Any] = {}
        features = None
        n_features = 0
        self._scheduler = _Scheduler(self.workers)
        try:
            # The other attributes' chunks are queued, and start coding, before the SH stage is fitted.
            with self._timed("quantize"):
                if rp.rotation_form == "vector":
                    stream.require(ROTATION_VECTOR_FEATURE)
                for name, attr in coded_attributes(rp.rotation_form).items():
                    if name == "sh_dc" and stage is not None and stage.uses_dc:
                        continue  # the DC travels inside the stage's features
                    values, rows = attr.column(grid_cloud), attr.rows(ycbcr)
                    if name == "positions" and rp.positions_as_set:
                        attributes[name] = self._code_position_set(values, rows, rp.attributes[name], stream)
                        continue
                    attributes[name] = self._code_values(name, attr.transform, values, rp.attributes[name],
                                                         cell_rows, grid.shape, attr.groups, rows=rows)
                values = None
            # one BLAS thread: the scheduler is coding the other attributes meanwhile (a second BLAS
            # thread only competed with x265 and spun: 0.6 s of CPU at 1M Gaussians, the same bytes)
            from threadpoolctl import threadpool_limits  # only an encode needs it

            with self._timed("sh_stage"), threadpool_limits(1, user_api="blas"):
                features = self._sh_features(stage, grid_cloud, ac, dc_only_weight)
            ac = None
            if features is not None and features.shape[1]:
                attributes["sh"], n_features = self._code_sh(stage, features, *self._sh_grid(grid, cell_rows))
            features = grid_cloud = None  # the coders hold the planes only
            with self._timed("code"):
                for job in optional_bar(self._jobs, self.progress, desc="encode", unit="chunk", leave=False):  # in queue order
                    data = job.result(self._scheduler)
                    if job.key is not None:
                        self._chunk_cache[job.key] = data  # type: ignore[index]
                    stream.add_chunk(job.name, data, **job.meta)
        finally:
            self._scheduler.close()
            self._jobs = []

        sh_header = None
        if stage is not None:
            raw = stage.state().to_bytes()
            stream.add_chunk("sh_state", zlib.compress(raw, 9), attribute="sh_state", encoding="zlib", raw_size=len(raw))
            for feature in stage.stream_features():
                stream.require(feature)
            sh_header = {
                "stage": stage.name,
                "features": int(n_features),
                "lossless": stage.feature_kind == "labels",
                "uses_dc": bool(stage.uses_dc),
                "ycbcr": bool(ycbcr and stage.ycbcr_applies(n_features)),
            }
            if self._dc_only is not None and n_features:  # per-Gaussian SH degree (sh_degree.py)
                packed, raw_size = degrees.flags_chunk(self._dc_only)
                stream.add_chunk(degrees.CHUNK, packed, attribute=degrees.CHUNK, encoding="zlib",
                                 raw_size=raw_size)
                stream.require(degrees.FEATURE)
                sh_header["dc_only"] = int(self._dc_only.sum())
                sh_header["grid"] = {"height": self._dc_only_shape[0], "width": self._dc_only_shape[1],
                                     "padding": degrees.sh_padding(padding)}
        # each HEVC stream's parameter sets once per file (codec/parameter_sets.py), in streams that need format 2
        # anyway (a stream without features stays a 1.0 one, byte for byte); the chunk cache keeps whole chunks
        if stream.features:
            parameter_sets.share(stream, {index for (name, _), (_, index) in self._codecs.items()
                                          if name == parameter_sets.CODEC})
        stream.header = {
            "producer": f"gscodec-shac {gscodec_shac.__version__}",
            "num_gaussians": n,
            "input_gaussians": n_input,
            "sh_degree": sh_degree,
            "grid": {"height": grid.shape[0], "width": grid.shape[1], "padding": padding, "policy": grid.policy,
                     "dropped": grid.dropped, "sort": None if rp.positions_as_set else rp.sort.to_json()},
            "prune": {**rp.prune_json(), "pruned": int(n_input - kept.size)},
            "color": rp.color,
            "sh": sh_header,
            "attributes": attributes,
            "codecs": [codec.describe() for codec, _ in sorted(self._codecs.values(), key=lambda item: item[1])],
            "rate_point": rp.to_json(),
        }
        return stream

    def _encode_tiers(self, cloud: GaussianCloud) -> Bitstream:
        """A tiered stream (:mod:`.tiers`): the kept Gaussians split by importance, each tier coded by
        an encoder of its own at the tier's rate point, one SH stage fitted on all of them."""
        rp = self.rate_point
        assert rp.tiers is not None
        self.timings_ = {}
        with self._timed("prune"):
            kept = self.kept_rows(cloud)
            importance = self._importance(cloud)
        stage, features = self._tier_stage(cloud, kept)
        split = tiers.tier_rows(importance, kept, rp.tiers.shares)
        if rp.tiers.spread == "importance":  # the offsets this scene's importance asks for, recorded as coded
            rp = dataclasses.replace(rp, tiers=rp.tiers.with_spread(tiers.importance_spread(importance, split)))
        dc_only = self._tier_dc_only(cloud, kept, split)
        streams, orders, indices = [], [], []
        for index, rows in enumerate(split):
            if not rows.size:  # a few Gaussians left this tier empty
                continue
            tier_stage = None
            if stage is not None:  # the per-row side information (pca-spatial's regions) of the tier's rows
                tier_stage = copy.deepcopy(stage)
                tier_stage.restrict_rows(rows)
            encoder = Encoder(rp.tier_point(index), sh_stage=tier_stage, fit_stage=False, progress=self.progress,
                              workers=self.workers, chunk_cache=self._chunk_cache, importance=importance[rows],
                              stage_features=None if features is None else features[rows],
                              dc_only_rows=None if dc_only is None else dc_only[rows])
            encoder._tag = json.dumps([self._tag, rp.prune_json(), rp.tiers.to_json(), index])
            streams.append(encoder.encode(cloud.select(rows)))
            orders.append(rows[encoder.order_])
            indices.append(index)
            for step, seconds in encoder.timings_.items():
                self.timings_[step] = self.timings_.get(step, 0.0) + seconds
        self.order_ = np.concatenate(orders)
        return tiers.join(streams, {
            "producer": f"gscodec-shac {gscodec_shac.__version__}",
            "num_gaussians": int(self.order_.size),
            "input_gaussians": cloud.num_gaussians,
            "sh_degree": cloud.sh_degree,
            "prune": {**rp.prune_json(), "pruned": int(cloud.num_gaussians - kept.size)},
            "rate_point": rp.to_json(),
        }, indices)

    def _tier_dc_only(self, cloud: GaussianCloud, kept: np.ndarray, split: list[np.ndarray]) -> np.ndarray | None:
        """The DC-only Gaussians of a tiered encode, one bool per input row: chosen over all ``kept`` rows
        by the rate point's bar (:mod:`.sh_degree`), as one grid would choose them, so that a bar of
        the whole scene's energy is not spent again in each tier (tier by tier, bonsai's important half
        dropped 3x the energy one grid drops there: -1.5 dB). A tier whose rows would all be DC-only
        keeps the SH of its row of most energy. None when the rate point has no DC-only Gaussians."""
        rp = self.rate_point
        if cloud.sh_degree == 0:
            return None
        weight = self._dc_only_weight(cloud, kept)  # the importance or opacity of the kept rows
        if weight is None:
            return None
        energy = np.zeros(cloud.num_gaussians, dtype=np.float64)
        energy[kept] = degrees.ac_energy(GatheredRows(cloud.ac_matrix(), kept), weight)
        flags = np.zeros(cloud.num_gaussians, dtype=bool)
        flags[kept] = degrees.dc_only_flags(energy[kept], rp.dc_only_share, rp.dc_only_energy)
        for rows in split:
            if rows.size and flags[rows].all():
                flags[rows[np.argmax(energy[rows])]] = False
        return flags

    def _tier_stage(self, cloud: GaussianCloud, kept: np.ndarray) -> tuple[ShStage | None, np.ndarray | None]:
        """The SH stage the tiers share and its features of every input row (None where the caller's
        stage has none: the tiers then transform their own rows), fitted here on the ``kept`` rows
        when the encoder fits its stage."""
        if cloud.sh_degree == 0:
            return None, None
        if not (self.fit_stage or self._stage_instance is None):
            return self._stage_instance, self.stage_features
        stage = self._make_stage(cloud.sh_degree)
        assert stage is not None
        with self._timed("sh_stage"):  # as one grid's encode fits it, on the kept rows
            fitted = self._stage_features(stage, placement_view(cloud, kept), GatheredRows(cloud.ac_matrix(), kept), "")
        features = np.zeros((cloud.num_gaussians, fitted.shape[1]), dtype=fitted.dtype)
        features[kept] = fitted
        # per-row side information of every input row, as the caller's fitted stage has it (pruned rows: any)
        position = np.zeros(cloud.num_gaussians, dtype=np.int64)
        position[kept] = np.arange(kept.size)
        stage.restrict_rows(position)
        return stage, features

    def _placement(self, cloud: GaussianCloud, grid: GridOrder | None) -> tuple:
        """Prune and place on the grid: (kept rows, grid order, occupied cells, the cloud in grid order
        without its SH AC coefficients: :func:`placement_view`)."""
        with self._timed("prune"):
            kept = self.kept_rows(cloud)
            work = placement_view(cloud, kept)
        grid = self._plan(work) if grid is None else check_grid(grid, work)
        cells = grid.cells()
        return kept, grid, cells, work.select(grid.order[cells])

    def kept_rows(self, cloud: GaussianCloud) -> np.ndarray:
        """Rows that survive the opacity threshold and then, with ``keep_share < 1``, the most
        important of them (``keep_share`` of the input; :mod:`.importance`)."""
        kept = kept_rows(cloud, self.rate_point.min_opacity)
        share = self.rate_point.keep_share
        if share >= 1.0:
            return kept
        return most_important(self._importance(cloud), kept, keep_count(cloud.num_gaussians, share))

    def _importance(self, cloud: GaussianCloud) -> np.ndarray:
        """The caller's render-based importance of each input Gaussian, or its measurement (once per cloud)."""
        importance = self.importance
        if importance is None:  # measured once per cloud (grid_order and encode both ask)
            if self._measured is None or self._measured[0] is not cloud:
                self._measured = (cloud, gaussian_importance(cloud, importance_views(cloud, self.views),
                                                             progress=self.progress))
            importance = self._measured[1]
        elif np.shape(importance) != (cloud.num_gaussians,):
            raise ValidationError(f"importance has shape {np.shape(importance)}, expected one value per Gaussian "
                                  f"({cloud.num_gaussians:,})")
        return np.asarray(importance, dtype=np.float64)

    def _dc_only_weight(self, cloud: GaussianCloud, rows: np.ndarray) -> np.ndarray | None:
        """What the AC energy of the input ``rows`` is weighted by when choosing the DC-only ones
        (rate point ``sh.dc_only_weight``); None when none is DC-only."""
        rp = self.rate_point
        if not rp.dc_only:
            return None
        if rp.dc_only_weight == "render":
            return self._importance(cloud)[rows]
        return cloud.activated_opacities()[rows]

    def _work_cache_key(self, what: str) -> tuple | None:
        """The shared cache's key of ``what`` under this encode's pruning and sorting settings (None: no cache)."""
        return None if self._work_key is None else ("__work__", what, self._work_key)

    def _cached(self, what: str, compute: Any) -> Any:
        """``compute()``, kept in the shared cache under this encode's pruning and sorting settings."""
        key = self._work_cache_key(what)
        if key is None:
            return compute()
        if key not in self._chunk_cache:  # type: ignore[operator]
            self._chunk_cache[key] = compute()  # type: ignore[index]
        return self._chunk_cache[key]  # type: ignore[index]

    @contextmanager
    def _timed(self, step: str) -> Iterator[None]:
        tic = time.perf_counter()
        yield
        self.timings_[step] = time.perf_counter() - tic

    # -------------------------------------------------------------- steps
    def _make_stage(self, sh_degree: int) -> ShStage | None:
        """The SH stage to fit (None for SH degree 0); a caller's stage is copied, as water-filling
        may drop features of the copy."""
        if sh_degree == 0:
            return None
        stage = copy.deepcopy(self._stage_instance) or make_stage(self.rate_point.sh_stage, **self.rate_point.sh_params)
        stage.progress = self.progress
        if self.sh_metric is not None and (self.fit_stage or self._stage_instance is None):
            if not metric_applies(self.rate_point.sh_stage, self.rate_point.sh_params):
                raise ValidationError(f"SH stage {self.rate_point.sh_stage!r} cannot weigh the SH by the cameras' "
                                      "views: only SHAC-PCA over R, G and B together can (pca, joint_rgb)")
            stage.set_metric(self.sh_metric)
        return stage

    def _sh_features(self, stage: ShStage | None, cloud: GaussianCloud, ac: GatheredRows | None,
                     dc_only_weight: np.ndarray | None = None) -> np.ndarray | None:
        """The stage's features of the AC matrix ``ac`` in grid order (``cloud``: the grid-order cloud,
        for the DC and positions). With ``dc_only_weight`` the DC-only Gaussians are chosen
        (:attr:`_dc_only`) and the stage sees, and gives the features of, the others only (:mod:`.sh_degree`)."""
        self._dc_only = None
        if stage is None or ac is None:
            return None
        if dc_only_weight is None:
            return self._stage_features(stage, cloud, ac, "")
        if stage.uses_dc:
            raise ValidationError(f"SH stage {stage.name!r} codes the DC inside its features: it cannot leave "
                                  f"Gaussians DC-only (sh.dc_only_share, sh.dc_only_energy)")
        rp = self.rate_point
        if self.dc_only_rows is not None:  # the caller's choice (the importance tiers': :meth:`_encode_tiers`)
            flags = np.asarray(self.dc_only_rows, dtype=bool)[self.order_]
        else:
            flags = degrees.dc_only_flags(degrees.ac_energy(ac, dc_only_weight), rp.dc_only_share, rp.dc_only_energy)
        coded = np.flatnonzero(~flags)
        features = self._stage_features(stage, cloud.select(coded), GatheredRows(ac.base, ac.index[coded]),
                                        f"-dc{rp.dc_only_share}-{rp.dc_only_energy}-{rp.dc_only_weight}")
        self._dc_only = flags
        return features

    def _sh_grid(self, grid: GridOrder, cell_rows: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
        """(cell rows, shape) of the SH planes: the main grid's, or with DC-only Gaussians the grid of
        the coded ones (:func:`.sh_degree.sh_grid_order`)."""
        if self._dc_only is None:
            return cell_rows, grid.shape
        sh_grid = degrees.sh_grid_order(int(np.count_nonzero(~self._dc_only)), grid.padding,
                                        self.rate_point.sort.multiple)
        self._dc_only_shape = sh_grid.shape
        return sh_grid.cell_rows(sh_grid.cells()), sh_grid.shape

    def _stage_features(self, stage: ShStage, cloud: GaussianCloud, ac: GatheredRows, key: str) -> np.ndarray:
        """The stage fitted on (or, fitted already, applied to) the rows ``ac`` of ``cloud``."""
        fit = self.fit_stage or self._stage_instance is None
        if not fit and self.stage_features is not None:  # the caller's features of the input rows, gathered
            stage.restrict_rows(ac.index)  # and the stage's per-row side information (pca-spatial's regions)
            return np.asarray(self.stage_features[ac.index])
        if not fit:  # other rows of the fitted scene (the controller's probe): per-row side information anew
            stage.locate_rows(cloud.means)
        if not stage.reads_row_blocks or stage.uses_dc:
            ac = np.asarray(ac)
        if stage.uses_dc:
            ac = np.concatenate([cloud.sh_dc, ac], axis=1)
        if fit and stage.uses_positions:
            stage.set_positions(cloud.means)
        if fit:
            return np.asarray(stage.fit_transform(ac))
        # a fitted caller's stage transforms the same cloud to the same features: once per placement
        return self._cached(f"features-{id(self._stage_instance)}{key}", lambda: np.asarray(stage.transform(ac)))

    def _code_position_set(self, values: np.ndarray, rows: qz.RowTransform | None, spec: AttributeSpec,
                           stream: Bitstream) -> dict:
        """Positions (``rows(values)``) as a Morton-sorted set (:mod:`.positions`); the grid order is their Morton order."""
        quantizer = qz.Quantizer.fit(values, spec.bits, rows)
        stream.require("positions_set")
        job = _Job("positions", {"attribute": "positions", "encoding": "morton_set", "bits": spec.bits})
        job.key = None if self._work_key is None else position_set_cache_key(self.rate_point, spec.bits) + (self._tag,)
        if job.key is not None and job.key in self._chunk_cache:  # type: ignore[operator]
            job.data = self._chunk_cache[job.key]  # type: ignore[index]
        else:
            codes = morton_encode(quantizer.quantize(values, rows))
            job.parts, job.join = [self._scheduler.submit(3 * len(codes), lambda: encode_sorted_codes(codes))], _first
        self._jobs.append(job)
        return {"chunks": ["positions"], "channels": 3, "coding": "set", "transform": ATTRIBUTES["positions"].transform,
                "quantizer": quantizer.to_json()}

    def _code_sh(
        self, stage: ShStage, features: np.ndarray, cell_rows: np.ndarray, shape: tuple[int, int]
    ) -> tuple[dict, int]:
        """Queue the SH features' chunks; returns the header entry and the number of features coded
        (water-filling may drop some)."""
        spec = self.rate_point.attributes[stage.rate_attribute]
        if stage.feature_kind == "labels":
            bits = int(stage.feature_bits)  # type: ignore[attr-defined]
            labels = np.rint(features).astype(np.int64)
            if labels.size and (labels.min() < 0 or labels.max() >= 1 << bits):
                raise ValidationError(f"SH stage {stage.name!r} gave labels outside 0..2^{bits}-1")
            entry = self._code_integers("sh", SH_FEATURES_TRANSFORM, labels.astype(np.uint16), bits, spec, cell_rows, shape)
            return entry, features.shape[1]
        rows = None  # the YCbCr triplets are computed a block of rows at a time (no float64 copy of all features)
        if self.rate_point.color == "ycbcr" and stage.ycbcr_applies(features.shape[1]):
            rows = qz.triplets_to_ycbcr
        if spec.allocation == "waterfill":
            if stage.feature_kind != "components":
                raise ValidationError(f"waterfill allocation needs a components stage such as pca, not {stage.name!r}")
            lo, hi = qz.column_extrema(features, rows)
            qps = waterfill_qps(hi - lo, stage.feature_weights(), float(spec.qp))
            if len(qps) < features.shape[1]:
                stage.keep_features(len(qps))
                features = features[:, : len(qps)]
        else:
            qps = [spec.qp_for_degree(d) for d in stage.feature_degrees(features.shape[1])]
        entry = self._code_values("sh", SH_FEATURES_TRANSFORM, features, spec, cell_rows, shape, None, qps, rows)
        return entry, features.shape[1]

    def _code_values(
        self, name: str, transform: str, values: np.ndarray, spec: AttributeSpec,
        cell_rows: np.ndarray, shape: tuple[int, int], groups: tuple | None, qps: list | None = None,
        rows: qz.RowTransform | None = None,
    ) -> dict:
        """Quantise (N, C) floats (``rows(values)``, a block of rows at a time) and queue their chunks;
        returns the attribute's header entry."""
        quantizer = qz.Quantizer.fit(values, spec.bits, rows)
        q = quantizer.quantize(values, rows)
        if spec.lossless:
            entry = self._code_integers(name, transform, q, spec.bits, spec, cell_rows, shape)
        else:
            channels = q.shape[1]
            qps = qps or _channel_qps(name, spec, channels)
            runs = groups or qp_runs(qps)
            entry = {"chunks": []}
            for index, (start, stop) in enumerate(runs):
                chunk = f"{name}_{index}" if len(runs) > 1 else name
                self._queue(chunk, name, planes(q[:, start:stop], cell_rows, shape), spec.bits, qps[start], spec,
                            (start, stop), "all")
                entry["chunks"].append(chunk)
        entry.update(transform=transform, channels=int(q.shape[1]), quantizer=quantizer.to_json())
        return entry

    def _code_integers(
        self, name: str, transform: str, q: np.ndarray, bits: int, spec: AttributeSpec,
        cell_rows: np.ndarray, shape: tuple[int, int],
    ) -> dict:
        """Code (N, C) integers of ``bits`` bits losslessly (split into two 8-bit halves or not)."""
        channels = (0, q.shape[1])
        if spec.layout == "split8" and bits > 8:
            high, low = qz.split_planes(q, bits)
            self._queue(f"{name}_hi", name, planes(high, cell_rows, shape), bits - 8, None, spec, channels, "hi")
            self._queue(f"{name}_lo", name, planes(low, cell_rows, shape), 8, None, spec, channels, "lo")
            chunks = [f"{name}_hi", f"{name}_lo"]
        else:
            self._queue(name, name, planes(q, cell_rows, shape), bits, None, spec, channels, "all")
            chunks = [name]
        return {"chunks": chunks, "channels": int(q.shape[1]), "integer_bits": bits, "transform": transform}

    def _queue(
        self, chunk: str, attribute: str, planes: np.ndarray, bits: int,
        qp: int | None, spec: AttributeSpec, channels: tuple[int, int], part: str,
    ) -> None:
        if self._analysis != "preset":  # a small scene's full analysis (:mod:`.effort`); the preset's adds nothing
            spec = with_analysis(spec, self._analysis)
        codec, index = self._codec(spec.codec, spec.options)
        meta = {"attribute": attribute, "channels": list(channels), "part": part,
                "shape": list(planes.shape), "bits": bits, "qp": qp, "codec": index}
        job = _Job(chunk, meta)
        if self._chunk_cache is not None:
            job.key = _cache_key(chunk, codec, planes, bits, qp)
            job.data = self._chunk_cache.get(job.key)
        if job.data is None:
            parts, job.join = codec.encode_parts(planes, bits, qp)
            job.parts = [self._scheduler.submit(cost, work) for cost, work in parts]
        self._jobs.append(job)

    def _codec(self, name: str, options: dict) -> tuple[GridCodec, int]:
        """A codec instance and its index in the header's codec table."""
        key = (name, json.dumps(options, sort_keys=True))
        if key not in self._codecs:
            self._codecs[key] = (get_codec(name, **options), len(self._codecs))
        return self._codecs[key]


def _work_key(rp: RatePoint) -> str:
    """What decides the grid placement (hence the cloud in grid order): pruning and sorting settings."""
    positions = rp.attributes["positions"]
    return json.dumps([rp.prune_json(), rp.positions_as_set, positions.bits if rp.positions_as_set else None,
                       rp.sort.to_json(), rp.sort.multiple], sort_keys=True, default=str)


def position_set_cache_key(rp: RatePoint, bits: int) -> tuple:
    """The shared cache's key of the set-coded position chunk at ``bits`` under ``rp``'s pruning and
    sorting (the rate controller stores the chunks it coded to model the position bits under it)."""
    return ("__work__", f"positions-{bits}", _work_key(rp))


def _cache_key(name: str, codec: GridCodec, planes: np.ndarray, bits: int, qp: int | None) -> tuple:
    """What decides a chunk's bytes: its name, codec and settings, and its planes."""
    digest = hashlib.sha1(np.ascontiguousarray(planes).view(np.uint8)).hexdigest()
    return (name, json.dumps(codec.describe(), sort_keys=True), bits, qp, planes.shape, digest)


def _first(outputs: list[bytes]) -> bytes:
    return outputs[0]


def _channel_qps(name: str, spec: AttributeSpec, channels: int) -> list[int]:
    """One QP per channel of a lossy attribute: the spec's QP, or for ``rotation`` with two QPs
    (rate point ``rotation: [xyz, w]``) the second one on channel 0 (w) and the first on x, y, z."""
    if name == "rotation" and isinstance(spec.qp, tuple):
        return [spec.qp[-1]] + [spec.qp[0]] * (channels - 1)
    return [spec.qp_for_degree(1)] * channels
