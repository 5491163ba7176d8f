"""Our slow, straightforward numpy re-implementation of published PLAS, for comparison only.

This is NOT the fraunhoferhhi code (which needs torch + kornia and is not on
PyPI): it is our own port of the algorithm as described in "Compact 3D Scene
Representation via Self-Organizing Gaussian Grids" (Morgenstern et al.) and
its public reference implementation, written to measure how close
``sorting.sort_to_grid`` gets to it. Faithful to the reference's choices:

- square grids only; blur radius from side/2 - 1, times 0.95 per stage, down to 1;
- target = exact Gaussian blur of the current grid with kernel size
  min(side - 1, 2*radius + 1) and sigma equal to that size, circular border
  along x and reflecting border along y, computed once per radius;
- block side = max(min(size + 1, side) rounded down to even, 16);
- per block offset (random roll of the grid), passes of: one random permutation
  of the block's positions shared by all blocks, cut into groups of 4, each
  group takes the best of the 24 assignments (squared L2 to the target);
  a pass whose relative improvement is below ``improvement_break`` ends the
  offset; a radius ends after at least 4 offsets once an offset improves nothing.

Usage: ``python scripts/plas_reference.py`` sorts a random RGB grid as a smoke test.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.ndimage import correlate1d

PERMS = np.array(list(itertools.permutations(range(4))), dtype=np.int64)


def gaussian_kernel(size: int) -> np.ndarray:
    """Normalised Gaussian of odd ``size`` with sigma = size."""
    d = np.arange(size, dtype=np.float64) - size // 2
    w = np.exp(-(d * d) / (2.0 * size * size))
    return w / w.sum()


def blur(grid: np.ndarray, size: int) -> np.ndarray:
    """(H, W, C) grid blurred: circular along x (axis 1), reflecting along y (axis 0)."""
    k = gaussian_kernel(size)
    out = correlate1d(grid, k, axis=1, mode="wrap")
    return correlate1d(out, k, axis=0, mode="mirror")


def radius_sequence(side: int, min_radius: float = 1.0, step: float = 0.95) -> list[int]:
    out, r = [], side / 2 - 1
    while True:
        out.append(int(r))
        r *= step
        if r < min_radius:
            return out


def improve_blocks(grid, idx, target, block, rng):
    """One pass: random groups of 4 inside each block take their best assignment. Returns (before, after)."""
    side = grid.shape[0]
    c = grid.shape[2]
    nb = side // block
    span = nb * block
    p = grid[:span, :span].reshape(nb, block, nb, block, c).transpose(0, 2, 1, 3, 4).reshape(nb * nb, block * block, c)
    t = target[:span, :span].reshape(nb, block, nb, block, c).transpose(0, 2, 1, 3, 4).reshape(nb * nb, block * block, c)
    ids = idx[:span, :span].reshape(nb, block, nb, block).transpose(0, 2, 1, 3).reshape(nb * nb, block * block)
    groups = rng.permutation(block * block).reshape(-1, 4)  # (G, 4) positions, shared by all blocks
    pg, tg = p[:, groups], t[:, groups]  # (B, G, 4, C)
    cost = ((pg[:, :, :, None, :] - tg[:, :, None, :, :]) ** 2).sum(-1)  # (B, G, item, cell)
    perm_cost = cost[:, :, np.arange(4)[None, :], PERMS].sum(-1)  # (B, G, 24)
    best = perm_cost.argmin(-1)  # (B, G)
    before = float(perm_cost[:, :, 0].sum())
    after = float(np.take_along_axis(perm_cost, best[..., None], -1).sum())
    dest = np.take_along_axis(groups[None].repeat(len(p), 0), PERMS[best], -1)  # cell of item i
    new_p, new_ids = p.copy(), ids.copy()
    b_index = np.arange(len(p))[:, None, None]
    new_p[b_index, dest] = pg
    new_ids[b_index, dest] = ids[:, groups]
    grid[:span, :span] = new_p.reshape(nb, nb, block, block, c).transpose(0, 2, 1, 3, 4).reshape(span, span, c)
    idx[:span, :span] = new_ids.reshape(nb, nb, block, block).transpose(0, 2, 1, 3).reshape(span, span)
    return before, after


def plas_reference(
    features: np.ndarray,
    side: int,
    *,
    seed: int = 0,
    improvement_break: float = 1e-4,
    min_block_size: int = 16,
    record: list | None = None,
) -> np.ndarray:
    """Sort side*side rows of (N, C) ``features``; returns the order (row per cell, row-major).

    Rows are shuffled first (seeded). With ``record`` (a list), one
    ``(passes so far, radius, order so far)`` snapshot per radius is appended.
    """
    n, c = features.shape
    if n != side * side:
        raise ValueError(f"reference PLAS needs exactly side*side = {side * side} rows, got {n}")
    rng = np.random.default_rng(seed)
    start = rng.permutation(n)
    grid = features[start].astype(np.float32).reshape(side, side, c).copy()
    idx = start.reshape(side, side).copy()
    passes = 0
    for radius in radius_sequence(side):
        size = min(side - 1, int(2 * radius + 1))
        target = blur(grid, size).astype(np.float32)
        block = max(min(size + 1, side) // 2 * 2, min_block_size)
        offset = 0
        while True:
            sy, sx = int(rng.integers(0, block)), int(rng.integers(0, block))
            grid = np.roll(grid, (sy, sx), axis=(0, 1))
            idx = np.roll(idx, (sy, sx), axis=(0, 1))
            rolled_target = np.roll(target, (sy, sx), axis=(0, 1))
            improved = False
            while True:
                before, after = improve_blocks(grid, idx, rolled_target, block, rng)
                passes += 1
                gain = 0.0 if before == 0 else 1.0 - after / before
                if gain < improvement_break:
                    break
                improved = True
            grid = np.roll(grid, (-sy, -sx), axis=(0, 1))
            idx = np.roll(idx, (-sy, -sx), axis=(0, 1))
            if not improved and offset >= 3:
                break
            offset += 1
        if record is not None:
            record.append((passes, radius, idx.reshape(-1).astype(np.int64)))
    return idx.reshape(-1).astype(np.int64)


if __name__ == "__main__":
    import time

    side = 32
    colours = np.random.default_rng(1).random((side * side, 3)).astype(np.float32)
    t0 = time.perf_counter()
    order = plas_reference(colours, side)
    grid = colours[order].reshape(side, side, 3)
    dist = np.sqrt(((grid[:, 1:] - grid[:, :-1]) ** 2).sum(-1)).mean()
    print(f"{side}x{side} random RGB sorted in {time.perf_counter() - t0:.1f} s, mean right-neighbour L2 {dist:.4f}")
