"""gsplat's vector quantisation followed by SHAC-PCA of the codebook (stage ``"vq-pca"``).

The paper's *gsplat+SHAC-PCA* (Sec. VI-C2, Fig. 4): the SH AC vectors are vector
quantised as gsplat does (a k-means codebook of K entries and one label per
Gaussian, :mod:`gscodec_shac.shac.vq`), and SHAC-PCA (eq. 23-29) is then applied
to the *codebook*, not to the Gaussians: the K x K' codebook C is standardised and
projected onto its first M principal components (M from an energy retention, 99%
by default), and the codebook's features ``F_C = C' P`` (K x M) are stored quantised
to ``centroid_bits`` (8) per value with a min/max per component, together with the
basis P (K' x M) and the mean and scale (K' each) as float32. The decoder rebuilds
the codebook ``C~ = F_C P^T D_sigma + 1 mu^T`` (eq. 29, the consistent form of
:mod:`gscodec_shac.shac.pca`) and looks the labels up in it.

The stored codebook shrinks from K x K' values to K x M plus (M + 2) x K' floats, the
per-Gaussian labels stay as they are (``feature_kind = "labels"``, coded losslessly
through the rate point's ``sh_labels``). After the codebook is rebuilt the fitted
rows are labelled again with their nearest rebuilt entry within their k-means leaf
(the same rule vq applies to its dequantised centres), so the labels match the
codebook the decoder sees.

The k-means runs on the float codebook (held at 16 bits per component, far below
the PCA and 8-bit feature error); its parameters are vq's.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.shac.base import ShStage, StageParam, StageState, check_ac_matrix, register_stage
from gscodec_shac.shac.pca import DEFAULT_ENERGY_RETENTION, ShacPCA
from gscodec_shac.shac.vq import INITS, VectorQuantizer, _dequantize_codebook, _nearest, _quantize_codebook, lookup_labels
from gscodec_shac.validate import Where

#: Bits per component of the k-means codebook before the PCA (effectively float).
_KMEANS_BITS = 16


@register_stage
class VqPca(ShStage):
    """SH stage "vq-pca": a vq codebook compressed by SHAC-PCA; features are integer labels.

    Parameters
    ----------
    n_clusters, n_iter, init, seed, leaf_work, sample_per_branch: the k-means of vq.
    energy_retention: ER(M) (eq. 26) of the codebook PCA (0.99, the paper's setting).
    n_components: M instead of an energy retention.
    centroid_bits: bits per stored codebook PCA feature (8, the paper's codebook precision).
    standardize: z-score the codebook columns before the PCA (eq. 23).

    Fitted attributes: ``pca_`` (the :class:`ShacPCA` of the codebook), ``codes_`` (K, M)
    integer codebook features, ``lo_``/``hi_`` (M,) their ranges, ``codebook_`` (K, K')
    rebuilt codebook (float32), ``labels_`` of the fitted rows.
    """

    name = "vq-pca"
    summary = ("vq followed by SHAC-PCA of its codebook (gsplat+SHAC-PCA, Fig. 4): labels per Gaussian, "
               "the codebook as M principal-component features")
    feature_kind = "labels"
    rate_attribute = "sh_labels"
    params = (
        StageParam("n_clusters", "int", 65536, "codebook size", flag="clusters", lo=1, hi=1 << 24),
        StageParam("energy_retention", "float", DEFAULT_ENERGY_RETENTION,
                   "energy retention of the codebook PCA (eq. 26)", flag="er", lo=0.0, hi=1.0, open_lo=True),
        StageParam("n_components", "int", None, "components M of the codebook PCA (instead of an ER)",
                   flag="components", lo=1, hi=128),
        StageParam("centroid_bits", "int", 8, "bits per codebook PCA feature", flag="centroid_bits", lo=1, hi=16),
        StageParam("standardize", "bool", True, "z-score the codebook columns first (eq. 23)"),
        StageParam("n_iter", "int", 10, "k-means iterations", lo=1, hi=1000),
        StageParam("init", "choice", "random", "k-means initialisation", choices=INITS),
        StageParam("seed", "int", 0, "k-means seed (encode's --seed sets it too)", lo=0, hi=2**32 - 1),
        StageParam("leaf_work", "int", 1 << 22, "work budget of one k-means leaf", lo=1),
        StageParam("sample_per_branch", "int", 64, "samples per branch of the hierarchical k-means", lo=1),
    )

    @classmethod
    def check_params(cls, raw: Any, where: Where, prefix: str = "") -> dict[str, Any]:
        params = super().check_params(raw, where, prefix)
        if "energy_retention" in params and "n_components" in params:
            raise where.error(prefix, "give energy_retention or n_components, not both")
        return params

    def __init__(
        self,
        n_clusters: int = 65536,
        energy_retention: float | None = None,
        n_components: int | None = None,
        centroid_bits: int = 8,
        standardize: bool = True,
        n_iter: int = 10,
        init: str = "random",
        seed: int = 0,
        leaf_work: int = 1 << 22,
        sample_per_branch: int = 64,
    ) -> None:
        if isinstance(centroid_bits, bool) or not isinstance(centroid_bits, (int, np.integer)) or not 1 <= centroid_bits <= 16:
            raise ValidationError(f"vq-pca: centroid_bits must be an integer in 1-16, got {centroid_bits!r}")
        # validate the k-means and PCA settings by building them once
        self._vq_params = dict(n_clusters=n_clusters, centroid_bits=_KMEANS_BITS, n_iter=n_iter, init=init,
                               seed=seed, leaf_work=leaf_work, sample_per_branch=sample_per_branch)
        VectorQuantizer(**self._vq_params)
        self._pca_params = dict(n_components=n_components, energy_retention=energy_retention,
                                standardize=bool(standardize))
        ShacPCA(**self._pca_params)
        self.n_clusters = int(n_clusters)
        self.centroid_bits = int(centroid_bits)
        self.standardize = bool(standardize)
        self.pca_: ShacPCA | None = None
        self.codes_: np.ndarray | None = None
        self.lo_: np.ndarray | None = None
        self.hi_: np.ndarray | None = None
        self.codebook_: np.ndarray | None = None
        self.labels_: np.ndarray | None = None
        self._vq: VectorQuantizer | None = None

    # ----------------------------------------------------------------- fit
    def fit(self, ac: np.ndarray) -> "VqPca":
        """k-means codebook (vq), PCA of the codebook (eq. 23-28), quantised codebook features, labels."""
        x = np.ascontiguousarray(check_ac_matrix(ac), dtype=np.float32)
        vq = VectorQuantizer(**self._vq_params)
        vq.progress = self.progress
        vq.fit(x)
        centres = vq.codebook_.astype(np.float64)
        if x.shape[1] % 3:
            raise ValidationError(f"expected R, G, B columns (a multiple of 3), got {x.shape[1]} columns")
        pca = ShacPCA(**self._pca_params).fit(centres)
        codes, lo, hi = _quantize_codebook(pca.transform(centres).astype(np.float32), self.centroid_bits)
        self._set(pca, codes, lo, hi)
        vq.codebook_ = self.codebook_  # label against the rebuilt codebook, down the k-means tree
        self._vq = vq
        self.labels_ = vq.transform(x)[:, 0].astype(np.int64)
        return self

    def fit_transform(self, ac: np.ndarray) -> np.ndarray:
        """Fit, then the labels of the fitted rows as an (N, 1) float column."""
        return self.fit(ac).labels_.astype(np.float64)[:, None]

    def _set(self, pca: ShacPCA, codes: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
        """Keep the fitted parts and rebuild the codebook from them (eq. 29)."""
        self.pca_, self.codes_, self.lo_, self.hi_ = pca, codes, lo, hi
        features = _dequantize_codebook(codes, lo, hi, self.centroid_bits).astype(np.float64)
        self.codebook_ = np.ascontiguousarray(pca.inverse_transform(features), dtype=np.float32)

    # ------------------------------------------------------------ transform
    def transform(self, ac: np.ndarray) -> np.ndarray:
        """(N, K') -> labels (N, 1): nearest rebuilt entry (down the k-means tree when fitted here)."""
        self._check_fitted()
        x = np.ascontiguousarray(check_ac_matrix(ac, self.codebook_.shape[1]), dtype=np.float32)
        if self._vq is not None:
            return self._vq.transform(x)
        return _nearest(x, self.codebook_).astype(np.float64)[:, None]

    def inverse_transform(self, features: np.ndarray) -> np.ndarray:
        """Labels (N, 1) -> rebuilt codebook rows (N, K') as float32."""
        self._check_fitted()
        return lookup_labels(self.codebook_, features, self.name)

    # ---------------------------------------------------------------- sizes
    @property
    def n_features(self) -> int:
        return 1

    @property
    def n_components_(self) -> int:
        """M, the principal components kept for the codebook."""
        self._check_fitted()
        return int(self.pca_.n_components_)

    @property
    def feature_bits(self) -> int:
        """Bits per label: ceil(log2 K), at least 1."""
        self._check_fitted()
        return max(1, int(self.codebook_.shape[0] - 1).bit_length())

    def state(self) -> StageState:
        """Codebook features (K x M codes, ranges) and the codebook PCA's P, mu, sigma (float32)."""
        self._check_fitted()
        pca = self.pca_.state()
        params = {"centroid_bits": self.centroid_bits, "n_clusters": int(self.codes_.shape[0]),
                  "pca": pca.params}
        return StageState(self.name, params, {"codes": self.codes_, "lo": self.lo_, "hi": self.hi_,
                                              **{f"pca_{k}": v for k, v in pca.arrays.items()}})

    @classmethod
    def from_state(cls, state: StageState) -> "VqPca":
        try:
            bits = int(state.params["centroid_bits"])
            k = int(state.params["n_clusters"])
            pca_params = state.params["pca"]
            codes, lo, hi = state.arrays["codes"], state.arrays["lo"], state.arrays["hi"]
            if not isinstance(pca_params, dict):
                raise TypeError("pca")
            pca_arrays = {key[4:]: value for key, value in state.arrays.items() if key.startswith("pca_")}
        except (KeyError, TypeError, ValueError):
            raise GscodecError("vq-pca state is incomplete (needs centroid_bits, n_clusters, pca, codes, lo, hi)") from None
        pca = ShacPCA.from_state(StageState("pca", pca_params, pca_arrays))
        m = int(pca.n_components_)
        if (not 1 <= bits <= 16 or k < 1 or codes.shape != (k, m) or lo.shape != (m,) or hi.shape != (m,)
                or pca.include_dc or not pca.joint_rgb):
            raise GscodecError("vq-pca state is inconsistent (codebook shape, bit depth or PCA settings)")
        if not np.issubdtype(codes.dtype, np.unsignedinteger) or (codes.size and int(codes.max()) >= 1 << bits):
            raise GscodecError(f"vq-pca state codebook holds values above {bits} bits")
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            raise GscodecError("vq-pca state has non-finite feature ranges")
        stage = cls(n_clusters=k, n_components=m, centroid_bits=bits, standardize=pca.standardize)
        stage._set(pca, codes, lo.astype(np.float32), hi.astype(np.float32))
        return stage

    def _check_fitted(self) -> None:
        if self.codebook_ is None:
            raise GscodecError("vq-pca stage is not fitted: call fit() first")

    def __repr__(self) -> str:
        if self.codebook_ is None:
            return f"VqPca(unfitted, n_clusters={self.n_clusters}, centroid_bits={self.centroid_bits})"
        return f"VqPca(K={self.codebook_.shape[0]}, M={self.n_components_}, centroid_bits={self.centroid_bits})"
