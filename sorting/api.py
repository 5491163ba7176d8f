"""``sort_to_grid``: one entry point for all sorting methods."""

from __future__ import annotations

import numpy as np

from sorting.errors import SortingError
from sorting.grid import check_shape, grid_shape, identity_order
from sorting.morton import morton_order
from sorting.plas import make_schedule, plas_sort

METHODS = ("plas", "morton", "random", "none")


def check_features(features: np.ndarray) -> np.ndarray:
    """(N, C) finite real features as float32, or :class:`SortingError`."""
    arr = np.asarray(features)
    if arr.ndim != 2:
        raise SortingError(f"features must be a 2-D (N, C) array, got {arr.ndim}-D shape {arr.shape}")
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise SortingError(f"features must have at least one row and one column, got shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool) or np.issubdtype(arr.dtype, np.complexfloating):
        raise SortingError(f"features must be real numbers, got dtype {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr).all(axis=1)))
        raise SortingError(f"features contain NaN or infinite values ({bad} rows)")
    return np.ascontiguousarray(arr, dtype=np.float32)


def sort_to_grid(
    features: np.ndarray,
    shape: tuple[int, int] | None = None,
    *,
    method: str = "plas",
    seed: int = 0,
    progress: bool = False,
    **schedule: object,
) -> np.ndarray:
    """Arrange N rows of ``features`` (N, C) on an (H, W) grid so that neighbours are similar.

    Returns ``order`` (H*W,) int64: ``order[cell]`` (cells row-major) is the row
    placed there, ``-1`` for an empty cell when N < H*W. ``shape`` defaults to
    ``grid_shape(N)`` (padding). Methods: ``"plas"`` (block-wise assignment
    sorting, see :class:`sorting.plas.PlasSchedule` for the ``schedule``
    keywords), ``"morton"`` (Z-order of the feature vectors, all columns; call
    :func:`sorting.morton_order` with positions for a purely spatial order),
    ``"random"`` and ``"none"`` (rows in raster order). The same seed gives the
    same order.
    """
    if method not in METHODS:
        raise SortingError(f"method must be one of {METHODS}, got {method!r}")
    feats = check_features(features)
    n = feats.shape[0]
    h, w = grid_shape(n) if shape is None else check_shape(shape)
    if n > h * w:
        raise SortingError(
            f"{n} rows do not fit a {h}x{w} grid ({h * w} cells); "
            "pick a larger shape or drop rows with select_for_grid"
        )
    if schedule and method != "plas":
        raise SortingError(f"schedule options {sorted(schedule)} apply only to method='plas'")
    sched = make_schedule(**schedule) if method == "plas" else None
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise SortingError(f"seed must be an integer, got {seed!r}")
    rng = np.random.default_rng(int(seed))
    if method == "none":
        return identity_order(n, (h, w))
    if method == "random":
        order = np.full(h * w, -1, dtype=np.int64)
        order[rng.permutation(h * w)[:n]] = np.arange(n, dtype=np.int64)
        return order
    if method == "morton":
        return morton_order(feats, (h, w))
    return plas_sort(feats, (h, w), rng, sched, progress=progress)
