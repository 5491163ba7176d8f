"""SHAC-PCA: post-hoc PCA of the SH AC coefficients (paper Sec. V-A, eq. 23, 25-31).

Fit: standardise A column-wise (eq. 23), take the eigen-decomposition of the
K' x K' matrix A'^T A' (accumulated in float64 over row chunks; its eigenvalues
are the s_k^2 of the SVD of eq. 25 and its eigenvectors the columns of V), and
keep the first M eigenvectors as P (eq. 27). M is given, or is the smallest rank
whose energy retention ER(M) (eq. 26) reaches a target.

Transform / inverse (eq. 28-29)::

    F  = A' P = (A - 1 mu^T) D_sigma^-1 P
    A~ = F P^T D_sigma + 1 mu^T

The paper prints eq. 29 as (F P^T + 1 mu^T) D_sigma, which scales the mean by
sigma as well; that is not the inverse of eq. 23, so we implement the
consistent form above.

Ablation switches (Sec. VII-D1 and the RGB-joint design choice of Sec. V-A):

* ``include_dc=True``: PCA over [DC | A] (N x (3 + K')); the stage then has
  ``uses_dc = True`` and its input and output are [DC | A].
* ``joint_rgb=False``: one PCA per colour channel, over that channel's columns
  (every third column). The M components are shared out by *global* eigenvalue
  order: M given -> the M largest eigenvalues over the three channel PCAs; ER
  given -> the fewest such eigenvalues whose sum reaches the target. This is
  the optimal split (largest captured energy for the count). P is then
  block-structured and stored compactly, (K'/3) x M plus each component's
  channel.

In a metric (:meth:`ShacPCA.set_metric`, e.g. the cameras' view metric of
:mod:`gscodec_shac.shac.view_metric`) the rank M stays the paper's and its basis becomes the
principal axes in that metric; P is then the back-projection of eq. 29 and no longer
orthonormal, which decoders do not need to know.

Side information (P, mu, sigma) is rounded to ``side_dtype`` (float32 by default,
float16 or float64 allowed) right after fitting, and the rounded values are used
by transform and inverse alike, so encoder and decoder agree exactly.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.shac.analysis import (
    DEFAULT_CHUNK,
    check_energy_target,
    column_moments,
    cumulative_energy,
    rank_for_energy,
    safe_scale,
)
from gscodec_shac.shac.base import ShStage, StageParam, StageState, check_ac_matrix, register_stage
from gscodec_shac.validate import Where

SIDE_DTYPES = {"float16": np.float16, "float32": np.float32, "float64": np.float64}
#: The energy retention used when neither it nor ``n_components`` is given (the paper's ER 99%).
DEFAULT_ENERGY_RETENTION = 0.99
#: Bytes of one float32 (the unit of eq. 30's parameter counts in bytes).
FLOAT32_BYTES = 4


@register_stage
class ShacPCA(ShStage):
    """SHAC-PCA stage "pca" (scikit-learn transformer style; see module docstring).

    Parameters
    ----------
    n_components: M, the number of principal components kept (eq. 27).
    energy_retention: target ER in (0, 1]; M is the smallest rank reaching it
        (eq. 26-27). If neither is given, 0.99 (the paper's pipeline setting,
        Sec. VI-C2).
    standardize: apply eq. 23 before the PCA (True in the paper).
    include_dc: PCA over [DC | A] (ablation, Sec. VII-D1).
    joint_rgb: one joint PCA over R, G, B (paper) or one per channel (ablation).
    side_dtype: storage type of P, mu, sigma: "float32", "float16" or "float64".

    Fitted attributes: ``components_`` (P, (K_in, M)), ``mean_`` and ``scale_``
    (K_in,), ``n_components_``, ``singular_values_`` (s_k of A', all K_in),
    ``energy_ratio_`` (s_k^2 / sum s^2 per component) and ``energy_`` (the
    cumulative ER curve, eq. 26), ``component_channels_`` (per-channel mode).
    K_in is K' or 3 + K' with ``include_dc``.
    """

    name = "pca"
    summary = "SHAC-PCA: principal components of the standardised AC matrix (eq. 23-31)"
    feature_kind = "components"
    rate_attribute = "sh_features"
    reads_row_blocks = True
    inverts_row_blocks = True
    params = (
        StageParam("energy_retention", "float", DEFAULT_ENERGY_RETENTION,
                   "energy retention ER(M) (eq. 26) the kept components reach", flag="er", lo=0.0, hi=1.0, open_lo=True),
        StageParam("n_components", "int", None, "number of components M (instead of an ER)", flag="components",
                   lo=1, hi=128),
        StageParam("include_dc", "bool", False, "PCA over [DC | AC] (ablation, Sec. VII-D1)"),
        StageParam("standardize", "bool", True, "z-score the columns first (eq. 23)"),
        StageParam("joint_rgb", "bool", True, "one PCA over R, G and B together"),
        StageParam("side_dtype", "choice", "float32", "precision of P, mu, sigma", choices=tuple(SIDE_DTYPES)),
        StageParam("chunk_size", "int", DEFAULT_CHUNK, "rows per accumulation chunk", lo=1),
    )

    @classmethod
    def check_params(cls, raw: Any, where: Where, prefix: str = "") -> dict[str, Any]:
        params = super().check_params(raw, where, prefix)
        if "energy_retention" in params and "n_components" in params:
            raise where.error(prefix, "give energy_retention or n_components, not both")
        return params

    def __init__(
        self,
        n_components: int | None = None,
        energy_retention: float | None = None,
        *,
        standardize: bool = True,
        include_dc: bool = False,
        joint_rgb: bool = True,
        side_dtype: str = "float32",
        chunk_size: int = DEFAULT_CHUNK,
    ) -> None:
        if n_components is not None and energy_retention is not None:
            raise ValidationError("give either n_components or energy_retention for SHAC-PCA, not both")
        if n_components is not None and not _is_positive_int(n_components):
            raise ValidationError(f"n_components must be a positive integer, got {n_components!r}")
        if n_components is None and energy_retention is None:
            energy_retention = DEFAULT_ENERGY_RETENTION
        if energy_retention is not None:
            energy_retention = check_energy_target(energy_retention)
        if side_dtype not in SIDE_DTYPES:
            raise ValidationError(f"side_dtype must be one of {', '.join(SIDE_DTYPES)}, got {side_dtype!r}")
        if not _is_positive_int(chunk_size):
            raise ValidationError(f"chunk_size must be positive, got {chunk_size}")
        self.n_components = None if n_components is None else int(n_components)
        self.energy_retention = energy_retention
        self.standardize = bool(standardize)
        self.include_dc = bool(include_dc)
        self.joint_rgb = bool(joint_rgb)
        self.side_dtype = side_dtype
        self.chunk_size = int(chunk_size)
        self.uses_dc = self.include_dc
        self.components_: np.ndarray | None = None
        self.mean_: np.ndarray | None = None
        self.scale_: np.ndarray | None = None
        self.n_components_: int | None = None
        self.singular_values_: np.ndarray | None = None
        self.energy_ratio_: np.ndarray | None = None
        self.energy_: np.ndarray | None = None
        self.component_channels_: np.ndarray | None = None
        #: the (K_in, K_in) error metric of the input columns the next fit orders its components in
        #: (:meth:`set_metric`); None: every column alike (the paper)
        self.metric_: np.ndarray | None = None
        self._n_in = 0

    def set_metric(self, metric: np.ndarray | None) -> None:
        """Fit the next components in the error metric ``metric`` (K_in, K_in), symmetric positive
        definite, e.g. :func:`~gscodec_shac.shac.view_metric.view_metric`: the rank M is the paper's
        (eq. 26-27, from the SH's own energy), its basis the first M principal axes in the metric, so a
        unit error on any component costs one unit of ``e^T metric e`` in the input columns and the
        water-filled QPs follow what the metric weighs. The stored side information keeps its form
        (P is the back-projection of eq. 29, no longer orthonormal), so decoders are unchanged.
        Joint-RGB stages without the DC only; None restores the paper's stage."""
        if metric is not None:
            if not self.joint_rgb or self.include_dc:
                raise ValidationError("a metric applies to joint-RGB SHAC-PCA over the AC coefficients only")
            metric = np.asarray(metric, dtype=np.float64)
            if metric.ndim != 2 or metric.shape[0] != metric.shape[1] or not np.allclose(metric, metric.T):
                raise ValidationError(f"a metric must be a symmetric square matrix, got shape {metric.shape}")
        self.metric_ = metric

    # ------------------------------------------------------------------ fit
    def fit(self, ac: np.ndarray) -> "ShacPCA":
        """Learn mu, sigma (eq. 23) and P (eq. 25-27) from (N, K_in)."""
        ac = check_ac_matrix(ac)
        n_in = ac.shape[1]
        if n_in == 0 or (self.include_dc and n_in <= 3):
            raise ValidationError("SHAC-PCA needs AC coefficients (SH degree >= 1)")
        if n_in % 3:
            raise ValidationError(f"expected R, G, B columns (a multiple of 3), got {n_in} columns")
        if self.n_components is not None and self.n_components > n_in:
            raise ValidationError(f"n_components={self.n_components} exceeds the {n_in} input columns")
        moments = column_moments(ac, self.chunk_size)
        scale = safe_scale(moments.std(), moments.mean) if self.standardize else np.ones(n_in)
        scatter = moments.scatter / np.outer(scale, scale)  # A'^T A'

        if self.joint_rgb:
            values, vectors = _sorted_eigh(scatter)
            channels = None
        else:
            values, vectors, channels = self._per_channel_eigh(scatter)
        # the spectrum and the energy retention are the SH's own (eq. 26-27), with or without a metric
        self.singular_values_ = np.sqrt(values)
        self.energy_ratio_ = values / values.sum() if values.sum() > 0 else np.full(n_in, 1.0 / n_in)
        self.energy_ = cumulative_energy(values)
        m = self.n_components or rank_for_energy(self.energy_, self.energy_retention)
        if self.metric_ is not None:  # the rank's basis: the principal axes in the metric (set_metric)
            if self.metric_.shape[0] != n_in:
                raise ValidationError(f"the metric is {self.metric_.shape[0]} x {self.metric_.shape[0]}, "
                                      f"the AC matrix has {n_in} columns")
            root, root_inv = _sqrt_and_inverse(self.metric_ * np.outer(scale, scale))
            _, axes = _sorted_eigh(root @ scatter @ root)  # the standardised columns in the metric
            vectors = root_inv @ axes  # F = A' L V, A' = F V^T L^-1: P = L^-1 V back-projects

        side = SIDE_DTYPES[self.side_dtype]
        self.n_components_ = m
        self.components_ = vectors[:, :m].astype(side).astype(np.float64)
        self.mean_ = moments.mean.astype(side).astype(np.float64)
        self.scale_ = scale.astype(side).astype(np.float64)
        if np.any(self.scale_ == 0) or not all(np.isfinite(a).all() for a in (self.scale_, self.mean_)):
            raise ValidationError(
                f"a mean or standard deviation does not fit in {self.side_dtype}; use side_dtype='float32'"
            )
        self.component_channels_ = None if channels is None else channels[:m].copy()
        self._n_in = n_in
        return self

    @staticmethod
    def _per_channel_eigh(scatter: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Eigen-pairs of each channel's block, embedded in K_in and merged by eigenvalue."""
        n_in = scatter.shape[0]
        values, vectors, channels = [], [], []
        for c in range(3):
            idx = np.arange(c, n_in, 3)
            vals, vecs = _sorted_eigh(scatter[np.ix_(idx, idx)])
            full = np.zeros((n_in, idx.size))
            full[idx] = vecs
            values.append(vals)
            vectors.append(full)
            channels.append(np.full(idx.size, c))
        values_all = np.concatenate(values)
        order = np.argsort(-values_all, kind="stable")
        return values_all[order], np.concatenate(vectors, axis=1)[:, order], np.concatenate(channels)[order]

    # ------------------------------------------------------------ transform
    def transform(self, ac: np.ndarray) -> np.ndarray:
        """Eq. 28: F = A' P, shape (N, M); float32 input gives float32 output.

        The product is accumulated in float64 and rounded once to the output type, so
        the features (and the stream) are the same whatever order the BLAS of this CPU
        sums in: a float32 product differed by an ulp between CPUs and BLAS thread counts.
        """
        self._check_fitted()
        ac = check_ac_matrix(ac, self._n_in)
        dtype = np.result_type(ac.dtype, np.float32)
        weights = self._forward() / self.scale_[:, None]  # float64
        out = np.empty((ac.shape[0], self.n_components_), dtype=dtype)
        for start in range(0, ac.shape[0], self.chunk_size):
            stop = start + self.chunk_size
            out[start:stop] = (ac[start:stop] - self.mean_) @ weights
        return out

    def _forward(self) -> np.ndarray:
        """(K_in, M): the standardised columns -> features. P itself in the paper's metric (orthonormal);
        in a metric M the weighted least-squares projection onto P's columns, ``M P (P^T M P)^-1``
        (with every component kept, the exact inverse of the back-projection)."""
        if self.metric_ is None:
            return self.components_
        metric = self.metric_ * np.outer(self.scale_, self.scale_)
        weighted = metric @ self.components_
        return weighted @ np.linalg.inv(self.components_.T @ weighted)

    def inverse_transform(self, features: np.ndarray) -> np.ndarray:
        """Eq. 29 (consistent form): A~ = F P^T D_sigma + 1 mu^T, shape (N, K_in)."""
        self._check_fitted()
        features = check_ac_matrix(features, self.n_components_)
        out = np.empty((features.shape[0], self._n_in), dtype=np.result_type(features.dtype, np.float32))
        self.inverse_transform_into(features, out)
        return out

    def inverse_transform_into(self, features: np.ndarray, out: np.ndarray) -> None:
        """Eq. 29 into ``out`` (N, K_in): one BLAS product per call, each output row from its own
        feature row only (so row blocks give the rows of the whole product)."""
        self._check_fitted()
        features = check_ac_matrix(features, self.n_components_)
        back = (self.components_ * self.scale_[:, None]).astype(out.dtype)  # (K_in, M)
        # Row-major (N, K_in) out of the BLAS directly (channel-major features go in as a
        # transposed operand, no copy): the cloud's sh_rest needs no transposing copy after it.
        np.matmul(features, back.T, out=out)
        out += self.mean_.astype(out.dtype)

    def feature_weights(self) -> np.ndarray:
        """Unit error on component j moves the input columns by ``b_j = P_:j sigma`` (eq. 29): weight
        ``sum_k b_kj^2``, or ``b_j^T M b_j`` in a metric M (:meth:`set_metric`)."""
        self._check_fitted()
        back = self.components_ * self.scale_[:, None]
        if self.metric_ is None:
            return (back ** 2).sum(axis=0)
        return np.einsum("kj,kl,lj->j", back, self.metric_, back)

    def keep_features(self, count: int) -> None:
        """Keep the first ``count`` components (the side information shrinks with them)."""
        self._check_fitted()
        if not 1 <= count <= self.n_components_:
            raise ValidationError(f"SHAC-PCA can keep 1 to {self.n_components_} components, not {count}")
        self.n_components_ = int(count)
        self.components_ = self.components_[:, :count]
        if self.component_channels_ is not None:
            self.component_channels_ = self.component_channels_[:count]

    # ------------------------------------------------------------- sizes
    @property
    def n_features(self) -> int:
        self._check_fitted()
        return int(self.n_components_)

    @property
    def n_ac_columns(self) -> int:
        """K', the AC columns (K_in minus the DC when ``include_dc``)."""
        self._check_fitted()
        return self._n_in - 3 if self.include_dc else self._n_in

    def n_side_parameters(self) -> int:
        """Stored side-information values: P plus mu and sigma (eq. 30: K'M + 2K' when joint)."""
        self._check_fitted()
        rows = self._n_in if self.joint_rgb else self._n_in // 3
        return rows * self.n_components_ + self._n_in * (2 if self.standardize else 1)

    def compression_ratio(self, n_gaussians: int) -> float:
        """Eq. 30 by parameter counts: (N(3 + M) + side) / (N K), K = K' + 3.

        With ``include_dc`` the DC lives inside the M features (no separate 3N).
        """
        n = _check_n(n_gaussians)
        dc = 0 if self.include_dc else 3
        k = self.n_ac_columns + 3
        return (n * (dc + self.n_features) + self.n_side_parameters()) / (n * k)

    def compression_ratio_bytes(self, n_gaussians: int, feature_bytes: float = FLOAT32_BYTES) -> float:
        """Eq. 30 from bytes: float32 DC + features of ``feature_bytes`` each + the
        whole serialised state (:meth:`StageState.to_bytes`), over N K float32."""
        n = _check_n(n_gaussians)
        dc = 0 if self.include_dc else 3 * FLOAT32_BYTES
        k = self.n_ac_columns + 3
        side = len(self.state().to_bytes())
        return (n * (dc + self.n_features * feature_bytes) + side) / (n * k * FLOAT32_BYTES)

    # ------------------------------------------------------------- state
    def state(self) -> StageState:
        """P, mu (and sigma when standardising) in ``side_dtype``; settings as JSON."""
        self._check_fitted()
        side = SIDE_DTYPES[self.side_dtype]
        if self.joint_rgb:
            comps = self.components_
        else:  # compact: each column only on its channel's rows
            comps = np.stack([self.components_[c::3, j] for j, c in enumerate(self.component_channels_)], axis=1)
        arrays = {"components": comps.astype(side), "mean": self.mean_.astype(side)}
        if self.standardize:
            arrays["scale"] = self.scale_.astype(side)
        params: dict[str, Any] = {
            "n_components": self.n_components_,
            "n_input_columns": self._n_in,
            "energy_retention": self.energy_retention if self.n_components is None else None,
            "standardize": self.standardize,
            "include_dc": self.include_dc,
            "joint_rgb": self.joint_rgb,
            "side_dtype": self.side_dtype,
        }
        if not self.joint_rgb:
            params["component_channels"] = [int(c) for c in self.component_channels_]
        return StageState(self.name, params, arrays)

    @classmethod
    def from_state(cls, state: StageState) -> "ShacPCA":
        """Rebuild the fitted stage; raises :class:`GscodecError` on an inconsistent state."""
        try:
            p = state.params
            stage = cls(
                n_components=int(p["n_components"]), standardize=bool(p["standardize"]),
                include_dc=bool(p["include_dc"]), joint_rgb=bool(p["joint_rgb"]), side_dtype=str(p["side_dtype"]),
            )
            stage.energy_retention = p.get("energy_retention")
            n_in, m = int(p["n_input_columns"]), int(p["n_components"])
            comps = np.asarray(state.arrays["components"], dtype=np.float64)
            mean = np.asarray(state.arrays["mean"], dtype=np.float64)
            scale = np.asarray(state.arrays["scale"], dtype=np.float64) if stage.standardize else np.ones(n_in)
            if mean.shape != (n_in,) or scale.shape != (n_in,) or n_in % 3 or np.any(scale == 0):
                raise ValueError("mean/scale")
            if stage.joint_rgb:
                if comps.shape != (n_in, m):
                    raise ValueError("components")
                full, channels = comps, None
            else:
                channels = np.asarray(p["component_channels"], dtype=np.int64)
                if comps.shape != (n_in // 3, m) or channels.shape != (m,) or np.any((channels < 0) | (channels > 2)):
                    raise ValueError("components")
                full = np.zeros((n_in, m))
                for j, c in enumerate(channels):
                    full[c::3, j] = comps[:, j]
        except (KeyError, TypeError, ValueError, ValidationError) as exc:
            raise GscodecError(f"SHAC-PCA state is inconsistent ({exc})") from None
        stage.components_, stage.mean_, stage.scale_ = full, mean, scale
        stage.n_components_, stage.component_channels_, stage._n_in = m, channels, n_in
        return stage

    def _check_fitted(self) -> None:
        if self.components_ is None:
            raise ValidationError("this SHAC-PCA stage is not fitted yet; call fit() first")

    def __repr__(self) -> str:
        target = (
            f"n_components={self.n_components}" if self.n_components else f"energy_retention={self.energy_retention}"
        )
        return (
            f"ShacPCA({target}, standardize={self.standardize}, include_dc={self.include_dc}, "
            f"joint_rgb={self.joint_rgb}, side_dtype={self.side_dtype!r})"
        )


def _sqrt_and_inverse(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The symmetric square root of a symmetric positive definite matrix and its inverse."""
    values, vectors = np.linalg.eigh(matrix)
    if values.min() <= values.max() * 1e-12:
        raise ValidationError("the SH error metric is not positive definite")
    return (vectors * np.sqrt(values)) @ vectors.T, (vectors / np.sqrt(values)) @ vectors.T


def _sorted_eigh(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (descending, clipped at 0) and eigenvectors with a fixed sign
    (largest-magnitude entry positive), so a fit is reproducible."""
    values, vectors = np.linalg.eigh(matrix)
    values, vectors = np.clip(values[::-1], 0.0, None), vectors[:, ::-1]
    pivot = np.argmax(np.abs(vectors), axis=0)
    signs = np.sign(vectors[pivot, np.arange(vectors.shape[1])])
    signs[signs == 0] = 1.0
    return values, vectors * signs


def _is_positive_int(value: Any) -> bool:
    try:
        return not isinstance(value, bool) and int(value) == value and value >= 1
    except (TypeError, ValueError):
        return False


def _check_n(n_gaussians: int) -> int:
    if int(n_gaussians) < 1:
        raise ValidationError(f"the number of Gaussians must be positive, got {n_gaussians}")
    return int(n_gaussians)
