"""Grid shapes, selection of what fits, and moving values between rows and grid cells.

An *order* is an int64 array with one entry per grid cell (cells in row-major
order): ``order[cell]`` is the row placed in that cell, or ``-1`` for an empty
(padding) cell.
"""

from __future__ import annotations

import math

import numpy as np

from sorting.errors import SortingError

#: Inputs with at least this many rows are prepared for sorting by the numba kernels of
#: ``sorting/_prep.py`` (on all threads); smaller ones in numpy (the same values).
PARALLEL_ROWS = 65536
#: Widest allowed ratio of the long to the short grid side in :func:`grid_shape`.
MAX_ASPECT = 1.5


def _positive_int(value: object, name: str) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < 1:
        raise SortingError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def check_shape(shape: object) -> tuple[int, int]:
    """Validate a ``(H, W)`` grid shape and return it as two Python ints."""
    if not isinstance(shape, (tuple, list)) or len(shape) != 2:
        raise SortingError(f"a grid shape must be a pair (H, W), got {shape!r}")
    return _positive_int(shape[0], "grid height"), _positive_int(shape[1], "grid width")


def grid_shape(n: int, *, multiple: int = 8, policy: str = "pad", max_aspect: float = MAX_ASPECT) -> tuple[int, int]:
    """A near-square ``(H, W)`` for ``n`` rows, both sides multiples of ``multiple``.

    ``policy="pad"``: the smallest ``H*W >= n`` (empty cells are padding);
    ``policy="drop"``: the largest ``H*W <= n`` (drop the surplus, see
    :func:`select_for_grid`). The long side is at most ``max_aspect`` times the
    short one; ties go to the squarer shape, then to ``H <= W``.
    """
    n = _positive_int(n, "n")
    m = _positive_int(multiple, "multiple")
    if policy not in ("pad", "drop"):
        raise SortingError(f"policy must be 'pad' or 'drop', got {policy!r}")
    if not max_aspect >= 1.0:
        raise SortingError(f"max_aspect must be >= 1, got {max_aspect!r}")
    if policy == "drop" and n < m * m:
        raise SortingError(f"{n} rows do not fill even one {m}x{m} grid; use policy='pad'")
    side = math.isqrt(n)
    if policy == "pad":
        h_top = max(m, -(-side // m) * m + (m if side * side < n else 0))
    else:
        h_top = side // m * m
    best_key: tuple[int, int, int] | None = None
    best_shape = (h_top, h_top)
    for h in range(m, h_top + 1, m):  # h <= w; the transposed shape is never better
        if policy == "pad":
            w = max(h, -(-n // (h * m)) * m)
        else:
            w = min((n // h) // m * m, int(max_aspect * h) // m * m)
            if w < h:
                continue
        if w > max_aspect * h:
            continue
        key = (h * w if policy == "pad" else -h * w, w - h, h)
        if best_key is None or key < best_key:
            best_key, best_shape = key, (h, w)
    return best_shape


def select_for_grid(importance: np.ndarray, capacity: int) -> np.ndarray:
    """Indices (ascending) of the ``capacity`` most important rows.

    Ties are broken by row index (the earlier row wins), so the result is
    deterministic. Used with ``grid_shape(n, policy="drop")`` to drop the least
    important Gaussians (e.g. the least opaque) so the rest fill a grid.
    """
    imp = np.asarray(importance)
    if imp.ndim != 1:
        raise SortingError(f"importance must be one value per row (1-D), got shape {imp.shape}")
    if not np.issubdtype(imp.dtype, np.number) or np.issubdtype(imp.dtype, np.complexfloating):
        raise SortingError(f"importance must be real numbers, got dtype {imp.dtype}")
    if not np.all(np.isfinite(imp)):
        raise SortingError("importance contains NaN or infinite values")
    capacity = _positive_int(capacity, "capacity")
    if capacity >= imp.shape[0]:
        return np.arange(imp.shape[0], dtype=np.int64)
    ranked = np.argsort(-imp.astype(np.float64), kind="stable")
    return np.sort(ranked[:capacity]).astype(np.int64)


def check_order(order: np.ndarray, n: int | None = None) -> np.ndarray:
    """Validate an order (a permutation of ``0..n-1`` plus ``-1`` padding); return it as int64."""
    arr = np.asarray(order)
    if arr.ndim not in (1, 2) or arr.size == 0:
        raise SortingError(f"an order must be a non-empty 1-D (cells) or 2-D (H, W) array, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.integer):
        raise SortingError(f"an order must hold integers, got dtype {arr.dtype}")
    flat = arr.reshape(-1).astype(np.int64)
    filled = flat[flat >= 0]
    if n is None:
        n = int(filled.size)
    if np.any(flat < -1) or (filled.size and filled.max() >= n):
        raise SortingError(f"order entries must be -1 (empty) or row numbers 0..{n - 1}")
    if filled.size != n or np.bincount(filled, minlength=n).max(initial=0) > 1:
        raise SortingError(f"order must place each of the {n} rows in exactly one cell")
    return flat


def invert_order(order: np.ndarray, n: int | None = None) -> np.ndarray:
    """The cell index (row-major) of each row: the inverse of ``order``."""
    flat = check_order(order, n)
    cells = np.flatnonzero(flat >= 0)
    inverse = np.empty(cells.size, dtype=np.int64)
    inverse[flat[cells]] = cells
    return inverse


def _order_shape(order: np.ndarray, shape: tuple[int, int] | None) -> tuple[int, int]:
    arr = np.asarray(order)
    if shape is None:
        if arr.ndim == 2:
            return int(arr.shape[0]), int(arr.shape[1])
        raise SortingError("a 1-D order needs shape=(H, W) to form a grid (or pass order.reshape(H, W))")
    h, w = check_shape(shape)
    if h * w != arr.size:
        raise SortingError(f"order has {arr.size} cells but shape {h}x{w} has {h * w}")
    return h, w


def apply_order(
    values: np.ndarray, order: np.ndarray, fill: float = 0, *, shape: tuple[int, int] | None = None
) -> np.ndarray:
    """Place rows of ``values`` (N, ...) on the grid: returns (H, W, ...), empty cells = ``fill``.

    ``shape`` is needed when ``order`` is 1-D; a 2-D ``order`` carries it.
    """
    vals = np.asarray(values)
    if vals.ndim < 1:
        raise SortingError("values must have one row per Gaussian (at least 1-D)")
    h, w = _order_shape(order, shape)
    flat = check_order(order, vals.shape[0])
    grid = np.full((h * w,) + vals.shape[1:], fill, dtype=vals.dtype)
    cells = np.flatnonzero(flat >= 0)
    grid[cells] = vals[flat[cells]]
    return grid.reshape((h, w) + vals.shape[1:])


def grid_to_values(grid: np.ndarray, order: np.ndarray, n: int) -> np.ndarray:
    """Inverse of :func:`apply_order`: rows (n, ...) read back from a (H, W, ...) grid."""
    arr = np.asarray(grid)
    if arr.ndim < 2:
        raise SortingError(f"grid must be (H, W, ...), got shape {arr.shape}")
    flat = check_order(order, n)
    if arr.shape[0] * arr.shape[1] != flat.size:
        raise SortingError(f"grid has {arr.shape[0] * arr.shape[1]} cells but order has {flat.size}")
    cells = arr.reshape((flat.size,) + arr.shape[2:])
    out = np.empty((n,) + arr.shape[2:], dtype=arr.dtype)
    used = np.flatnonzero(flat >= 0)
    out[flat[used]] = cells[used]
    return out


def identity_order(n: int, shape: tuple[int, int]) -> np.ndarray:
    """Rows in raster order, then ``-1`` padding."""
    h, w = shape
    order = np.full(h * w, -1, dtype=np.int64)
    order[:n] = np.arange(n, dtype=np.int64)
    return order
