"""Positions coded as a set, and the grid order that follows from them (rate-point layout ``set``).

A grid codec codes positions in grid order, and a grid order chosen by the encoder
(PLAS) is information the file must carry: the positions then cost the set of points
plus the permutation (log2 N! bits, about 15 bits per Gaussian at 75k). Coding the
positions as a *set* drops that permutation:

1. quantise ``sign(x) log1p(|x|)`` per axis to ``bits`` bits (the min/max quantiser of
   every attribute, :class:`gscodec_shac.codec.quantize.Quantizer`);
2. interleave the three integers into one 3-D Morton (Z-order) code and sort the codes;
3. code the sorted codes as gaps: each gap's bit length ``k`` (one byte, deflated with
   LZMA, which learns their skewed distribution) and its ``k - 1`` bits below the
   leading one (packed as they are: they are close to uniform).

The decoder recovers the sorted codes, hence the positions in Morton order. Every other
attribute is coded on the grid in that same order, the k-th Gaussian in the k-th cell of
the grid's own 2-D Z-order curve (:func:`sorting.morton.grid_z_cells`), so the decoder
places them without any side information. The price is a grid less smooth than a PLAS
sort of positions, colours, scales and opacities (measured in docs/rate_control.md).
Gaussians with the same quantised position keep their input order among themselves.
"""

from __future__ import annotations

import lzma
import struct

import numpy as np

from gscodec_shac.errors import BitstreamError, ValidationError

#: Bits per axis a 63-bit Morton code holds.
MAX_BITS = 21
_HEADER = struct.Struct("<II")  # gap count, bytes of the LZMA'd lengths
_LZMA_FILTERS = [{"id": lzma.FILTER_LZMA2, "preset": 9 | lzma.PRESET_EXTREME}]


def check_bits(bits: int) -> int:
    if isinstance(bits, bool) or not isinstance(bits, (int, np.integer)) or not 1 <= bits <= MAX_BITS:
        raise ValidationError(f"set-coded positions take 1-{MAX_BITS} bits per axis, got {bits!r}")
    return int(bits)


# ------------------------------------------------------------------ Morton codes
def _spread(v: np.ndarray) -> np.ndarray:
    """Put bit i of each 21-bit integer at bit 3i (the 'part 1 by 2' of 3-D Morton codes)."""
    x = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    x = (x | (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    x = (x | (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    x = (x | (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    x = (x | (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    x = (x | (x << np.uint64(2))) & np.uint64(0x1249249249249249)
    return x


def _compact(x: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_spread`."""
    x = x & np.uint64(0x1249249249249249)
    x = (x | (x >> np.uint64(2))) & np.uint64(0x10C30C30C30C30C3)
    x = (x | (x >> np.uint64(4))) & np.uint64(0x100F00F00F00F00F)
    x = (x | (x >> np.uint64(8))) & np.uint64(0x1F0000FF0000FF)
    x = (x | (x >> np.uint64(16))) & np.uint64(0x1F00000000FFFF)
    x = (x | (x >> np.uint64(32))) & np.uint64(0x1FFFFF)
    return x


def morton_encode(q: np.ndarray) -> np.ndarray:
    """(N, 3) integers below 2**21 -> (N,) uint64 Morton codes (x in the lowest bit of each triple)."""
    q = np.asarray(q)
    return _spread(q[:, 0]) | (_spread(q[:, 1]) << np.uint64(1)) | (_spread(q[:, 2]) << np.uint64(2))


def morton_decode(codes: np.ndarray) -> np.ndarray:
    """(N,) uint64 Morton codes -> (N, 3) int64 integers."""
    codes = np.asarray(codes, dtype=np.uint64)
    return np.stack([_compact(codes >> np.uint64(axis)) for axis in range(3)], axis=1).astype(np.int64)


def set_order(q: np.ndarray) -> np.ndarray:
    """Rows sorted by Morton code (ties in row order): the grid order of a set-coded stream."""
    return np.argsort(morton_encode(q), kind="stable")


# ----------------------------------------------------------------- gap coding
def encode_sorted_codes(codes: np.ndarray) -> bytes:
    """Sorted uint64 codes -> bytes (gap lengths through LZMA, the bits below each leading one packed)."""
    codes = np.asarray(codes, dtype=np.uint64)
    if codes.size and np.any(codes[1:] < codes[:-1]):
        raise ValidationError("set coding needs sorted Morton codes")
    gaps = np.diff(codes, prepend=np.uint64(0))
    lengths = _bit_lengths(gaps)
    packed_lengths = lzma.compress(lengths.astype(np.uint8).tobytes(), format=lzma.FORMAT_RAW, filters=_LZMA_FILTERS)
    return _HEADER.pack(codes.size, len(packed_lengths)) + packed_lengths + _pack_mantissas(gaps, lengths)


def decode_sorted_codes(data: bytes, count: int, bits: int) -> np.ndarray:
    """Inverse of :func:`encode_sorted_codes` for ``count`` codes of ``3 * bits`` bits; BitstreamError if inconsistent."""
    if len(data) < _HEADER.size:
        raise BitstreamError("position set is truncated (no header)")
    stored, size = _HEADER.unpack_from(data)
    if stored != count or _HEADER.size + size > len(data):
        raise BitstreamError(f"position set holds {stored:,} codes in {size:,} bytes; the header says {count:,}")
    try:
        raw = lzma.LZMADecompressor(format=lzma.FORMAT_RAW, filters=_LZMA_FILTERS).decompress(
            data[_HEADER.size : _HEADER.size + size], max_length=count + 1)
    except lzma.LZMAError:
        raise BitstreamError("position set is corrupt (gap lengths do not decompress)") from None
    lengths = np.frombuffer(raw, dtype=np.uint8).astype(np.int64)
    if lengths.size != count or (count and int(lengths.max()) > 3 * bits):
        raise BitstreamError("position set is corrupt (gap lengths)")
    gaps = _unpack_mantissas(data[_HEADER.size + size :], lengths)
    codes = np.cumsum(gaps, dtype=np.uint64)
    if count and int(codes[-1]) >> (3 * bits):
        raise BitstreamError("position set is corrupt (a position lies outside the grid of its bit depth)")
    return codes


def _bit_lengths(values: np.ndarray) -> np.ndarray:
    """Number of significant bits of each uint64 (0 for 0)."""
    from gscodec_shac.codec.gap_packing import bit_lengths

    return bit_lengths(np.ascontiguousarray(values, dtype=np.uint64))


def _pack_mantissas(gaps: np.ndarray, lengths: np.ndarray) -> bytes:
    """The ``k - 1`` bits below the leading one of each gap, most significant first, as one bit string
    (compiled: :func:`.gap_packing.pack_low_bits`)."""
    from gscodec_shac.codec.gap_packing import pack_low_bits

    widths = np.maximum(np.asarray(lengths, dtype=np.int64) - 1, 0)
    return pack_low_bits(np.ascontiguousarray(gaps, dtype=np.uint64), widths).tobytes()


def _unpack_mantissas(data: bytes, lengths: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_pack_mantissas`: the gaps, leading ones restored (whole-array numpy, no compiled kernel).

    Each gap's ``m = k - 1`` bits start at bit ``s`` (the running sum of ``m``); the 64 bits
    from byte ``s // 8`` plus the next byte hold them (``m <= 62``, ``s % 8 <= 7``).
    """
    total = int(np.maximum(lengths - 1, 0).sum())
    if (total + 7) // 8 != len(data):
        raise BitstreamError(f"position set is corrupt ({len(data):,} mantissa bytes, {(total + 7) // 8:,} expected)")
    lengths = np.asarray(lengths, dtype=np.int64)
    gaps = np.zeros(lengths.size, dtype=np.uint64)
    raw = np.frombuffer(data + bytes(9), dtype=np.uint8)
    base = 0
    for start in range(0, lengths.size, _UNPACK_BLOCK):
        block = lengths[start : start + _UNPACK_BLOCK]
        width = np.maximum(block - 1, 0)
        ends = np.cumsum(width) + base
        gaps[start : start + _UNPACK_BLOCK] = _read_fields(raw, ends - width, block)
        base = int(ends[-1])
    return gaps


#: Gaps unpacked per block in :func:`_unpack_mantissas` (bounds the (B, 9) byte windows).
_UNPACK_BLOCK = 1 << 20


def _read_fields(raw: np.ndarray, first: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Gaps of bit lengths ``lengths`` whose ``k - 1`` low bits start at bit offsets ``first`` of ``raw``.

    ``raw`` is the bit string's bytes followed by 9 zero bytes.
    """
    width = np.maximum(lengths - 1, 0).astype(np.uint64)
    byte = first >> 3
    # Big-endian 64-bit words starting at every byte (an unaligned view, no copy).
    words = np.ndarray((raw.size - 8,), dtype=">u8", buffer=raw, strides=(1,))
    offset = (first & 7).astype(np.uint64)
    window = (words[byte].astype(np.uint64) << offset) | (raw[byte + 8].astype(np.uint64) >> (np.uint64(8) - offset))
    # The m leading bits of the window; m = 0 reads nothing (a shift by 64 is undefined: masked).
    bits = np.where(width > 0, window >> (np.uint64(64) - np.maximum(width, np.uint64(1))), np.uint64(0))
    return np.where(lengths > 0, (np.uint64(1) << width) | bits, np.uint64(0))
