"""Per-Gaussian SH degree: Gaussians whose view-dependent colour is negligible keep their DC only.

A Gaussian's view-dependent colour is its AC coefficients times the SH basis (paper Eq. 2);
the basis is orthonormal over the sphere, so the mean square of that colour over all view
directions is proportional to the squared norm of its AC row. Weighted by how much the
Gaussian shows (``alpha``: its opacity; ``render``: its summed blending weight over the views,
:mod:`.importance`), that is the energy dropped from the images when the AC row is zeroed. The
rate point's ``sh.dc_only_share`` of the kept Gaussians with the least of it are coded DC-only,
or with ``sh.dc_only_energy`` (an energy bar) as many of them as drop at most that fraction of the
cloud's total: a bar adapts the share to the scene (bonsai has half its Gaussians under a 2% bar,
the trained chair a quarter; docs/rate_control.md, "Per-Gaussian SH degree").

In the stream (feature ``sh_dc_only``): one bit per Gaussian in grid order (set: DC only),
packed and deflated in the zlib chunk ``sh_dc_only``, and their count in the header
(``sh.dc_only``). The SH stage is fitted on, and transforms, the other (coded) Gaussians only,
and their features go on a grid of their own (:func:`sh_grid_order`, header ``sh.grid``): the
coded Gaussians in grid order fill its first cells along the Z-order curve when the main grid
is Z-ordered (set-coded positions), else in raster order. Its planes shrink with the share:
on bonsai, half the Gaussians DC-only, a third fewer SH bytes than leaving their cells in the
main grid with the previous Gaussian's features, and 14-21% fewer than with zeros there
(docs/rate_control.md, "Per-Gaussian SH degree"). The decoder zeroes the DC-only Gaussians'
AC coefficients.
"""

from __future__ import annotations

import zlib

import numpy as np

from gscodec_shac.codec.layout import GEOMETRY, GridOrder, occupied_cells
from gscodec_shac.errors import BitstreamError
from gscodec_shac.row_blocks import GatheredRows

#: The stream feature and its zlib chunk.
FEATURE = "sh_dc_only"
CHUNK = "sh_dc_only"
#: Rows of the AC matrix read at a time when measuring the energies.
_BLOCK = 65536


def ac_energy(ac: np.ndarray | GatheredRows, weight: np.ndarray) -> np.ndarray:
    """(N,) float64 view-dependent energy: each row's squared AC norm times its ``weight``."""
    n = len(weight)
    energy = np.empty(n, dtype=np.float64)
    for start in range(0, n, _BLOCK):
        block = np.asarray(ac[start : start + _BLOCK], dtype=np.float64)
        energy[start : start + _BLOCK] = np.einsum("ij,ij->i", block, block)
    return energy * np.asarray(weight, dtype=np.float64)


def dc_only_flags(energy: np.ndarray, share: float, bar: float = 0.0) -> np.ndarray:
    """(N,) bool: the rows of least ``energy`` (ties: the earlier row first), never all of them:
    ``round(share * N)`` of them, or with ``bar > 0`` the most whose summed energy is at most
    ``bar`` times the total."""
    n = energy.size
    order = np.argsort(energy, kind="stable")
    count = bar_count(energy[order], bar) if bar > 0 else min(int(round(share * n)), n - 1)
    flags = np.zeros(n, dtype=bool)
    flags[order[:count]] = True
    return flags


def bar_count(ascending_energy: np.ndarray, bar: float) -> int:
    """How many of the rows whose energies are ``ascending_energy`` (sorted) keep their DC only under
    ``bar``: the most whose summed energy is at most ``bar`` times the total, never all of them."""
    n = ascending_energy.size
    if n == 0:
        return 0
    dropped = np.cumsum(ascending_energy)
    return min(int(np.searchsorted(dropped, bar * dropped[-1], side="right")), n - 1)


def sh_padding(grid_padding: str) -> str:
    """How the coded Gaussians fill the SH grid: along its Z-order curve when the main grid is
    Z-ordered, else in raster order."""
    return "zorder" if grid_padding == "zorder" else "tail"


def sh_grid_order(count: int, grid_padding: str, multiple: int) -> GridOrder:
    """The grid of the SH planes for ``count`` coded Gaussians (the main grid's ``multiple``)."""
    import sorting

    shape = sorting.grid_shape(count, multiple=multiple, policy="pad")
    padding = sh_padding(grid_padding)
    order = np.full(shape[0] * shape[1], -1, dtype=np.int64)
    order[occupied_cells(padding, shape, count)] = np.arange(count)
    return GridOrder(shape, order, 0, GEOMETRY if padding == "zorder" else "pad")


def flags_chunk(flags: np.ndarray) -> tuple[bytes, int]:
    """The flags packed (one bit per Gaussian) and deflated, and the packed size."""
    packed = np.packbits(flags)
    return zlib.compress(packed.tobytes(), 9), int(packed.size)


def read_flags(raw: bytes, n: int, count: int) -> np.ndarray:
    """Inverse of :func:`flags_chunk` (already inflated), checked against ``n`` Gaussians and the
    header's ``count`` of DC-only ones."""
    packed = np.frombuffer(raw, dtype=np.uint8)
    if packed.size != (n + 7) // 8:
        raise BitstreamError(f"corrupt .gsc file: chunk {CHUNK!r} holds {packed.size} bytes of flags, "
                             f"{n:,} Gaussians need {(n + 7) // 8}")
    flags = np.unpackbits(packed, count=n).astype(bool)
    found = int(flags.sum())
    if found != count:
        raise BitstreamError(f"corrupt .gsc file: chunk {CHUNK!r} flags {found:,} Gaussians as DC-only, "
                             f"the header says {count:,}")
    return flags
