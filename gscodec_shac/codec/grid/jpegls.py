"""``jpegls``: lossless JPEG-LS per plane through the FFmpeg encoder in the PyAV wheel.

FFmpeg's JPEG-LS encoder takes 8-bit (``gray``) or 16-bit (``gray16le``)
single-channel frames; it writes no LSE marker, so a 10-bit grid travels with
16-bit precision (MAXVAL 65535). Its context modelling adapts to the actual
range, so little is lost. Each plane is one JPEG-LS image; images are joined
with uint32 length prefixes. The frame header (SOF55) is checked against the
expected shape before decoding, and a stream must end with the EOI marker.
"""

from __future__ import annotations

import fractions
import struct

import av
import numpy as np

from gscodec_shac.codec.grid.base import GridCodec, join_chunks, register_codec, split_chunks
from gscodec_shac.errors import BitstreamError

_SOI, _SOF55, _EOI = b"\xff\xd8", b"\xff\xf7", b"\xff\xd9"


@register_codec
class JpeglsCodec(GridCodec):
    """One lossless JPEG-LS image per plane (no options)."""

    name = "jpegls"
    lossless_only = True

    def version(self) -> str:
        return f"FFmpeg jpegls (libavcodec {'.'.join(map(str, av.library_versions['libavcodec']))}, PyAV {av.__version__})"

    def encode(self, planes: np.ndarray, bit_depth: int, qp: int | None) -> bytes:
        planes = self._check_planes(planes, bit_depth, qp)
        pix_fmt, dtype = ("gray", np.uint8) if bit_depth <= 8 else ("gray16le", np.uint16)
        chunks = []
        for plane in planes:
            ctx = av.CodecContext.create("jpegls", "w")
            ctx.width, ctx.height = plane.shape[1], plane.shape[0]
            ctx.pix_fmt = pix_fmt
            ctx.time_base = fractions.Fraction(1, 1)
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(plane, dtype=dtype), format=pix_fmt)
            packets = ctx.encode(frame) + ctx.encode(None)
            chunks.append(b"".join(bytes(p) for p in packets))
        return join_chunks(chunks)

    def decode(self, data: bytes, shape: tuple[int, int, int], bit_depth: int) -> np.ndarray:
        channels, height, width = self._check_shape(shape, bit_depth)
        precision = 8 if bit_depth <= 8 else 16
        out = np.empty((channels, height, width), dtype=np.uint16)
        for index, chunk in enumerate(split_chunks(data, channels, self.name)):
            _check_header(chunk, height, width, precision, index)
            try:
                ctx = av.CodecContext.create("jpegls", "r")
                frames = ctx.decode(av.Packet(chunk))
            except (av.FFmpegError, ValueError) as exc:
                raise BitstreamError(f"jpegls plane {index} is corrupt: {exc}") from None
            if len(frames) != 1:
                raise BitstreamError(f"jpegls plane {index} decodes to {len(frames)} images, expected 1")
            plane = frames[0].to_ndarray()
            if plane.shape != (height, width):
                raise BitstreamError(f"jpegls plane {index} decodes to {plane.shape}, expected {(height, width)}")
            if int(plane.max()) >= 2**bit_depth:
                raise BitstreamError(f"jpegls plane {index} holds values above {bit_depth} bits")
            out[index] = plane
        return self._check_decoded(self.name, out, shape)


def _check_header(chunk: bytes, height: int, width: int, precision: int, index: int) -> None:
    """Refuse an image whose SOF55 header disagrees with the expected size (before allocating)."""
    if len(chunk) < 17 or chunk[:2] != _SOI or chunk[2:4] != _SOF55:
        raise BitstreamError(f"jpegls plane {index} is not a JPEG-LS image")
    bits, h, w, components = struct.unpack(">BHHB", chunk[6:12])
    if (bits, h, w, components) != (precision, height, width, 1):
        raise BitstreamError(
            f"jpegls plane {index} is a {w}x{h} {bits}-bit {components}-component image, "
            f"expected {width}x{height} {precision}-bit grayscale"
        )
    if chunk[-2:] != _EOI:
        raise BitstreamError(f"jpegls plane {index} is truncated (no end-of-image marker)")

