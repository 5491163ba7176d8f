"""Low-rank analysis of the SH AC matrix (paper Sec. IV-B, Table I, Fig. 1).

Everything is computed from K' x K' second moments accumulated in float64 over
row chunks (:func:`column_moments`), never from an N x K' SVD, so a 1M-Gaussian
scene costs one pass over its AC matrix.

Two different "energies" appear in Table I and are easy to confuse:

* **SVD column** ("SVD singu."): singular values ``s_k`` of the *standardised*
  matrix A' (eq. 23, 25); ``ER(r)`` of eq. 26. :func:`svd_energy_curve`.
* **Truncation column** ("SHAC coeff."): the share of energy held by the first
  ``k`` AC columns in degree order, i.e. what a degree truncation keeps. On A'
  every column has energy N-1, so this is exactly k/K' for every scene
  (53.3% at k = 24, rank 43 at 95%) and cannot be what the paper tabulates
  (its values vary by scene: 43-44 and 49-56.5%). We therefore report it on
  the *raw* coefficients (``mode="raw"``: plain sum of squares, the energy a
  truncation actually discards, since it zeroes the dropped coefficients) and,
  for comparison, on mean-centred ones (``"centred"``) and on A'
  (``"standardized"``). :func:`truncation_energy_curve`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np

from gscodec_shac.errors import ValidationError
from gscodec_shac.shac.base import check_ac_matrix

EnergyMode = Literal["raw", "centred", "standardized"]
_MODES = ("raw", "centred", "standardized")
#: Slack when comparing a cumulative energy with a target (float64 round-off).
ER_TOLERANCE = 1e-12
#: Rows per chunk when accumulating moments (bounds the float64 copy to ~100 MB).
DEFAULT_CHUNK = 262_144


@dataclass
class ColumnMoments:
    """First and second moments of an (N, K) matrix, all float64.

    ``mean`` (K,), ``scatter`` = (X - 1 mean^T)^T (X - 1 mean^T) (K, K), and
    ``raw_gram`` = X^T X (K, K).
    """

    n: int
    mean: np.ndarray
    scatter: np.ndarray
    raw_gram: np.ndarray

    def std(self) -> np.ndarray:
        """Column standard deviations with the 1/(N-1) of eq. 24 (0 when N < 2)."""
        if self.n < 2:
            return np.zeros_like(self.mean)
        return np.sqrt(np.clip(np.diag(self.scatter), 0.0, None) / (self.n - 1))


def column_moments(x: np.ndarray, chunk: int = DEFAULT_CHUNK) -> ColumnMoments:
    """One float64 pass over ``x``: mean, centred scatter and raw Gram matrix.

    The rows are shifted by the mean of the first chunk before accumulating, so
    the centred scatter does not suffer from cancellation when |mean| >> std.
    """
    x = check_ac_matrix(x)
    n, k = x.shape
    if n == 0:
        raise ValidationError("the matrix has no rows (no Gaussians)")
    shift = x[: min(n, chunk)].mean(axis=0, dtype=np.float64)
    sums = np.zeros(k)
    gram = np.zeros((k, k))
    buffer = np.empty((min(n, chunk), k))
    for start in range(0, n, chunk):
        block = x[start : start + chunk]
        y = np.subtract(block, shift, out=buffer[: len(block)])  # float64, one allocation in all
        sums += y.sum(axis=0)
        gram += y.T @ y
    d = sums / n  # mean of the shifted rows
    scatter = gram - n * np.outer(d, d)
    raw = gram + n * (np.outer(shift, d) + np.outer(d, shift) + np.outer(shift, shift))
    scatter = (scatter + scatter.T) / 2
    raw = (raw + raw.T) / 2
    return ColumnMoments(n=n, mean=shift + d, scatter=scatter, raw_gram=raw)


def safe_scale(std: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """Standard deviations for eq. 23 with (numerically) constant columns mapped to 1.

    A column whose std is below 1e-12 (1 + |mean|) carries no variance; dividing
    by its round-off-sized std would inflate noise, dividing by 0 gives NaN.
    """
    scale = np.array(std, dtype=np.float64, copy=True)
    scale[scale <= 1e-12 * (1.0 + np.abs(mean))] = 1.0
    return scale


def standardize(ac: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 23: A' = (A - 1 mu^T) D_sigma^-1; returns (A', mu, sigma) in float64.

    Zero-variance columns get sigma = 1 (their A' column is 0, never NaN).
    """
    moments = column_moments(ac)
    scale = safe_scale(moments.std(), moments.mean)
    return (np.asarray(ac, dtype=np.float64) - moments.mean) / scale, moments.mean, scale


def correlation_matrix(ac: np.ndarray, moments: ColumnMoments | None = None) -> np.ndarray:
    """Eq. 24: Pearson correlation C = A'^T A' / (N - 1), shape (K', K').

    Entries involving a zero-variance column are undefined; they are returned as
    0 off the diagonal and 1 on it.
    """
    moments = moments or column_moments(ac)
    std = np.sqrt(np.clip(np.diag(moments.scatter), 0.0, None))
    live = std > 1e-12 * (1.0 + np.abs(moments.mean)) * max(np.sqrt(moments.n), 1.0)
    denom = np.outer(std, std)
    corr = np.zeros_like(moments.scatter)
    both = np.outer(live, live)
    corr[both] = moments.scatter[both] / denom[both]
    np.fill_diagonal(corr, 1.0)
    return np.clip(corr, -1.0, 1.0)


def correlation_groups(corr: np.ndarray) -> dict[str, float]:
    """Mean |C| over column pairs grouped as in the paper's Fig. 1 observations.

    ``rgb``: the R, G, B of one (l, m) (inter-component); ``same_order``: one
    channel, same m, different l (intra-order); ``other_order``: one channel,
    different m. Columns are in paper order (3 per (l, m)).
    """
    n = corr.shape[0]
    k = np.arange(n) // 3 + 1  # SH coefficient index of each column
    l = np.floor(np.sqrt(k)).astype(int)
    m = k - l * l - l
    channel = np.arange(n) % 3
    i, j = np.triu_indices(n, 1)
    groups = {
        "rgb": (k[i] == k[j]),
        "same_order": (channel[i] == channel[j]) & (m[i] == m[j]) & (l[i] != l[j]),
        "other_order": (channel[i] == channel[j]) & (m[i] != m[j]),
    }
    values = np.abs(corr[i, j])
    return {name: float(values[mask].mean()) if mask.any() else float("nan") for name, mask in groups.items()}


def standardized_scatter(moments: ColumnMoments) -> np.ndarray:
    """A'^T A' (eq. 23) from the moments; its eigenvalues are the s_k^2 of eq. 25."""
    scale = safe_scale(moments.std(), moments.mean)
    return moments.scatter / np.outer(scale, scale)


def squared_singular_values(
    ac: np.ndarray, mode: EnergyMode = "standardized", moments: ColumnMoments | None = None
) -> np.ndarray:
    """s_k^2 (descending) of A' (eq. 25) or of the centred / raw matrix."""
    _check_mode(mode)
    moments = moments or column_moments(ac)
    matrix = {
        "standardized": standardized_scatter,
        "centred": lambda m: m.scatter,
        "raw": lambda m: m.raw_gram,
    }[mode](moments)
    return np.clip(np.linalg.eigvalsh(matrix)[::-1], 0.0, None)


def cumulative_energy(energies: np.ndarray) -> np.ndarray:
    """ER(r) for r = 1..K (eq. 26) of non-negative energies in the order given.

    An all-zero input (nothing to retain) gives a curve of ones.
    """
    energies = np.asarray(energies, dtype=np.float64)
    total = energies.sum()
    if total <= 0:
        return np.ones_like(energies)
    return np.cumsum(energies) / total


def svd_energy_curve(
    ac: np.ndarray, mode: EnergyMode = "standardized", moments: ColumnMoments | None = None
) -> np.ndarray:
    """Eq. 26: cumulative energy retention of the singular values (Table I, "SVD singu.")."""
    return cumulative_energy(squared_singular_values(ac, mode, moments))


def column_energies(ac: np.ndarray, mode: EnergyMode = "raw", moments: ColumnMoments | None = None) -> np.ndarray:
    """Energy (sum of squares) of each AC column, raw, mean-centred or standardised."""
    _check_mode(mode)
    moments = moments or column_moments(ac)
    if mode == "raw":
        return np.clip(np.diag(moments.raw_gram).copy(), 0.0, None)
    if mode == "centred":
        return np.clip(np.diag(moments.scatter).copy(), 0.0, None)
    return np.clip(np.diag(standardized_scatter(moments)).copy(), 0.0, None)


def truncation_energy_curve(
    ac: np.ndarray, mode: EnergyMode = "raw", moments: ColumnMoments | None = None
) -> np.ndarray:
    """Energy kept by the first k AC columns in degree order, k = 1..K' (Table I, "SHAC coeff.").

    The paper-order AC matrix is already sorted by degree (then order, then RGB),
    so truncation to degree L keeps a prefix of 3((L+1)^2 - 1) columns.
    """
    return cumulative_energy(column_energies(ac, mode, moments))


def rank_for_energy(curve: np.ndarray, target: float) -> int:
    """Smallest r with ER(r) >= target (eq. 26-27), up to :data:`ER_TOLERANCE`."""
    check_energy_target(target)
    curve = np.asarray(curve, dtype=np.float64)
    if curve.size == 0:
        raise ValidationError("the energy curve is empty (no AC columns)")
    hits = np.nonzero(curve >= target - ER_TOLERANCE)[0]
    return int(hits[0]) + 1 if hits.size else int(curve.size)


def energy_at(curve: np.ndarray, k: int) -> float:
    """ER(k): the energy share captured by the first k components or columns."""
    curve = np.asarray(curve)
    if not 1 <= k <= curve.size:
        raise ValidationError(f"k must be between 1 and {curve.size} (the number of AC columns), got {k}")
    return float(curve[k - 1])


def check_energy_target(target: float) -> float:
    """Validate an energy retention target in (0, 1]."""
    if not 0.0 < float(target) <= 1.0:
        raise ValidationError(f"energy retention must be in (0, 1], got {target}")
    return float(target)


def untouched_mask(ac: np.ndarray) -> np.ndarray:
    """Rows whose AC coefficients are all exactly zero (never trained at degree > 0)."""
    return ~np.any(np.asarray(ac) != 0, axis=1)


@dataclass
class TableRow:
    """One Table-I-style row; energies are fractions in [0, 1], ranks are counts.

    ``svd_*`` is the paper's "SVD singu." column (standardised A', eq. 25-26);
    ``trunc_raw_*`` is our reading of its "SHAC coeff." column (degree-order
    truncation on raw coefficients); ``trunc_centred_*`` and ``trunc_std_*`` are
    the alternative definitions, ``svd_centred_*`` is PCA without eq. 23.
    """

    scene: str
    n_gaussians: int
    n_untouched: int
    n_ac_columns: int
    er: float
    k: int
    svd_rank: int
    svd_energy: float
    trunc_raw_rank: int
    trunc_raw_energy: float
    trunc_centred_rank: int
    trunc_centred_energy: float
    trunc_std_rank: int
    trunc_std_energy: float
    svd_centred_rank: int
    svd_centred_energy: float
    degree_energy_raw: list[float] = field(default_factory=list)
    mean_abs_correlation: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


NUMERIC_FIELDS = (
    "n_gaussians", "n_untouched", "svd_rank", "svd_energy", "trunc_raw_rank", "trunc_raw_energy",
    "trunc_centred_rank", "trunc_centred_energy", "trunc_std_rank", "trunc_std_energy",
    "svd_centred_rank", "svd_centred_energy",
)


def table_row(scene: str, ac: np.ndarray, er: float = 0.95, k: int = 24, n_untouched: int | None = None) -> TableRow:
    """Rank at ``er`` and energy at ``k`` for every definition (Table I columns)."""
    check_energy_target(er)
    moments = column_moments(ac)
    n_cols = moments.mean.size
    if not 1 <= k <= n_cols:
        raise ValidationError(f"k must be between 1 and {n_cols} (the number of AC columns), got {k}")
    curves = {
        "svd": svd_energy_curve(ac, "standardized", moments),
        "svd_centred": svd_energy_curve(ac, "centred", moments),
        "trunc_raw": truncation_energy_curve(ac, "raw", moments),
        "trunc_centred": truncation_energy_curve(ac, "centred", moments),
        "trunc_std": truncation_energy_curve(ac, "standardized", moments),
    }
    values = {}
    for name, curve in curves.items():
        values[f"{name}_rank"] = rank_for_energy(curve, er)
        values[f"{name}_energy"] = energy_at(curve, k)
    if n_untouched is None:
        n_untouched = int(untouched_mask(ac).sum())
    return TableRow(
        scene=scene, n_gaussians=moments.n, n_untouched=n_untouched, n_ac_columns=n_cols, er=er, k=k,
        degree_energy_raw=degree_energy_shares(column_energies(ac, "raw", moments)),
        mean_abs_correlation=correlation_groups(correlation_matrix(ac, moments)), **values,
    )


def degree_energy_shares(energies: np.ndarray) -> list[float]:
    """Share of the energy per SH degree l = 1..L for per-column energies in paper order."""
    shares = []
    start, l = 0, 1
    total = float(np.sum(energies)) or 1.0
    while start < len(energies):
        width = 3 * (2 * l + 1)
        shares.append(float(np.sum(energies[start : start + width])) / total)
        start += width
        l += 1
    return shares


def row_degree(row: TableRow) -> int:
    """SH degree of a row's scene, from its AC column count (3 colours x ((d+1)^2 - 1))."""
    return int(round((row.n_ac_columns // 3 + 1) ** 0.5)) - 1


def average_row(rows: list[TableRow], label: str = "Average") -> dict:
    """The "Average" line of Table I: mean of every numeric column over scenes of one SH degree.

    Ranks and energies of different degrees are not comparable (the rank of a degree-1 scene
    is out of 9 columns, of a degree-3 scene out of 45), so mixing degrees is refused; see
    :func:`average_rows`.
    """
    if not rows:
        raise ValidationError("no rows to average")
    degrees = sorted({row_degree(r) for r in rows})
    if len(degrees) > 1:
        raise ValidationError(f"cannot average scenes of SH degrees {degrees} together: average per degree")
    out: dict = {"scene": label, "sh_degree": degrees[0], "n_scenes": len(rows), "er": rows[0].er, "k": rows[0].k}
    for name in NUMERIC_FIELDS:
        out[name] = float(np.mean([getattr(r, name) for r in rows]))
    return out


def average_rows(rows: list[TableRow]) -> list[dict]:
    """One average line per SH degree present, lowest degree first.

    A single degree gives the one line labelled "Average"; several give "Average (SH d)" lines.
    """
    if not rows:
        raise ValidationError("no rows to average")
    groups: dict[int, list[TableRow]] = {}
    for row in rows:
        groups.setdefault(row_degree(row), []).append(row)
    if len(groups) == 1:
        return [average_row(rows)]
    return [average_row(group, f"Average (SH {degree})") for degree, group in sorted(groups.items())]


def _check_mode(mode: str) -> None:
    if mode not in _MODES:
        raise ValidationError(f"energy mode must be one of {', '.join(_MODES)}, got {mode!r}")
