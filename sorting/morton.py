"""Morton (Z-order) sorting: points ordered by their Z-order code, laid out in 2-D Z-order.

The k-th point along the D-dimensional Z-order curve goes to the k-th cell along
the grid's own 2-D Z-order curve (not row-major), so that points close on the
curve stay close on the grid in both directions.
"""

from __future__ import annotations

import numpy as np

from sorting.errors import SortingError
from sorting.grid import PARALLEL_ROWS, check_shape

_CODE_BITS = 63


def morton_codes(points: np.ndarray) -> np.ndarray:
    """Z-order codes (uint64) of (N, D) points, each dimension min/max-quantised.

    ``min(21, 63 // D)`` bits per dimension (21 for 3-D, 4 for 14-D); only the
    first 63 columns count. The first column takes the lowest bit of each
    interleaved group.
    """
    pts = np.asarray(points)
    if pts.ndim == 1:
        pts = pts[:, None]
    n, d = pts.shape
    bits = min(21, _CODE_BITS // d) if d <= _CODE_BITS else 1
    if d > _CODE_BITS:
        pts = pts[:, :_CODE_BITS]
        d = _CODE_BITS
    if n >= PARALLEL_ROWS and pts.dtype in (np.float32, np.float64):
        return _codes_parallel(pts, bits)
    pts = pts.astype(np.float64)
    lo = pts.min(axis=0)
    span = pts.max(axis=0) - lo
    span[span <= 0] = 1.0
    levels = (1 << bits) - 1
    q = np.clip(np.rint((pts - lo) / span * levels), 0, levels).astype(np.uint64)
    codes = np.zeros(n, dtype=np.uint64)
    # Bit b of dimension j goes to bit b * d + j: per dimension, runs of up to 8 bits are
    # spread by a lookup table (a few whole-array passes instead of four per bit).
    for dim in range(d):
        for start in range(0, bits, 8):
            width = min(8, bits - start)
            part = q[:, dim] if width == bits else (q[:, dim] >> np.uint64(start)) & np.uint64((1 << width) - 1)
            codes |= _spread_table(width, start, d, dim)[part.astype(np.intp)]
    return codes


def _codes_parallel(pts: np.ndarray, bits: int) -> np.ndarray:
    """:func:`morton_codes` of many float rows on all threads (the same codes, no float64 copy)."""
    from sorting._prep import column_ranges, zorder_codes

    lo, hi, _ = column_ranges(pts)
    span = hi - lo
    span[span <= 0] = 1.0
    return zorder_codes(pts, lo, span, bits)


def _spread_table(width: int, start: int, d: int, dim: int) -> np.ndarray:
    """(2^width,) uint64: bit j of each index moved to bit (start + j) * d + dim."""
    values = np.arange(1 << width, dtype=np.uint64)
    table = np.zeros(1 << width, dtype=np.uint64)
    for j in range(width):
        table |= ((values >> np.uint64(j)) & np.uint64(1)) << np.uint64((start + j) * d + dim)
    return table


def grid_z_cells(shape: tuple[int, int]) -> np.ndarray:
    """Cell indices (row-major) of a grid visited in 2-D Z-order (ascending :func:`morton_codes_2d`).

    The Z-order codes of the smallest power-of-two square holding the grid are all the
    integers below its area, so counting through them and keeping the cells inside the
    grid lists the grid in Z-order without a sort (linear; the same cells as sorting the
    grid's codes). A grid much longer than wide, whose square is more than 4x its area,
    is sorted instead.
    """
    h, w = check_shape(shape)
    side = 1 << max(h - 1, w - 1).bit_length()
    if side * side > 4 * h * w:
        ys, xs = np.divmod(np.arange(h * w, dtype=np.int64), w)
        return np.argsort(morton_codes_2d(ys, xs), kind="stable")
    codes = np.arange(side * side, dtype=np.uint32 if side <= 1 << 16 else np.uint64)
    xs, ys = _compact_2d(codes), _compact_2d(codes >> codes.dtype.type(1))
    inside = (xs < w) & (ys < h)
    return ys[inside].astype(np.int64) * w + xs[inside]


def morton_codes_2d(ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """Interleave the bits of integer cell coordinates below 2**31 (x in the even bits)."""
    return _spread_2d(xs) | (_spread_2d(ys) << np.uint64(1))


def _compact_2d(x: np.ndarray) -> np.ndarray:
    """The even bits of each uint32 / uint64, packed (the inverse of :func:`_spread_2d`); same dtype."""
    t, wide = x.dtype.type, x.dtype == np.uint64
    x = x & t(0x5555555555555555 if wide else 0x55555555)
    for shift, mask in ((1, 0x3333333333333333), (2, 0x0F0F0F0F0F0F0F0F), (4, 0x00FF00FF00FF00FF),
                        (8, 0x0000FFFF0000FFFF), (16, 0x00000000FFFFFFFF)):
        if shift == 16 and not wide:
            break
        x = (x | (x >> t(shift))) & t(mask & (0xFFFFFFFFFFFFFFFF if wide else 0xFFFFFFFF))
    return x


def _spread_2d(v: np.ndarray) -> np.ndarray:
    """Bit i of each integer (< 2**32) at bit 2i (the 'part 1 by 1' of 2-D Morton codes)."""
    x = np.asarray(v).astype(np.uint64) & np.uint64(0xFFFFFFFF)
    for shift, mask in ((16, 0x0000FFFF0000FFFF), (8, 0x00FF00FF00FF00FF), (4, 0x0F0F0F0F0F0F0F0F),
                        (2, 0x3333333333333333), (1, 0x5555555555555555)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def morton_order(points: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Order (one row per cell, ``-1`` = empty) placing ``points`` (N, D) in Z-order on an (H, W) grid.

    Pass positions (N, 3) for the classic spatial Morton order; any (N, D)
    features work (with ``63 // D`` bits per dimension). Empty cells are the
    last ones along the grid's Z-order curve.
    """
    pts = np.asarray(points)
    if pts.ndim not in (1, 2) or pts.shape[0] == 0:
        raise SortingError(f"points must be a non-empty (N, D) array, got shape {pts.shape}")
    h, w = check_shape(shape)
    n = pts.shape[0]
    if n > h * w:
        raise SortingError(f"{n} points do not fit a {h}x{w} grid ({h * w} cells)")
    if not np.all(np.isfinite(pts)):
        raise SortingError("points contain NaN or infinite values")
    rows = np.argsort(morton_codes(pts), kind="stable")
    order = np.full(h * w, -1, dtype=np.int64)
    order[grid_z_cells((h, w))[:n]] = rows
    return order
