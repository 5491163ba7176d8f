"""numba kernels of the sort's preparation (features, Morton start, cell vectors) on all threads.

Each computes exactly what the numpy code it replaces computes (the same float64 operations in the
same order per element; minima and maxima do not depend on the order), only without the temporary
arrays and on all threads: at 1M Gaussians the numpy preparation was ~1 s on one thread while the
other core waited. Used from ``sorting.grid.PARALLEL_ROWS`` rows on (``features.py``, ``morton.py``, ``plas.py``).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

#: Rows per parallel task.
ROWS = 16384


@njit(parallel=True, cache=True)
def column_ranges(x):
    """Per column of (N, k) ``x``: (min, max) as float64, and whether every value is finite."""
    n, k = x.shape
    tasks = (n + ROWS - 1) // ROWS
    lo = np.empty((tasks, k))
    hi = np.empty((tasks, k))
    bad = np.zeros(tasks, dtype=np.int64)
    for t in prange(tasks):
        for j in range(k):
            lo[t, j] = np.inf
            hi[t, j] = -np.inf
        for i in range(t * ROWS, min(n, (t + 1) * ROWS)):
            for j in range(k):
                v = np.float64(x[i, j])
                if not np.isfinite(v):
                    bad[t] += 1
                if v < lo[t, j]:
                    lo[t, j] = v
                if v > hi[t, j]:
                    hi[t, j] = v
    out_lo = np.empty(k)
    out_hi = np.empty(k)
    for j in range(k):
        out_lo[j] = lo[:, j].min()
        out_hi[j] = hi[:, j].max()
    return out_lo, out_hi, bad.sum() == 0


@njit(parallel=True, cache=True)
def scale_into(out, col, x, lo, scale, weight):
    """``out[:, col:col+k] = float32(((x - lo) / scale) * weight)``, computed in float64 (as numpy would)."""
    n, k = x.shape
    for t in prange((n + ROWS - 1) // ROWS):
        for i in range(t * ROWS, min(n, (t + 1) * ROWS)):
            for j in range(k):
                out[i, col + j] = np.float32(((np.float64(x[i, j]) - lo[j]) / scale) * weight)


@njit(parallel=True, cache=True)
def zorder_codes(pts, lo, span, bits):
    """Z-order codes of (N, d) ``pts``: each column quantised as
    ``clip(rint((p - lo) / span * levels), 0, levels)`` and bit ``b`` of column ``c`` put at ``b * d + c``."""
    n, d = pts.shape
    levels = np.float64((1 << bits) - 1)
    codes = np.zeros(n, dtype=np.uint64)
    for t in prange((n + ROWS - 1) // ROWS):
        for i in range(t * ROWS, min(n, (t + 1) * ROWS)):
            code = np.uint64(0)
            for c in range(d):
                v = np.rint((np.float64(pts[i, c]) - lo[c]) / span[c] * levels)
                v = min(max(v, 0.0), levels)
                q = np.uint64(v)
                for b in range(bits):
                    code |= ((q >> np.uint64(b)) & np.uint64(1)) << np.uint64(b * d + c)
            codes[i] = code
    return codes


@njit(parallel=True, cache=True)
def scatter_centred(feat, cells, x, mean):
    """``feat[cells[i], j] = float32(float64(x[i, j]) - mean[j])`` and the item flag (channel K-2) set to 1."""
    n, c = x.shape
    flag = feat.shape[1] - 2
    for t in prange((n + ROWS - 1) // ROWS):
        for i in range(t * ROWS, min(n, (t + 1) * ROWS)):
            row = cells[i]
            for j in range(c):
                feat[row, j] = np.float32(np.float64(x[i, j]) - mean[j])
            feat[row, flag] = 1.0


@njit(cache=True, inline="always")
def _squared_norm(x, row):
    """``einsum("ij,ij->i")`` of one row of (N, K) float32, K a multiple of 4, summed as numpy's 4-lane
    kernel sums it: lanes ``c % 4`` over blocks of 16 channels (last first) then 4, then lanes (0+1)+(2+3)."""
    k = x.shape[1]
    a0 = a1 = a2 = a3 = np.float32(0.0)
    c = 0
    while c + 16 <= k:
        for q in (12, 8, 4, 0):
            a0 += x[row, c + q] * x[row, c + q]
            a1 += x[row, c + q + 1] * x[row, c + q + 1]
            a2 += x[row, c + q + 2] * x[row, c + q + 2]
            a3 += x[row, c + q + 3] * x[row, c + q + 3]
        c += 16
    while c < k:
        a0 += x[row, c] * x[row, c]
        a1 += x[row, c + 1] * x[row, c + 1]
        a2 += x[row, c + 2] * x[row, c + 2]
        a3 += x[row, c + 3] * x[row, c + 3]
        c += 4
    return (a0 + a1) + (a2 + a3)


@njit(parallel=True, cache=True)
def finish_target(blurred, divide):
    """``plas.finish_target`` in place on all threads: with ``divide`` each row divided by its item
    weight (channel K-2; a row whose weight is at most float32(1e-6) zeroed), then channels K-2 and K-1
    zeroed and channel K-1 set to the row's squared norm."""
    n, k = blurred.shape
    tiny = np.float32(1e-6)
    for t in prange((n + ROWS - 1) // ROWS):
        for i in range(t * ROWS, min(n, (t + 1) * ROWS)):
            if divide:
                weight = blurred[i, k - 2]
                if weight > tiny:
                    for j in range(k):
                        blurred[i, j] = blurred[i, j] / weight
                else:
                    for j in range(k):
                        blurred[i, j] = 0.0
            blurred[i, k - 2] = 0.0
            blurred[i, k - 1] = 0.0
            blurred[i, k - 1] = _squared_norm(blurred, i)
