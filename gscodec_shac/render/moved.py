"""The image of a cloud with a few rows moved (new means, shapes, opacities or colours), from the cloud's own
prepared frame: only the tiles those rows touch, before or after, are blended again.

A fresh render of the moved cloud lists, in each tile, every Gaussian whose alpha ellipse meets it,
by ``(float32 depth, row)``. The rows that did not move project, shade and bin exactly as in the
cloud's frame (the per-Gaussian kernels work row by row), so a tile that neither the old nor the new
versions of the moved rows touch has the frame's list and the frame's pixels. In the other tiles the
list is the frame's without the moved rows' old entries, merged by the same key with the moved rows'
new entries (binned by a renderer of those rows alone). The image equals a fresh render's bit for
bit (tests/test_render_moved.py), at the cost of a render of the moved rows and of the tiles they touch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numba
import numpy as np

from gscodec_shac.render.binning import TileBins
from gscodec_shac.render.projection import BLOCK
from gscodec_shac.render.raster import rasterize

if TYPE_CHECKING:
    from gscodec_shac.camera import Camera
    from gscodec_shac.render.renderer import Renderer

_LOW = np.uint64(0xFFFFFFFF)


@numba.njit(cache=True)
def _touched_tiles(tile_start, ids, entry_moved, touched):  # pragma: no cover - compiled
    """Mark the tiles whose lists hold an entry of a moved row."""
    for t in range(tile_start.shape[0] - 1):
        for e in range(tile_start[t], tile_start[t + 1]):
            if entry_moved[ids[e]]:
                touched[t] = True
                break


@numba.njit(cache=True)
def _merge_lists(tiles, f_start, f_ids, f_keys, f_moved, p_start, p_ids, p_keys, offset,
                 n_tiles):  # pragma: no cover - compiled
    """Tile lists of ``tiles``: the frame's entries of rows that stayed and the part's entries (ids
    shifted by ``offset``), merged by key; every other tile's list is empty."""
    counts = np.zeros(n_tiles, dtype=np.int64)
    for t in tiles:
        kept = 0
        for e in range(f_start[t], f_start[t + 1]):
            if not f_moved[f_ids[e]]:
                kept += 1
        counts[t] = kept + p_start[t + 1] - p_start[t]
    start = np.zeros(n_tiles + 1, dtype=np.int64)
    for t in range(n_tiles):
        start[t + 1] = start[t] + counts[t]
    ids = np.empty(start[n_tiles], dtype=np.int32)
    for t in tiles:
        out = start[t]
        i, i_end = f_start[t], f_start[t + 1]
        j, j_end = p_start[t], p_start[t + 1]
        while True:
            while i < i_end and f_moved[f_ids[i]]:
                i += 1
            if i >= i_end and j >= j_end:
                break
            if j >= j_end or (i < i_end and f_keys[f_ids[i]] < p_keys[p_ids[j]]):
                ids[out] = f_ids[i]
                i += 1
            else:
                ids[out] = p_ids[j] + offset
                j += 1
            out += 1
    return start, ids


def moved_image(bins: TileBins, num_rows: int, camera: "Camera", background: np.ndarray, reference: np.ndarray,
                rows: np.ndarray, part: "Renderer", pack_with: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """(H, W, 3) float32: the image of a cloud of ``num_rows`` Gaussians, prepared for ``camera`` as
    ``bins`` (its image over ``background``: ``reference``), with its ``rows`` (ascending) replaced by
    ``part``'s Gaussians (a renderer of as many, in the order of ``rows``); ``pack_with(part_pack)``: the
    frame's parameter rows followed by ``part_pack``'s (:meth:`.variants.FrameVariants.pack_with`)."""
    rows = np.asarray(rows, dtype=np.int64)
    if part.num_gaussians != rows.size:
        raise ValueError(f"{part.num_gaussians} moved Gaussians for {rows.size} rows")
    if rows.size > 1 and not np.all(np.diff(rows) > 0):  # the keys' ties go by row, as in a whole render
        raise ValueError("the moved rows must be ascending")
    moved_row = np.zeros(num_rows, dtype=np.bool_)
    moved_row[rows] = True
    entry_moved = moved_row[bins.order]
    n_tiles = bins.tile_start.size - 1
    touched = np.zeros(n_tiles, dtype=np.bool_)
    _touched_tiles(bins.tile_start, bins.ids, entry_moved, touched)
    new = part.prepare(camera).bins
    touched |= np.diff(new.tile_start) > 0
    tiles = np.flatnonzero(touched)
    part_keys = (new.keys & ~_LOW) | rows[new.order].astype(np.uint64)  # the moved rows' keys in the cloud
    start, ids = _merge_lists(tiles, bins.tile_start, bins.ids, bins.keys, entry_moved,
                              new.tile_start, new.ids, part_keys, bins.order.size, n_tiles)
    pack = pack_with(new.pack)
    merged = TileBins(bins.order, pack, bins.rects, start, ids, bins.tiles_x, bins.tiles_y, 0)
    color, trans, _, _ = rasterize(merged, camera.width, camera.height, only=tiles)
    image = reference.copy()
    pixels = _tile_pixels(touched, bins.tiles_x, camera.width, camera.height).reshape(-1)
    # the blend's sum over the background, cast to float32 as Renderer.blend does
    image.reshape(-1, 3)[pixels] = color[pixels] + trans[pixels, None] * background
    return image


def _tile_pixels(tiles: np.ndarray, tiles_x: int, width: int, height: int) -> np.ndarray:
    """(H, W) bool: the pixels of the marked tiles."""
    grid = tiles.reshape(-1, tiles_x)
    return np.repeat(np.repeat(grid, BLOCK, axis=0), BLOCK, axis=1)[:height, :width]
