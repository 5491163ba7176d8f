"""Read and write Niantic SPZ files (versions 1-3: one gzip stream; version 4: zstd streams, ``zstandard``).

Layout of versions 1-3 (little-endian, the whole file gzip-compressed)::

    header (16 B)  magic "NGSP" (0x5053474e) u32, version u32, count u32,
                   SH degree u8, fractional bits u8, flags u8 (1 = antialiased), reserved u8
    positions      count x 3 x 24-bit signed fixed point (x / 2**fractional_bits);
                   version 1: count x 3 float16
    alphas         count x u8 = sigmoid(opacity) * 255
    colours        count x 3 x u8 = f_dc * 0.15 * 255 + 127.5
    scales         count x 3 x u8 = (log scale + 10) * 16
    rotations      version 3: count x u32, index of the largest |component| (2 bits) and the
                   other three (sign bit + 9-bit magnitude / sqrt(1/2)) of the xyzw quaternion;
                   version 2: count x 3 x u8 = x, y, z * 127.5 + 127.5 with w >= 0 implied
    SH             count x K-1 x 3 x u8 = coefficient * 128 + 128 (coefficient-major,
                   colour innermost); degree 1 is stored on 5 bits, higher ones on 4 by default

Version 4 holds the same six streams each zstd-compressed behind a 32-byte header and a
table of contents (per stream: compressed and raw size, u64 each) right after the header;
``zstandard`` (a dependency) reads and writes it.

Coordinates: SPZ stores RUB (x right, y up, z back); 3DGS PLYs and this package use RDF,
so y and z are flipped on the way in and out (``coordinates="rub"``, as Niantic's
library and splat-transform do); ``coordinates="raw"`` keeps the stored axes.

What SPZ loses: everything is 8-bit or fixed point. Positions have 2**-12 steps (fewer
fractional bits are chosen for scenes wider than +-2048); log-scales 1/16 steps within
[-10, 5.94]; rotations ~0.002 (version 3) or ~0.008 (version 2) per component; alpha
and colour 1/255 (colour range f_dc in [-3.33, 3.33]); SH 1/128 steps in [-1, 1),
coarsened to 5/4 bits; extra properties are dropped. Alpha 0 or 255 reads as an
infinite logit, clamped with a note.
"""

from __future__ import annotations

import gzip
import os
import struct

import numpy as np

from gscodec_shac import sh_index
from gscodec_shac.atomic import write_atomic
from gscodec_shac.errors import ModelFormatError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.bounded import DEFLATE_MAX_RATIO, READ_COPIES, Inflater, check_memory, cloud_bytes, read_file
from gscodec_shac.limits import MAX_GAUSSIANS, memory_budget
from gscodec_shac.io.model_common import (
    check_rows, flip_axes, logits_from_alpha, note, round_half_away, sigmoid, to_uint8, unit_quats,
)

MAGIC = 0x5053474E  # "NGSP"
_LEGACY_HEADER = struct.Struct("<IIIBBBB")
_V4_HEADER = struct.Struct("<IIIBBBBI12x")
COLOR_SCALE = 0.15
SQRT1_2 = np.float32(0.7071067811865476)
_RUB = (1.0, -1.0, -1.0)
_COORDINATES = ("rub", "raw")


def read_spz(path: str | os.PathLike, *, coordinates: str = "rub") -> GaussianCloud:
    """Read an SPZ file (see the module docstring) into a :class:`GaussianCloud` in RDF axes."""
    _check_coordinates(coordinates)
    raw = read_file(path, memory_budget(), "SPZ")
    if raw[:2] == b"\x1f\x8b":
        cloud = _unpack_legacy(path, raw)
    elif raw[:4] == struct.pack("<I", MAGIC):
        cloud = _unpack_v4(path, raw)
    else:
        raise ModelFormatError(f"{path}: not an SPZ file (neither gzip nor an NGSP header)")
    return flip_axes(cloud, _RUB) if coordinates == "rub" else cloud


def write_spz(
    path: str | os.PathLike,
    cloud: GaussianCloud,
    *,
    version: int = 3,
    coordinates: str = "rub",
    sh1_bits: int = 5,
    sh_rest_bits: int = 4,
) -> None:
    """Write ``cloud`` as a gzip SPZ of ``version`` 2 or 3, or a zstd SPZ of version 4, atomically.

    ``sh1_bits``/``sh_rest_bits`` (1-8): precision kept for SH degree 1 and for
    degrees 2+ (Niantic's defaults 5 and 4; 8 keeps all the format holds).
    """
    _check_coordinates(coordinates)
    if version not in (2, 3, 4):
        raise ModelFormatError(f"{path}: SPZ version {version} cannot be written (versions 2, 3 and 4 can)")
    for name, bits in (("sh1_bits", sh1_bits), ("sh_rest_bits", sh_rest_bits)):
        if not 1 <= bits <= 8:
            raise ModelFormatError(f"{path}: {name} must be 1-8, got {bits}")
    if coordinates == "rub":
        cloud = flip_axes(cloud, _RUB)
    n = cloud.num_gaussians
    fractional_bits = _fractional_bits(path, cloud.means)
    fixed = np.rint(cloud.means.astype(np.float64) * 2.0**fractional_bits).astype(np.int64)
    positions = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], axis=-1).astype(np.uint8)

    log_scales = cloud.scales.astype(np.float64)
    clipped = int(np.sum((log_scales < -10.0) | (log_scales > 255.0 / 16.0 - 10.0)))
    if clipped:
        note(f"{path}: {clipped:,} log-scale value(s) outside SPZ's range [-10, 5.94] clamped")
    scales = to_uint8((log_scales + 10.0) * 16.0)
    quats = unit_quats(cloud.quats)[:, [1, 2, 3, 0]]  # xyzw, the order SPZ packs
    rotations = _pack_smallest_three(quats) if version >= 3 else _pack_first_three(quats)
    alphas = to_uint8(sigmoid(cloud.opacities) * 255.0)
    colors = to_uint8(cloud.sh_dc.astype(np.float64) * (COLOR_SCALE * 255.0) + 127.5)
    sh_bytes = _quantize_sh(cloud.sh_rest, sh1_bits, sh_rest_bits)

    if cloud.extra:
        note(f"{path}: SPZ has no place for extra properties; dropped {', '.join(cloud.extra)}")
    streams = [a.tobytes() for a in (positions, alphas, colors, scales, rotations, sh_bytes)]
    if version == 4:
        write_atomic(path, _pack_v4(n, cloud.sh_degree, fractional_bits, streams), error=ModelFormatError)
        return
    header = _LEGACY_HEADER.pack(MAGIC, version, n, cloud.sh_degree, fractional_bits, 0, 0)
    write_atomic(path, gzip.compress(header + b"".join(streams), compresslevel=6, mtime=0), error=ModelFormatError)


def _pack_v4(n: int, degree: int, fractional_bits: int, streams: list[bytes]) -> bytes:
    """Version 4: the 32-byte header, the table of contents, then each non-empty stream zstd-compressed."""
    import zstandard

    packed = [zstandard.ZstdCompressor(level=12).compress(s) for s in streams if s]
    raw_sizes = [len(s) for s in streams if s]
    header = _V4_HEADER.pack(MAGIC, 4, n, degree, fractional_bits, 0, len(packed), _V4_HEADER.size)
    toc = b"".join(struct.pack("<QQ", len(p), size) for p, size in zip(packed, raw_sizes))
    return header + toc + b"".join(packed)


# ------------------------------------------------------------------ reading
def _unpack_legacy(path: str | os.PathLike, raw: bytes) -> GaussianCloud:
    """Versions 1-3: the gzip stream is inflated header first, then exactly the bytes the
    header's count needs, and not one byte more (unless the extensions flag says more follows)."""
    gz = Inflater(raw, f"{path}: corrupt or truncated SPZ (gzip)", wbits=31)
    header = gz.read(_LEGACY_HEADER.size)
    magic, version, n, degree, fractional_bits, flags, _ = _LEGACY_HEADER.unpack_from(header)
    if magic != MAGIC:
        raise ModelFormatError(f"{path}: not an SPZ file (bad magic {magic:#010x})")
    if version not in (1, 2, 3):
        raise ModelFormatError(f"{path}: gzip SPZ of version {version} is not supported (1-3 are)")
    _check_header(path, n, degree)
    sizes = _stream_sizes(n, degree, version)
    needed = sum(sizes)
    if _LEGACY_HEADER.size + needed > DEFLATE_MAX_RATIO * len(raw):
        raise ModelFormatError(f"{path}: truncated SPZ: {n:,} Gaussians need {needed:,} bytes, more than "
                               f"{len(raw):,} gzip bytes can hold")
    check_memory(str(path), _read_memory(n, degree, needed), f"reading {n:,} Gaussians")
    try:
        data = gz.read(needed)
    except ModelFormatError:
        raise ModelFormatError(f"{path}: truncated SPZ (the gzip data ends before the {needed:,} bytes "
                               f"{n:,} Gaussians need)") from None
    if flags & 0x2:
        note(f"{path}: SPZ extensions are ignored")
    else:
        gz.finish()
    streams, offset = [], 0
    for size in sizes:
        streams.append(np.frombuffer(data, dtype=np.uint8, count=size, offset=offset))
        offset += size
    return _unpack(path, n, degree, fractional_bits, version, streams)


def _unpack_v4(path: str | os.PathLike, raw: bytes) -> GaussianCloud:
    if len(raw) < _V4_HEADER.size:
        raise ModelFormatError(f"{path}: truncated SPZ (no 32-byte header)")
    _, version, n, degree, fractional_bits, flags, n_streams, toc = _V4_HEADER.unpack_from(raw)
    if version != 4:
        raise ModelFormatError(f"{path}: SPZ with an NGSP header must be version 4, got {version}")
    try:
        import zstandard
    except ImportError:
        raise ModelFormatError(
            f"{path}: SPZ version 4 is zstd-compressed; install 'zstandard' (pip install zstandard) "
            "or convert it to version 3"
        ) from None
    _check_header(path, n, degree)
    sizes = [s for s in _stream_sizes(n, degree, version) if s]
    check_memory(str(path), _read_memory(n, degree, sum(sizes)), f"reading {n:,} Gaussians")
    if n_streams != len(sizes) or toc < _V4_HEADER.size or toc + 16 * n_streams > len(raw):
        raise ModelFormatError(f"{path}: corrupt SPZ version 4 table of contents")
    offset = toc + 16 * n_streams
    streams = []
    for i, size in enumerate(sizes):
        packed, unpacked = struct.unpack_from("<QQ", raw, toc + 16 * i)
        if unpacked != size or offset + packed > len(raw):
            raise ModelFormatError(f"{path}: corrupt or truncated SPZ version 4 stream {i}")
        block = _unzstd(path, i, raw[offset:offset + packed], size)
        if len(block) != size:
            raise ModelFormatError(f"{path}: SPZ version 4 stream {i} has {len(block)} bytes, expected {size}")
        streams.append(np.frombuffer(block, dtype=np.uint8))
        offset += packed
    if degree == 0:
        streams.append(np.zeros(0, dtype=np.uint8))
    if flags & 0x2:
        note(f"{path}: SPZ extensions are ignored")
    return _unpack(path, n, degree, fractional_bits, version, streams)


def _unzstd(path: str | os.PathLike, index: int, data: bytes, size: int) -> bytes:
    """A zstd stream that must hold ``size`` bytes: a frame declaring another size is refused
    before inflating, and a stream is never inflated past ``size + 1`` bytes."""
    import io

    import zstandard

    try:
        declared = zstandard.frame_content_size(data)
        if declared not in (-1, size):  # -1: the frame does not say
            raise ModelFormatError(f"{path}: SPZ version 4 stream {index} declares {declared:,} bytes, "
                                   f"expected {size:,}")
        with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data)) as reader:
            return reader.read(size + 1)
    except zstandard.ZstdError as exc:
        raise ModelFormatError(f"{path}: corrupt SPZ version 4 stream {index} ({exc})") from None


def _unpack(path, n: int, degree: int, fractional_bits: int, version: int, streams: list[np.ndarray]) -> GaussianCloud:
    positions, alphas, colors, scales, rotations, sh_bytes = streams
    if version == 1:
        means = positions.view("<f2").reshape(n, 3).astype(np.float32)
    else:
        b = positions.reshape(n, 3, 3).astype(np.int32)
        fixed = b[..., 0] | (b[..., 1] << 8) | (b[..., 2] << 16)
        fixed = (fixed ^ 0x800000) - 0x800000  # sign-extend 24 bits
        means = fixed.astype(np.float32) * np.float32(2.0**-fractional_bits)
    if version >= 3:
        xyzw = _unpack_smallest_three(rotations.view("<u4"))
    else:
        xyz = rotations.reshape(n, 3).astype(np.float32) / np.float32(127.5) - np.float32(1.0)
        w = np.sqrt(np.maximum(0.0, 1.0 - np.sum(xyz * xyz, axis=1, dtype=np.float32)))
        xyzw = np.concatenate([xyz, w[:, None]], axis=1)
    k = sh_index.num_rest_coeffs(degree)
    return GaussianCloud(
        means=means,
        scales=scales.reshape(n, 3).astype(np.float32) / np.float32(16.0) - np.float32(10.0),
        quats=xyzw[:, [3, 0, 1, 2]],
        opacities=logits_from_alpha(alphas.astype(np.float64) / 255.0, path),
        sh_dc=(colors.reshape(n, 3).astype(np.float32) / np.float32(255.0) - np.float32(0.5)) / np.float32(COLOR_SCALE),
        sh_rest=(sh_bytes.reshape(n, k, 3).astype(np.float32) - np.float32(128.0)) / np.float32(128.0),
    )


def _unpack_smallest_three(packed: np.ndarray) -> np.ndarray:
    """(N,) u32 -> (N, 4) xyzw: 2-bit index of the dropped largest component, then 3 x 10 bits."""
    comp = packed.astype(np.uint32)
    largest = (comp >> 30).astype(np.int64)
    n = comp.shape[0]
    out = np.zeros((n, 4), dtype=np.float32)
    rows = np.arange(n)
    # the three stored components fill slots 3, 2, 1, 0 (skipping the largest), lowest bits first
    others = np.array([[j for j in range(4) if j != i] for i in range(4)])[largest]
    for slot in (2, 1, 0):
        magnitude = (comp & 0x1FF).astype(np.float32)
        negative = ((comp >> 9) & 1).astype(bool)
        comp = comp >> 10
        value = SQRT1_2 * magnitude / np.float32(511.0)
        out[rows, others[:, slot]] = np.where(negative, -value, value)
    out[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(out * out, axis=1, dtype=np.float32)))
    return out


def _read_memory(n: int, degree: int, stream_bytes: int) -> int:
    """Bytes a read of ``n`` Gaussians needs at its peak: the streams and a few float copies."""
    return stream_bytes + READ_COPIES * cloud_bytes(n, degree)


def _check_header(path, n: int, degree: int) -> None:
    check_rows(path, n, "SPZ file")
    if n > MAX_GAUSSIANS:
        raise ModelFormatError(f"{path}: the SPZ header declares {n:,} Gaussians (at most {MAX_GAUSSIANS:,})")
    if degree > sh_index.MAX_SH_DEGREE:
        raise ModelFormatError(f"{path}: SPZ SH degree {degree} is not supported (0-{sh_index.MAX_SH_DEGREE})")


def _stream_sizes(n: int, degree: int, version: int) -> list[int]:
    """Bytes of positions, alphas, colours, scales, rotations and SH."""
    return [n * (6 if version == 1 else 9), n, 3 * n, 3 * n, n * (4 if version >= 3 else 3),
            3 * n * sh_index.num_rest_coeffs(degree)]


# ------------------------------------------------------------------ writing
def _fractional_bits(path, means: np.ndarray) -> int:
    """12 (SPZ's choice) unless the scene is too wide for 24-bit fixed point at that precision."""
    extent = float(np.max(np.abs(means))) if means.size else 0.0
    bits = 12
    while bits > 0 and extent * 2.0**bits >= 2.0**23 - 1:
        bits -= 1
    if extent * 2.0**bits >= 2.0**23 - 1:
        raise ModelFormatError(f"{path}: positions up to {extent:g} do not fit SPZ's 24-bit fixed point")
    if bits < 12:
        note(f"{path}: positions up to {extent:g}: SPZ written with {bits} fractional bits instead of 12")
    return bits


def _pack_smallest_three(xyzw: np.ndarray) -> np.ndarray:
    """(N, 4) unit xyzw -> (N,) u32: largest |component| dropped (sign folded), 3 x (sign, 9 bits)."""
    n = xyzw.shape[0]
    largest = np.argmax(np.abs(xyzw), axis=1)
    rows = np.arange(n)
    negate = xyzw[rows, largest] < 0
    comp = largest.astype(np.uint32)
    others = np.array([[j for j in range(4) if j != i] for i in range(4)])[largest]
    for slot in range(3):
        value = xyzw[rows, others[:, slot]]
        sign = ((value < 0) ^ negate).astype(np.uint32)
        magnitude = np.minimum(np.floor(511.0 * np.abs(value) / float(SQRT1_2) + 0.5), 511).astype(np.uint32)
        comp = (comp << np.uint32(10)) | (sign << np.uint32(9)) | magnitude
    return comp.astype("<u4")


def _pack_first_three(xyzw: np.ndarray) -> np.ndarray:
    """(N, 4) unit xyzw -> (N, 3) u8 of x, y, z with the sign chosen so that w >= 0."""
    q = np.where(xyzw[:, 3:4] < 0, -xyzw, xyzw)
    return to_uint8(q[:, :3] * 127.5 + 127.5)


def _quantize_sh(sh_rest: np.ndarray, sh1_bits: int, sh_rest_bits: int) -> np.ndarray:
    """(N, K-1, 3) -> u8 of coefficient * 128 + 128, rounded to buckets of 2**(8 - bits)."""
    k = sh_rest.shape[1]
    bucket = np.full((1, k, 1), 1 << (8 - sh_rest_bits), dtype=np.int64)
    bucket[:, :3] = 1 << (8 - sh1_bits)
    q = round_half_away(sh_rest.astype(np.float32) * np.float32(128.0)).astype(np.int64) + 128
    q = (q + bucket // 2) // bucket * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


def _check_coordinates(coordinates: str) -> None:
    if coordinates not in _COORDINATES:
        raise ModelFormatError(f"SPZ coordinates must be one of {', '.join(_COORDINATES)}, got {coordinates!r}")

