"""Which cells of a block form the groups of 4 in one pass: keyed pseudo-random bijections.

Position ``i`` of a block of ``bh*bw`` cells goes to ``(pos_y[i], pos_x[i])``;
group ``q`` takes positions ``4q .. 4q+3``. The plain grouping is a 4-round
Feistel network on the position bits with cycle walking (a bijection of
``[0, bh*bw)`` per set of 4 keys, cheap to compute on the fly and the same on
any number of threads). In big blocks, the tile-pair grouping takes 2 cells of
one 8x8 tile and 2 of another (tiles paired at random), so consecutive groups
stay inside two tiles and are read from the cache.
"""

from __future__ import annotations

from numba import njit, prange

#: Positions filled per parallel task.
CHUNK = 8192
_M32 = 0xFFFFFFFF
#: Tile side of the tile-pair grouping used in big blocks.
TILE = 8
#: Position tables longer than this are filled on all threads.
PARALLEL_POSITIONS = 65536


@njit(cache=True, inline="always")
def _feistel(i, half_bits, half_mask, k0, k1, k2, k3):
    """A 4-round balanced Feistel bijection on ``[0, 2**(2*half_bits))``."""
    left = i >> half_bits
    right = i & half_mask
    for r in range(4):
        key = k0 if r == 0 else (k1 if r == 1 else (k2 if r == 2 else k3))
        x = (right ^ key) & _M32
        x = (x * 0x5BD1E995) & _M32
        x ^= x >> 15
        x = (x * 0x27D4EB2D) & _M32
        x ^= x >> 13
        left, right = right, left ^ (x & half_mask)
    return (left << half_bits) | right


@njit(cache=True, inline="always")
def _position(i, n, half_bits, half_mask, k0, k1, k2, k3):
    j = _feistel(i, half_bits, half_mask, k0, k1, k2, k3)
    while j >= n:  # cycle walking keeps it a bijection of [0, n)
        j = _feistel(j, half_bits, half_mask, k0, k1, k2, k3)
    return j


@njit(cache=True)
def _positions_range(pos_y, pos_x, bw, keys, start, stop):
    n = pos_y.shape[0]
    bits = 2
    while (1 << bits) < n:
        bits += 1
    half_bits = (bits + 1) // 2
    half_mask = (1 << half_bits) - 1
    k0, k1, k2, k3 = keys[0], keys[1], keys[2], keys[3]
    for i in range(start, stop):
        p = _position(i, n, half_bits, half_mask, k0, k1, k2, k3)
        row = p // bw
        pos_y[i] = row
        pos_x[i] = p - row * bw


@njit(cache=True)
def block_positions_serial(pos_y, pos_x, bw, keys):
    """Row and column in a block of width ``bw`` of position ``i`` under a keyed bijection."""
    _positions_range(pos_y, pos_x, bw, keys, 0, pos_y.shape[0])


@njit(parallel=True, cache=True)
def block_positions_parallel(pos_y, pos_x, bw, keys):
    """:func:`block_positions_serial` on all threads."""
    n = pos_y.shape[0]
    n_chunks = (n + CHUNK - 1) // (CHUNK)
    for chunk in prange(n_chunks):
        _positions_range(pos_y, pos_x, bw, keys, chunk * CHUNK, min(n, (chunk + 1) * CHUNK))


@njit(cache=True)
def _tile_pair_range(pos_y, pos_x, bw, keys, start, stop):
    """Positions for groups of 2 cells from one 8x8 tile and 2 from another (pairs of tiles at random).

    A bijection of the block's positions like :func:`_positions_range`, but
    consecutive groups stay inside the same two tiles, so big blocks are read
    from the cache instead of at random from memory. Needs both block sides to
    be multiples of 8 and an even number of tiles.
    """
    n = pos_y.shape[0]
    t = TILE
    tiles_x = bw // t
    n_tiles = n // (t * t)
    bits = 2
    while (1 << bits) < n_tiles:
        bits += 1
    th = (bits + 1) // 2
    tm = (1 << th) - 1
    ch = (6 + 1) // 2  # 64 cells per tile: 6 bits
    cm = (1 << ch) - 1
    k0, k1, k2, k3 = keys[0], keys[1], keys[2], keys[3]
    per_pair = t * t // 2  # groups per pair of tiles
    for i in range(start, stop):
        q = i // 4
        m = i - 4 * q
        pair = q // per_pair
        j = q - pair * per_pair
        side = m // 2
        tile = _position(2 * pair + side, n_tiles, th, tm, k0, k1, k2, k3)
        if side == 0:
            c = _position(2 * j + (m & 1), t * t, ch, cm, k2, k3, k0, k1)
        else:
            c = _position(2 * j + (m & 1), t * t, ch, cm, k3, k1, k2, k0)
        ty = tile // tiles_x
        cy = c // t
        pos_y[i] = ty * t + cy
        pos_x[i] = (tile - ty * tiles_x) * t + (c - cy * t)


@njit(cache=True)
def tile_pair_positions_serial(pos_y, pos_x, bw, keys):
    """:func:`_tile_pair_range` over the whole block."""
    _tile_pair_range(pos_y, pos_x, bw, keys, 0, pos_y.shape[0])


@njit(parallel=True, cache=True)
def tile_pair_positions_parallel(pos_y, pos_x, bw, keys):
    """:func:`tile_pair_positions_serial` on all threads."""
    n = pos_y.shape[0]
    n_chunks = (n + CHUNK - 1) // (CHUNK)
    for chunk in prange(n_chunks):
        _tile_pair_range(pos_y, pos_x, bw, keys, chunk * CHUNK, min(n, (chunk + 1) * CHUNK))


@njit(cache=True)
def fill_positions(pos_y, pos_x, row, bw, keys, tiled, parallel):
    """Row ``row`` of the position tables for one pass (plain or tile-pair grouping)."""
    n = pos_y.shape[1]
    if parallel and n > PARALLEL_POSITIONS:
        if tiled:
            tile_pair_positions_parallel(pos_y[row], pos_x[row], bw, keys)
        else:
            block_positions_parallel(pos_y[row], pos_x[row], bw, keys)
    elif tiled:
        tile_pair_positions_serial(pos_y[row], pos_x[row], bw, keys)
    else:
        block_positions_serial(pos_y[row], pos_x[row], bw, keys)
