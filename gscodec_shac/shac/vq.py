"""Vector quantisation of the SH AC vectors (stage ``"vq"``), as gsplat's PNG codec does.

Each Gaussian's AC vector (one row of the N x K' matrix) is replaced by the
index of its nearest codebook entry; the codebook (``n_clusters`` entries,
65,536 by default) is stored quantised to ``centroid_bits`` per component with
a per-dimension min/max.

**Features are integer labels.** :meth:`VectorQuantizer.transform` returns the
labels as one float column (exact: labels < 2**24), and the class declares
``feature_kind = "labels"`` and :attr:`feature_bits`: a pipeline must code that
column losslessly as ``feature_bits``-bit integers, not through the min/max
quantiser (:mod:`gscodec_shac.codec.encoder` does). Keeping the float column keeps
the :class:`~gscodec_shac.shac.base.ShStage` contract unchanged for every caller.

**Fitting on a CPU.** A flat k-means with 65,536 centres costs N x K x K'
multiply-adds per assignment pass (3e12 for 1M Gaussians), far too slow on a
few cores. We fit a *k-means tree* instead: a node with more work than
``leaf_work`` (points x centres) is split by a small k-means (sqrt(work /
leaf_work) branches, at most 256, so the branches come out about leaf-sized;
fitted on a random sample of the node's points, seeded), its centre
budget is shared among the branches in proportion to their sizes, and each
branch is handled the same way; a small enough node runs plain Lloyd
iterations (``n_iter``, random or k-means++ initialisation). Each pass then
costs about N x (branches + leaf centres) x K', and the codebook comes out in
tree order, so similar centres have nearby labels. Labels of the fitted rows
are the nearest *dequantised* centre within their leaf.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from tqdm.auto import tqdm

from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.shac.base import ShStage, StageParam, StageState, check_ac_matrix, register_stage

INITS = ("random", "kmeans++")
#: Rows per block when computing distances (bounds temporary memory).
_BLOCK_CELLS = 1 << 22


@dataclass
class _Node:
    """A k-means tree node: a leaf owns codebook rows ``[offset, offset + size)``."""

    offset: int = 0
    size: int = 0
    centres: np.ndarray | None = None  # branch centres of an inner node
    children: list["_Node"] = field(default_factory=list)
    members: np.ndarray | None = None  # fitted rows that reached this leaf (dropped after fit)
    identity: bool = False  # one centre per member row, in member order


@register_stage
class VectorQuantizer(ShStage):
    """SH stage "vq": k-means codebook of the AC vectors; features are integer labels.

    Parameters
    ----------
    n_clusters: codebook size K (gsplat: 65,536); fewer rows than K -> one entry per row.
    centroid_bits: bits per stored codebook component (gsplat: 6; the paper's gsplat runs: 8).
    n_iter: Lloyd iterations per k-means (fixed: no convergence test).
    init: ``"random"`` (distinct random rows) or ``"kmeans++"``.
    seed: seeds every random choice; same input and seed -> same codebook and labels.
    leaf_work: largest points x centres of a plain k-means before the tree splits.
    sample_per_branch: rows sampled per branch to fit a split.

    Fitted attributes: ``codes_`` (K, K') integer codebook, ``lo_``/``hi_`` (K',)
    float32 ranges, ``codebook_`` (dequantised, float32), ``labels_`` of the fitted rows.
    """

    name = "vq"
    summary = "vector quantisation: a k-means codebook of SH vectors and one label per Gaussian (gsplat style)"
    feature_kind = "labels"
    rate_attribute = "sh_labels"
    params = (
        StageParam("n_clusters", "int", 65536, "codebook size", flag="clusters", lo=1, hi=1 << 24),
        StageParam("centroid_bits", "int", 6, "bits per codebook component", flag="centroid_bits", lo=1, hi=16),
        StageParam("n_iter", "int", 10, "k-means iterations", lo=1, hi=1000),
        StageParam("init", "choice", "random", "k-means initialisation", choices=INITS),
        StageParam("seed", "int", 0, "k-means seed (encode's --seed sets it too)", lo=0, hi=2**32 - 1),
        StageParam("leaf_work", "int", 1 << 22, "work budget of one k-means leaf", lo=1),
        StageParam("sample_per_branch", "int", 64, "samples per branch of the hierarchical k-means", lo=1),
    )

    def __init__(
        self,
        n_clusters: int = 65536,
        centroid_bits: int = 6,
        n_iter: int = 10,
        init: str = "random",
        seed: int = 0,
        leaf_work: int = 1 << 22,
        sample_per_branch: int = 64,
    ) -> None:
        for label, value, lo, hi in (
            ("n_clusters", n_clusters, 1, 1 << 24),
            ("centroid_bits", centroid_bits, 1, 16),
            ("n_iter", n_iter, 0, 1000),
            ("seed", seed, 0, 2**63 - 1),
            ("leaf_work", leaf_work, 1, 1 << 40),
            ("sample_per_branch", sample_per_branch, 1, 1 << 20),
        ):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
                raise ValidationError(f"vq: {label} must be an integer in {lo}-{hi}, got {value!r}")
        if init not in INITS:
            raise ValidationError(f"vq: init must be one of {', '.join(INITS)}, got {init!r}")
        self.n_clusters = int(n_clusters)
        self.centroid_bits = int(centroid_bits)
        self.n_iter = int(n_iter)
        self.init = init
        self.seed = int(seed)
        self.leaf_work = int(leaf_work)
        self.sample_per_branch = int(sample_per_branch)
        self.codes_: np.ndarray | None = None
        self.lo_: np.ndarray | None = None
        self.hi_: np.ndarray | None = None
        self.codebook_: np.ndarray | None = None
        self.labels_: np.ndarray | None = None
        self._tree: _Node | None = None

    # ----------------------------------------------------------------- fit
    def fit(self, ac: np.ndarray) -> "VectorQuantizer":
        """Build the codebook and label the rows of ``ac`` (kept in ``labels_``)."""
        x = np.ascontiguousarray(check_ac_matrix(ac), dtype=np.float32)
        if x.shape[1] == 0:
            raise ValidationError("vq needs AC coefficients (SH degree >= 1)")
        if x.shape[0] == 0:
            raise ValidationError("vq cannot fit an empty matrix (N = 0)")
        rng = np.random.default_rng(self.seed)
        leaves: list[_Node] = []
        with tqdm(total=x.shape[0], desc="SH k-means", unit="G", unit_scale=True, disable=not self.progress,
                  leave=False) as bar:
            self._bar = bar
            try:
                self._tree = self._build(x, np.arange(x.shape[0]), min(self.n_clusters, x.shape[0]), rng, leaves)
            finally:
                del self._bar
        centres = np.empty((sum(leaf.size for leaf in leaves), x.shape[1]), dtype=np.float32)
        offset = 0
        for leaf in leaves:
            leaf.offset = offset
            centres[offset : offset + leaf.size] = leaf.centres
            leaf.centres = None
            offset += leaf.size
        self._set_codebook(*_quantize_codebook(centres, self.centroid_bits))
        labels = np.empty(x.shape[0], dtype=np.int64)
        for leaf in leaves:
            if leaf.identity:
                labels[leaf.members] = leaf.offset + np.arange(leaf.size)
            else:
                block = self.codebook_[leaf.offset : leaf.offset + leaf.size]
                labels[leaf.members] = leaf.offset + _nearest(x[leaf.members], block)
            leaf.members = None
        self.labels_ = labels
        return self

    def fit_transform(self, ac: np.ndarray) -> np.ndarray:
        """Fit, then the labels of the fitted rows as an (N, 1) float column."""
        return self.fit(ac).labels_.astype(np.float64)[:, None]

    def _build(self, x: np.ndarray, rows: np.ndarray, k: int, rng: np.random.Generator, leaves: list[_Node]) -> _Node:
        """Recursively split ``rows`` into ``k`` centres (see module docstring)."""
        n = rows.size
        if k >= n or n * k <= self.leaf_work or k == 1:
            return self._leaf(x, rows, k, rng, leaves)
        branches = int(min(k, 256, max(2, math.ceil(math.sqrt(n * k / self.leaf_work)))))
        sample = rows if n <= branches * self.sample_per_branch else rng.choice(rows, branches * self.sample_per_branch, replace=False)
        sample = np.sort(sample)
        centres = _kmeans(x[sample], branches, rng, self.n_iter, self.init)
        branch_of = _nearest(x[rows], centres)
        counts = np.bincount(branch_of, minlength=branches)
        if counts.max() == n:  # (near-)identical rows: no split possible, use a smaller leaf
            return self._leaf(x, rows, max(1, self.leaf_work // n), rng, leaves)
        budget = _share(counts, k)
        node = _Node(centres=centres)
        for b in np.flatnonzero(counts):
            node.children.append(self._build(x, rows[branch_of == b], int(budget[b]), rng, leaves))
        node.centres = centres[counts > 0]
        return node

    def _leaf(self, x: np.ndarray, rows: np.ndarray, k: int, rng: np.random.Generator, leaves: list[_Node]) -> _Node:
        identity = k >= rows.size
        centres = x[rows] if identity else _kmeans(x[rows], k, rng, self.n_iter, self.init)
        leaf = _Node(size=centres.shape[0], centres=centres, members=rows, identity=identity)
        leaves.append(leaf)
        self._bar.update(rows.size)
        return leaf

    def _set_codebook(self, codes: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
        self.codes_, self.lo_, self.hi_ = codes, lo, hi
        self.codebook_ = _dequantize_codebook(codes, lo, hi, self.centroid_bits)

    # ------------------------------------------------------------ transform
    def transform(self, ac: np.ndarray) -> np.ndarray:
        """(N, K') -> labels (N, 1) as floats: nearest codebook entry (down the tree when fitted here)."""
        self._check_fitted()
        x = np.ascontiguousarray(check_ac_matrix(ac, self.codebook_.shape[1]), dtype=np.float32)
        labels = np.empty(x.shape[0], dtype=np.int64)
        if self._tree is None:  # rebuilt from a state: exact search over the whole codebook
            labels[:] = _nearest(x, self.codebook_)
        else:
            self._descend(self._tree, x, np.arange(x.shape[0]), labels)
        return labels.astype(np.float64)[:, None]

    def _descend(self, node: _Node, x: np.ndarray, rows: np.ndarray, labels: np.ndarray) -> None:
        if not node.children:
            block = self.codebook_[node.offset : node.offset + node.size]
            labels[rows] = node.offset + _nearest(x[rows], block)
            return
        branch_of = _nearest(x[rows], node.centres)
        for b, child in enumerate(node.children):
            picked = rows[branch_of == b]
            if picked.size:
                self._descend(child, x, picked, labels)

    def inverse_transform(self, features: np.ndarray) -> np.ndarray:
        """Labels (N, 1) -> codebook rows (N, K') as float32."""
        self._check_fitted()
        return lookup_labels(self.codebook_, features, self.name)

    # ---------------------------------------------------------------- sizes
    @property
    def n_features(self) -> int:
        return 1

    @property
    def feature_bits(self) -> int:
        """Bits per label: ceil(log2 K) (16 for 65,536 entries), at least 1."""
        self._check_fitted()
        return max(1, int(self.codebook_.shape[0] - 1).bit_length())

    def state(self) -> StageState:
        self._check_fitted()
        params = {"centroid_bits": self.centroid_bits, "n_clusters": int(self.codes_.shape[0]), "n_columns": int(self.codes_.shape[1])}
        return StageState(self.name, params, {"codes": self.codes_, "lo": self.lo_, "hi": self.hi_})

    @classmethod
    def from_state(cls, state: StageState) -> "VectorQuantizer":
        try:
            bits = int(state.params["centroid_bits"])
            k, d = int(state.params["n_clusters"]), int(state.params["n_columns"])
            codes, lo, hi = state.arrays["codes"], state.arrays["lo"], state.arrays["hi"]
        except (KeyError, TypeError, ValueError):
            raise GscodecError("vq state is incomplete (needs centroid_bits, n_clusters, n_columns, codes, lo, hi)") from None
        if not 1 <= bits <= 16 or codes.shape != (k, d) or lo.shape != (d,) or hi.shape != (d,) or k < 1:
            raise GscodecError("vq state is inconsistent (codebook shape or bit depth)")
        if not np.issubdtype(codes.dtype, np.unsignedinteger) or (codes.size and int(codes.max()) >= 1 << bits):
            raise GscodecError(f"vq state codebook holds values above {bits} bits")
        stage = cls(n_clusters=k, centroid_bits=bits)
        stage._set_codebook(codes, lo.astype(np.float32), hi.astype(np.float32))
        return stage

    def _check_fitted(self) -> None:
        if self.codebook_ is None:
            raise GscodecError("vq stage is not fitted: call fit() first")

    def __repr__(self) -> str:
        k = "unfitted" if self.codebook_ is None else f"K={self.codebook_.shape[0]}"
        return f"VectorQuantizer({k}, centroid_bits={self.centroid_bits})"


# ------------------------------------------------------------------ k-means
def _kmeans(x: np.ndarray, k: int, rng: np.random.Generator, n_iter: int, init: str) -> np.ndarray:
    """Lloyd's k-means on (n, D) float32 rows; empty clusters keep their centre."""
    n = x.shape[0]
    if k >= n:
        return x.copy()
    centres = _kmeanspp(x, k, rng) if init == "kmeans++" else x[np.sort(rng.choice(n, k, replace=False))].copy()
    for _ in range(n_iter):
        labels = _nearest(x, centres)
        counts = np.bincount(labels, minlength=k)
        order = np.argsort(labels, kind="stable")
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        filled = counts > 0
        sums = np.add.reduceat(x[order].astype(np.float64), starts[filled], axis=0)
        centres[filled] = (sums / counts[filled, None]).astype(np.float32)
    return centres


def _kmeanspp(x: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding (D^2 sampling)."""
    n = x.shape[0]
    chosen = [int(rng.integers(n))]
    best = ((x - x[chosen[0]]) ** 2).sum(axis=1, dtype=np.float64)
    for _ in range(1, k):
        total = best.sum()
        pick = int(rng.integers(n)) if total <= 0 else int(np.searchsorted(np.cumsum(best), rng.random() * total))
        pick = min(pick, n - 1)
        chosen.append(pick)
        np.minimum(best, ((x - x[pick]) ** 2).sum(axis=1, dtype=np.float64), out=best)
    return x[chosen].copy()


def _nearest(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Index of the nearest centre (squared Euclidean) for each row, in row blocks."""
    half_norms = 0.5 * np.einsum("ij,ij->i", centres, centres, dtype=np.float32)
    out = np.empty(x.shape[0], dtype=np.int64)
    step = max(1, _BLOCK_CELLS // max(1, centres.shape[0]))
    for start in range(0, x.shape[0], step):
        scores = x[start : start + step] @ centres.T
        np.subtract(half_norms, scores, out=scores)
        out[start : start + step] = scores.argmin(axis=1)
    return out


def _share(counts: np.ndarray, k: int) -> np.ndarray:
    """Split ``k`` centres among branches in proportion to ``counts`` (>= 1 and <= count each)."""
    counts = counts.astype(np.int64)
    target = counts * (k / counts.sum())
    alloc = np.where(counts > 0, np.clip(np.floor(target), 1, counts), 0).astype(np.int64)
    while alloc.sum() < k:  # add where the shortfall is largest and room is left
        room = np.where(alloc < counts, target - alloc, -np.inf)
        alloc[int(np.argmax(room))] += 1
    while alloc.sum() > k:  # take where the surplus is largest, keeping one each
        surplus = np.where(alloc > 1, alloc - target, -np.inf)
        alloc[int(np.argmax(surplus))] -= 1
    return alloc


def _quantize_codebook(centres: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-dimension min/max ``bits``-bit codes of the centres."""
    lo = centres.min(axis=0).astype(np.float32)
    hi = centres.max(axis=0).astype(np.float32)
    levels = (1 << bits) - 1
    span = hi.astype(np.float64) - lo
    scale = np.where(span > 0, levels / np.where(span > 0, span, 1.0), 0.0)
    codes = np.clip(np.rint((centres - lo) * scale), 0, levels)
    return codes.astype(np.uint8 if bits <= 8 else np.uint16), lo, hi


def _dequantize_codebook(codes: np.ndarray, lo: np.ndarray, hi: np.ndarray, bits: int) -> np.ndarray:
    step = (hi.astype(np.float64) - lo) / ((1 << bits) - 1)
    return (lo + codes.astype(np.float64) * step).astype(np.float32)


def lookup_labels(codebook: np.ndarray, features: np.ndarray, stage: str) -> np.ndarray:
    """Codebook rows for a label column (N, 1), checking the labels are integers in range."""
    features = np.asarray(features)
    if features.ndim != 2 or features.shape[1] != 1:
        raise ValidationError(f"{stage} features must be one label column (N, 1), got shape {features.shape}")
    labels = features[:, 0]
    if not np.isfinite(labels).all() or np.any(labels != np.round(labels)):
        raise ValidationError(f"{stage} labels must be integers")
    labels = labels.astype(np.int64)
    if labels.size and (labels.min() < 0 or labels.max() >= codebook.shape[0]):
        raise ValidationError(f"{stage} labels must lie in 0..{codebook.shape[0] - 1}")
    return codebook[labels]
