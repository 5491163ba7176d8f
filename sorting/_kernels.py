"""numba kernels of the block-wise improvement step (fused, in place, no slicing inside prange).

One *pass* visits every block of the current block layout. Inside each block,
cells are cut into groups of 4 by a keyed pseudo-random bijection of the block
positions (the same for every block, as in PLAS; see ``_groups.py``); each group tries all 24 ways
of assigning its 4 items to its 4 cells and keeps the one closest (squared L2)
to the target. Groups are disjoint, so they run in parallel and write in place.
Distances are summed per fixed chunk of groups, so results do not depend on the
number of threads or on running serially.

With ``e_ij = 2 p_i.t_j - |t_j|^2`` (zero for an empty item ``i``), the squared
distance of an assignment is ``sum|p_i|^2 - sum_i e_i,sigma(i)``, so the best
of the 24 assignments maximises the sum of 4 ``e`` terms (unrolled below).
Everything a group needs sits in one cache line per cell and array: the item
flag and the target's squared norm ride in two spare channels (see
``plas.make_state``), so the row index array is touched only to move items.
"""

from __future__ import annotations

import itertools

import numpy as np
from numba import njit, prange

from sorting._groups import fill_positions

#: All 24 assignments of 4 items to 4 cells (item i -> cell PERMS[p, i]), identity first.
PERMS = np.array(list(itertools.permutations(range(4))), dtype=np.int64)
#: Groups per chunk: the unit of parallel work and of partial sums.
CHUNK = 2048


@njit(cache=True)
def _scratch(k):
    """The per-caller scratch of :func:`_improve_groups`: (4, K) float32 and two (4,) int64 arrays."""
    return np.empty((4, k), dtype=np.float32), np.empty(4, dtype=np.int64), np.empty(4, dtype=np.int64)


@njit(cache=True, fastmath=True)
def _improve_groups(feat, idx, target, pos_y, pos_x, row, geom, g_start, g_end, tmp, cs, ids, warm):
    """Groups ``[g_start, g_end)``: apply each group's best assignment; return (before, after).

    Group ``q`` of a block takes positions ``4q .. 4q+3`` of row ``row`` of the
    position tables ``pos_y``/``pos_x`` (tables, rows, block cells). ``tmp``, ``cs`` and ``ids``
    are scratch (:func:`_scratch`), allocated once by the caller, not per call: a small block
    is a call per pass, and the three allocations were ~5% of a 1M-cell sort. ``warm``: read each
    block row by row before its random groups (the caller passes ``geom[9] != 0``, or False for a
    block still in the cache from its previous pass).
    """
    height, width, bh, bw, sy, sx, nbx = geom[0], geom[1], geom[2], geom[3], geom[4], geom[5], geom[6]
    gpb = (bh * bw) // 4
    k = feat.shape[1]
    sum_before = 0.0
    sum_after = 0.0
    # block (by, bx) and group q inside it, advanced incrementally (no divisions per group)
    b = g_start // gpb
    q = g_start - b * gpb
    by = b // nbx
    bx = b - by * nbx
    y0 = by * bh + sy
    x0 = bx * bw + sx
    touched = np.float32(0.0)
    for g in range(g_start, g_end):
        if warm and (q == 0 or g == g_start):
            # read the block row by row first: the random group accesses then hit the cache
            for py in range(bh):
                y = y0 + py
                if y >= height:
                    y -= height
                base = y * width
                for px in range(bw):
                    x = x0 + px
                    if x >= width:
                        x -= width
                    touched += feat[base + x, 0] + target[base + x, 0]
        for m in range(4):
            j = 4 * q + m
            y = y0 + pos_y[row, j]
            if y >= height:
                y -= height
            x = x0 + pos_x[row, j]
            if x >= width:
                x -= width
            cs[m] = y * width + x
        q += 1
        if q == gpb:
            q = 0
            bx += 1
            x0 += bw
            if bx == nbx:
                bx = 0
                x0 = sx
                y0 += bh
        c0 = cs[0]
        c1 = cs[1]
        c2 = cs[2]
        c3 = cs[3]
        d00 = d01 = d02 = d03 = d10 = d11 = d12 = d13 = np.float32(0.0)
        d20 = d21 = d22 = d23 = d30 = d31 = d32 = d33 = np.float32(0.0)
        n0 = n1 = n2 = n3 = np.float32(0.0)
        for c in range(k):
            p0 = feat[c0, c]
            p1 = feat[c1, c]
            p2 = feat[c2, c]
            p3 = feat[c3, c]
            t0 = target[c0, c]
            t1 = target[c1, c]
            t2 = target[c2, c]
            t3 = target[c3, c]
            d00 += p0 * t0
            d01 += p0 * t1
            d02 += p0 * t2
            d03 += p0 * t3
            d10 += p1 * t0
            d11 += p1 * t1
            d12 += p1 * t2
            d13 += p1 * t3
            d20 += p2 * t0
            d21 += p2 * t1
            d22 += p2 * t2
            d23 += p2 * t3
            d30 += p3 * t0
            d31 += p3 * t1
            d32 += p3 * t2
            d33 += p3 * t3
            n0 += p0 * p0
            n1 += p1 * p1
            n2 += p2 * p2
            n3 += p3 * p3
        # channel k-2 of a cell vector is 1 for an item, 0 for an empty cell; channel k-1 of
        # a target is its squared norm (the item channel k-1 is 0, so dot products ignore it)
        v0 = feat[c0, k - 2]
        v1 = feat[c1, k - 2]
        v2 = feat[c2, k - 2]
        v3 = feat[c3, k - 2]
        tn0 = target[c0, k - 1]
        tn1 = target[c1, k - 1]
        tn2 = target[c2, k - 1]
        tn3 = target[c3, k - 1]
        e00 = 2 * d00 - v0 * tn0
        e01 = 2 * d01 - v0 * tn1
        e02 = 2 * d02 - v0 * tn2
        e03 = 2 * d03 - v0 * tn3
        e10 = 2 * d10 - v1 * tn0
        e11 = 2 * d11 - v1 * tn1
        e12 = 2 * d12 - v1 * tn2
        e13 = 2 * d13 - v1 * tn3
        e20 = 2 * d20 - v2 * tn0
        e21 = 2 * d21 - v2 * tn1
        e22 = 2 * d22 - v2 * tn2
        e23 = 2 * d23 - v2 * tn3
        e30 = 2 * d30 - v3 * tn0
        e31 = 2 * d31 - v3 * tn1
        e32 = 2 * d32 - v3 * tn2
        e33 = 2 * d33 - v3 * tn3
        best = e00+e11+e22+e33
        identity = best
        bp = 0
        s = e00+e11+e23+e32
        if s > best:
            best = s
            bp = 1
        s = e00+e12+e21+e33
        if s > best:
            best = s
            bp = 2
        s = e00+e12+e23+e31
        if s > best:
            best = s
            bp = 3
        s = e00+e13+e21+e32
        if s > best:
            best = s
            bp = 4
        s = e00+e13+e22+e31
        if s > best:
            best = s
            bp = 5
        s = e01+e10+e22+e33
        if s > best:
            best = s
            bp = 6
        s = e01+e10+e23+e32
        if s > best:
            best = s
            bp = 7
        s = e01+e12+e20+e33
        if s > best:
            best = s
            bp = 8
        s = e01+e12+e23+e30
        if s > best:
            best = s
            bp = 9
        s = e01+e13+e20+e32
        if s > best:
            best = s
            bp = 10
        s = e01+e13+e22+e30
        if s > best:
            best = s
            bp = 11
        s = e02+e10+e21+e33
        if s > best:
            best = s
            bp = 12
        s = e02+e10+e23+e31
        if s > best:
            best = s
            bp = 13
        s = e02+e11+e20+e33
        if s > best:
            best = s
            bp = 14
        s = e02+e11+e23+e30
        if s > best:
            best = s
            bp = 15
        s = e02+e13+e20+e31
        if s > best:
            best = s
            bp = 16
        s = e02+e13+e21+e30
        if s > best:
            best = s
            bp = 17
        s = e03+e10+e21+e32
        if s > best:
            best = s
            bp = 18
        s = e03+e10+e22+e31
        if s > best:
            best = s
            bp = 19
        s = e03+e11+e20+e32
        if s > best:
            best = s
            bp = 20
        s = e03+e11+e22+e30
        if s > best:
            best = s
            bp = 21
        s = e03+e12+e20+e31
        if s > best:
            best = s
            bp = 22
        s = e03+e12+e21+e30
        if s > best:
            best = s
            bp = 23
        norms = n0 + n1 + n2 + n3 - (v0 + v1 + v2 + v3)  # without the item channel
        sum_before += norms - identity
        sum_after += norms - best
        if bp != 0:
            for i in range(4):
                ci = cs[i]
                ids[i] = idx[ci]
                for c in range(k):
                    tmp[i, c] = feat[ci, c]
            for i in range(4):
                cj = cs[PERMS[bp, i]]
                idx[cj] = ids[i]
                for c in range(k):
                    feat[cj, c] = tmp[i, c]
    if touched == np.float32(1e30):  # keeps the warm-up reads alive
        sum_before += 1.0
    return sum_before, sum_after


@njit(parallel=True, cache=True)
def improve_pass_parallel(feat, idx, target, pos_y, pos_x, geom, before, after):
    """One pass over all blocks, chunks of groups in parallel; per-chunk sums into ``before``/``after``."""
    n_groups = geom[7]
    for chunk in prange(before.shape[0]):
        g0 = chunk * CHUNK
        tmp, cs, ids = _scratch(feat.shape[1])
        b, a = _improve_groups(feat, idx, target, pos_y, pos_x, 0, geom, g0, min(g0 + CHUNK, n_groups), tmp, cs, ids,
                               geom[9] != 0)
        before[chunk] = b
        after[chunk] = a


@njit(cache=True)
def improve_pass_serial(feat, idx, target, pos_y, pos_x, geom, before, after):
    """The same pass on one thread (cheaper for small grids: no thread hand-offs)."""
    n_groups = geom[7]
    tmp, cs, ids = _scratch(feat.shape[1])
    for chunk in range(before.shape[0]):
        g0 = chunk * CHUNK
        b, a = _improve_groups(feat, idx, target, pos_y, pos_x, 0, geom, g0, min(g0 + CHUNK, n_groups), tmp, cs, ids,
                               geom[9] != 0)
        before[chunk] = b
        after[chunk] = a


@njit(cache=True)
def _gain(before, after):
    b = 0.0
    a = 0.0
    for i in range(before.shape[0]):  # fixed order: the same sum on any number of threads
        b += before[i]
        a += after[i]
    return 0.0 if b <= 0.0 else 1.0 - a / b


@njit(cache=True)
def sort_one_radius(feat, idx, target, pos_y, pos_x, geom, before, after, keys, shifts, improvement_break, min_offsets, parallel, tiled):
    """PLAS's loop for one target, for few big blocks: every pass runs over all blocks.

    Block offsets, each improved until a pass gains < ``improvement_break``
    (over all blocks); stops after ``min_offsets`` offsets once an offset has
    not improved, or when the pre-drawn ``keys`` (passes, 4) / ``shifts``
    (passes, 2) run out. ``pos_y``/``pos_x`` are (1, block cells) scratch.
    Returns the number of passes run.
    """
    max_passes = keys.shape[0]
    passes = 0
    offset = 0
    while passes < max_passes:
        geom[4] = shifts[offset, 0]
        geom[5] = shifts[offset, 1]
        improved = False
        while passes < max_passes:
            fill_positions(pos_y, pos_x, 0, geom[3], keys[passes], tiled, parallel)
            if parallel:
                improve_pass_parallel(feat, idx, target, pos_y, pos_x, geom, before, after)
            else:
                improve_pass_serial(feat, idx, target, pos_y, pos_x, geom, before, after)
            passes += 1
            if _gain(before, after) < improvement_break:
                break
            improved = True
        offset += 1
        if not improved and offset >= min_offsets:
            break
    return passes


@njit(cache=True)
def _block_until_converged(feat, idx, target, pos_y, pos_x, geom, block, improvement_break, stats, tmp, cs, ids):
    """Passes over one block until one gains < ``improvement_break``; pass ``p`` uses table row ``p % rows``.

    Only the first pass warms the cache (geom[9]): the later ones find the block where it left it.
    ``tmp``, ``cs``, ``ids``: the caller's :func:`_scratch`.
    """
    gpb = (geom[2] * geom[3]) // 4
    rows = pos_y.shape[0]
    max_passes = geom[8]
    for p in range(max_passes):
        b, a = _improve_groups(feat, idx, target, pos_y, pos_x, p % rows, geom, block * gpb, (block + 1) * gpb,
                               tmp, cs, ids, p == 0 and geom[9] != 0)
        if p == 0:
            stats[block, 0] = b
            stats[block, 1] = a
        stats[block, 2] = p + 1
        if b <= 0.0 or 1.0 - a / b < improvement_break:
            break


@njit(cache=True)
def _block_run(feat, idx, target, pos_y, pos_x, geom, improvement_break, stats, run, per_run):
    """Blocks ``run * per_run ..`` (at most ``per_run``) one after the other, with one scratch."""
    tmp, cs, ids = _scratch(feat.shape[1])
    for block in range(run * per_run, min((run + 1) * per_run, stats.shape[0])):
        _block_until_converged(feat, idx, target, pos_y, pos_x, geom, block, improvement_break, stats, tmp, cs, ids)


@njit(parallel=True, cache=True)
def _offset_blocks_parallel(feat, idx, target, pos_y, pos_x, geom, improvement_break, stats, per_run):
    for run in prange((stats.shape[0] + per_run - 1) // per_run):
        _block_run(feat, idx, target, pos_y, pos_x, geom, improvement_break, stats, run, per_run)


@njit(cache=True)
def _offset_blocks_serial(feat, idx, target, pos_y, pos_x, geom, improvement_break, stats, per_run):
    _block_run(feat, idx, target, pos_y, pos_x, geom, improvement_break, stats, 0, stats.shape[0])


@njit(cache=True)
def sort_one_radius_blockwise(feat, idx, target, pos_y, pos_x, geom, stats, shifts, improvement_break, min_offsets, parallel,
                              per_run):
    """PLAS's loop for one target, for many small blocks: each block runs its own passes.

    Blocks are independent while the offset stays, so every block is improved
    until its own pass gains < ``improvement_break`` (one parallel region per
    offset, and a block stays in the cache for all its passes). An offset
    counts as improving when its first passes together gained at least
    ``improvement_break``; the loop over offsets ends as in :func:`sort_one_radius`.
    ``stats`` is (blocks, 3) scratch; blocks are handed out in runs of ``per_run`` (one scratch
    per run). Returns the block passes run, averaged over blocks.
    """
    n_blocks = stats.shape[0]
    total = 0.0
    offset = 0
    while offset < shifts.shape[0]:
        geom[4] = shifts[offset, 0]
        geom[5] = shifts[offset, 1]
        if parallel:
            _offset_blocks_parallel(feat, idx, target, pos_y, pos_x, geom, improvement_break, stats, per_run)
        else:
            _offset_blocks_serial(feat, idx, target, pos_y, pos_x, geom, improvement_break, stats, per_run)
        before = 0.0
        after = 0.0
        for block in range(n_blocks):  # fixed order: the same sums on any number of threads
            before += stats[block, 0]
            after += stats[block, 1]
            total += stats[block, 2]
        offset += 1
        improved = before > 0.0 and 1.0 - after / before >= improvement_break
        if not improved and offset >= min_offsets:
            break
    return total / n_blocks
