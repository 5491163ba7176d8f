"""The grid-codec contract and the registry that finds codecs by name.

A grid codec turns integer planes (C, H, W) of ``bit_depth``-bit samples into
bytes and back. ``qp=None`` means lossless; a lossy codec takes an integer QP.
``decode`` is told the expected shape and bit depth (from the container header),
so it can refuse a stream that does not match and never allocates more than the
header justifies. Each codec reports the version of the library that made the
bytes; the container records it.
"""

from __future__ import annotations

import struct
from abc import ABC, abstractmethod
from typing import Any, Callable, ClassVar

import numpy as np

from gscodec_shac.errors import BitstreamError, CodecUnavailableError, ValidationError
from gscodec_shac.registry import Registry


#: Independent pieces of an encode, ``(cost, work)`` each, and the function joining their outputs
#: (in order) into the codec's bytes: :meth:`GridCodec.encode_parts`.
EncodeParts = tuple[list[tuple[int, Callable[[], bytes]]], Callable[[list[bytes]], bytes]]
#: Receives decoded planes as they come: ``sink(first_channel, planes)`` with (k, H, W) uint16 planes
#: of channels ``first_channel .. first_channel + k - 1`` (its own array; called from codec threads).
PlaneSink = Callable[[int, np.ndarray], None]


class GridCodec(ABC):
    """Base class of the grid codecs (``hevc``, ``png``, ``jpegls``, ``raw``, ``hm``, ...)."""

    #: Registry name.
    name: ClassVar[str]
    #: True when the codec has no lossy mode (``qp`` must be ``None``).
    lossless_only: ClassVar[bool] = False

    def __init__(self, **options: Any) -> None:
        self.options = options

    @classmethod
    def check_available(cls) -> None:
        """Raise :class:`CodecUnavailableError` (saying how to install) when unusable here."""

    @abstractmethod
    def version(self) -> str:
        """Name and version of the library or binary doing the work, e.g. ``'x265 4.2 (PyAV 18.1.0)'``."""

    @abstractmethod
    def encode(self, planes: np.ndarray, bit_depth: int, qp: int | None) -> bytes:
        """(C, H, W) uint16 planes with values < 2**bit_depth -> bytes."""

    @abstractmethod
    def decode(self, data: bytes, shape: tuple[int, int, int], bit_depth: int) -> np.ndarray:
        """Bytes -> (C, H, W) uint16 planes of exactly ``shape``; raise BitstreamError otherwise."""

    def encode_parts(self, planes: np.ndarray, bit_depth: int, qp: int | None) -> EncodeParts:
        """:meth:`encode` as independent pieces of work, each with a cost estimate (samples coded),
        so a caller may run them in threads, costliest first; joining their outputs gives the
        bytes of :meth:`encode`. By default one piece; ``hevc`` makes one per stream."""
        return [(int(np.size(planes)), lambda: self.encode(planes, bit_depth, qp))], lambda outputs: outputs[0]

    def decode_into(self, data: bytes, shape: tuple[int, int, int], bit_depth: int, sink: PlaneSink) -> None:
        """:meth:`decode`, the planes handed to ``sink`` (a codec that decodes picture by picture,
        such as ``hevc``, calls it per picture, so the caller's work overlaps the decoding)."""
        sink(0, self.decode(data, shape, bit_depth))

    # -------------------------------------------------------------- helpers
    def describe(self) -> dict[str, Any]:
        """What the container stores about this codec (name, version, options)."""
        return {"name": self.name, "version": self.version(), "options": dict(self.options)}

    def _check_planes(self, planes: np.ndarray, bit_depth: int, qp: int | None) -> np.ndarray:
        planes = np.asarray(planes)
        if planes.ndim != 3:
            raise ValidationError(f"{self.name}: planes must be (C, H, W), got shape {planes.shape}")
        if 0 in planes.shape:
            raise ValidationError(f"{self.name}: planes must not be empty, got shape {planes.shape}")
        if not np.issubdtype(planes.dtype, np.integer):
            raise ValidationError(f"{self.name}: planes must be integers, got dtype {planes.dtype}")
        if not 1 <= bit_depth <= 16:
            raise ValidationError(f"{self.name}: bit depth must be 1-16, got {bit_depth}")
        if planes.size and (planes.min() < 0 or planes.max() >= 2**bit_depth):
            raise ValidationError(f"{self.name}: values exceed {bit_depth} bits")
        if qp is not None and self.lossless_only:
            raise ValidationError(f"{self.name} is lossless only; it takes no QP (got {qp})")
        return planes.astype(np.uint16, copy=False)

    def _check_shape(self, shape: tuple[int, int, int], bit_depth: int) -> tuple[int, int, int]:
        """Validate the ``shape`` and ``bit_depth`` handed to :meth:`decode`."""
        try:
            dims = tuple(int(d) for d in shape)
        except (TypeError, ValueError):
            raise ValidationError(f"{self.name}: shape must be (C, H, W) integers, got {shape!r}") from None
        if len(dims) != 3 or min(dims) < 1:
            raise ValidationError(f"{self.name}: shape must be three positive integers (C, H, W), got {shape!r}")
        if not 1 <= bit_depth <= 16:
            raise ValidationError(f"{self.name}: bit depth must be 1-16, got {bit_depth}")
        return dims  # type: ignore[return-value]

    @staticmethod
    def _check_decoded(name: str, planes: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
        if tuple(planes.shape) != tuple(shape):
            raise BitstreamError(f"{name} stream decodes to shape {tuple(planes.shape)}, header says {tuple(shape)}")
        return planes


def join_chunks(chunks: list[bytes]) -> bytes:
    """Concatenate byte strings, each preceded by its length (uint32 little-endian)."""
    return b"".join(struct.pack("<I", len(chunk)) + chunk for chunk in chunks)


def split_chunks(data: bytes, count: int, name: str) -> list[bytes]:
    """Inverse of :func:`join_chunks` for exactly ``count`` chunks; BitstreamError otherwise."""
    view = memoryview(data)
    chunks, offset = [], 0
    for index in range(count):
        if offset + 4 > len(view):
            raise BitstreamError(f"{name} stream is truncated: chunk {index + 1} of {count} is missing")
        (length,) = struct.unpack_from("<I", view, offset)
        offset += 4
        if offset + length > len(view):
            raise BitstreamError(f"{name} stream is truncated: chunk {index + 1} of {count} runs past the end")
        chunks.append(bytes(view[offset : offset + length]))
        offset += length
    if offset != len(view):
        raise BitstreamError(f"{name} stream has {len(view) - offset} unexpected bytes after its {count} chunks")
    return chunks


CODECS: Registry[GridCodec] = Registry("grid codec", "gscodec_shac.codec.grid",
                                     {name: name for name in ("raw", "png", "jpegls", "hevc", "hm")})
register_codec = CODECS.register


def get_codec(name: str, **options: Any) -> GridCodec:
    """A codec instance by registry name; raises if unknown or unavailable here."""
    cls = CODECS.get(name)
    cls.check_available()
    try:
        return cls(**options)
    except TypeError as exc:
        raise ValidationError(f"bad options for codec {name!r}: {exc}") from None


def available_codecs() -> list[str]:
    """Names of the codecs usable on this machine."""
    usable = []
    for name, cls in CODECS.items():
        try:
            cls.check_available()
        except CodecUnavailableError:
            continue
        usable.append(name)
    return usable
