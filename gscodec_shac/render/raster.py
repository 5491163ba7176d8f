"""Per-pixel front-to-back alpha blending over the tile lists (the reference's ``renderCUDA``).

For every pixel, walking its tile's list front to back (reference semantics):

* ``alpha = min(0.99, opacity * exp(power))``, skipped when ``power > 0`` or ``alpha < 1/255``;
* ``T_next = T (1 - alpha)``; if ``T_next < 1e-4`` the pixel stops *without* accumulating;
* otherwise ``C += colour * alpha * T`` and ``T = T_next``;
* output ``C + T * background``.

The kernel is kept apart from projection and colour so a backward pass can reuse its inputs
(the tile lists, the final transmittance and each pixel's ``last`` contributor position in its
tile's list, as the reference's backward pass uses them).

It loops Gaussian-outer / pixel-inner per 16x16 tile (parameters loaded once per tile), and
only visits pixels inside each Gaussian's alpha ellipse (outside it the alpha test fails
anyway) and inside each row's span of pixels that have not stopped yet (stopped pixels skip
everything). ``exp(power)`` is evaluated along a row with an exact multiplicative recurrence
(``power`` is quadratic in x, so the ratio between neighbours is geometric): two ``exp`` per row
segment instead of one per pixel, agreeing with direct evaluation to ~1e-14 relative. With a
positive-definite conic (guaranteed by the 0.3 dilation) ``power <= 0`` everywhere, so the
reference's ``power > 0`` test never fires and is not repeated per pixel. All in float64.

A tile's list is walked in blocks of :data:`GATHER_BLOCK` entries whose parameter rows are first
copied into a small per-tile buffer (the copy's loads are independent of each other, so the memory
system overlaps them; the blend's own reads of a large scene's pack wait one by one).

Modes: ``MODE_IMAGE`` (colour, transmittance, depth, last contributor), ``MODE_COUNT``
(contributions per pixel), ``MODE_WEIGHTS`` (each contribution's Gaussian and weight
``alpha * T``, written at ``indptr[pixel]``) and ``MODE_TOTALS`` (the weights ``alpha * T``
summed over the pixels of a tile, per tile-list entry: a Gaussian is listed at most once per
tile and a tile belongs to one thread, so the sums need no synchronisation).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from gscodec_shac.render.binning import TileBins
from gscodec_shac.render.projection import (
    ALPHA_MIN,
    BLOCK,
    P_A,
    P_B,
    P_BLUE,
    P_C,
    P_DEPTH,
    P_DETC,
    P_G,
    P_HY,
    P_OPACITY,
    P_R,
    P_STEP,
    P_TAU,
    P_X,
    P_Y,
)

#: Tile-list entries whose parameter rows the blend copies at a time before it walks them: the
#: rows are scattered over the depth-sorted pack, and a loop of independent loads fetches them
#: several times faster than the blend's own dependent reads (docs/benchmarks.md, "This stop: the
#: blend's memory reads ..."; 64 and 1,024 entries gave the same times).
GATHER_BLOCK = 256
MODE_IMAGE = 0
MODE_COUNT = 1
MODE_WEIGHTS = 2
MODE_TOTALS = 3
#: Maximum alpha of one Gaussian and the transmittance at which a pixel stops (reference values).
ALPHA_MAX = 0.99
T_MIN = 1e-4


@numba.njit(cache=True, inline="always")
def tile_pixels(tile, tiles_x, width, height):  # pragma: no cover - compiled
    """The pixel columns ``x0..x1`` and rows ``y0..y1`` (inclusive) of tile ``tile`` (row-major tiles)."""
    ty = tile // tiles_x
    tx = tile - ty * tiles_x
    x0 = tx * BLOCK
    y0 = ty * BLOCK
    return x0, y0, min(x0 + BLOCK, width) - 1, min(y0 + BLOCK, height) - 1


@numba.njit(cache=True, parallel=True)
def _raster_kernel(
    mode, tile_start, ids, pack, order, width, height, tiles_x, tile_order, worker_start,
    color_out, t_out, depth_out, last_out, count_out, indptr, w_cols, w_vals,
):  # pragma: no cover - compiled
    npix = BLOCK * BLOCK
    for worker in numba.prange(worker_start.shape[0] - 1):
        for k in range(worker_start[worker], worker_start[worker + 1]):
            tile = tile_order[k]
            x0, y0, x1, y1 = tile_pixels(tile, tiles_x, width, height)
            # per pixel: transmittance, r, g, b, depth sum
            state = np.zeros((npix, 5))
            state[:, 0] = 1.0
            done = np.zeros(npix, dtype=np.bool_)
            last = np.zeros(npix, dtype=np.int32)
            cursor = np.zeros(npix, dtype=np.int64)
            # columns [span_lo, span_hi] of each row still hold every pixel that is not done
            span_lo = np.full(BLOCK, x0, dtype=np.int64)
            span_hi = np.full(BLOCK, x1, dtype=np.int64)
            if mode == MODE_WEIGHTS:
                for yy in range(y0, y1 + 1):
                    for xx in range(x0, x1 + 1):
                        cursor[(yy - y0) * BLOCK + xx - x0] = indptr[yy * width + xx]
            active = (x1 - x0 + 1) * (y1 - y0 + 1)
            start = tile_start[tile]
            end = tile_start[tile + 1]
            local = np.empty((GATHER_BLOCK, P_DEPTH + 1))  # the next entries' parameter rows, copied together
            for e in range(start, end):
                j = (e - start) % GATHER_BLOCK
                if j == 0:
                    for q in range(min(GATHER_BLOCK, end - e)):
                        row_q = ids[e + q]
                        for col in range(P_DEPTH + 1):
                            local[q, col] = pack[row_q, col]
                s = ids[e]
                mx = local[j, P_X]
                my = local[j, P_Y]
                a = local[j, P_A]
                b = local[j, P_B]
                c = local[j, P_C]
                opacity = local[j, P_OPACITY]
                tau = local[j, P_TAU]
                hy = local[j, P_HY]
                detc = local[j, P_DETC]
                step = local[j, P_STEP]
                cr = local[j, P_R]
                cg = local[j, P_G]
                cb = local[j, P_BLUE]
                cz = local[j, P_DEPTH]
                inv_a = 1.0 / a
                row_lo = max(y0, math.ceil(my - hy))
                row_hi = min(y1, math.floor(my + hy))
                for py in range(row_lo, row_hi + 1):
                    row = py - y0
                    if span_lo[row] > span_hi[row]:
                        continue
                    v = py - my
                    disc = a * tau - detc * v * v
                    if disc < 0.0:
                        continue
                    root = math.sqrt(disc)
                    x_lo = max(span_lo[row], math.ceil(mx - (b * v + root) * inv_a))
                    x_hi = min(span_hi[row], math.floor(mx - (b * v - root) * inv_a))
                    if x_lo > x_hi:
                        continue
                    dx = mx - x_lo
                    dy = my - py
                    g = opacity * math.exp(-0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy)
                    ratio = math.exp(a * dx - 0.5 * a + b * dy)
                    p = row * BLOCK + (x_lo - x0)
                    finished = False
                    for _ in range(x_lo, x_hi + 1):
                        if not done[p]:
                            alpha = min(ALPHA_MAX, g)
                            if alpha >= ALPHA_MIN:
                                t_now = state[p, 0]
                                t_next = t_now * (1.0 - alpha)
                                if t_next < T_MIN:
                                    done[p] = True
                                    finished = True
                                    active -= 1
                                else:
                                    w = alpha * t_now
                                    if mode == MODE_IMAGE:
                                        state[p, 1] += w * cr
                                        state[p, 2] += w * cg
                                        state[p, 3] += w * cb
                                        state[p, 4] += w * cz
                                        last[p] = e - start + 1
                                    elif mode == MODE_COUNT:
                                        cursor[p] += 1
                                    elif mode == MODE_TOTALS:
                                        w_vals[e] += w
                                    else:
                                        w_cols[cursor[p]] = order[s]
                                        w_vals[cursor[p]] = w
                                        cursor[p] += 1
                                    state[p, 0] = t_next
                        g *= ratio
                        ratio *= step
                        p += 1
                    if finished:
                        lo = span_lo[row]
                        hi = span_hi[row]
                        while lo <= hi and done[row * BLOCK + lo - x0]:
                            lo += 1
                        while hi >= lo and done[row * BLOCK + hi - x0]:
                            hi -= 1
                        span_lo[row] = lo
                        span_hi[row] = hi
                if active == 0:
                    break
            for yy in range(y0, y1 + 1):
                for xx in range(x0, x1 + 1):
                    p = (yy - y0) * BLOCK + xx - x0
                    pix = yy * width + xx
                    t_out[pix] = state[p, 0]
                    if mode == MODE_IMAGE:
                        for ch in range(3):
                            color_out[pix, ch] = state[p, ch + 1]
                        depth_out[pix] = state[p, 4]
                        last_out[pix] = last[p]
                    elif mode == MODE_COUNT:
                        count_out[pix] = cursor[p]


#: What a tile costs the blend besides its list entries (setting up and writing its pixels), in
#: entries: the weight of an empty tile in :func:`tile_schedule`.
TILE_COST = 64


@numba.njit(cache=True)
def _deal(cost, workers):  # pragma: no cover - compiled
    """Worker of each tile: the most costly tile first, each to the least loaded worker (LPT)."""
    load = np.zeros(workers)
    owner = np.empty(cost.shape[0], dtype=np.int64)
    for tile in np.argsort(-cost, kind="mergesort"):
        worker = np.argmin(load)
        owner[tile] = worker
        load[worker] += cost[tile]
    return owner


def tile_schedule(tile_start: np.ndarray, workers: int,
                  only: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(tiles, worker_start)``: the tiles dealt to ``workers`` threads, worker ``w`` blending
    ``tiles[worker_start[w]:worker_start[w + 1]]`` in increasing order (neighbours share Gaussians);
    ``only``: the tiles to blend (ascending), else every tile.

    The blend's parallel loop runs over the workers, one per thread: numba splits a loop's range
    into equal runs of iterations, so a loop over the tiles themselves left one thread the dense
    middle of an image and the other its empty border (a 192-pixel view of 1M Gaussians: 1.5 of
    2 cores busy). A tile's cost is taken as its list length plus :data:`TILE_COST`; every tile
    is blended alone, so the pixels do not depend on the schedule.
    """
    cost = np.diff(tile_start).astype(np.float64) + TILE_COST
    chosen = np.arange(cost.shape[0]) if only is None else np.asarray(only, dtype=np.int64)
    cost = cost[chosen]
    workers = max(1, min(int(workers), max(1, cost.shape[0])))
    owner = _deal(cost, workers)
    tiles = chosen[np.argsort(owner, kind="stable")]
    worker_start = np.zeros(workers + 1, dtype=np.int64)
    np.cumsum(np.bincount(owner, minlength=workers), out=worker_start[1:])
    return tiles, worker_start


def _run(mode: int, bins: TileBins, width: int, height: int, only: np.ndarray | None = None,
         **arrays: np.ndarray) -> None:
    npix = width * height
    empty_f = np.zeros(0)
    empty_i32 = np.zeros(0, dtype=np.int32)
    empty_i64 = np.zeros(0, dtype=np.int64)
    tiles, worker_start = tile_schedule(bins.tile_start, numba.get_num_threads(), only)
    _raster_kernel(
        mode, bins.tile_start, bins.ids, bins.pack, bins.order, width, height, bins.tiles_x, tiles, worker_start,
        arrays.get("color", np.zeros((0, 3))), arrays.get("trans", np.zeros(npix)),
        arrays.get("depth", empty_f), arrays.get("last", empty_i32), arrays.get("count", empty_i64),
        arrays.get("indptr", empty_i64), arrays.get("cols", empty_i32), arrays.get("vals", empty_f),
    )


def rasterize(
    bins: TileBins, width: int, height: int, buffers: dict[str, np.ndarray] | None = None,
    only: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(colour (H*W, 3), transmittance (H*W,), weighted depth sum (H*W,), last contributor (H*W,))``.

    The colour excludes the background term ``T * background``; ``last`` is the reference's
    per-pixel count of list entries up to the last one that contributed (for a backward pass).
    ``buffers`` (keys color, trans, depth, last) are reused when given. ``only``: blend these tiles
    (ascending), the other pixels are left as they were in the buffers.
    """
    npix = width * height
    buffers = buffers if buffers is not None else {}
    color = buffers.get("color")
    if color is None or color.shape != (npix, 3):
        color = np.empty((npix, 3))
        trans, depth, last = np.empty(npix), np.empty(npix), np.empty(npix, dtype=np.int32)
    else:
        trans, depth, last = buffers["trans"], buffers["depth"], buffers["last"]
    _run(MODE_IMAGE, bins, width, height, only, color=color, trans=trans, depth=depth, last=last)
    return color, trans, depth, last


def blend_weights(bins: TileBins, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """CSR parts ``(indptr, gaussian ids, weights alpha*T)`` per pixel (front to back) and final T."""
    npix = width * height
    count = np.empty(npix, dtype=np.int64)
    trans = np.empty(npix)
    _run(MODE_COUNT, bins, width, height, count=count, trans=trans)
    indptr = np.zeros(npix + 1, dtype=np.int64)
    np.cumsum(count, out=indptr[1:])
    cols = np.empty(int(indptr[-1]), dtype=np.int32)
    vals = np.empty(int(indptr[-1]))
    _run(MODE_WEIGHTS, bins, width, height, trans=trans, indptr=indptr, cols=cols, vals=vals)
    return indptr, cols, vals, trans


def blend_totals(bins: TileBins, width: int, height: int, n: int) -> np.ndarray:
    """(n,) each Gaussian's blending weights ``alpha * T`` summed over every pixel (one pass)."""
    per_entry = np.zeros(bins.n_pairs)
    _run(MODE_TOTALS, bins, width, height, vals=per_entry)
    return np.bincount(bins.order[bins.ids], weights=per_entry, minlength=n)
