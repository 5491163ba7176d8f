"""``png``: lossless grayscale PNG per plane through OpenCV.

Each plane becomes one single-channel PNG, 16-bit when ``bit_depth > 8`` and
8-bit otherwise, and the PNGs are joined with uint32 length prefixes
(:func:`~gscodec_shac.codec.grid.base.join_chunks`). Before anything is decoded the
PNG header (IHDR) is checked against the expected size, so a foreign or
oversized image is rejected without being allocated.
"""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np

from gscodec_shac.codec.grid.base import GridCodec, join_chunks, register_codec, split_chunks
from gscodec_shac.errors import BitstreamError, ValidationError

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_GRAY = 0  # PNG colour type of a grayscale image


@register_codec
class PngCodec(GridCodec):
    """One grayscale PNG per plane. Option: ``level`` (zlib level 0-9, default 9)."""

    name = "png"
    lossless_only = True

    def __init__(self, level: int = 9) -> None:
        if not isinstance(level, int) or not 0 <= level <= 9:
            raise ValidationError(f"png: level must be an integer 0-9, got {level!r}")
        super().__init__(level=level)
        self.level = level

    def version(self) -> str:
        return f"OpenCV {cv2.__version__} PNG"

    def encode(self, planes: np.ndarray, bit_depth: int, qp: int | None) -> bytes:
        planes = self._check_planes(planes, bit_depth, qp)
        dtype = np.uint8 if bit_depth <= 8 else np.uint16
        chunks = []
        for plane in planes:
            ok, buf = cv2.imencode(".png", plane.astype(dtype), [cv2.IMWRITE_PNG_COMPRESSION, self.level])
            if not ok:
                raise ValidationError(f"png: OpenCV could not encode a {plane.shape} plane")
            chunks.append(buf.tobytes())
        return join_chunks(chunks)

    def decode(self, data: bytes, shape: tuple[int, int, int], bit_depth: int) -> np.ndarray:
        channels, height, width = self._check_shape(shape, bit_depth)
        depth = 8 if bit_depth <= 8 else 16
        out = np.empty((channels, height, width), dtype=np.uint16)
        for index, chunk in enumerate(split_chunks(data, channels, self.name)):
            _check_png(chunk, height, width, depth, index)
            try:
                plane = cv2.imdecode(np.frombuffer(chunk, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
            except cv2.error:
                plane = None
            if plane is None or plane.shape != (height, width):
                raise BitstreamError(f"png plane {index} is corrupt (OpenCV could not decode it)")
            if int(plane.max()) >= 2**bit_depth:
                raise BitstreamError(f"png plane {index} holds values above {bit_depth} bits")
            out[index] = plane
        return self._check_decoded(self.name, out, shape)


def _check_png(chunk: bytes, height: int, width: int, depth: int, index: int) -> None:
    """Walk the PNG's chunks (CRCs, IHDR fields, IEND last) before OpenCV sees it.

    This rejects truncated, corrupt, foreign or oversized images with a clear
    message (and keeps libpng from printing its own errors to stderr).
    """
    if len(chunk) < 33 or chunk[:8] != _SIGNATURE or chunk[12:16] != b"IHDR":
        raise BitstreamError(f"png plane {index} is not a PNG image")
    w, h, bits, colour = struct.unpack(">IIBB", chunk[16:26])
    if (h, w, bits, colour) != (height, width, depth, _GRAY):
        raise BitstreamError(
            f"png plane {index} is a {w}x{h} {bits}-bit image of colour type {colour}, "
            f"expected {width}x{height} {depth}-bit grayscale"
        )
    offset = 8
    while True:
        if offset + 12 > len(chunk):
            raise BitstreamError(f"png plane {index} is truncated")
        length, kind = struct.unpack(">I4s", chunk[offset : offset + 8])
        end = offset + 8 + length
        if end + 4 > len(chunk):
            raise BitstreamError(f"png plane {index} is truncated")
        (crc,) = struct.unpack(">I", chunk[end : end + 4])
        if zlib.crc32(chunk[offset + 4 : end]) != crc:
            raise BitstreamError(f"png plane {index} is corrupt (CRC mismatch in its {kind!r} chunk)")
        offset = end + 4
        if kind == b"IEND":
            break
    if offset != len(chunk):
        raise BitstreamError(f"png plane {index} has unexpected bytes after its end")
