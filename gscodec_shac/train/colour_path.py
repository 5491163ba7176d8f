"""Differentiable colour path: rendering with fixed geometry as a sparse linear map of colours.

With means, scales, rotations and opacities fixed, the 3DGS blend of one view is linear in the
per-Gaussian colours (the alpha values and transmittances do not depend on colour)::

    image(h) = W c(h) + T_final * background,        c_i(h) = max(0, 0.5 + sum_k y_k(d_i) h_ik)

``W`` (H*W x N) holds the blending weights ``alpha_i T_i`` that the rasteriser exports
(:func:`gscodec_shac.render.render_weights`), ``T_final`` the transmittance left after the
last contributor, ``y_k(d_i)`` the SH basis (paper eq. 8, 3DGS constants) for the direction
``d_i = mean_i - camera centre`` and ``h`` the SH coefficients (DC and AC). With SHAC-LST the
AC part is ``A~ = S T`` (eq. 33), so the image is differentiable in ``S`` and ``T``.

Per view, :func:`build_view` runs the rasteriser's weight export once and keeps only the
Gaussians that reach at least one pixel (``ViewData.index``), with ``W`` restricted to them
(CSR, int32 indices) and their SH basis values ``Y`` (n_used x (L+1)^2). A step then costs two
sparse products with three columns (forward ``W c``, backward ``W^T g``; numba kernels, ~3 ms
each for 1.3M non-zeros) plus small dense algebra: about 15x cheaper than differentiating
the rasteriser. (torch's CSR product was measured: its forward is as fast, but its backward
to the dense operand took ~170 ms per view here, hence the kernels.)

:class:`ViewCache` holds the views under a byte budget (least recently used views are dropped
and rebuilt on demand); ``ViewData.nbytes`` is what each one costs.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numba
import numpy as np
import torch

from gscodec_shac.camera import Camera
from gscodec_shac.errors import ValidationError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.render import Renderer
from gscodec_shac.render.renderer import parse_background
from gscodec_shac.sh import sh_basis

#: Default byte budget of a :class:`ViewCache` (4 GiB).
DEFAULT_CACHE_BYTES = 4 << 30

_DTYPES = {"float32": (np.float32, torch.float32), "float64": (np.float64, torch.float64)}


def resolve_dtype(dtype: str | torch.dtype | np.dtype | type) -> tuple[np.dtype, torch.dtype]:
    """``(numpy dtype, torch dtype)`` for ``"float32"`` / ``"float64"`` (or the matching dtypes)."""
    if isinstance(dtype, torch.dtype):
        name = {torch.float32: "float32", torch.float64: "float64"}.get(dtype)
    else:
        try:
            name = np.dtype(dtype).name
        except TypeError:
            name = None
    if name not in _DTYPES:
        raise ValidationError(f"the colour path works in float32 or float64, got {dtype!r}")
    np_dtype, torch_dtype = _DTYPES[name]
    return np.dtype(np_dtype), torch_dtype


# ----------------------------------------------------------------------------- kernels
@numba.njit(cache=True)
def _csr_times(indptr, columns, values, x, out):  # pragma: no cover - compiled
    """out = W x for W in CSR form and x with three columns (float64 accumulation)."""
    for i in range(indptr.shape[0] - 1):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        for j in range(indptr[i], indptr[i + 1]):
            w = np.float64(values[j])
            k = columns[j]
            a0 += w * x[k, 0]
            a1 += w * x[k, 1]
            a2 += w * x[k, 2]
        out[i, 0] = a0
        out[i, 1] = a1
        out[i, 2] = a2


@numba.njit(cache=True)
def _csr_transpose_times(indptr, columns, values, g, out):  # pragma: no cover - compiled
    """out = W^T g (out zeroed here); serial scatter, so the result is deterministic."""
    out[:] = 0.0
    for i in range(indptr.shape[0] - 1):
        g0 = g[i, 0]
        g1 = g[i, 1]
        g2 = g[i, 2]
        if g0 == 0.0 and g1 == 0.0 and g2 == 0.0:
            continue
        for j in range(indptr[i], indptr[i + 1]):
            w = values[j]
            k = columns[j]
            out[k, 0] += w * g0
            out[k, 1] += w * g1
            out[k, 2] += w * g2


# ----------------------------------------------------------------------------- one view
@dataclass
class ViewData:
    """Everything a view needs for differentiable colour rendering (geometry fixed).

    ``index`` (n_used,) ascending ids of the Gaussians with a non-zero weight somewhere;
    ``indptr`` / ``columns`` / ``values``: ``W`` restricted to them, CSR (H*W x n_used), columns
    indexing ``index``; ``trans`` (H*W,) final transmittance; ``basis`` (n_used, (L+1)^2) SH
    basis ``y_k(d_i)``; ``target`` (H, W, 3) float32 image the loss compares with, or None.
    """

    camera: Camera
    index: torch.Tensor
    indptr: np.ndarray
    columns: np.ndarray
    values: np.ndarray
    trans: torch.Tensor
    basis: torch.Tensor
    target: torch.Tensor | None = None
    build_seconds: float = 0.0

    @property
    def n_pixels(self) -> int:
        return int(self.indptr.shape[0] - 1)

    @property
    def n_used(self) -> int:
        return int(self.index.shape[0])

    @property
    def nnz(self) -> int:
        return int(self.values.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the image."""
        return (self.camera.height, self.camera.width)

    @property
    def nbytes(self) -> int:
        """Memory held by this view's arrays."""
        arrays = [self.indptr, self.columns, self.values]
        tensors = [self.index, self.trans, self.basis] + ([self.target] if self.target is not None else [])
        return int(sum(a.nbytes for a in arrays) + sum(t.element_size() * t.numel() for t in tensors))

    def weights_dense(self, n_gaussians: int) -> np.ndarray:
        """``W`` as a dense (H*W, N) float64 array over all Gaussians (tests, tiny scenes only)."""
        out = np.zeros((self.n_pixels, n_gaussians))
        rows = np.repeat(np.arange(self.n_pixels), np.diff(self.indptr))
        np.add.at(out, (rows, self.index.numpy()[self.columns]), self.values.astype(np.float64))
        return out


def build_view(
    renderer: Renderer, camera: Camera, *, dtype: str | torch.dtype = "float32"
) -> ViewData:
    """Export ``W`` and ``T_final`` of ``camera`` once and the SH basis of its directions."""
    np_dtype, torch_dtype = resolve_dtype(dtype)
    start = time.perf_counter()
    weights, trans = renderer.weights(camera)
    n = renderer.num_gaussians
    index = np.flatnonzero(np.bincount(weights.indices, minlength=n))
    remap = np.full(n, -1, dtype=np.int32)
    remap[index] = np.arange(index.shape[0], dtype=np.int32)
    if weights.nnz >= np.iinfo(np.int32).max:
        raise ValidationError(f"view {camera.name!r} has {weights.nnz} blending weights, too many for int32 indices")
    directions = renderer.means[index].astype(np.float64) - camera.center
    basis = sh_basis(directions, renderer.cloud.sh_degree)
    return ViewData(
        camera=camera,
        index=torch.from_numpy(index.astype(np.int64)),
        indptr=weights.indptr.astype(np.int32),
        columns=remap[weights.indices],
        values=weights.data.astype(np_dtype),
        trans=torch.from_numpy(np.asarray(trans, dtype=np_dtype)),
        basis=torch.from_numpy(basis.astype(np_dtype)),
        build_seconds=time.perf_counter() - start,
    )


class _Blend(torch.autograd.Function):
    """``W c`` with the backward ``W^T g`` (W constant)."""

    @staticmethod
    def forward(ctx, colours: torch.Tensor, view: ViewData) -> torch.Tensor:  # type: ignore[override]
        c = np.ascontiguousarray(colours.detach().numpy())
        out = np.empty((view.n_pixels, 3), dtype=c.dtype)
        _csr_times(view.indptr, view.columns, view.values, c, out)
        ctx.view = view
        return torch.from_numpy(out)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:  # type: ignore[override]
        view: ViewData = ctx.view
        g = np.ascontiguousarray(grad.detach().numpy())
        out = np.empty((view.n_used, 3), dtype=g.dtype)
        _csr_transpose_times(view.indptr, view.columns, view.values, g, out)
        return torch.from_numpy(out), None


def blend(view: ViewData, colours: torch.Tensor) -> torch.Tensor:
    """``W c`` (H*W, 3) for colours (n_used, 3) of ``view.index``, differentiable in ``c``."""
    if colours.shape != (view.n_used, 3):
        raise ValidationError(f"expected colours of shape ({view.n_used}, 3), got {tuple(colours.shape)}")
    return _Blend.apply(colours, view)


def sh_colours(basis: torch.Tensor, dc: torch.Tensor, ac: torch.Tensor) -> torch.Tensor:
    """``max(0, 0.5 + y_0 dc + sum_{k>0} y_k h_k)`` per row (eq. 8, 3DGS offset and clamp).

    ``basis`` (n, K), ``dc`` (n, 3), ``ac`` (n, 3(K-1)) in the paper's AC order (R, G, B of
    each coefficient adjacent, :mod:`gscodec_shac.sh_index`).
    """
    n, k = basis.shape
    if dc.shape != (n, 3) or ac.shape != (n, 3 * (k - 1)):
        raise ValidationError(
            f"expected dc ({n}, 3) and ac ({n}, {3 * (k - 1)}), got {tuple(dc.shape)} and {tuple(ac.shape)}"
        )
    rest = ac.reshape(n, k - 1, 3)
    raw = 0.5 + basis[:, :1] * dc + (basis[:, 1:, None] * rest).sum(dim=1)
    return torch.clamp_min(raw, 0.0)


def render_view(
    view: ViewData, dc: torch.Tensor, ac: torch.Tensor, background: Sequence[float] | torch.Tensor = (0.0, 0.0, 0.0)
) -> torch.Tensor:
    """(H, W, 3) image of ``view`` from the SH of its used Gaussians (rows of ``view.index``)."""
    colours = sh_colours(view.basis, dc, ac)
    image = blend(view, colours)
    bg = torch.as_tensor(parse_background(background) if not torch.is_tensor(background) else background,
                         dtype=image.dtype)
    image = image + view.trans.to(image.dtype)[:, None] * bg
    return image.reshape(view.camera.height, view.camera.width, 3)


def render_cloud_view(view: ViewData, cloud: GaussianCloud, background: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(H, W, 3) float32 image of ``cloud``'s own SH through the colour path (no gradient)."""
    idx = view.index.numpy()
    dtype = view.basis.dtype
    with torch.no_grad():
        image = render_view(
            view,
            torch.from_numpy(cloud.sh_dc[idx].astype(np.float64)).to(dtype),
            torch.from_numpy(cloud.ac_matrix()[idx].astype(np.float64)).to(dtype),
            background,
        )
    return image.numpy().astype(np.float32)


# ----------------------------------------------------------------------------- cache
TargetFn = Callable[[int, ViewData], np.ndarray]


@dataclass
class CacheStats:
    """Hits, misses (builds), seconds spent building, bytes held now and at most."""

    hits: int = 0
    misses: int = 0
    build_seconds: float = 0.0
    bytes: int = 0
    peak_bytes: int = 0
    evictions: int = 0
    view_bytes: list[int] = field(default_factory=list)

    def as_dict(self) -> dict:
        sizes = self.view_bytes
        return {
            "hits": self.hits, "misses": self.misses, "evictions": self.evictions,
            "build_seconds": round(self.build_seconds, 3), "bytes": self.bytes, "peak_bytes": self.peak_bytes,
            "median_view_bytes": int(np.median(sizes)) if sizes else 0,
        }


class ViewCache:
    """Per-camera :class:`ViewData` for one fixed geometry, least recently used first out.

    ``target`` (optional) gives each view's target image when it is built (kept in the
    entry, counted in its bytes). At least one view is always kept, whatever the budget.
    """

    def __init__(
        self,
        cloud: GaussianCloud,
        cameras: Sequence[Camera],
        *,
        dtype: str | torch.dtype = "float32",
        max_bytes: int = DEFAULT_CACHE_BYTES,
        target: TargetFn | None = None,
    ) -> None:
        if not cameras:
            raise ValidationError("the colour path needs at least one camera")
        if max_bytes < 0:
            raise ValidationError(f"the view cache budget must be >= 0 bytes, got {max_bytes}")
        self.cloud = cloud
        self.cameras = list(cameras)
        self.dtype = resolve_dtype(dtype)[1]
        self.max_bytes = int(max_bytes)
        self.target = target
        self.renderer = Renderer(cloud)
        self.stats = CacheStats()
        self._views: OrderedDict[int, ViewData] = OrderedDict()

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def n_cached(self) -> int:
        return len(self._views)

    def __contains__(self, i: int) -> bool:
        return i in self._views

    def __getitem__(self, i: int) -> ViewData:
        view = self._views.get(i)
        if view is not None:
            self._views.move_to_end(i)
            self.stats.hits += 1
            return view
        if not 0 <= i < len(self.cameras):
            raise IndexError(f"view {i} out of range (0..{len(self.cameras) - 1})")
        start = time.perf_counter()
        view = build_view(self.renderer, self.cameras[i], dtype=self.dtype)
        if self.target is not None:
            view.target = torch.from_numpy(np.ascontiguousarray(self.target(i, view), dtype=np.float32))
            if tuple(view.target.shape) != (*view.shape, 3):
                raise ValidationError(
                    f"target of view {self.cameras[i].name!r} has shape {tuple(view.target.shape)}, "
                    f"expected {(*view.shape, 3)}"
                )
        self.stats.misses += 1
        self.stats.build_seconds += time.perf_counter() - start
        self.stats.view_bytes.append(view.nbytes)
        self._views[i] = view
        self.stats.bytes += view.nbytes
        while self.stats.bytes > self.max_bytes and len(self._views) > 1:
            _, old = self._views.popitem(last=False)
            self.stats.bytes -= old.nbytes
            self.stats.evictions += 1
        self.stats.peak_bytes = max(self.stats.peak_bytes, self.stats.bytes)
        return view

    def fits_all(self) -> bool:
        """Whether every view would fit the budget, judged from the views built so far."""
        if not self.stats.view_bytes:
            return True
        return float(np.max(self.stats.view_bytes)) * len(self.cameras) <= self.max_bytes

    def clear(self) -> None:
        self._views.clear()
        self.stats.bytes = 0
