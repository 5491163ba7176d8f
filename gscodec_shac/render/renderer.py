"""The CPU renderer: :class:`Renderer`, :func:`render`, :func:`render_weights`, :func:`render_views`.

A :class:`Renderer` caches what does not depend on the camera (3D covariances, activated
opacities); per camera it projects (:mod:`.projection`), shades (:mod:`.shading`), bins
(:mod:`.binning`) and blends (:mod:`.raster`). Images are float32 ``(H, W, 3)`` and *not*
clipped (clip when saving or measuring, as :func:`gscodec_shac.render.output.save_png` and
:mod:`gscodec_shac.metrics` do).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import scipy.sparse

from gscodec_shac.camera import Camera
from gscodec_shac.errors import ValidationError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.geometry import covariances
from gscodec_shac.limits import check_render_memory
from gscodec_shac.render.binning import TileBins, bin_gaussians
from gscodec_shac.render.projection import (
    P_A,
    P_C,
    P_DEPTH,
    P_R,
    P_X,
    PACK_WIDTH,
    Projection,
    alpha_extent,
    camera_params,
    project_into,
)
from gscodec_shac.render.raster import blend_totals, blend_weights, rasterize
from gscodec_shac.render.shading import view_colors

_COV_CHUNK = 1 << 18


@dataclass
class RenderResult:
    """One rendered view.

    ``image`` (H, W, 3) float32 in [0, inf), not clipped, background included; ``alpha``
    (H, W) float32 accumulated opacity ``1 - T_final``; ``depth`` (H, W) float32 expected
    camera-space depth ``sum(w z) / alpha`` (0 where alpha is 0), only when asked for;
    ``n_rendered`` Gaussians listed in at least one tile; ``n_visible`` Gaussians that pass the
    reference's culling (``radii > 0``); ``n_pairs`` tile-list entries; ``radii`` (N,) int32.
    """

    image: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray | None
    n_rendered: int
    n_visible: int
    n_pairs: int
    radii: np.ndarray


@dataclass
class Frame:
    """Everything computed for one camera before blending (what a backward pass would reuse).

    Arrays are views into the renderer's workspace, valid until its next call.
    """

    camera: Camera
    projection: Projection
    colors: np.ndarray  # (N, 3) float64; rows of culled Gaussians are meaningless
    bins: TileBins


class _Workspace:
    """Buffers reused from view to view (fresh multi-100 MB arrays per view cost page faults)."""

    def __init__(self, n: int) -> None:
        # the packs' last column is padding no kernel writes: zeros (calloc, no page touched here), so
        # that a frame's rows hold the same bytes in every workspace (garbage made equal packs differ)
        self.pack_n = np.zeros((n, PACK_WIDTH))
        self.rects_n = np.empty((n, 4), dtype=np.int32)
        self.radii = np.empty(n, dtype=np.int32)
        self.keys = np.empty(n, dtype=np.uint64)
        self.order = np.empty(n, dtype=np.int64)
        self.pack = np.zeros((n, PACK_WIDTH))
        self.rects = np.empty((n, 4), dtype=np.int32)
        self.pixels: dict[str, np.ndarray] = {}

    def reserve_pack(self, rows: int) -> None:
        """Room for ``rows`` depth-sorted parameter rows (a frame's, then rows appended behind them,
        :meth:`.variants.FrameVariants.pack_with`); call it before preparing the frame."""
        if self.pack.shape[0] < rows:
            self.pack = np.zeros((rows, PACK_WIDTH))


def parse_background(background: Sequence[float] | np.ndarray) -> np.ndarray:
    """A background colour as a float64 (3,) array (one value per RGB channel)."""
    try:
        bg = np.asarray(background, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValidationError(f"background must be three numbers (R, G, B), got {background!r}") from None
    if bg.shape != (3,) or not np.all(np.isfinite(bg)):
        raise ValidationError(f"background must be three finite numbers (R, G, B), got {background!r}")
    return bg


def _upper_covariances(cloud: GaussianCloud) -> np.ndarray:
    """(N, 6) float64 (xx, xy, xz, yy, yz, zz) of the 3D covariances, computed in chunks."""
    n = cloud.num_gaussians
    out = np.empty((n, 6))
    rows, cols = np.triu_indices(3)
    for start in range(0, n, _COV_CHUNK):
        sl = slice(start, start + _COV_CHUNK)
        out[sl] = covariances(cloud.scales[sl], cloud.quats[sl])[:, rows, cols]
    return out


class Renderer:
    """Renders one :class:`GaussianCloud` from any number of cameras.

    Caches the camera-independent parts (3D covariances, activated opacities, alpha extents)
    and reuses its buffers between views. The cloud's arrays are read, never modified; build a
    new renderer after changing them. Not thread-safe: use one renderer per thread.
    """

    def __init__(self, cloud: GaussianCloud, *, covariances: np.ndarray | None = None) -> None:
        """``covariances``: the cloud's (N, 6) upper 3D covariances when the caller has them (e.g. the
        ``cov3`` of a renderer of a cloud with the same scales and rotations), else computed here."""
        if not isinstance(cloud, GaussianCloud):
            raise ValidationError(f"Renderer needs a GaussianCloud, got {type(cloud).__name__}")
        if covariances is not None and np.shape(covariances) != (cloud.num_gaussians, 6):
            raise ValidationError(f"covariances have shape {np.shape(covariances)}, "
                                  f"expected ({cloud.num_gaussians}, 6)")
        self.cloud = cloud
        self.means = np.ascontiguousarray(cloud.means, dtype=np.float32)
        self.cov3 = _upper_covariances(cloud) if covariances is None else np.asarray(covariances, dtype=np.float64)
        self.opacities = cloud.activated_opacities()
        self.tau = alpha_extent(self.opacities)
        self._ws: _Workspace | None = None

    @property
    def num_gaussians(self) -> int:
        return self.cloud.num_gaussians

    def _workspace(self) -> _Workspace:
        if self._ws is None:
            self._ws = _Workspace(self.num_gaussians)
        return self._ws

    # ----------------------------------------------------------------- stages
    def _project(self, camera: Camera) -> Projection:
        ws = self._workspace()
        project_into(
            self.means, self.cov3, self.opacities, self.tau, camera_params(_check_camera(camera)),
            ws.pack_n, ws.rects_n, ws.radii, ws.keys,
        )
        pack = ws.pack_n
        return Projection(pack[:, P_X:P_X + 2], pack[:, P_A:P_C + 1], pack[:, P_DEPTH], ws.radii, ws.rects_n)

    def project(self, camera: Camera) -> Projection:
        """Screen-space means, conics, depths, radii and tile rectangles for ``camera`` (a copy)."""
        return self._project(camera).copy()

    def colors(self, camera: Camera, mask: np.ndarray | None = None) -> np.ndarray:
        """(N, 3) float64 clamped SH colours seen from ``camera`` (rows outside ``mask`` are 0)."""
        out = np.zeros((self.num_gaussians, 3))
        view_colors(self.means, self.cloud.sh_dc, self.cloud.sh_rest, _check_camera(camera).center, mask, out)
        return out

    def prepare(self, camera: Camera, *, shade: bool = True) -> Frame:
        """Project, shade and bin for ``camera`` (everything but the per-pixel blend); without ``shade``
        the colours are left unset (for the blend's weights, which do not depend on them)."""
        projection = self._project(camera)
        check_render_memory(camera.width, camera.height, f"camera {camera.name!r}")
        ws = self._workspace()
        if shade:
            view_colors(
                self.means, self.cloud.sh_dc, self.cloud.sh_rest, camera.center, projection.radii > 0, ws.pack_n, P_R
            )
        colors = ws.pack_n[:, P_R:P_R + 3]
        bins = bin_gaussians(ws.keys, ws.pack_n, ws.rects_n, camera.width, camera.height, ws.order, ws.pack, ws.rects)
        return Frame(camera, projection, colors, bins)

    # ---------------------------------------------------------------- outputs
    def render(
        self, camera: Camera, *, background: Sequence[float] = (0.0, 0.0, 0.0), depth: bool = False
    ) -> RenderResult:
        """Render ``camera``; see :class:`RenderResult`."""
        bg = parse_background(background)
        frame = self.prepare(camera)
        w, h = camera.width, camera.height
        image, trans, depth_sum = self.blend(frame.bins, camera, bg)
        alpha = (1.0 - trans).reshape(h, w)
        depth_map = None
        if depth:
            with np.errstate(divide="ignore", invalid="ignore"):
                depth_map = np.where(alpha > 0, depth_sum.reshape(h, w) / alpha, 0.0).astype(np.float32)
        return RenderResult(
            image=image, alpha=alpha.astype(np.float32), depth=depth_map,
            n_rendered=frame.bins.n_touching, n_visible=int(np.count_nonzero(frame.projection.radii)),
            n_pairs=frame.bins.n_pairs, radii=frame.projection.radii.copy(),
        )

    def blend(self, bins: TileBins, camera: Camera,
              background: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(image (H, W, 3) float32, transmittance (H*W,), weighted depth sum (H*W,))`` of tile lists ``bins``
        (:meth:`prepare`'s, or lists derived from them) over ``background`` (a (3,) float64 array)."""
        w, h = camera.width, camera.height
        ws = self._workspace()
        color, trans, depth_sum, last = rasterize(bins, w, h, ws.pixels)
        ws.pixels = {"color": color, "trans": trans, "depth": depth_sum, "last": last}
        image = np.empty((h, w, 3), dtype=np.float32)
        np.add(color, trans[:, None] * background, out=image.reshape(-1, 3), casting="unsafe")
        return image, trans, depth_sum

    def weights(self, camera: Camera) -> tuple[scipy.sparse.csr_matrix, np.ndarray]:
        """``(W, T)``: blending weights (H*W, N) and final transmittance (H*W,).

        ``W[i, j] = alpha_j T_j`` at pixel ``i`` (row-major, ``i = y * width + x``), so the
        image is ``W @ colours + T[:, None] * background`` exactly, with ``colours`` from
        :meth:`colors`. With geometry fixed the image is linear in the colours.
        """
        frame = self.prepare(camera)
        indptr, cols, vals, trans = blend_weights(frame.bins, camera.width, camera.height)
        matrix = scipy.sparse.csr_matrix(
            (vals, cols, indptr), shape=(camera.width * camera.height, self.num_gaussians)
        )
        matrix.sort_indices()
        return matrix, trans

    def contributions(self, camera: Camera) -> np.ndarray:
        """(N,) each Gaussian's blending weights ``alpha_j T_j`` summed over the pixels of ``camera``.

        The column sums of :meth:`weights`' matrix, accumulated inside the blend (no matrix).
        """
        frame = self.prepare(camera, shade=False)
        return blend_totals(frame.bins, camera.width, camera.height, self.num_gaussians)


def _check_camera(camera: Camera) -> Camera:
    if not isinstance(camera, Camera):
        raise ValidationError(f"expected a Camera, got {type(camera).__name__}")
    return camera


def render(
    cloud: GaussianCloud, camera: Camera, *, background: Sequence[float] = (0.0, 0.0, 0.0), depth: bool = False
) -> RenderResult:
    """Render ``cloud`` from ``camera`` (one-off; use :class:`Renderer` for many views)."""
    return Renderer(cloud).render(camera, background=background, depth=depth)


def render_weights(cloud: GaussianCloud, camera: Camera) -> tuple[scipy.sparse.csr_matrix, np.ndarray]:
    """Blending weights (H*W, N) CSR and final transmittance (H*W,); see :meth:`Renderer.weights`."""
    return Renderer(cloud).weights(camera)


def gaussian_colors(cloud: GaussianCloud, camera: Camera) -> np.ndarray:
    """(N, 3) float64 clamped SH colours of every Gaussian seen from ``camera``."""
    return Renderer(cloud).colors(camera)


def render_views(
    cloud: GaussianCloud,
    cameras: Sequence[Camera],
    out_dir: str | os.PathLike | None = None,
    *,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    progress: bool = True,
) -> list[np.ndarray] | list[Path]:
    """Render every camera, with a tqdm progress bar.

    Without ``out_dir`` returns the float32 images; with it, writes ``<camera name>.png``
    (8-bit, clipped) there (created) and returns the paths, keeping no image in memory.
    """
    from tqdm import tqdm

    from gscodec_shac.render.output import png_names, save_png

    bg = parse_background(background)
    renderer = Renderer(cloud)
    out = Path(out_dir) if out_dir is not None else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    results: list = []
    cameras = list(cameras)
    names = png_names([camera.name for camera in cameras])
    for index, camera in enumerate(tqdm(cameras, desc="render", unit="view", disable=not progress)):
        image = renderer.render(camera, background=bg).image
        if out is None:
            results.append(image)
        else:
            path = out / names[index]
            save_png(path, image)
            results.append(path)
    return results

