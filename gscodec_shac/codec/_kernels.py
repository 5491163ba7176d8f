"""The codec's compiled (numba) kernels, imported lazily by the encoder only.

A process that only decodes never imports this module, hence never numba (its import
and kernel-cache loading cost seconds; tests/test_decode_imports.py checks it).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def pack_mantissas(gaps: np.ndarray, lengths: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """The ``k - 1`` bits below the leading one of each gap (bit length ``k``), MSB first, into ``out``."""
    position = 0
    for i in range(gaps.size):
        for bit in range(lengths[i] - 2, -1, -1):
            if (gaps[i] >> np.uint64(bit)) & np.uint64(1):
                out[position >> 3] |= np.uint8(128 >> (position & 7))
            position += 1
