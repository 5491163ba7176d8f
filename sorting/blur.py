"""Wide, nearly flat blurs whose cost does not depend on the radius.

PLAS's target is a Gaussian blur whose sigma equals its kernel size, so the
weights over the window fall only from 1 to ~0.88. A weight ``alpha - beta*d**2``
(fitted by least squares to that Gaussian) matches it to ~1e-3 and can be
slid along a line with three running sums (of f, d*f, d**2*f): O(1) per cell
for any radius.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

BORDERS = {"reflect": 0, "circular": 1}


def quadratic_weights(half: int, sigma: float) -> tuple[float, float]:
    """``(alpha, beta)`` of the normalised weights ``alpha - beta*d**2``, ``|d| <= half``.

    Least-squares fit to the normalised Gaussian ``exp(-d**2 / (2 sigma**2))``
    over the window; exact for ``half <= 1``.
    """
    d = np.arange(-half, half + 1, dtype=np.float64)
    g = np.exp(-(d * d) / (2.0 * sigma * sigma))
    g /= g.sum()
    design = np.stack([np.ones_like(d), -(d * d)], axis=1)
    (alpha, beta), *_ = np.linalg.lstsq(design, g, rcond=None)
    return float(alpha), float(beta)


@njit(cache=True, inline="always")
def _src_index(j: int, n: int, circular: int) -> int:
    if circular:
        j = j % n
        return j + n if j < 0 else j
    if j < 0:
        return -j
    if j >= n:
        return 2 * (n - 1) - j
    return j


@njit(cache=True, fastmath=True)
def _blur_line(src, dst, base, line_len, step, half, alpha, beta, circular):
    """Blur one line: cell ``i`` is row ``base + i*step`` of the (cells, K) arrays."""
    k = src.shape[1]
    s0 = np.zeros(k, dtype=np.float64)
    s1 = np.zeros(k, dtype=np.float64)
    s2 = np.zeros(k, dtype=np.float64)
    for d in range(-half, half + 1):
        row = base + _src_index(d, line_len, circular) * step
        for c in range(k):
            v = src[row, c]
            s0[c] += v
            s1[c] += d * v
            s2[c] += d * d * v
    h1 = half + 1
    for i in range(line_len):
        out = base + i * step
        for c in range(k):
            dst[out, c] = alpha * s0[c] - beta * s2[c]
        if i + 1 == line_len:
            break
        # re-centre on i + 1, then drop cell i - half and add cell i + half + 1
        r_old = base + _src_index(i - half, line_len, circular) * step
        r_new = base + _src_index(i + half + 1, line_len, circular) * step
        for c in range(k):
            a0 = s0[c]
            a1 = s1[c]
            v_old = src[r_old, c]
            v_new = src[r_new, c]
            s2[c] += -2.0 * a1 + a0 - h1 * h1 * v_old + half * half * v_new
            s1[c] = a1 - a0 + h1 * v_old + half * v_new
            s0[c] = a0 - v_old + v_new


@njit(parallel=True, cache=True)
def _blur_lines_parallel(src, dst, n_lines, line_len, line_stride, step, half, alpha, beta, circular):
    for line in prange(n_lines):
        _blur_line(src, dst, line * line_stride, line_len, step, half, alpha, beta, circular)


@njit(cache=True)
def _blur_lines_serial(src, dst, n_lines, line_len, line_stride, step, half, alpha, beta, circular):
    for line in range(n_lines):
        _blur_line(src, dst, line * line_stride, line_len, step, half, alpha, beta, circular)


#: Grids with at least this many cells are blurred on all threads.
PARALLEL_CELLS = 65536


def blur_grid(
    cells: np.ndarray,
    shape: tuple[int, int],
    size_y: int,
    size_x: int,
    border_y: str = "reflect",
    border_x: str = "reflect",
    *,
    out: np.ndarray | None = None,
    tmp: np.ndarray | None = None,
) -> np.ndarray:
    """Separable near-Gaussian blur of (H*W, K) float32 cells; kernel sizes odd, sigma = size.

    ``out`` / ``tmp``: (H*W, K) float32 buffers for the result and the row pass, for a caller that
    blurs many times (no fresh pages per blur).
    """
    h, w = shape
    tmp = np.empty_like(cells) if tmp is None else tmp
    out = np.empty_like(cells) if out is None else out
    half_x, half_y = size_x // 2, size_y // 2
    ax, bx = quadratic_weights(half_x, float(size_x))
    ay, by = quadratic_weights(half_y, float(size_y))
    lines = _blur_lines_parallel if h * w >= PARALLEL_CELLS else _blur_lines_serial
    lines(cells, tmp, h, w, w, 1, half_x, ax, bx, BORDERS[border_x])
    # columns in strips of s adjacent cells: each step along a column reads s*K contiguous floats
    s = max(d for d in (8, 4, 2, 1) if w % d == 0)
    k = cells.shape[1]
    strip_in = tmp.reshape(h * (w // s), s * k)
    strip_out = out.reshape(h * (w // s), s * k)
    lines(strip_in, strip_out, w // s, h, 1, w // s, half_y, ay, by, BORDERS[border_y])
    return out
