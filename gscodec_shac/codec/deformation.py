"""The deformation network of a dynamic model as one more chunk of a ``.gsc`` stream.

A dynamic model (:mod:`gscodec_shac.deform`) is coded as its canonical Gaussians (the ordinary
pipeline) plus the chunk ``deformation``, deflated (zlib), which holds every weight tensor in
``state_dict`` order (:func:`gscodec_shac.deform_arch.weight_shapes`) in one of two forms, named
by the header entry ``deformation`` = ``{"arch": {...}, "dtype": ..., ["bits": B]}``:

* ``dtype: "float16"`` (format 2.0): every weight as little-endian float16;
* ``dtype: "uint8"`` (format 2.1, feature ``deformation_quantised``): each weight matrix
  quantised per output channel (row) to ``B``-bit integers (2 <= B <= 8) with
  ``w = lo + code * step``; ``lo`` and ``step`` per row, and every bias vector, as
  float16. Layout: for each tensor in order its float16 part (a matrix's ``lo`` of every
  row, then its ``step`` of every row; a vector's values), then the codes of every matrix
  in order, row-major, packed at its ``B`` bits each (most significant bit first) into one
  bit string, the last byte padded with zeros. Packing matters: deflate's byte-wise Huffman
  codes lose up to 14% on 4-6-bit codes stored one per byte (measured on a trained network,
  docs/dynamic.md).
* the same with ``bits`` a list, one ``B`` per matrix in order (format 2.2, feature
  ``deformation_mixed_bits``): the encoder keeps the three small output heads and the time
  network's first layer (:data:`PROTECTED`) at :data:`HEAD_BITS` when the other matrices get
  fewer: a head's rounding error reaches the deformation directly, and every row of the time
  layer feeds every Gaussian's time code (per-layer sensitivity in docs/dynamic.md; together 3.3%
  of the weights); the matrix after the skip (:func:`~gscodec_shac.deform_arch.skip_input_layer`,
  which takes the encoded input again) gets one bit more than the rest. Streams written with
  other allocations decode the same way (the list is in the header). A list whose values are all
  equal is written as the single ``B`` of format 2.1 (the same bytes).

The encoder picks the codes on each row's grid by output-aware rounding when it has the
canonical centres (:mod:`.deformation_fit`), unless the weights already lie on the grid (a network
trained with ``train-dynamic --network-bits``, :func:`on_grid`): those are coded as they are. The
decoder does not need to know.

The chunk records ``encoding: zlib`` and ``raw_size`` (:func:`raw_size`, checked by
:mod:`gscodec_shac.codec.header`). The stream needs the container feature ``deformation``
(format 2.0), a quantised one also ``deformation_quantised`` (format 2.1), one with bits per
matrix also ``deformation_mixed_bits`` (format 2.2), so a decoder that does not know them
refuses the stream by name instead of decoding it wrongly.
"""

from __future__ import annotations

import zlib
import numpy as np

from gscodec_shac.codec.container import Bitstream
from gscodec_shac.codec.deformation_fit import fitted_codes, quantise_rows
from gscodec_shac.deform_arch import DeformArch, skip_input_layer, weight_count, weight_shapes
from gscodec_shac.errors import ModelFormatError

CHUNK = "deformation"
FEATURE = "deformation"
QUANTISED_FEATURE = "deformation_quantised"
MIXED_FEATURE = "deformation_mixed_bits"
DTYPES = ("float16", "uint8")
#: ``bits`` of the ``uint8`` form; 16 stands for float16 (the ``--network-bits`` values).
MIN_BITS, MAX_BITS = 2, 8
DEFAULT_BITS = 8
#: Bits of the output heads' matrices when the others get fewer (format 2.2).
HEAD_BITS = 8
HEADS = ("head_xyz.weight", "head_rot.weight", "head_scale.weight")
#: Matrices kept at :data:`HEAD_BITS` below it: the heads and the time network's first layer
#: (256 x 13 weights; at 4 bits it alone cost 0.45 dB on standup, docs/dynamic.md).
PROTECTED = HEADS + ("time_layers.0.weight",)
Bits = int | tuple[int, ...]


def dtype_of(bits: int) -> str:
    """``float16`` for 16, ``uint8`` for 2..8 (anything else: ValueError)."""
    if bits == 16:
        return "float16"
    if isinstance(bits, int) and MIN_BITS <= bits <= MAX_BITS:
        return "uint8"
    raise ValueError(f"network bits must be 16 (float16) or {MIN_BITS}..{MAX_BITS}, got {bits!r}")


def matrix_bits(arch: DeformArch, bits: Bits) -> tuple[int, ...]:
    """Bits of every matrix in order: ``bits`` itself when a tuple, else ``bits`` for each."""
    count = len(_matrices(arch))
    if isinstance(bits, tuple):
        if len(bits) != count:
            raise ValueError(f"{len(bits)} network bit counts for {count} matrices")
        return bits
    return (bits,) * count


def encoder_bits(arch: DeformArch, bits: int) -> Bits:
    """What the encoder writes for ``--network-bits bits``: when ``bits`` is below :data:`HEAD_BITS`
    a tuple (format 2.2) with the :data:`PROTECTED` matrices at :data:`HEAD_BITS`, the matrix after
    the skip at ``bits + 1`` and the rest at ``bits``; else ``bits`` (16: float16; 8: uniform, format 2.1)."""
    dtype_of(bits)
    if bits == 16 or bits >= HEAD_BITS:
        return bits
    skip = skip_input_layer(arch)
    return tuple(HEAD_BITS if name in PROTECTED else bits + 1 if name == skip else bits for name in _matrices(arch))


def encoder_grid(arch: DeformArch, bits: int) -> dict[str, int]:
    """``{matrix name: bits}`` that ``--network-bits bits`` (2..8) codes each weight matrix with
    (what quantisation-aware training trains against, :mod:`gscodec_shac.train.dynamic`)."""
    if dtype_of(bits) != "uint8":
        raise ValueError(f"network bits for a grid must be {MIN_BITS}..{MAX_BITS}, got {bits!r}")
    return dict(zip(_matrices(arch), matrix_bits(arch, encoder_bits(arch, bits))))


def raw_size(arch: DeformArch, dtype: str, bits: Bits = 16) -> int:
    """Bytes of the inflated chunk for ``arch`` in form ``dtype`` with ``bits`` (from the sizes alone)."""
    if dtype == "float16":
        return 2 * weight_count(arch)
    code_bits = sum(b * s[0] * s[1] for b, s in zip(matrix_bits(arch, bits), _matrices(arch).values()))
    return _half_bytes(arch) + (code_bits + 7) // 8


def add_deformation(stream: Bitstream, arch: DeformArch, weights: dict[str, np.ndarray],
                    bits: Bits = DEFAULT_BITS, means: np.ndarray | None = None) -> int:
    """Append the network chunk + header entry to ``stream``; returns the chunk's size in bytes.

    ``bits``: 16 for float16, 2..8 for the per-row quantised form, or a tuple of 2..8 per matrix.
    ``means``: the canonical centres; when given (and the form is quantised) the codes are chosen
    by quantisation-aware rounding (:mod:`.deformation_fit`), else by plain rounding."""
    dtype = "uint8" if isinstance(bits, tuple) else dtype_of(bits)
    per_matrix = matrix_bits(arch, bits) if dtype == "uint8" else ()
    if any(not (MIN_BITS <= b <= MAX_BITS) for b in per_matrix):
        raise ValueError(f"network bits per matrix must be {MIN_BITS}..{MAX_BITS}, got {per_matrix}")
    for name, shape in weight_shapes(arch):
        if np.shape(weights[name]) != shape:
            raise ValueError(f"deformation weight {name} has shape {np.shape(weights[name])}, expected {shape}")
    fitted: dict = {}
    grid = dict(zip(_matrices(arch), per_matrix))
    if dtype == "uint8" and means is not None and len(means) and not on_grid(weights, grid):
        codes_of, biases = fitted_codes(arch, weights, means, grid)
        fitted, weights = codes_of, {**weights, **biases}
    halves, packed, widths = [], [], iter(per_matrix)
    for name, shape in weight_shapes(arch):
        value = np.asarray(weights[name], dtype=np.float32)
        if dtype == "float16" or value.ndim == 1:
            halves.append(value.astype("<f2").tobytes())
            continue
        width = next(widths)
        lo, step, code = fitted[name] if name in fitted else quantise_rows(value, width)
        halves += [lo.astype("<f2").tobytes(), step.astype("<f2").tobytes()]
        packed.append((code.ravel(), width))
    raw = b"".join(halves) + pack_codes(packed)
    uniform = len(set(per_matrix)) <= 1
    header_bits = (per_matrix[0] if per_matrix else 16) if uniform else list(per_matrix)
    assert len(raw) == raw_size(arch, dtype, header_bits if uniform else per_matrix)
    data = zlib.compress(raw, 9)
    stream.add_chunk(CHUNK, data, attribute=CHUNK, encoding="zlib", raw_size=len(raw))
    stream.header[CHUNK] = {"arch": arch.to_dict(), "dtype": dtype, **({"bits": header_bits} if dtype == "uint8" else {})}
    stream.require(FEATURE)
    if dtype == "uint8":
        stream.require(QUANTISED_FEATURE)
    if not uniform:
        stream.require(MIXED_FEATURE)
    return len(data)


#: How far (in grid steps) a weight may sit from its row's grid point and still count as on it.
ON_GRID_TOLERANCE = 1e-3


def on_grid(weights: dict[str, np.ndarray], grid: dict[str, int]) -> bool:
    """True when every matrix ``name`` of ``grid`` already lies on its per-row grid
    ``min + k (max - min) / (2^B - 1)``, ``B = grid[name]`` (a network trained with ``train-dynamic
    --network-bits``): plain rounding then codes what was trained, and the output-aware rounding
    would only move codes to compensate for errors that are not there."""
    for name, bits in grid.items():
        value = np.asarray(weights[name], dtype=np.float64)
        lo = value.min(axis=1, keepdims=True)
        step = (value.max(axis=1, keepdims=True) - lo) / ((1 << bits) - 1)
        position = (value - lo) / np.where(step > 0, step, 1.0)
        if np.any(np.abs(position - np.rint(position)) > ON_GRID_TOLERANCE):
            return False
    return True


def heads_only_grid(arch: DeformArch, bits: int) -> dict[str, int]:
    """The grid ``--network-bits bits`` trained against before this version kept the time layer and
    the matrix after the skip finer: the heads at :data:`HEAD_BITS`, every other matrix at ``bits``."""
    return {name: HEAD_BITS if name in HEADS and bits < HEAD_BITS else bits for name in _matrices(arch)}


def trained_grid(arch: DeformArch, weights: dict[str, np.ndarray]) -> tuple[int, ...] | None:
    """The bits per matrix of the coarsest grid (2..7 bits: this version's :func:`encoder_grid`, else
    the earlier :func:`heads_only_grid`) that every weight matrix already lies on (a network trained
    with ``train-dynamic --network-bits``), else None: what ``encode`` codes such a network with when
    ``--network-bits`` is not given."""
    for bits in range(MIN_BITS, MAX_BITS):
        for grid in (encoder_grid(arch, bits), heads_only_grid(arch, bits)):
            if on_grid(weights, grid):
                return tuple(grid.values())
    return None


def pack_codes(parts: list[tuple[np.ndarray, int]]) -> bytes:
    """Each ``(codes, bits)`` part (uint8 codes, each < 2^bits) at ``bits`` bits per code, most
    significant bit first, all parts in one bit string (zero-padded to whole bytes)."""
    if parts and all(bits == 8 for _, bits in parts):
        return np.concatenate([c for c, _ in parts]).astype(np.uint8).tobytes()
    planes = [((c[:, None] >> np.arange(b - 1, -1, -1, dtype=np.uint8)) & 1).astype(np.uint8).ravel()
              for c, b in parts]
    return np.packbits(np.concatenate(planes)).tobytes() if planes else b""


def unpack_codes(data: bytes, counts: list[int], bits: list[int]) -> list[np.ndarray]:
    """The codes of :func:`pack_codes`: ``counts[i]`` codes at ``bits[i]`` bits for each part (uint8)."""
    total = sum(n * b for n, b in zip(counts, bits))
    if all(b == 8 for b in bits):
        flat = np.frombuffer(data, dtype=np.uint8, count=total // 8)
        return np.split(flat, np.cumsum(counts)[:-1])
    stream = np.unpackbits(np.frombuffer(data, dtype=np.uint8), count=total)
    out, at = [], 0
    for n, b in zip(counts, bits):
        planes = stream[at : at + n * b].reshape(n, b)
        out.append((planes << np.arange(b - 1, -1, -1, dtype=np.uint8)).sum(axis=1, dtype=np.uint8))
        at += n * b
    return out


def decode_weights(raw: bytes, arch: DeformArch, dtype: str = "float16", bits: Bits = 16) -> dict[str, np.ndarray]:
    """The float32 weights from the inflated chunk (its size is checked by the header validator)."""
    out: dict[str, np.ndarray] = {}
    halves = np.frombuffer(raw, dtype="<f2", count=(len(raw) if dtype == "float16" else _half_bytes(arch)) // 2)
    offset = 0
    if dtype != "float16":
        shapes = list(_matrices(arch).values())
        codes = iter(unpack_codes(raw[2 * len(halves):], [r * c for r, c in shapes], list(matrix_bits(arch, bits))))
    for name, shape in weight_shapes(arch):
        if dtype == "float16" or len(shape) == 1:
            size = int(np.prod(shape))
            out[name] = halves[offset : offset + size].astype(np.float32).reshape(shape)
            offset += size
            continue
        rows = shape[0]
        lo = halves[offset : offset + rows].astype(np.float32)
        step = halves[offset + rows : offset + 2 * rows].astype(np.float32)
        offset += 2 * rows
        out[name] = (lo[:, None] + next(codes).reshape(shape).astype(np.float32) * step[:, None]).astype(np.float32)
    return out


def _half_bytes(arch: DeformArch) -> int:
    """Bytes of the float16 part of the quantised form."""
    return sum(4 * s[0] if len(s) == 2 else 2 * s[0] for _, s in weight_shapes(arch))


def _matrices(arch: DeformArch) -> dict[str, tuple[int, int]]:
    """``{name: shape}`` of the weight matrices in order (the quantised form codes these)."""
    return {name: shape for name, shape in weight_shapes(arch) if len(shape) == 2}

