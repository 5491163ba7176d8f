"""Compiled halves of the position set coding that only the encoder runs (:mod:`.positions`).

A gap's bit length and the ``k - 1`` bits below its leading one, packed most significant bit
first into one bit string. The decoder unpacks with whole-array numpy
(:func:`.positions._unpack_mantissas`), so a process that only decodes never loads numba; the
encoder packs here because the rate controller codes the whole cloud's positions at eight bit
depths (a 1M scene: 0.4 s of numpy per depth, a few ms here).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def bit_lengths(values):  # pragma: no cover - compiled
    """(N,) int64 number of significant bits of each uint64 (0 for 0)."""
    out = np.zeros(values.shape[0], dtype=np.int64)
    for i in range(values.shape[0]):
        v = values[i]
        k = 0
        while v != np.uint64(0):
            v >>= np.uint64(1)
            k += 1
        out[i] = k
    return out


@numba.njit(cache=True)
def pack_low_bits(values, widths):  # pragma: no cover - compiled
    """The low ``widths[i]`` bits (at most 63) of each ``values[i]``, most significant first, one
    after the other in a uint8 array (the last byte padded with zero bits)."""
    total = 0
    for i in range(widths.shape[0]):
        if widths[i] > 0:
            total += widths[i]
    out = np.zeros((total + 7) // 8, dtype=np.uint8)
    acc = np.uint64(0)  # the bits not yet written, at most 7 between fields
    held = 0
    pos = 0
    for i in range(values.shape[0]):
        left = widths[i]
        while left > 0:
            take = min(left, 56)  # held <= 7: the accumulator never holds more than 63 bits
            part = (values[i] >> np.uint64(left - take)) & ((np.uint64(1) << np.uint64(take)) - np.uint64(1))
            acc = (acc << np.uint64(take)) | part
            held += take
            left -= take
            while held >= 8:
                held -= 8
                out[pos] = np.uint8((acc >> np.uint64(held)) & np.uint64(0xFF))
                pos += 1
            acc &= (np.uint64(1) << np.uint64(held)) - np.uint64(1)
    if held > 0:
        out[pos] = np.uint8((acc << np.uint64(8 - held)) & np.uint64(0xFF))
    return out
