"""Per-attribute value transforms and per-channel min/max n-bit quantisers.

Everything here is a pure function on numpy arrays: the pipeline decides which
transform and bit depth each attribute gets (from the rate point) and records
the ranges in the container header.

=============  ============================================  ==============================
attribute      forward transform                             inverse
=============  ============================================  ==============================
positions      ``sign(x) * log1p(|x|)`` (as gsplat / MPEG)   ``sign(y) * expm1(|y|)``
rotation       unit quaternion, canonical sign ``w >= 0``    as is (unit quaternion)
rotation       or its rotation vector ``angle * axis``       the unit quaternion
scale          log-scales as stored                          as is
opacity        logits as stored                              as is
SH colour      optional RGB -> YCbCr (BT.709) per triplet    YCbCr -> RGB
=============  ============================================  ==============================

Quantiser: per channel ``lo = min``, ``hi = max`` rounded to float32 (so the
header stores them exactly), ``q = round((x - lo) / (hi - lo) * (2^b - 1))``;
``x~ = lo + q * (hi - lo) / (2^b - 1)``, computed in float64 then cast to
float32. The error is at most half a step, ``(hi - lo) / (2^b - 1) / 2`` (plus
float32 rounding of the result).
"""

from __future__ import annotations

from dataclasses import dataclass

from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np

from gscodec_shac.errors import ValidationError
from gscodec_shac.gaussians import GaussianCloud

# BT.709 luma weights.
_KR, _KB = 0.2126, 0.0722
_KG = 1.0 - _KR - _KB
#: Rows per block in :meth:`Quantizer.quantize` (bounds the float64 temporary).
_BLOCK_ROWS = 1 << 16
#: A row-wise transform of (n, C) values (each output row depends on its input row only).
RowTransform = Callable[[np.ndarray], np.ndarray]


# ----------------------------------------------------------------- transforms
def log_transform(x: np.ndarray) -> np.ndarray:
    """``sign(x) * log1p(|x|)``: compresses large coordinates (positions)."""
    x = np.asarray(x, dtype=np.float64)
    return np.sign(x) * np.log1p(np.abs(x))


def inverse_log_transform(y: np.ndarray) -> np.ndarray:
    """Inverse of :func:`log_transform`."""
    y = np.asarray(y, dtype=np.float64)
    return np.sign(y) * np.expm1(np.abs(y))


def canonical_quaternions(quats: np.ndarray) -> np.ndarray:
    """Unit quaternions (w first) with ``w >= 0``; a zero quaternion becomes the identity."""
    q = np.asarray(quats, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 4:
        raise ValidationError(f"quaternions must have shape (N, 4), got {q.shape}")
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    unit = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))
    return np.where(unit[:, :1] < 0, -unit, unit)


def rotation_vectors(quats: np.ndarray) -> np.ndarray:
    """Rotation vectors ``angle * axis`` (the log map, radians; length at most pi) of quaternions (w first).

    Three numbers per rotation where a quaternion takes four: a step of the vector turns the
    rotation by at most the step's length, uniformly over all rotations.
    """
    q = canonical_quaternions(quats)
    sine = np.linalg.norm(q[:, 1:], axis=1)
    angle = 2.0 * np.arctan2(sine, q[:, 0])
    # angle / sin(angle / 2) -> 2 as the angle -> 0
    scale = np.where(sine > 1e-12, angle / np.maximum(sine, 1e-12), 2.0)
    return q[:, 1:] * scale[:, None]


def quaternions_from_rotation_vectors(vectors: np.ndarray) -> np.ndarray:
    """Unit quaternions (w first) of rotation vectors (:func:`rotation_vectors`' inverse; any length)."""
    r = np.asarray(vectors, dtype=np.float64)
    angle = np.linalg.norm(r, axis=1)
    # sin(angle / 2) / angle -> 1/2 as the angle -> 0
    scale = np.where(angle > 1e-12, np.sin(angle / 2) / np.maximum(angle, 1e-12), 0.5)
    return np.concatenate([np.cos(angle / 2)[:, None], r * scale[:, None]], axis=1)


def rgb_to_ycbcr(rgb: np.ndarray) -> np.ndarray:
    """BT.709 RGB -> YCbCr on the last axis (size 3), no offsets (values stay signed)."""
    return _apply_3x3(rgb, _RGB_TO_YCBCR)


def ycbcr_to_rgb(ycc: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rgb_to_ycbcr`."""
    return _apply_3x3(ycc, _YCBCR_TO_RGB)


def _apply_3x3(values: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """``matrix @ v`` for every colour triplet ``v`` on the last axis, in float64.

    ``einsum`` without BLAS: a BLAS product with an inner dimension of 3 is many
    times slower on tall arrays (thread start-up per call on a busy machine).
    """
    values = np.asarray(values, dtype=np.float64)
    if values.shape[-1:] != (3,):
        raise ValidationError(f"colour values need a last axis of size 3, got shape {values.shape}")
    return np.einsum("ij,...j->...i", matrix, values, optimize=False)


# Y = KR R + KG G + KB B;  Cb = (B - Y) / (2 (1 - KB));  Cr = (R - Y) / (2 (1 - KR))
_RGB_TO_YCBCR = np.array(
    [
        [_KR, _KG, _KB],
        [-_KR / (2 * (1 - _KB)), -_KG / (2 * (1 - _KB)), 0.5],
        [0.5, -_KG / (2 * (1 - _KR)), -_KB / (2 * (1 - _KR))],
    ]
)
_YCBCR_TO_RGB = np.linalg.inv(_RGB_TO_YCBCR)


def triplets_to_ycbcr(values: np.ndarray) -> np.ndarray:
    """(N, 3m) columns holding m RGB triplets -> the same layout in YCbCr."""
    n, c = _check_triplets(values)
    return rgb_to_ycbcr(values.reshape(n, c // 3, 3)).reshape(n, c)


def triplets_from_ycbcr(values: np.ndarray) -> np.ndarray:
    """Inverse of :func:`triplets_to_ycbcr`."""
    n, c = _check_triplets(values)
    return ycbcr_to_rgb(values.reshape(n, c // 3, 3)).reshape(n, c)


def _check_triplets(values: np.ndarray) -> tuple[int, int]:
    if values.ndim != 2 or values.shape[1] % 3:
        raise ValidationError(f"colour triplets need shape (N, 3m), got {values.shape}")
    return values.shape[0], values.shape[1]


# -------------------------------------------------------------- pruning
def prune_mask(cloud: GaussianCloud, min_opacity: float) -> np.ndarray:
    """Boolean mask of the Gaussians kept: ``sigmoid(opacity) >= min_opacity``."""
    if not 0.0 <= min_opacity < 1.0:
        raise ValidationError(f"min_opacity must be in [0, 1), got {min_opacity}")
    return cloud.activated_opacities() >= min_opacity


# ------------------------------------------------------------- quantiser
@dataclass(frozen=True)
class Quantizer:
    """Per-channel min/max quantiser to ``bits``-bit unsigned integers."""

    bits: int
    lo: np.ndarray  # (C,) float32
    hi: np.ndarray  # (C,) float32

    def __post_init__(self) -> None:
        if not 1 <= self.bits <= 16:
            raise ValidationError(f"quantiser bit depth must be 1-16, got {self.bits}")
        lo = np.asarray(self.lo, dtype=np.float32).reshape(-1)
        hi = np.asarray(self.hi, dtype=np.float32).reshape(-1)
        if lo.shape != hi.shape:
            raise ValidationError(f"quantiser ranges differ in length: {lo.shape} vs {hi.shape}")
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()) or (hi < lo).any():
            raise ValidationError("quantiser ranges must be finite with min <= max")
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)

    @classmethod
    def fit(cls, values: np.ndarray, bits: int, rows: RowTransform | None = None,
            block_rows: int = _BLOCK_ROWS) -> "Quantizer":
        """Ranges from the data: per-column min and max, as float32.

        ``rows``: a row-wise transform (e.g. :func:`log_transform`) the ranges are taken of,
        applied ``block_rows`` rows at a time (the same ranges as of ``rows(values)``, without
        that whole array)."""
        values = _as_2d(values)
        if values.shape[0] == 0:
            zeros = np.zeros(values.shape[1], dtype=np.float32)
            return cls(bits, zeros, zeros)
        lo, hi = column_extrema(values, rows, block_rows)
        return cls.from_extrema(bits, lo, hi)

    @classmethod
    def from_extrema(cls, bits: int, lo: np.ndarray, hi: np.ndarray) -> "Quantizer":
        """The quantiser of data whose per-column min and max are ``lo`` and ``hi``: float32 ranges
        that still cover them."""
        lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
        # float32 rounding of the extremes must still cover the data.
        lo32 = np.where(lo32.astype(np.float64) > lo, np.nextafter(lo32, np.float32(-np.inf)), lo32)
        hi32 = np.where(hi32.astype(np.float64) < hi, np.nextafter(hi32, np.float32(np.inf)), hi32)
        return cls(bits, lo32, hi32)

    @property
    def levels(self) -> int:
        return (1 << self.bits) - 1

    @property
    def step(self) -> np.ndarray:
        """Quantisation step per channel (0 for a constant channel)."""
        return (self.hi.astype(np.float64) - self.lo.astype(np.float64)) / self.levels

    def quantize(self, values: np.ndarray, rows: RowTransform | None = None, block_rows: int = _BLOCK_ROWS) -> np.ndarray:
        """(N, C) floats -> (N, C) uint16 in ``[0, 2^bits)`` (float64 arithmetic, ``block_rows`` rows
        at a time); with ``rows``, of ``rows(values)``, transformed block by block."""
        values = _as_2d(values)
        if rows is None and values.shape[1] != self.lo.shape[0]:
            raise ValidationError(f"quantiser has {self.lo.shape[0]} channels, values have {values.shape[1]}")
        out = np.empty((values.shape[0], self.lo.shape[0]), dtype=np.uint16)
        span = self.hi.astype(np.float64) - self.lo.astype(np.float64)
        scale = np.where(span > 0, self.levels / np.where(span > 0, span, 1.0), 0.0)
        lo = self.lo.astype(np.float64)
        for start in range(0, values.shape[0], block_rows):
            raw = values[start : start + block_rows]
            block = raw.astype(np.float64) if rows is None else np.array(rows(raw), dtype=np.float64)
            if block.shape[1] != self.lo.shape[0]:
                raise ValidationError(f"quantiser has {self.lo.shape[0]} channels, values have {block.shape[1]}")
            block -= lo
            block *= scale
            np.rint(block, out=block)
            np.clip(block, 0, self.levels, out=block)
            out[start : start + block_rows] = block
        return out

    def tables(self) -> np.ndarray:
        """(C, 2^bits) float32: the reconstruction of every code, computed in float64 per channel."""
        codes = np.arange(self.levels + 1, dtype=np.float64)
        return (self.lo.astype(np.float64)[:, None] + codes[None, :] * self.step[:, None]).astype(np.float32)

    def dequantize_cells(self, planes: np.ndarray, cells: np.ndarray, workers: int = 1) -> np.ndarray:
        """(C, H*W) coded planes -> (N, C) float32 reconstructions of the ``cells`` (a column-major view).

        The same values as ``dequantize(planes[:, cells].T)``: per channel one gather of the
        occupied cells and one lookup in the channel's table of ``2^bits`` reconstructions,
        both whole-array numpy operations that release the GIL, so ``workers`` threads
        run channels side by side.
        """
        if planes.shape[0] != self.lo.shape[0]:
            raise ValidationError(f"quantiser has {self.lo.shape[0]} channels, the planes {planes.shape[0]}")
        cells = np.asarray(cells, dtype=np.intp)
        tables = self.tables()
        out = np.empty((planes.shape[0], cells.size), dtype=np.float32)

        def channel(c: int) -> None:
            np.take(tables[c], np.take(planes[c], cells), mode="clip", out=out[c])

        map_channels(channel, planes.shape[0], workers)
        return out.T

    def dequantize(self, q: np.ndarray) -> np.ndarray:
        """(N, C) integers -> (N, C) float32 reconstructions ``lo + q * step`` (a column-major view).

        Computed once per code in float64 (a table of ``2^bits`` entries per
        channel) and looked up, so the result is the same as evaluating the
        formula for every value.
        """
        q = _as_2d(q)
        if q.shape[1] != self.lo.shape[0]:
            raise ValidationError(f"quantiser has {self.lo.shape[0]} channels, values have {q.shape[1]}")
        if not np.issubdtype(q.dtype, np.integer):
            raise ValidationError(f"quantised values must be integers, got dtype {q.dtype}")
        codes = np.arange(self.levels + 1, dtype=np.float64)
        # Channel-major storage: each channel is one contiguous write (3-4x faster
        # than strided column writes at N = 1M); the (N, C) result is its transpose.
        out = np.empty((q.shape[1], q.shape[0]), dtype=np.float32)
        for c in range(q.shape[1]):
            table = (self.lo[c].astype(np.float64) + codes * self.step[c]).astype(np.float32)
            np.take(table, q[:, c], mode="clip", out=out[c])
        return out.T

    def to_json(self) -> dict:
        """Header form; float32 values print as the shortest decimal that reads back exactly."""
        return {"bits": self.bits, "min": [float32_json(v) for v in self.lo], "max": [float32_json(v) for v in self.hi]}

    @classmethod
    def from_json(cls, data: dict) -> "Quantizer":
        return cls(int(data["bits"]), np.asarray(data["min"], dtype=np.float64), np.asarray(data["max"], dtype=np.float64))


def float32_json(value: float) -> float:
    """A Python float that prints short in JSON and reads back as exactly ``float32(value)``."""
    exact = np.float32(value)
    short = float(str(exact))
    return short if np.float32(short) == exact else float(exact)


def column_extrema(values: np.ndarray, rows: RowTransform | None = None,
                   block_rows: int = _BLOCK_ROWS) -> tuple[np.ndarray, np.ndarray]:
    """Per-column min and max of (N, C) ``values`` (N > 0), or of ``rows(values)`` computed
    ``block_rows`` rows at a time (exactly the extrema of the whole transformed array)."""
    values = _as_2d(values)
    if rows is None:
        return values.min(axis=0), values.max(axis=0)
    lo = hi = None
    for start in range(0, values.shape[0], block_rows):
        block = _as_2d(rows(values[start : start + block_rows]))
        low, high = block.min(axis=0), block.max(axis=0)
        lo = low if lo is None else np.minimum(lo, low)
        hi = high if hi is None else np.maximum(hi, high)
    return lo, hi


def _as_2d(values: np.ndarray) -> np.ndarray:
    values = np.asarray(values)
    if values.ndim == 1:
        values = values[:, None]
    if values.ndim != 2:
        raise ValidationError(f"expected (N, C) values, got shape {values.shape}")
    return values


# ---------------------------------------------------- integer plane layouts
def split_planes(values: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """``bits``-bit integers (9-16 bits) -> (high part, low 8 bits), as two uint16 arrays."""
    if not 9 <= bits <= 16:
        raise ValidationError(f"split into two 8-bit planes needs 9-16 bits, got {bits}")
    values = np.asarray(values, dtype=np.uint16)
    return values >> 8, values & 0xFF


def join_planes(high: np.ndarray, low: np.ndarray) -> np.ndarray:
    """Inverse of :func:`split_planes`."""
    return (np.asarray(high, dtype=np.uint16) << 8) | np.asarray(low, dtype=np.uint16)


def map_channels(work: Callable[[int], None], count: int, workers: int) -> None:
    """Run ``work(c)`` for ``c`` in ``range(count)``, in ``workers`` threads when more than one."""
    if workers <= 1 or count <= 1:
        for c in range(count):
            work(c)
        return
    with ThreadPoolExecutor(min(workers, count)) as pool:
        list(pool.map(work, range(count)))
