"""Spatially varying SHAC-PCA bases (stage ``"pca-spatial"``; beyond the paper, its Sec. IX).

The paper uses one global basis P for the whole scene and names "spatially varying
transformations" as future work for scenes with strong spatial appearance variation.
This stage splits the Gaussians into ``spatial_clusters`` regions by k-means on their
positions (each axis standardised, k-means++ seeded, fixed iterations) and fits one
SHAC-PCA (eq. 23-29, :class:`~gscodec_shac.shac.pca.ShacPCA`) per region:

* ``n_components`` M given: every region keeps M components;
* else ``energy_retention`` (0.99 by default): every region keeps the fewest components
  reaching it (eq. 26-27), so a simple region may keep fewer than a busy one.

The features are the regions' scores in one set of ``max M_c`` channels (a region with a
lower rank leaves its trailing channels at 0), coded like SHAC-PCA's. The state holds
every region's P, mu, sigma (``side_dtype``) and the region label of every Gaussian, in the
order the features are coded (the codec's grid order); the codec deflates it, so the
labels are counted in the rate. The decoder needs no positions.

``unit_weights`` (the default; format 2.5, feature ``sh_spatial_unit_weights``; states without it
decode as before): each region's component j is scaled by the square root of its weight (eq. 29's
``b_j``), so a unit error on any channel costs one unit of rendered SH error in every region.
Without it, in the paper's metric, channel j of two regions carries scores of different weights
under one quantiser and one water-filled QP, which :meth:`feature_weights` can only average: at
the rate controller's 100 bits/G plan on the chair, k = 4 coded 3.9-4.5 dB below the global basis
at its QPs for 17-19% fewer bytes, its curve out of the global one's reach (with the gains: 0.2-0.8
dB below for 3-4% more bytes; docs/ablations.md, "Spatially varying bases"). In a metric (:meth:`set_metric`, e.g. the cameras'
view metric) SHAC-PCA's components already cost one unit each and the gains are 1. The gains
travel in the state (float32, M_c per region).

Positions come from the encoder (``uses_positions``: :meth:`set_positions` before
:meth:`fit`). :meth:`transform` and :meth:`inverse_transform` work on the N fitted rows in
their order; any other row count (the decoder's one-row probe of a state) takes the first
region's basis. Measured on bonsai: docs/ablations.md ("Spatially varying bases").
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.shac.base import ShStage, StageParam, StageState, check_ac_matrix, register_stage
from gscodec_shac.shac.pca import DEFAULT_ENERGY_RETENTION, SIDE_DTYPES, ShacPCA
from gscodec_shac.shac.vq import _kmeans, _nearest
from gscodec_shac.validate import Where

MAX_REGIONS = 255
#: Fewest rows a region keeps its own basis for (smaller k-means regions are merged).
MIN_REGION_ROWS = 64


def cluster_positions(positions: np.ndarray, k: int, seed: int = 0, n_iter: int = 20) -> np.ndarray:
    """Region label (0..k'-1, consecutive) of each position by k-means; k' <= k, as regions of fewer
    than ``MIN_REGION_ROWS`` rows are merged into the nearest larger one. Independent of the row order."""
    return fit_regions(positions, k, seed, n_iter)[0]


def fit_regions(positions: np.ndarray, k: int, seed: int = 0,
                n_iter: int = 20) -> tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """:func:`cluster_positions`' labels and the function that gives any positions the label of their
    nearest region centre (for the fitted positions, their labels)."""
    x = np.asarray(positions, dtype=np.float64)
    if k <= 1 or x.shape[0] <= 1:
        return np.zeros(x.shape[0], dtype=np.int64), _one_region
    mean, std = x.mean(axis=0), np.maximum(x.std(axis=0), 1e-12)

    def standardised(p: np.ndarray) -> np.ndarray:
        return ((np.asarray(p, dtype=np.float64) - mean) / std).astype(np.float32)

    x = standardised(x)
    canonical = x[np.lexsort(x.T[::-1])]  # the regions do not depend on the row order
    centres = _kmeans(canonical, min(k, x.shape[0]), np.random.default_rng(seed), n_iter, "kmeans++")
    large = np.bincount(_nearest(x, centres), minlength=centres.shape[0]) >= MIN_REGION_ROWS
    if not large.any():
        return np.zeros(x.shape[0], dtype=np.int64), _one_region
    # a region too small for a PCA joins the nearest large one: the large centres, in their order, are the regions
    kept = centres[large]

    def locate(p: np.ndarray) -> np.ndarray:
        return _nearest(standardised(p), kept).astype(np.int64)

    return _nearest(x, kept).astype(np.int64), locate  # x: the fitted positions, standardised already


def _one_region(positions: np.ndarray) -> np.ndarray:
    return np.zeros(len(positions), dtype=np.int64)


@register_stage
class SpatialPCA(ShStage):
    """SH stage "pca-spatial": one SHAC-PCA basis per spatial k-means region (see module docstring).

    Fitted attributes: ``labels_`` (N,) region of each row, ``pcas_`` one fitted
    :class:`ShacPCA` per region, ``n_components_`` the coded channels (max M_c).
    """

    name = "pca-spatial"
    summary = "SHAC-PCA with one basis per spatial k-means region (paper Sec. IX, future work)"
    feature_kind = "components"
    rate_attribute = "sh_features"
    uses_positions = True
    params = (
        StageParam("spatial_clusters", "int", 16, "spatial regions, each with its own PCA basis",
                   flag="spatial_clusters", lo=1, hi=MAX_REGIONS),
        StageParam("energy_retention", "float", DEFAULT_ENERGY_RETENTION,
                   "energy retention ER(M) (eq. 26) each region's components reach", flag="er", lo=0.0, hi=1.0,
                   open_lo=True),
        StageParam("n_components", "int", None, "components M of every region (instead of an ER)",
                   flag="components", lo=1, hi=128),
        StageParam("seed", "int", 0, "seed of the spatial k-means (encode's --seed sets it too)", lo=0, hi=2**32 - 1),
        StageParam("unit_weights", "bool", True, "scale every region's components to one unit of rendered error "
                   "(false: the scores as fitted, as before format 2.5)"),
        StageParam("side_dtype", "choice", "float32", "precision of every region's P, mu, sigma",
                   choices=tuple(SIDE_DTYPES)),
    )

    @classmethod
    def check_params(cls, raw: Any, where: Where, prefix: str = "") -> dict[str, Any]:
        params = super().check_params(raw, where, prefix)
        if "energy_retention" in params and "n_components" in params:
            raise where.error(prefix, "give energy_retention or n_components, not both")
        return params

    def __init__(self, spatial_clusters: int = 16, energy_retention: float | None = None,
                 n_components: int | None = None, seed: int = 0, unit_weights: bool = True,
                 side_dtype: str = "float32") -> None:
        if isinstance(spatial_clusters, bool) or not isinstance(spatial_clusters, (int, np.integer)) \
                or not 1 <= spatial_clusters <= MAX_REGIONS:
            raise ValidationError(f"pca-spatial: spatial_clusters must be an integer in 1-{MAX_REGIONS}, "
                                  f"got {spatial_clusters!r}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValidationError(f"pca-spatial: seed must be a non-negative integer, got {seed!r}")
        ShacPCA(n_components=n_components, energy_retention=energy_retention, side_dtype=side_dtype)  # validates
        self.spatial_clusters = int(spatial_clusters)
        self.energy_retention = energy_retention
        self.n_components = n_components
        self.seed = int(seed)
        self.unit_weights = bool(unit_weights)
        self.side_dtype = side_dtype
        self.positions_: np.ndarray | None = None
        self.metric_: np.ndarray | None = None
        self.labels_: np.ndarray | None = None
        self.pcas_: list[ShacPCA] | None = None
        #: per region, the float32 factor of each component's scores (``unit_weights``); None: all 1
        self.gains_: list[np.ndarray] | None = None
        self._locate: Callable[[np.ndarray], np.ndarray] | None = None  # positions -> regions (after fit)

    def set_metric(self, metric: np.ndarray | None) -> None:
        """Fit every region's components in the error metric ``metric`` (:meth:`ShacPCA.set_metric`, e.g.
        the cameras' view metric); with ``unit_weights`` the channels are then in units of that metric."""
        ShacPCA().set_metric(metric)  # validates
        self.metric_ = None if metric is None else np.asarray(metric, dtype=np.float64)

    # ----------------------------------------------------------------- fit
    def fit(self, ac: np.ndarray) -> "SpatialPCA":
        """Regions from the positions (:meth:`set_positions`), then one SHAC-PCA per region."""
        ac = check_ac_matrix(ac)
        if self.positions_ is None or self.positions_.shape != (ac.shape[0], 3):
            raise ValidationError("pca-spatial needs the positions of the rows it fits (set_positions)")
        labels, self._locate = fit_regions(self.positions_, self.spatial_clusters, self.seed)
        pcas = []
        for region in range(int(labels.max()) + 1):
            rows = ac[labels == region]
            m = None if self.n_components is None else min(self.n_components, ac.shape[1])
            pca = ShacPCA(n_components=m, energy_retention=None if m else self.energy_retention,
                          side_dtype=self.side_dtype)
            pca.set_metric(self.metric_)
            pcas.append(pca.fit(rows))
        self.labels_, self.pcas_ = labels, pcas
        self.gains_ = [np.sqrt(np.maximum(p.feature_weights(), 1e-30)).astype(np.float32) for p in pcas] \
            if self.unit_weights else None
        return self

    # ------------------------------------------------------------ transform
    def _row_labels(self, rows: int) -> np.ndarray:
        return self.labels_ if rows == self.labels_.size else np.zeros(rows, dtype=np.int64)

    def transform(self, ac: np.ndarray) -> np.ndarray:
        """(N, K') -> (N, max M_c) region scores (eq. 28 per region), zero past a region's rank."""
        self._check_fitted()
        ac = check_ac_matrix(ac, self.pcas_[0].n_ac_columns)
        labels = self._row_labels(ac.shape[0])
        out = np.zeros((ac.shape[0], self.n_components_), dtype=np.result_type(ac.dtype, np.float32))
        for region, pca in enumerate(self.pcas_):
            rows = labels == region
            if rows.any():
                scores = pca.transform(ac[rows])
                out[rows, : pca.n_components_] = scores if self.gains_ is None else scores * self.gains_[region]
        return out

    def inverse_transform(self, features: np.ndarray) -> np.ndarray:
        """(N, max M_c) -> (N, K'): each row through its region's basis (eq. 29)."""
        self._check_fitted()
        features = check_ac_matrix(features, self.n_components_)
        labels = self._row_labels(features.shape[0])
        out = np.zeros((features.shape[0], self.pcas_[0].n_ac_columns), dtype=np.result_type(features.dtype, np.float32))
        for region, pca in enumerate(self.pcas_):
            rows = labels == region
            if rows.any():
                scores = features[rows, : pca.n_components_]
                out[rows] = pca.inverse_transform(scores if self.gains_ is None else scores / self.gains_[region])
        return out

    def feature_weights(self) -> np.ndarray:
        """Each channel's weight (see ShacPCA): 1 with ``unit_weights``, else averaged over the rows of
        the regions that use it."""
        self._check_fitted()
        if self.gains_ is not None:
            return np.ones(self.n_components_)
        counts = np.bincount(self.labels_, minlength=len(self.pcas_)).astype(np.float64)
        weights = np.zeros(self.n_components_)
        for count, pca in zip(counts, self.pcas_):
            weights[: pca.n_components_] += count * pca.feature_weights()
        return weights / max(counts.sum(), 1.0)

    def keep_features(self, count: int) -> None:
        """Keep the first ``count`` channels: every region keeps at most ``count`` components."""
        self._check_fitted()
        if not 1 <= count <= self.n_components_:
            raise ValidationError(f"pca-spatial can keep 1 to {self.n_components_} components, not {count}")
        for region, pca in enumerate(self.pcas_):
            if pca.n_components_ > count:
                pca.keep_features(count)
                if self.gains_ is not None:
                    self.gains_[region] = self.gains_[region][:count]

    def restrict_rows(self, index: np.ndarray) -> None:
        """The region labels of the fitted rows ``index``, in that order (the rows an encode codes)."""
        self._check_fitted()
        self.labels_ = self.labels_[np.asarray(index, dtype=np.int64)]

    def locate_rows(self, positions: np.ndarray) -> None:
        """The next rows are other Gaussians of the fitted scene (e.g. the rate controller's probe): each
        takes the region of the nearest region centre (for a fitted row, its own region)."""
        self._check_fitted()
        if self._locate is None:
            raise ValidationError("this pca-spatial stage was rebuilt from a state: it has no region centres")
        self.labels_ = self._locate(positions)

    def stream_features(self) -> tuple[str, ...]:
        """``sh_spatial_unit_weights`` (format 2.5) with ``unit_weights``: an older decoder would read the
        scaled features as scores."""
        self._check_fitted()
        return ("sh_spatial_unit_weights",) if self.gains_ is not None else ()

    # ---------------------------------------------------------------- sizes
    @property
    def n_components_(self) -> int:
        self._check_fitted()
        return max(p.n_components_ for p in self.pcas_)

    @property
    def n_features(self) -> int:
        return self.n_components_

    def ranks(self) -> list[int]:
        """M_c of every region."""
        self._check_fitted()
        return [int(p.n_components_) for p in self.pcas_]

    def state(self) -> StageState:
        """Region labels (uint8, row order), every region's SHAC-PCA state (``side_dtype``) and, with
        ``unit_weights``, its gains (float32)."""
        self._check_fitted()
        arrays: dict[str, np.ndarray] = {"labels": self.labels_.astype(np.uint8)}
        regions = []
        for region, pca in enumerate(self.pcas_):
            state = pca.state()
            regions.append(state.params)
            arrays.update({f"r{region}_{key}": value for key, value in state.arrays.items()})
            if self.gains_ is not None:
                arrays[f"g{region}"] = self.gains_[region]
        params: dict[str, Any] = {"regions": regions, "spatial_clusters": self.spatial_clusters}
        if self.gains_ is not None:  # recorded only when on: a state without it is one of before the option
            params["unit_weights"] = True
        return StageState(self.name, params, arrays)

    @classmethod
    def from_state(cls, state: StageState) -> "SpatialPCA":
        try:
            regions = state.params["regions"]
            labels = np.asarray(state.arrays["labels"])
            if not isinstance(regions, list) or not 1 <= len(regions) <= MAX_REGIONS:
                raise ValueError("regions")
            pcas = []
            for region, params in enumerate(regions):
                prefix = f"r{region}_"
                arrays = {key[len(prefix):]: v for key, v in state.arrays.items() if key.startswith(prefix)}
                pcas.append(ShacPCA.from_state(StageState("pca", params, arrays)))
            unit = state.params.get("unit_weights", False) is True
            gains = [np.asarray(state.arrays[f"g{region}"], dtype=np.float32) for region in range(len(pcas))] \
                if unit else None
        except (KeyError, TypeError, ValueError) as exc:
            raise GscodecError(f"pca-spatial state is incomplete ({exc})") from None
        if gains is not None and any(g.shape != (p.n_components_,) or not np.all(np.isfinite(g)) or np.any(g <= 0)
                                     for g, p in zip(gains, pcas)):
            raise GscodecError("pca-spatial state is inconsistent (a region's gains do not fit its components)")
        columns = {p.n_ac_columns for p in pcas}
        if (len(columns) != 1 or any(p.include_dc or not p.joint_rgb for p in pcas) or labels.ndim != 1
                or labels.dtype != np.uint8 or (labels.size and int(labels.max()) >= len(pcas))):
            raise GscodecError("pca-spatial state is inconsistent (regions, columns or labels)")
        stage = cls(spatial_clusters=max(1, len(pcas)), unit_weights=gains is not None,
                    side_dtype=pcas[0].side_dtype)
        stage.labels_, stage.pcas_, stage.gains_ = labels.astype(np.int64), pcas, gains
        return stage

    def _check_fitted(self) -> None:
        if self.pcas_ is None:
            raise ValidationError("this pca-spatial stage is not fitted yet; call set_positions() and fit() first")

    def __repr__(self) -> str:
        if self.pcas_ is None:
            return f"SpatialPCA(unfitted, spatial_clusters={self.spatial_clusters})"
        return f"SpatialPCA(regions={len(self.pcas_)}, ranks={self.ranks()})"
