"""Grid layout: where each Gaussian sits on the 2-D grid, and values <-> planes.

Encode: prune (rate point ``prune.min_opacity``) -> :func:`plan_grid` sorts the kept
Gaussians onto an (H, W) grid (:mod:`sorting`; PLAS, Morton, random or none) ->
:class:`GridOrder` (``order``: for each cell its row of the pruned cloud, or -1 when
empty) -> :func:`planes` turns (N, C) values in grid order into (C, H, W) planes, empty
cells repeating the previous value (smooth for the grid codecs). When empty cells lie
inside the grid, the container stores which cells are occupied (``grid_mask``).

With positions coded as a set (rate-point layout ``set``, :mod:`.positions`) the order is
not sorted but follows from the quantised positions: :func:`plan_positions_grid` puts the
k-th Gaussian in Morton order into the k-th cell of the grid's 2-D Z-order curve
(``padding = "zorder"``: the decoder knows the occupied cells without a mask).

Sorting is the slowest step of an encode and depends only on the cloud and the
rate point's sort and prune settings: :meth:`gscodec_shac.codec.Encoder.grid_order`
computes a :class:`GridOrder` once and ``Encoder.encode(cloud, grid=...)`` reuses it
(the bytes are the same).
"""

from __future__ import annotations

import zlib
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from gscodec_shac.codec import quantize as qz
from gscodec_shac.errors import BitstreamError, ValidationError
from gscodec_shac.gaussians import GaussianCloud

if TYPE_CHECKING:  # the rate points' YAML loader is not needed to place or decode a grid
    from gscodec_shac.codec.rate_points import SortSpec


class GridOrder(NamedTuple):
    """Where the (pruned) Gaussians go: grid ``shape`` (H, W), ``order`` (H*W cells ->
    row or -1), how many were ``dropped`` to fill the grid, and the ``policy`` used."""

    shape: tuple[int, int]
    order: np.ndarray
    dropped: int
    policy: str

    @property
    def padding(self) -> str:
        """``tail`` when the occupied cells are the first N, ``zorder`` when they are the first N along
        the grid's Z-order curve (positions coded as a set), else ``mask`` (stored in the file)."""
        if self.policy == GEOMETRY:
            return "zorder"
        n = int(np.count_nonzero(self.order >= 0))
        return "tail" if bool(np.all(self.order[:n] >= 0)) else "mask"

    def cells(self) -> np.ndarray:
        """The cell of each Gaussian in grid order (:func:`occupied_cells` of the padding)."""
        n = int(np.count_nonzero(self.order >= 0))
        return occupied_cells(self.padding, self.shape, n, self.order >= 0)

    def cell_rows(self, cells: np.ndarray) -> np.ndarray:
        """For each cell, the grid-order index it shows (``cells`` from :meth:`cells`): its own, or that
        of the previous occupied cell in raster order for an empty cell (the first occupied one before any)."""
        index = np.full(self.order.size, -1, dtype=np.int64)
        index[cells] = np.arange(cells.size)
        filled = np.maximum.accumulate(np.where(index >= 0, np.arange(index.size), -1))
        return np.where(filled >= 0, index[np.maximum(filled, 0)], index[cells[np.argmin(cells)]])

    def mask_chunk(self) -> tuple[bytes, int]:
        """The occupancy bits, packed and deflated, and their count (for ``padding == "mask"``)."""
        mask = np.packbits(self.order >= 0)
        return zlib.compress(mask.tobytes(), 9), int(mask.size)


#: The grid policy of set-coded positions: the order follows from them.
GEOMETRY = "geometry"


def occupied_cells(padding: str, shape: tuple[int, int], n: int, mask: np.ndarray | None = None) -> np.ndarray:
    """The cells (row-major indices) holding the ``n`` Gaussians, in grid order.

    ``tail``: the first ``n`` cells; ``mask``: the cells set in ``mask``, in raster order;
    ``zorder``: the first ``n`` cells along the grid's 2-D Z-order curve.
    """
    if padding == "tail":
        return np.arange(n)
    if padding == "zorder":
        from sorting.morton import grid_z_cells

        return grid_z_cells(shape)[:n]
    if mask is None:
        raise BitstreamError("corrupt .gsc file: a masked grid needs its mask")
    return np.flatnonzero(mask)


def plan_positions_grid(cloud: GaussianCloud, bits: int, multiple: int) -> GridOrder:
    """The grid order of set-coded positions: Morton order of the ``bits``-bit positions on the Z-order curve."""
    import sorting
    from sorting.morton import grid_z_cells

    from gscodec_shac.codec.positions import set_order

    quantizer = qz.Quantizer.fit(cloud.means, bits, qz.log_transform)
    rows = set_order(quantizer.quantize(cloud.means, qz.log_transform))
    shape = sorting.grid_shape(cloud.num_gaussians, multiple=multiple, policy="pad")
    order = np.full(shape[0] * shape[1], -1, dtype=np.int64)
    order[grid_z_cells(shape)[: rows.size]] = rows
    return GridOrder(shape, order, 0, GEOMETRY)


def kept_rows(cloud: GaussianCloud, min_opacity: float) -> np.ndarray:
    """Rows surviving opacity pruning (all rows when ``min_opacity`` is 0)."""
    if min_opacity <= 0:
        return np.arange(cloud.num_gaussians)
    kept = np.flatnonzero(qz.prune_mask(cloud, min_opacity))
    if kept.size == 0:
        raise ValidationError(f"pruning at opacity {min_opacity} removes every Gaussian")
    return kept


def placement_view(cloud: GaussianCloud, rows: np.ndarray) -> GaussianCloud:
    """The Gaussians ``rows`` of ``cloud`` with only what placement and the non-SH attributes read:
    no SH AC coefficients (an SH degree 0 cloud) and no extra properties. When ``rows`` are all of
    them (sorted, as :func:`kept_rows` gives them) the arrays are shared, else 14 floats per Gaussian
    are copied instead of the 59 of a degree-3 model."""
    view = GaussianCloud(means=cloud.means, scales=cloud.scales, quats=cloud.quats, opacities=cloud.opacities,
                         sh_dc=cloud.sh_dc, sh_rest=np.zeros((cloud.num_gaussians, 0, 3), np.float32))
    return view if rows.size == cloud.num_gaussians else view.select(rows)


def plan_grid(cloud: GaussianCloud, spec: SortSpec, progress: bool = False) -> GridOrder:
    """Sort ``cloud`` onto a grid as ``spec`` says.

    The drop policy falls back to padding when the cloud fills less than one
    ``multiple`` x ``multiple`` block.
    """
    import sorting

    n = cloud.num_gaussians
    try:
        policy = spec.policy if not (spec.policy == "drop" and n < spec.multiple**2) else "pad"
        shape = sorting.grid_shape(n, multiple=spec.multiple, policy=policy)
        keep = np.arange(n)
        if policy == "drop" and shape[0] * shape[1] < n:
            keep = sorting.select_for_grid(importance(cloud), shape[0] * shape[1])
        sources = {
            "xyz": lambda: cloud.means, "scale": lambda: cloud.scales, "opacity": lambda: cloud.opacities,
            "dc": lambda: cloud.sh_dc, "rotation": lambda: qz.canonical_quaternions(cloud.quats),
        }
        # only the attributes sorted by are read (the rotation's canonical form is not free: 0.3 s at 1M)
        attributes = {k: get() if keep.size == n else get()[keep]
                      for k, get in sources.items() if spec.weights.get(k, 0) > 0}
        if spec.method == "none":
            local = sorting.sort_to_grid(np.zeros((keep.size, 1), np.float32), shape, method="none")
        else:
            weights = {k: spec.weights[k] for k in attributes}
            features = sorting.prepare_features(attributes, weights, spec.normalize)
            schedule = spec.schedule if spec.method == "plas" else {}
            local = sorting.sort_to_grid(features, shape, method=spec.method, seed=spec.seed, progress=progress,
                                         **schedule)
    except sorting.SortingError as exc:
        raise ValidationError(f"sorting: {exc}") from None
    order = np.where(local >= 0, keep[np.maximum(local, 0)], -1)
    return GridOrder(shape, order, int(n - keep.size), policy)


def check_grid(grid: GridOrder, cloud: GaussianCloud) -> GridOrder:
    """A caller's placement, checked against the (pruned) cloud it is used for."""
    from sorting.errors import SortingError
    from sorting.grid import check_order

    shape, order, dropped, policy = grid
    order = np.asarray(order)
    if len(shape) != 2 or int(shape[0]) * int(shape[1]) != order.size:
        raise ValidationError(f"grid order has {order.size} cells, shape {tuple(shape)} has a different count")
    try:
        order = check_order(order.reshape(-1), cloud.num_gaussians)
    except SortingError as exc:
        raise ValidationError(f"grid order does not fit this cloud: {exc}") from None
    return GridOrder((int(shape[0]), int(shape[1])), order, int(dropped), str(policy))


def importance(cloud: GaussianCloud) -> np.ndarray:
    """What the drop policy keeps: opacity times footprint area (exp of twice the mean log-scale)."""
    return cloud.activated_opacities() * np.exp(2.0 * cloud.scales.astype(np.float64).mean(axis=1))


def planes(values: np.ndarray, cell_rows: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(N, C) grid-order values -> (C, H, W) planes; empty cells repeat the previous value.

    Gathered a channel at a time straight into the planes (no (H*W, C) intermediate)."""
    out = np.empty((values.shape[1], shape[0] * shape[1]), dtype=values.dtype)
    for c in range(values.shape[1]):
        np.take(values[:, c], cell_rows, out=out[c])
    return out.reshape(values.shape[1], *shape)


def occupied(flat: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(C, H*W) decoded planes -> (N, C) values of the occupied ``cells`` (in grid order)."""
    return flat[:, cells].T


def unpack_mask(bits: bytes, n: int, cells: int) -> np.ndarray:
    """Inverse of :meth:`GridOrder.mask_chunk` (already inflated); checked against ``n`` Gaussians."""
    packed = np.frombuffer(bits, dtype=np.uint8)
    if packed.size != (cells + 7) // 8:
        raise BitstreamError("corrupt .gsc file: grid mask has the wrong size")
    mask = np.unpackbits(packed, count=cells).astype(bool)
    if int(mask.sum()) != n:
        raise BitstreamError("corrupt .gsc file: grid mask does not match the Gaussian count")
    return mask


def qp_runs(qps: list) -> list[tuple[int, int]]:
    """Maximal runs of equal QP: [(start, stop), ...] (each run is one chunk)."""
    runs, start = [], 0
    for i in range(1, len(qps) + 1):
        if i == len(qps) or qps[i] != qps[start]:
            runs.append((start, i))
            start = i
    return runs
