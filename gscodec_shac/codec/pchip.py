"""Monotone piecewise-cubic Hermite interpolation (PCHIP, Fritsch-Carlson) inside the data's range.

The rate controller's rate and error curves are PCHIP in log(y) between its probe QPs. This is
``scipy.interpolate.PchipInterpolator(x, y)(at)`` for ``at`` within ``[x[0], x[-1]]``: the same
derivatives (the weighted harmonic mean of the neighbouring slopes, zero at a local extremum, the
one-sided three-point estimate at the ends) and the same polynomial evaluated with the same
floating-point operations in the same order, so the values are equal bit for bit
(tests/test_pchip.py). Importing ``scipy.interpolate`` took about 0.3 s of every target run.
"""

from __future__ import annotations

import numpy as np


def pchip(x: np.ndarray, y: np.ndarray, at: np.ndarray) -> np.ndarray:
    """The PCHIP curve through ``(x, y)`` (``x`` increasing, at least three points) at ``at`` (within
    ``[x[0], x[-1]]``)."""
    x, y, at = (np.asarray(v, dtype=np.float64) for v in (x, y, at))
    if x.ndim != 1 or x.shape != y.shape or x.size < 3 or not np.all(np.diff(x) > 0):
        raise ValueError("pchip needs at least three points with increasing x")
    if np.any(at < x[0]) or np.any(at > x[-1]):
        raise ValueError("pchip evaluates inside the data's range only")
    h = np.diff(x)
    slope = np.diff(y) / h
    d = _derivatives(h, slope)
    t = (d[:-1] + d[1:] - 2 * slope) / h
    c0, c1, c2, c3 = t / h, (slope - d[:-1]) / h - t, d[:-1], y[:-1]
    piece = np.clip(np.searchsorted(x, at, side="right") - 1, 0, x.size - 2)
    s = at - x[piece]
    # the power sum of scipy's PPoly evaluation: ((y + c2 s) + c1 s^2) + c0 s^3, s^3 as (s s) s
    s2 = s * s
    return ((0.0 + c3[piece]) + c2[piece] * s) + c1[piece] * s2 + c0[piece] * (s2 * s)


def _derivatives(h: np.ndarray, slope: np.ndarray) -> np.ndarray:
    """The derivative at each point: zero where the slopes around it change sign or one is zero, else
    their harmonic mean weighted by the interval lengths; the ends by :func:`_end_derivative`."""
    d = np.zeros(h.size + 1)
    sign = np.sign(slope)
    flat = (sign[1:] != sign[:-1]) | (slope[1:] == 0) | (slope[:-1] == 0)
    w1 = 2 * h[1:] + h[:-1]
    w2 = h[1:] + 2 * h[:-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = (w1 / slope[:-1] + w2 / slope[1:]) / (w1 + w2)
    inner = d[1:-1]
    inner[~flat] = 1.0 / mean[~flat]
    d[0] = _end_derivative(h[0], h[1], slope[0], slope[1])
    d[-1] = _end_derivative(h[-1], h[-2], slope[-1], slope[-2])
    return d


def _end_derivative(h0: float, h1: float, m0: float, m1: float) -> float:
    """The one-sided three-point derivative at an end, kept to the first slope's sign and to at most
    three times it where the slopes change sign."""
    d = ((2 * h0 + h1) * m0 - h0 * m1) / (h0 + h1)
    if np.sign(d) != np.sign(m0):
        return 0.0
    if np.sign(m0) != np.sign(m1) and abs(d) > 3.0 * abs(m0):
        return 3.0 * m0
    return d
