"""Bjontegaard delta metrics: BD-rate and BD-PSNR of one RD curve against an anchor.

The curves are compared the way MPEG's and VCEG's reference implementations do with
piecewise-cubic interpolation: each curve is a monotone piecewise-cubic Hermite
interpolant (PCHIP, :class:`scipy.interpolate.PchipInterpolator`) through its points,

* **BD-rate**: log10(rate) as a function of quality; the mean horizontal gap over the
  quality interval both curves cover, ``(10 ** mean_gap - 1) * 100`` percent
  (negative = fewer bytes for the same quality);
* **BD-PSNR** (BD-quality): quality as a function of log10(rate); the mean vertical gap
  over the log-rate interval both curves cover (positive = better quality).

The integrals are exact integrals of the interpolants (PCHIP's antiderivative), not
sampled sums. Points are sorted by the abscissa; points repeating an abscissa are averaged.

Both metrics are computed on each curve's **monotone hull** (:func:`monotone_hull`): the
points whose quality exceeds that of every cheaper point. A point costing more bytes for no
better quality is dominated, and keeping it would make quality-as-a-function-of-rate and
rate-as-a-function-of-quality two different curves (a non-monotone curve has no inverse),
so BD-rate and BD-PSNR could disagree in sign for a curve that lies above the anchor
everywhere. On monotone hulls, opposite signs only happen where the two curves cross
(the metrics integrate over different intervals); :func:`opposite_sign_reason` says so.
A curve needs at least two hull points (MPEG uses four); where there is no overlap, or
too few points, the result is NaN with a reason.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.interpolate import PchipInterpolator


@dataclass(frozen=True)
class BdResult:
    """A BD value (percent for BD-rate, quality units for BD-PSNR) and how it was obtained."""

    value: float
    overlap: tuple[float, float] | None = None  # integration interval
    monotonic: bool = True  # both curves had quality increasing with rate
    reason: str | None = None  # why ``value`` is NaN
    dropped: int = 0  # points left out of the two curves' monotone hulls

    @property
    def ok(self) -> bool:
        return math.isfinite(self.value)


def _curve(x: Sequence[float], y: Sequence[float], what: str) -> tuple[np.ndarray, np.ndarray] | str:
    """Sorted, de-duplicated finite (x, y) points, or the reason they are unusable."""
    xa, ya = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if xa.shape != ya.shape or xa.ndim != 1:
        return f"{what}: rates and qualities must be two equally long 1-D sequences"
    keep = np.isfinite(xa) & np.isfinite(ya)
    xa, ya = xa[keep], ya[keep]
    if xa.size == 0:
        return f"{what}: no finite points"
    ux, inverse = np.unique(xa, return_inverse=True)
    uy = np.bincount(inverse, weights=ya) / np.bincount(inverse)
    if ux.size < 2:
        return f"{what}: needs at least 2 distinct points, has {ux.size}"
    return ux, uy


def _is_monotonic(rate: np.ndarray, quality: np.ndarray) -> bool:
    keep = np.isfinite(rate) & np.isfinite(quality)
    rate, quality = rate[keep], quality[keep]
    order = np.argsort(rate, kind="stable")
    return bool(np.all(np.diff(quality[order]) > 0))


def monotone_hull(rate: Sequence[float], quality: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """The finite points whose quality is above that of every point with a lower rate.

    Sorted by rate; of points sharing a rate only the best one can survive. The result is
    strictly increasing in both rate and quality, so it is a function either way round.
    """
    r, q = np.asarray(rate, dtype=np.float64), np.asarray(quality, dtype=np.float64)
    keep = np.isfinite(r) & np.isfinite(q)
    r, q = r[keep], q[keep]
    order = np.lexsort((-q, r))  # by rate, best quality first within a rate
    hull_r: list[float] = []
    hull_q: list[float] = []
    for i in order:
        if not hull_q or (q[i] > hull_q[-1] and r[i] > hull_r[-1]):
            hull_r.append(float(r[i]))
            hull_q.append(float(q[i]))
    return np.asarray(hull_r), np.asarray(hull_q)


def _mean_gap(anchor: tuple[np.ndarray, np.ndarray], test: tuple[np.ndarray, np.ndarray]) -> tuple[float, tuple[float, float]] | str:
    """Mean of ``test(x) - anchor(x)`` over the common x interval, both PCHIP-interpolated."""
    lo = max(anchor[0][0], test[0][0])
    hi = min(anchor[0][-1], test[0][-1])
    if not hi > lo:
        return "the curves do not overlap"
    f_anchor = PchipInterpolator(*anchor, extrapolate=False)
    f_test = PchipInterpolator(*test, extrapolate=False)
    gap = (f_test.integrate(lo, hi) - f_anchor.integrate(lo, hi)) / (hi - lo)
    return float(gap), (float(lo), float(hi))


def _positive_rates(rate: Sequence[float], what: str) -> np.ndarray | str:
    r = np.asarray(rate, dtype=np.float64)
    if np.any(r[np.isfinite(r)] <= 0):
        return f"{what}: rates must be positive"
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log10(r)


def bd_rate(
    anchor_rate: Sequence[float], anchor_quality: Sequence[float],
    test_rate: Sequence[float], test_quality: Sequence[float],
) -> BdResult:
    """BD-rate (percent) of the test curve against the anchor (negative = saves bytes)."""
    result = _bjontegaard(anchor_rate, anchor_quality, test_rate, test_quality, rate_axis=True)
    if math.isnan(result.value):
        return result
    return dataclasses.replace(result, value=(10.0 ** result.value - 1.0) * 100.0)


def bd_quality(
    anchor_rate: Sequence[float], anchor_quality: Sequence[float],
    test_rate: Sequence[float], test_quality: Sequence[float],
) -> BdResult:
    """BD-PSNR (or BD-SSIM): mean quality gain of the test curve at equal rate."""
    return _bjontegaard(anchor_rate, anchor_quality, test_rate, test_quality, rate_axis=False)


def _bjontegaard(
    anchor_rate: Sequence[float], anchor_quality: Sequence[float],
    test_rate: Sequence[float], test_quality: Sequence[float], *, rate_axis: bool,
) -> BdResult:
    """Mean gap between the two PCHIP curves: of log10 rate over the common quality range
    (``rate_axis``) or of quality over the common log-rate range."""
    monotonic = _is_monotonic(np.asarray(anchor_rate, float), np.asarray(anchor_quality, float)) and _is_monotonic(
        np.asarray(test_rate, float), np.asarray(test_quality, float)
    )
    log_a, log_t = _positive_rates(anchor_rate, "anchor"), _positive_rates(test_rate, "test")
    for item in (log_a, log_t):
        if isinstance(item, str):
            return BdResult(math.nan, reason=item)
    n_points = int(np.sum(np.isfinite(log_a) & np.isfinite(np.asarray(anchor_quality, float))))
    n_points += int(np.sum(np.isfinite(log_t) & np.isfinite(np.asarray(test_quality, float))))
    log_a, anchor_quality = monotone_hull(log_a, anchor_quality)
    log_t, test_quality = monotone_hull(log_t, test_quality)
    dropped = n_points - log_a.size - log_t.size
    if rate_axis:
        anchor, test = _curve(anchor_quality, log_a, "anchor"), _curve(test_quality, log_t, "test")
    else:
        anchor, test = _curve(log_a, anchor_quality, "anchor"), _curve(log_t, test_quality, "test")
    for item in (anchor, test):
        if isinstance(item, str):
            return BdResult(math.nan, reason=item.replace("distinct points", "points on its monotone hull"),
                            monotonic=monotonic, dropped=dropped)
    gap = _mean_gap(anchor, test)
    if isinstance(gap, str):
        return BdResult(math.nan, reason=gap, monotonic=monotonic, dropped=dropped)
    return BdResult(gap[0], gap[1], monotonic, dropped=dropped)


def opposite_sign_reason(rate: BdResult, quality: BdResult) -> str | None:
    """Why BD-rate and BD-quality disagree (more bytes yet better quality, or the reverse), or None.

    On monotone hulls a curve above the anchor over the whole common rate range also needs
    fewer bytes at every common quality, so a disagreement means the curves cross: the
    two metrics average over different intervals (quality vs log-rate) and each sees more
    of one side of the crossing.
    """
    if not (rate.ok and quality.ok) or rate.value == 0 or quality.value == 0:
        return None
    if (rate.value < 0) == (quality.value > 0):
        return None
    return ("BD-rate and BD-quality disagree in sign: the curves cross, and BD-rate averages over the common "
            "quality range while BD-quality averages over the common rate range")


#: BD-PSNR is BD-quality with PSNR as the quality.
bd_psnr = bd_quality
