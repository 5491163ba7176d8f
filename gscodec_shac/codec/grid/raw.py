"""``raw``: samples packed at exactly ``bit_depth`` bits, optionally through zlib or lzma.

Stream layout: one byte naming the entropy coder (0 none, 1 zlib, 2 lzma), then
the (possibly compressed) bit string. Samples are written plane by plane, row by
row, most significant bit first; the last byte is zero-padded. Noise-like grids
(unsorted or high-frequency attributes) come out smaller this way than through
lossless HEVC, and packing needs no external library at all.
"""

from __future__ import annotations

import lzma
import sys
import zlib

import numpy as np

from gscodec_shac.codec.grid.base import GridCodec, register_codec
from gscodec_shac.errors import BitstreamError, ValidationError

_ENTROPY_IDS = {"none": 0, "zlib": 1, "lzma": 2}
_BLOCK = 1 << 20  # samples packed per step (a multiple of 8, so blocks stay byte-aligned)


def pack_bits(values: np.ndarray, bit_depth: int) -> bytes:
    """Flat unsigned samples (< 2**bit_depth) -> bytes holding ``bit_depth`` bits each, MSB first."""
    flat = np.ascontiguousarray(values, dtype=">u2").reshape(-1)
    if bit_depth == 16:
        return flat.tobytes()
    if bit_depth == 8:
        return flat.astype(np.uint8).tobytes()
    parts = []
    for start in range(0, flat.size, _BLOCK):
        bits = np.unpackbits(flat[start : start + _BLOCK].view(np.uint8).reshape(-1, 2), axis=1)
        parts.append(np.packbits(bits[:, 16 - bit_depth :]).tobytes())
    return b"".join(parts)


def unpack_bits(data: bytes, count: int, bit_depth: int) -> np.ndarray:
    """Inverse of :func:`pack_bits`: ``count`` samples as uint16 (``data`` must hold exactly them)."""
    buf = np.frombuffer(data, dtype=np.uint8)
    if bit_depth == 16:
        return buf.view(">u2").astype(np.uint16)
    if bit_depth == 8:
        return buf.astype(np.uint16)
    # Each sample lies inside the 3 bytes starting at its first bit (offset <= 7, width <= 15).
    padded = np.concatenate([buf, np.zeros(2, dtype=np.uint8)])
    out = np.empty(count, dtype=np.uint16)
    for start in range(0, count, _BLOCK):  # blocks start byte-aligned (_BLOCK is a multiple of 8)
        first_bit = np.arange(min(_BLOCK, count - start), dtype=np.int64) * bit_depth
        chunk = padded[start * bit_depth // 8 : (start + first_bit.size) * bit_depth // 8 + 3].astype(np.uint32)
        byte = first_bit >> 3
        word = (chunk[byte] << 16) | (chunk[byte + 1] << 8) | chunk[byte + 2]
        shift = (24 - bit_depth - (first_bit & 7)).astype(np.uint32)
        out[start : start + byte.size] = (word >> shift) & ((1 << bit_depth) - 1)
    return out


@register_codec
class RawCodec(GridCodec):
    """Bit-packed samples plus an optional stdlib entropy coder.

    Options: ``entropy`` (``"none"``, ``"zlib"`` or ``"lzma"``; default ``"lzma"``:
    on the benchmark grids it was up to 11% smaller than zlib, at worst 0.4%
    larger, and 2-6x slower to encode; see ``docs/benchmarks_codecs.md``) and
    ``level`` (zlib level or lzma preset, 0-9; default 9).
    """

    name = "raw"
    lossless_only = True

    def __init__(self, entropy: str = "lzma", level: int = 9) -> None:
        if entropy not in _ENTROPY_IDS:
            raise ValidationError(f"raw: entropy must be one of {', '.join(_ENTROPY_IDS)}, got {entropy!r}")
        if not isinstance(level, int) or not 0 <= level <= 9:
            raise ValidationError(f"raw: level must be an integer 0-9, got {level!r}")
        super().__init__(entropy=entropy, level=level)
        self.entropy, self.level = entropy, level

    def version(self) -> str:
        py = f"Python {sys.version_info.major}.{sys.version_info.minor}"
        if self.entropy == "zlib":
            return f"bit-packing + zlib {zlib.ZLIB_RUNTIME_VERSION} ({py})"
        if self.entropy == "lzma":
            return f"bit-packing + lzma/xz ({py})"
        return "bit-packing"

    def encode(self, planes: np.ndarray, bit_depth: int, qp: int | None) -> bytes:
        planes = self._check_planes(planes, bit_depth, qp)
        packed = pack_bits(planes, bit_depth)
        if self.entropy == "zlib":
            packed = zlib.compress(packed, self.level)
        elif self.entropy == "lzma":
            packed = lzma.compress(packed, format=lzma.FORMAT_RAW, filters=_lzma_filters(len(packed), self.level))
        return bytes([_ENTROPY_IDS[self.entropy]]) + packed

    def decode(self, data: bytes, shape: tuple[int, int, int], bit_depth: int) -> np.ndarray:
        shape = self._check_shape(shape, bit_depth)
        count = shape[0] * shape[1] * shape[2]
        expected = (count * bit_depth + 7) // 8
        if len(data) < 1:
            raise BitstreamError("raw stream is empty")
        method, body = data[0], bytes(data[1:])
        if method == _ENTROPY_IDS["zlib"]:
            body = _inflate(zlib.decompressobj(), zlib.error, body, expected)
        elif method == _ENTROPY_IDS["lzma"]:
            decompressor = lzma.LZMADecompressor(format=lzma.FORMAT_RAW, filters=_lzma_filters(expected, 0))
            body = _inflate(decompressor, lzma.LZMAError, body, expected)
        elif method != _ENTROPY_IDS["none"]:
            raise BitstreamError(f"raw stream names an unknown entropy coder (id {method})")
        if len(body) != expected:
            raise BitstreamError(
                f"raw stream holds {len(body)} bytes of samples; shape {shape} at {bit_depth} bits needs {expected}"
            )
        return self._check_decoded(self.name, unpack_bits(body, count, bit_depth).reshape(shape), shape)


def _lzma_filters(size: int, level: int) -> list[dict]:
    """Raw LZMA2 filter chain whose dictionary is no larger than the data (4 KiB-64 MiB).

    Both sides derive the dictionary size from the packed size, so the stream
    needs no header and the decoder allocates only what the shape justifies.
    """
    return [{"id": lzma.FILTER_LZMA2, "preset": level, "dict_size": min(max(size, 4096), 1 << 26)}]


def _inflate(decompressor, error: type[Exception], body: bytes, expected: int) -> bytes:
    """Decompress at most ``expected`` bytes; the stream must end exactly there."""
    try:
        out = decompressor.decompress(body, expected + 1)
    except error as exc:
        raise BitstreamError(f"raw stream is corrupt: {exc}") from None
    if len(out) > expected:
        raise BitstreamError(f"raw stream holds more samples than {expected} bytes")
    if not decompressor.eof:
        raise BitstreamError("raw stream is truncated (compressed data ends early)")
    if decompressor.unused_data:
        raise BitstreamError("raw stream has unexpected bytes after its compressed data")
    return out
