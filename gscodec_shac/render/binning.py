"""One global depth sort, then per-tile Gaussian lists as flat arrays (a counting sort).

The reference duplicates every Gaussian once per tile of its 3-sigma rectangle and radix-sorts
``(tile, float32 depth)`` keys (stable, so ties keep index order). Here the contributing
Gaussians are sorted once by ``float32 depth bits << 32 | index`` and a stable counting sort by
tile gives the same per-tile order: ``ids[tile_start[t]:tile_start[t+1]]`` are positions in
the depth-sorted rows, front to back.

**Exact pruning.** A Gaussian can only change a pixel where ``opacity * exp(power) >= 1/255``,
i.e. inside the ellipse ``q(d) <= tau = 2 ln(255 opacity)`` (``q = -2 power``). It is listed
for a tile only when that ellipse (slightly enlarged against rounding) meets the tile *and* the
tile lies in the reference's rectangle. Dropped (tile, Gaussian) pairs could not have passed
the reference's alpha test, so the image is unchanged; lists just get shorter. Gaussians with
opacity < 1/255 are dropped entirely for the same reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from gscodec_shac.render.key_sort import sort_depth_keys
from gscodec_shac.render.projection import BLOCK, NO_KEY, P_A, P_B, P_C, P_DETC, P_HX, P_HY, P_TAU, P_X, P_Y


@dataclass
class TileBins:
    """Depth-sorted contributing Gaussians and their per-tile lists."""

    order: np.ndarray  # (V,) original Gaussian index of each depth-sorted entry
    pack: np.ndarray  # (V, PACK_WIDTH) float64 parameter rows in depth order
    rects: np.ndarray  # (V, 4) int32 reference tile rectangles in depth order
    tile_start: np.ndarray  # (n_tiles + 1,) int64 offsets into ids
    ids: np.ndarray  # (M,) int32 positions into the depth-sorted rows
    tiles_x: int
    tiles_y: int
    n_touching: int  # entries listed in at least one tile
    keys: np.ndarray | None = None  # (V,) uint64 sort keys of the depth-sorted entries (a view of the sorted keys)

    @property
    def n_pairs(self) -> int:
        return int(self.ids.shape[0])


@numba.njit(cache=True, parallel=True)
def _gather_kernel(keys, pack_in, rects_in, order, pack, rects):  # pragma: no cover - compiled
    width = pack_in.shape[1]
    for k in numba.prange(order.shape[0]):
        i = np.int64(keys[k] & np.uint64(0xFFFFFFFF))
        order[k] = i
        for j in range(width):
            pack[k, j] = pack_in[i, j]
        for j in range(4):
            rects[k, j] = rects_in[i, j]


@numba.njit(cache=True, inline="always")
def _upper(a, b, tau, detc, v):  # pragma: no cover - compiled
    return (-b * v + math.sqrt(max(0.0, a * tau - detc * v * v))) / a


@numba.njit(cache=True, inline="always")
def _lower(a, b, tau, detc, v):  # pragma: no cover - compiled
    return (-b * v - math.sqrt(max(0.0, a * tau - detc * v * v))) / a


@numba.njit(cache=True)
def tile_row_span(pack, k, row0, row1, width):  # pragma: no cover - compiled
    """Pixel columns ``[lo, hi]`` the alpha ellipse of entry ``k`` can touch in rows row0..row1."""
    mx = pack[k, P_X]
    my = pack[k, P_Y]
    a = pack[k, P_A]
    b = pack[k, P_B]
    c = pack[k, P_C]
    tau = pack[k, P_TAU]
    hx = pack[k, P_HX]
    hy = pack[k, P_HY]
    detc = pack[k, P_DETC]
    y_lo = max(row0, math.ceil(my - hy))
    y_hi = min(row1, math.floor(my + hy))
    if y_lo > y_hi:
        return 1, 0
    v0 = y_lo - my
    v1 = y_hi - my
    v_right = -b * hx / c  # the ellipse's rightmost point is at this v
    if v0 <= v_right <= v1:
        u_hi = hx
    else:
        u_hi = max(_upper(a, b, tau, detc, v0), _upper(a, b, tau, detc, v1))
    if v0 <= -v_right <= v1:
        u_lo = -hx
    else:
        u_lo = min(_lower(a, b, tau, detc, v0), _lower(a, b, tau, detc, v1))
    lo = max(0, math.ceil(mx + u_lo))
    hi = min(width - 1, math.floor(mx + u_hi))
    return lo, hi


@numba.njit(cache=True)
def _tile_rows(pack, rects, k, height):  # pragma: no cover - compiled
    my = pack[k, P_Y]
    hy = pack[k, P_HY]
    row_lo = max(0, math.ceil(my - hy))
    row_hi = min(height - 1, math.floor(my + hy))
    if row_lo > row_hi:
        return 1, 0
    return max(rects[k, 1], row_lo // BLOCK), min(rects[k, 3] - 1, row_hi // BLOCK)


@numba.njit(cache=True, parallel=True)
def _bin_kernel(pack, rects, width, height, tiles_x, tiles_y, n_chunks, touched):  # pragma: no cover - compiled
    n = pack.shape[0]
    n_tiles = tiles_x * tiles_y
    hist = np.zeros((n_chunks, n_tiles), dtype=np.int64)
    size = (n + n_chunks - 1) // n_chunks
    for ch in numba.prange(n_chunks):
        for k in range(ch * size, min(n, (ch + 1) * size)):
            ty0, ty1 = _tile_rows(pack, rects, k, height)
            for ty in range(ty0, ty1 + 1):
                lo, hi = tile_row_span(pack, k, ty * BLOCK, min(height - 1, ty * BLOCK + BLOCK - 1), width)
                if lo > hi:
                    continue
                tx0 = max(rects[k, 0], lo // BLOCK)
                tx1 = min(rects[k, 2] - 1, hi // BLOCK)
                for tx in range(tx0, tx1 + 1):
                    hist[ch, ty * tiles_x + tx] += 1
                if tx1 >= tx0:
                    touched[k] = True
    tile_start = np.zeros(n_tiles + 1, dtype=np.int64)
    cursor = np.zeros((n_chunks, n_tiles), dtype=np.int64)
    running = 0
    for t in range(n_tiles):
        tile_start[t] = running
        for ch in range(n_chunks):
            cursor[ch, t] = running
            running += hist[ch, t]
    tile_start[n_tiles] = running
    ids = np.empty(running, dtype=np.int32)
    for ch in numba.prange(n_chunks):
        for k in range(ch * size, min(n, (ch + 1) * size)):
            ty0, ty1 = _tile_rows(pack, rects, k, height)
            for ty in range(ty0, ty1 + 1):
                lo, hi = tile_row_span(pack, k, ty * BLOCK, min(height - 1, ty * BLOCK + BLOCK - 1), width)
                if lo > hi:
                    continue
                tx0 = max(rects[k, 0], lo // BLOCK)
                tx1 = min(rects[k, 2] - 1, hi // BLOCK)
                for tx in range(tx0, tx1 + 1):
                    t = ty * tiles_x + tx
                    ids[cursor[ch, t]] = k
                    cursor[ch, t] += 1
    return tile_start, ids


def bin_gaussians(
    keys: np.ndarray, pack_in: np.ndarray, rects_in: np.ndarray, width: int, height: int,
    order: np.ndarray, pack: np.ndarray, rects: np.ndarray,
) -> TileBins:
    """Sort by ``keys`` (see :func:`projection.project_into`; :func:`.key_sort.sort_depth_keys`), gather rows,
    build tile lists.

    ``keys`` is sorted in place; ``order``, ``pack`` and ``rects`` are output buffers with at
    least as many rows as there are contributing Gaussians (views of them are returned).
    """
    tiles_x = (width + BLOCK - 1) // BLOCK
    tiles_y = (height + BLOCK - 1) // BLOCK
    sort_depth_keys(keys)
    count = int(np.searchsorted(keys, NO_KEY))
    order, pack, rects = order[:count], pack[:count], rects[:count]
    _gather_kernel(keys, pack_in, rects_in, order, pack, rects)
    n_chunks = max(1, min(4 * numba.get_num_threads(), count // 4096 + 1))
    touched = np.zeros(count, dtype=np.bool_)
    tile_start, ids = _bin_kernel(pack, rects, width, height, tiles_x, tiles_y, n_chunks, touched)
    return TileBins(order, pack, rects, tile_start, ids, tiles_x, tiles_y, int(np.count_nonzero(touched)),
                    keys[:count])
