"""How smooth a sorted grid is: mean neighbour distance and PLAS's VAD."""

from __future__ import annotations

import numpy as np

from sorting.errors import SortingError


def _grid_and_mask(grid: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    g = np.asarray(grid)
    if g.ndim == 2:
        g = g[:, :, None]
    if g.ndim != 3 or g.shape[0] < 1 or g.shape[1] < 1:
        raise SortingError(f"grid must be (H, W) or (H, W, C), got shape {np.shape(grid)}")
    if mask is None:
        m = np.ones(g.shape[:2], dtype=bool)
    else:
        m = np.asarray(mask, dtype=bool)
        if m.shape != g.shape[:2]:
            raise SortingError(f"mask must be (H, W) = {g.shape[:2]}, got {m.shape}")
    return g.astype(np.float64), m


def _pairs(g: np.ndarray, m: np.ndarray):
    """Differences between right and lower neighbours where both cells are occupied."""
    dx = (g[:, 1:] - g[:, :-1])[m[:, 1:] & m[:, :-1]]
    dy = (g[1:] - g[:-1])[m[1:] & m[:-1]]
    return dx, dy


def neighbour_distance(grid: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean L2 distance between 4-neighbour cells of a (H, W, C) feature grid.

    Pass the grid of normalised sorting features. ``mask`` (H, W) marks occupied
    cells; pairs touching an empty cell are skipped. Lower is smoother.
    """
    g, m = _grid_and_mask(grid, mask)
    dx, dy = _pairs(g, m)
    count = dx.shape[0] + dy.shape[0]
    if count == 0:
        return 0.0
    total = np.sqrt((dx * dx).sum(axis=1)).sum() + np.sqrt((dy * dy).sum(axis=1)).sum()
    return float(total / count)


def vad(grid: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Variance of absolute neighbour differences (PLAS's VAD).

    The variance of |horizontal differences| and of |vertical differences|
    over all cells and channels, averaged. Lower is smoother.
    """
    g, m = _grid_and_mask(grid, mask)
    dx, dy = _pairs(g, m)
    parts = [np.var(np.abs(d)) for d in (dx, dy) if d.size]
    return float(np.mean(parts)) if parts else 0.0
