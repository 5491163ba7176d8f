"""Rows of an array, gathered a block at a time: ``base[index]`` without building it.

The encoder's SH stage reads the AC matrix in grid order. Copying the whole (N, K')
matrix into that order costs as much memory as the matrix itself (0.7 GB for 4M
Gaussians at SH degree 3); a stage that only reads row blocks (SHAC-PCA's moments and
transform, :attr:`~gscodec_shac.shac.base.ShStage.reads_row_blocks`) gets a
:class:`GatheredRows` instead, and each slice it takes is gathered on the spot. The
blocks hold the same values, in the same layout, as slices of the gathered array, so
every result computed from them is the same.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class GatheredRows:
    """``base[index]`` on demand: slicing rows gathers them; :func:`numpy.asarray` builds the whole array."""

    def __init__(self, base: np.ndarray, index: np.ndarray) -> None:
        self.base = np.asarray(base)
        self.index = np.asarray(index, dtype=np.intp)
        if self.base.ndim < 1 or self.index.ndim != 1:
            raise ValueError("GatheredRows needs an array and a 1-D row index")

    @property
    def shape(self) -> tuple[int, ...]:
        return (self.index.size, *self.base.shape[1:])

    @property
    def ndim(self) -> int:
        return self.base.ndim

    @property
    def dtype(self) -> np.dtype:
        return self.base.dtype

    def __len__(self) -> int:
        return int(self.index.size)

    def __getitem__(self, rows: slice) -> np.ndarray:
        """The rows ``rows`` (a slice) of ``base[index]``, gathered now (a new C-contiguous array)."""
        if not isinstance(rows, slice):
            raise TypeError("GatheredRows takes row slices only")
        return self.base[self.index[rows]]

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        whole = self.base[self.index]
        return whole if dtype is None else whole.astype(dtype, copy=False)

    def all_finite(self) -> bool:
        """No NaN or inf in the gathered rows (checked on ``base``: min and max, no temporary array)."""
        return self.base.size == 0 or bool(np.isfinite(self.base.min()) and np.isfinite(self.base.max()))
