"""Renders of a cloud's variants from one camera that reuse the cloud's own prepared frame.

Two kinds of variant leave every remaining Gaussian's projection, depth and tile rectangle as
they were, so the per-Gaussian work of a render (projection, shading, depth sort, binning,
:meth:`Renderer.prepare`) is the cloud's and only the per-pixel blend runs again:

* a **subset** (``cloud.select(keep)`` with ``keep`` ascending, e.g. a pruning): its tile lists
  are the cloud's without the dropped Gaussians' entries (lists run by depth, then by row, and
  dropping rows keeps the order of the others);
* a **recoloured** cloud (some rows' SH coefficients replaced, their means, shapes and
  opacities not): the cloud's lists, with those rows' view colours in the depth-sorted rows;
* both at once (a subset with some of its rows recoloured, e.g. a pruning whose faintest
  view-dependent colours are zeroed).

Each image equals a fresh :class:`Renderer`'s of the variant bit for bit (the per-Gaussian
kernels work row by row): tests/test_render.py.

A third kind moves some rows (new means, shapes or opacities): :meth:`FrameVariants.moved` blends
again only the tiles those rows touch, before or after (:mod:`.moved`; tests/test_render_moved.py).
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from gscodec_shac.camera import Camera
from gscodec_shac.render.binning import TileBins
from gscodec_shac.render.projection import P_R
from gscodec_shac.render.renderer import Frame, Renderer, parse_background
from gscodec_shac.render.shading import view_colors


class FrameVariants:
    """The cloud of ``renderer`` prepared once for ``camera``; images of it and of its variants.

    Holds the renderer's workspace: render nothing else with ``renderer`` while this is in use.
    ``moved_rows``: the most rows a :meth:`moved` variant will replace (room for their parameter rows
    behind the frame's, so that the frame's are not copied for each).
    """

    def __init__(self, renderer: Renderer, camera: Camera, background: Sequence[float] = (0.0, 0.0, 0.0), *,
                 moved_rows: int = 0) -> None:
        self.renderer = renderer
        self.camera = camera
        self.background = parse_background(background)
        if moved_rows:
            renderer._workspace().reserve_pack(renderer.num_gaussians + moved_rows)
        self.frame: Frame = renderer.prepare(camera)
        self._pair_rows: np.ndarray | None = None  # the cloud's row of each tile-list entry

    def image(self) -> np.ndarray:
        """(H, W, 3) float32: the cloud's own image (as :meth:`Renderer.render`)."""
        return self.renderer.blend(self.frame.bins, self.camera, self.background)[0]

    def subset(self, keep: np.ndarray) -> np.ndarray:
        """The image of ``cloud.select(keep)`` (``keep``: ascending rows, or a boolean mask over the rows)."""
        return self.variant(keep=keep)

    def recoloured(self, rows: np.ndarray, sh_dc: np.ndarray, sh_rest: np.ndarray) -> np.ndarray:
        """The image of the cloud with the SH coefficients of ``rows`` replaced by ``sh_dc`` (len(rows), 3)
        and ``sh_rest`` (len(rows), K, 3), in the order of ``rows``."""
        return self.variant(rows=rows, sh_dc=sh_dc, sh_rest=sh_rest)

    def moved(self, rows: np.ndarray, part: Renderer, reference: np.ndarray | None = None) -> np.ndarray:
        """The image of the cloud with its ``rows`` (ascending) replaced by the Gaussians of ``part`` (a
        renderer of ``len(rows)`` Gaussians in that order: new means, shapes, opacities or colours);
        only the tiles they touch blend again (:mod:`.moved`). ``reference``: :meth:`image`, when known."""
        from gscodec_shac.render.moved import moved_image

        return moved_image(self.frame.bins, self.renderer.num_gaussians, self.camera, self.background,
                           self.image() if reference is None else reference, rows, part, self.pack_with)

    def pack_with(self, part_pack: np.ndarray) -> np.ndarray:
        """The frame's depth-sorted parameter rows followed by ``part_pack``'s: written behind the frame's
        rows in the renderer's workspace, whose first rows are the frame's, when it has room (the culled
        Gaussians' rows, and ``moved_rows``), else a new array (a copy of the frame's rows)."""
        own = self.frame.bins.pack
        rows = own.shape[0] + part_pack.shape[0]
        workspace = self.renderer._workspace().pack
        if rows > workspace.shape[0] or not np.shares_memory(own, workspace[:1]):
            return np.concatenate([own, part_pack])
        workspace[own.shape[0]:rows] = part_pack
        return workspace[:rows]

    def variant(self, keep: np.ndarray | None = None, rows: np.ndarray | None = None,
                sh_dc: np.ndarray | None = None, sh_rest: np.ndarray | None = None) -> np.ndarray:
        """The image of the cloud recoloured (``rows``' SH replaced, as :meth:`recoloured`), then reduced
        to ``keep`` (as :meth:`subset`); either may be left out."""
        bins = self.frame.bins
        lists = bins if keep is None else self._subset_lists(keep)
        if rows is None:
            return self.renderer.blend(lists, self.camera, self.background)[0]
        entry = np.full(self.renderer.num_gaussians, -1, dtype=np.int64)
        entry[bins.order] = np.arange(bins.order.size)
        entries = entry[np.asarray(rows)]
        listed = entries >= 0  # culled rows are in no list
        entries = entries[listed]
        colours = view_colors(np.ascontiguousarray(self.renderer.means[np.asarray(rows)[listed]]),
                              np.ascontiguousarray(sh_dc[listed]), np.ascontiguousarray(sh_rest[listed]),
                              self.camera.center)
        saved = bins.pack[entries, P_R:P_R + 3].copy()
        bins.pack[entries, P_R:P_R + 3] = colours  # the subset's lists share the pack
        try:
            return self.renderer.blend(lists, self.camera, self.background)[0]
        finally:
            bins.pack[entries, P_R:P_R + 3] = saved

    def _subset_lists(self, keep: np.ndarray) -> TileBins:
        """The cloud's tile lists without the entries of the rows ``keep`` leaves out."""
        bins = self.frame.bins
        mask = np.asarray(keep)
        if mask.dtype != np.bool_:
            mask = np.zeros(self.renderer.num_gaussians, dtype=np.bool_)
            mask[keep] = True
        if self._pair_rows is None:
            self._pair_rows = bins.order[bins.ids]
        listed = mask[self._pair_rows]
        kept_before = np.concatenate([[0], np.cumsum(listed, dtype=np.int64)])
        return dataclasses.replace(bins, tile_start=kept_before[bins.tile_start], ids=bins.ids[listed])
