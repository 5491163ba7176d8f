"""Read PlayCanvas ``compressed.ply`` files (SuperSplat's and splat-transform's compressed PLY).

A binary PLY with two or three elements::

    chunk   one row per 256 Gaussians, float32: min_x min_y min_z max_x max_y max_z,
            min_scale_x .. max_scale_z, optionally min_r min_g min_b max_r max_g max_b
    vertex  uint32 packed_position, packed_rotation, packed_scale, packed_color
    sh      (optional) uint8 f_rest_0 .. f_rest_{9|24|45}, Inria channel-major order

* position and log-scale: 11, 10, 11 bits of x, y, z (high to low) interpolating
  between the chunk's min and max;
* rotation: 2 bits (top) give which wxyz component is the largest and is dropped,
  then three 10-bit values ``c / sqrt(2) + 0.5`` of the others, in wxyz order;
* colour: 8 bits each of R, G, B (between the chunk's min_r..max_r when present,
  else in [0, 1]) and alpha, with f_dc = (colour - 0.5) / SH_C0, opacity = logit(alpha);
* SH: ``(v + 0.5) / 256`` (0 and 255 map to 0 and 1) spans coefficients in [-4, 4].

What it loses (this module only reads it): positions and scales to 10-11 bits within
each chunk's box, rotations to ~0.0014 per component, colour and alpha to 8 bits, SH to
8 bits in [-4, 4]. Alpha 0 or 255 reads as an infinite logit, clamped with a note.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import plyfile

from gscodec_shac import sh_index
from gscodec_shac.errors import ModelFormatError, PlyFormatError, ValidationError
from gscodec_shac.io.bounded import READ_COPIES, check_memory, cloud_bytes
from gscodec_shac.io.ply_header import check_layout, read_layout
from gscodec_shac.limits import MAX_GAUSSIANS
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.model_common import SH_C0, check_rows, logits_from_alpha, zero_sh_rest

CHUNK_SIZE = 256
_CHUNK_BOUNDS = [f"{end}_{axis}" for end in ("min", "max") for axis in "xyz"] + [
    f"{end}_scale_{axis}" for end in ("min", "max") for axis in "xyz"
]
_CHUNK_COLORS = [f"{end}_{c}" for end in ("min", "max") for c in "rgb"]
_PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")


def is_compressed_ply_header(header: str) -> bool:
    """Whether a PLY header (text up to ``end_header``) describes a compressed PLY."""
    return "element chunk" in header and "packed_position" in header


def read_compressed_ply(path: str | os.PathLike) -> GaussianCloud:
    """Read a PlayCanvas compressed PLY (see the module docstring) into a :class:`GaussianCloud`."""
    path = Path(path)
    if not path.is_file():
        raise ModelFormatError(f"{path}: no such compressed PLY file")
    try:  # the header (at most 64 KiB) and its element counts against the file size, before plyfile
        layout = read_layout(path)
        check_layout(layout, path)
    except PlyFormatError as exc:
        raise ModelFormatError(str(exc)) from None
    lists = [f"{e.name}.{p.name}" for e in layout.elements for p in e.properties if p.count_type]
    if lists:
        raise ModelFormatError(f"{path}: not a compressed PLY (list property {lists[0]}; every property is a scalar)")
    vertex_rows = layout.element("vertex").count if layout.element("vertex") else 0
    if vertex_rows > MAX_GAUSSIANS:
        raise ModelFormatError(f"{path}: {vertex_rows:,} Gaussians (at most {MAX_GAUSSIANS:,})")
    check_memory(str(path), READ_COPIES * cloud_bytes(vertex_rows, 3) + 2 * layout.file_bytes,
                 f"reading {vertex_rows:,} Gaussians")
    try:
        data = plyfile.PlyData.read(str(path))
    except Exception as exc:  # plyfile raises several types for malformed input
        raise ModelFormatError(f"{path}: malformed or truncated PLY ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    elements = {element.name: element.data for element in data.elements}
    if "chunk" not in elements or "vertex" not in elements:
        raise ModelFormatError(f"{path}: not a compressed PLY (needs 'chunk' and 'vertex' elements)")
    chunks, vertex = elements["chunk"], elements["vertex"]
    _require(path, chunks, _CHUNK_BOUNDS, "chunk")
    _require(path, vertex, _PACKED, "vertex")
    n = len(vertex)
    check_rows(path, n, "compressed PLY")
    if len(chunks) != -(-n // CHUNK_SIZE):
        raise ModelFormatError(f"{path}: {len(chunks)} chunk rows for {n:,} Gaussians (expected {-(-n // CHUNK_SIZE)})")
    owner = np.arange(n) // CHUNK_SIZE

    def bounds(prefix: str, axes: str) -> tuple[np.ndarray, np.ndarray]:
        low = np.stack([np.asarray(chunks[f"min_{prefix}{a}"], np.float64)[owner] for a in axes], axis=1)
        high = np.stack([np.asarray(chunks[f"max_{prefix}{a}"], np.float64)[owner] for a in axes], axis=1)
        return low, high

    packed = {name: np.asarray(vertex[name]).astype(np.uint32) for name in _PACKED}
    means = _lerp(*bounds("", "xyz"), _unpack_11_10_11(packed["packed_position"]))
    scales = _lerp(*bounds("scale_", "xyz"), _unpack_11_10_11(packed["packed_scale"]))
    color = np.stack([_unorm(packed["packed_color"] >> s, 8) for s in (24, 16, 8, 0)], axis=1)
    rgb = _lerp(*bounds("", "rgb"), color[:, :3]) if all(c in chunks.dtype.names for c in _CHUNK_COLORS) else color[:, :3]
    try:
        return GaussianCloud(
            means=means,
            scales=scales,
            quats=_unpack_rotation(packed["packed_rotation"]),
            opacities=logits_from_alpha(color[:, 3], path),
            sh_dc=(rgb - 0.5) / SH_C0,
            sh_rest=_sh_rest(path, elements.get("sh"), n),
        )
    except ValidationError as exc:
        raise ModelFormatError(f"{path}: {exc}") from None


def _require(path: Path, table: np.ndarray, names, element: str) -> None:
    missing = [name for name in names if name not in (table.dtype.names or ())]
    if missing:
        raise ModelFormatError(f"{path}: not a compressed PLY, element {element!r} lacks {', '.join(missing)}")


def _unorm(values: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return (values & np.uint32(top)).astype(np.float64) / top


def _unpack_11_10_11(values: np.ndarray) -> np.ndarray:
    return np.stack([_unorm(values >> 21, 11), _unorm(values >> 11, 10), _unorm(values, 11)], axis=1)


def _lerp(low: np.ndarray, high: np.ndarray, t: np.ndarray) -> np.ndarray:
    return low * (1.0 - t) + high * t


def _unpack_rotation(values: np.ndarray) -> np.ndarray:
    """(N,) u32 -> (N, 4) wxyz: the largest component (index in the top 2 bits) rebuilt."""
    stored = np.stack([(_unorm(values >> s, 10) - 0.5) * np.sqrt(2.0) for s in (20, 10, 0)], axis=1)
    largest = (values >> 30).astype(np.int64)
    n = values.shape[0]
    others = np.array([[j for j in range(4) if j != i] for i in range(4)])[largest]
    quats = np.zeros((n, 4))
    quats[np.arange(n)[:, None], others] = stored
    quats[np.arange(n), largest] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(stored * stored, axis=1)))
    return quats


def _sh_rest(path: Path, table: np.ndarray | None, n: int) -> np.ndarray:
    if table is None:
        return zero_sh_rest(n)
    names = table.dtype.names or ()
    count = len(names)
    if count % 3 or count // 3 not in (3, 8, 15) or any(f"f_rest_{i}" not in names for i in range(count)):
        raise ModelFormatError(f"{path}: the 'sh' element must hold f_rest_0..f_rest_8, _23 or _44, got {count} properties")
    if len(table) != n:
        raise ModelFormatError(f"{path}: the 'sh' element has {len(table):,} rows for {n:,} Gaussians")
    raw = np.stack([np.asarray(table[f"f_rest_{i}"]).astype(np.float64) for i in range(count)], axis=1)
    unit = np.where(raw == 0, 0.0, np.where(raw == 255, 1.0, (raw + 0.5) / 256.0))
    return sh_index.sh_rest_from_inria_rest(((unit - 0.5) * 8.0).astype(np.float32))
