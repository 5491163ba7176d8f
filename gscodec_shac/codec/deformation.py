"""The deformation network of a dynamic model as one more chunk of a ``.gsc`` stream.

A dynamic model (:mod:`gscodec_shac.deform`) is coded as its canonical Gaussians (the ordinary
pipeline) plus the chunk ``deformation``, deflated (zlib), which holds every weight tensor in
``state_dict`` order (:func:`gscodec_shac.deform_arch.weight_shapes`) in one of two forms, named
by the header entry ``deformation`` = ``{"arch": {...}, "dtype": ..., ["bits": B]}``:

* ``dtype: "float16"`` (format 2.0): every weight as little-endian float16;
* ``dtype: "uint8"`` (format 2.1, feature ``deformation_quantised``): each weight matrix
  quantised per output channel (row) to ``B``-bit integers (2 <= B <= 8, one byte each)
  with ``w = lo + code * step``; ``lo`` and ``step`` per row, and every bias vector, as
  float16. Layout: for each tensor in order its float16 part (a matrix's ``lo`` of every
  row, then its ``step`` of every row; a vector's values), then the codes of every matrix
  in order, row-major, packed at ``B`` bits each (most significant bit first; the last
  byte padded with zeros). Packing matters: deflate's byte-wise Huffman codes lose up to
  14% on 4-6-bit codes stored one per byte (measured on a trained network, docs/dynamic.md).

The chunk records ``encoding: zlib`` and ``raw_size`` (:func:`raw_size`, checked by
:mod:`gscodec_shac.codec.header`). The stream needs the container feature ``deformation``
(format 2.0), a quantised one also ``deformation_quantised`` (format 2.1), so a decoder that
does not know them refuses the stream by name instead of decoding it wrongly.
"""

from __future__ import annotations

import zlib
import numpy as np

from gscodec_shac.codec.container import Bitstream
from gscodec_shac.deform_arch import DeformArch, weight_count, weight_shapes
from gscodec_shac.errors import ModelFormatError

CHUNK = "deformation"
FEATURE = "deformation"
QUANTISED_FEATURE = "deformation_quantised"
DTYPES = ("float16", "uint8")
#: ``bits`` of the ``uint8`` form; 16 stands for float16 (the ``--network-bits`` values).
MIN_BITS, MAX_BITS = 2, 8
DEFAULT_BITS = 8


def dtype_of(bits: int) -> str:
    """``float16`` for 16, ``uint8`` for 2..8 (anything else: ValueError)."""
    if bits == 16:
        return "float16"
    if isinstance(bits, int) and MIN_BITS <= bits <= MAX_BITS:
        return "uint8"
    raise ValueError(f"network bits must be 16 (float16) or {MIN_BITS}..{MAX_BITS}, got {bits!r}")


def raw_size(arch: DeformArch, dtype: str, bits: int = 16) -> int:
    """Bytes of the inflated chunk for ``arch`` in form ``dtype`` with ``bits`` (from the sizes alone)."""
    if dtype == "float16":
        return 2 * weight_count(arch)
    return _half_bytes(arch) + (_code_count(arch) * bits + 7) // 8


def quantise_rows(value: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(lo, step, codes)`` of a matrix, per row: ``lo`` and ``step`` float16, ``codes`` uint8 in 0..2^bits-1.

    ``lo`` and ``step`` are rounded to float16 first and the codes computed from the rounded
    values, so the decoder's ``lo + code * step`` is what the encoder measured."""
    top = (1 << bits) - 1
    lo = value.min(axis=1).astype(np.float16)
    span = value.max(axis=1) - lo.astype(np.float32)
    step = (span / top).astype(np.float16)
    short = step.astype(np.float32) * top < span  # rounded down: one float16 unit up covers the row
    step[short] = np.nextafter(step[short], np.float16(np.inf))
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(step))):
        raise ModelFormatError("deformation network: a weight beyond the float16 range cannot be coded")
    safe = np.where(step > 0, step.astype(np.float32), 1.0)[:, None]
    codes = np.clip(np.rint((value - lo.astype(np.float32)[:, None]) / safe), 0, top).astype(np.uint8)
    return lo, step, codes


def add_deformation(stream: Bitstream, arch: DeformArch, weights: dict[str, np.ndarray],
                    bits: int = DEFAULT_BITS) -> int:
    """Append the network chunk + header entry to ``stream``; returns the chunk's size in bytes.

    ``bits``: 16 for float16, 2..8 for the per-row quantised form."""
    dtype = dtype_of(bits)
    halves, codes = [], []
    for name, shape in weight_shapes(arch):
        value = np.asarray(weights[name], dtype=np.float32)
        if value.shape != shape:
            raise ValueError(f"deformation weight {name} has shape {value.shape}, expected {shape}")
        if dtype == "float16" or value.ndim == 1:
            halves.append(value.astype("<f2").tobytes())
            continue
        lo, step, code = quantise_rows(value, bits)
        halves += [lo.astype("<f2").tobytes(), step.astype("<f2").tobytes()]
        codes.append(code.ravel())
    raw = b"".join(halves) + (pack_codes(np.concatenate(codes), bits) if codes else b"")
    assert len(raw) == raw_size(arch, dtype, bits)
    data = zlib.compress(raw, 9)
    stream.add_chunk(CHUNK, data, attribute=CHUNK, encoding="zlib", raw_size=len(raw))
    stream.header[CHUNK] = {"arch": arch.to_dict(), "dtype": dtype, **({"bits": bits} if dtype == "uint8" else {})}
    stream.require(FEATURE)
    if dtype == "uint8":
        stream.require(QUANTISED_FEATURE)
    return len(data)


def pack_codes(codes: np.ndarray, bits: int) -> bytes:
    """``codes`` (uint8, each < 2^bits) packed at ``bits`` bits each, most significant bit first."""
    if bits == 8:
        return codes.astype(np.uint8).tobytes()
    planes = (codes[:, None] >> np.arange(bits - 1, -1, -1, dtype=np.uint8)) & 1
    return np.packbits(planes.astype(np.uint8).ravel()).tobytes()


def unpack_codes(data: bytes, count: int, bits: int) -> np.ndarray:
    """The ``count`` codes of :func:`pack_codes` (uint8)."""
    if bits == 8:
        return np.frombuffer(data, dtype=np.uint8, count=count)
    planes = np.unpackbits(np.frombuffer(data, dtype=np.uint8), count=count * bits).reshape(count, bits)
    return (planes << np.arange(bits - 1, -1, -1, dtype=np.uint8)).sum(axis=1, dtype=np.uint8)


def decode_weights(raw: bytes, arch: DeformArch, dtype: str = "float16", bits: int = 16) -> dict[str, np.ndarray]:
    """The float32 weights from the inflated chunk (its size is checked by the header validator)."""
    out: dict[str, np.ndarray] = {}
    halves = np.frombuffer(raw, dtype="<f2", count=(len(raw) if dtype == "float16" else _half_bytes(arch)) // 2)
    offset, code_offset = 0, 0
    if dtype != "float16":
        all_codes = unpack_codes(raw[2 * len(halves):], _code_count(arch), bits)
    for name, shape in weight_shapes(arch):
        if dtype == "float16" or len(shape) == 1:
            size = int(np.prod(shape))
            out[name] = halves[offset : offset + size].astype(np.float32).reshape(shape)
            offset += size
            continue
        rows, cols = shape
        lo = halves[offset : offset + rows].astype(np.float32)
        step = halves[offset + rows : offset + 2 * rows].astype(np.float32)
        offset += 2 * rows
        codes = all_codes[code_offset : code_offset + rows * cols].reshape(shape)
        code_offset += rows * cols
        out[name] = (lo[:, None] + codes.astype(np.float32) * step[:, None]).astype(np.float32)
    return out


def _half_bytes(arch: DeformArch) -> int:
    """Bytes of the float16 part of the quantised form."""
    return sum(4 * s[0] if len(s) == 2 else 2 * s[0] for _, s in weight_shapes(arch))


def _code_count(arch: DeformArch) -> int:
    """Weights of the quantised form's matrices (one code each)."""
    return sum(s[0] * s[1] for _, s in weight_shapes(arch) if len(s) == 2)

