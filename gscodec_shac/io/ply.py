"""Read and write Inria 3DGS PLY files.

Layout (one ``vertex`` element, float32 scalars)::

    x y z [nx ny nz] f_dc_0..2 f_rest_0..(3(K-1)-1) opacity scale_0..2 rot_0..3

``f_rest`` is channel-major (all R coefficients, then G, then B); conversion to
the coefficient-major ``sh_rest`` of :class:`GaussianCloud` happens here via
:mod:`gscodec_shac.sh_index`. Any other vertex property (normals, custom fields)
is kept in ``GaussianCloud.extra`` and written back, so a read/write round trip is
bit-exact; for a file written by the Inria trainer it is byte-identical.

Binary little/big endian and ASCII files are read (via ``plyfile``), after the header
has been checked against the data (:mod:`gscodec_shac.io.ply_header`: counts, sizes,
PlayCanvas compressed PLYs); files are written binary little endian, atomically, so a
failed write never leaves a half-written PLY behind.
"""

from __future__ import annotations

import os
import re
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import plyfile

from gscodec_shac import sh_index
from gscodec_shac.atomic import atomic_output
from gscodec_shac.errors import PlyFormatError, ValidationError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.ply_header import (
    FLOAT_TYPES,
    PlyElement,
    PlyLayout,
    check_layout,
    playcanvas_compressed,
    read_layout,
)

_REQUIRED = (
    ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    + [f"scale_{i}" for i in range(3)]
    + [f"rot_{i}" for i in range(4)]
)
_F_REST = re.compile(r"^f_rest_(\d+)$")
_NORMALS = ("nx", "ny", "nz")
#: The cloud's float arrays a PLY fills (checked for NaN and inf after reading).
_FLOAT_ARRAYS = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")
#: Finite stand-in for an infinite opacity logit (8-bit alpha 0 or 255): sigmoid(20) = 1 - 2e-9.
OPACITY_LOGIT_LIMIT = 20.0


#: Rows per block when reading a binary PLY. The row buffer (1 MB at SH degree 3) and the block's
#: slice of the cloud's arrays stay in the CPU's cache while each property's column is copied out:
#: 1M Gaussians read in a median 0.15 s against 0.25 s with 65,536 rows (docs/benchmarks.md).
READ_BLOCK_ROWS = 1 << 12
#: Vertices from which a binary PLY is read in two threads (each half of the rows; the same arrays).
SPLIT_READ_ROWS = 1 << 17
#: numpy type of each PLY scalar type (both spellings of each).
_NUMPY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}


def read_ply(path: str | os.PathLike, *, clamp_opacity: bool = False, block_rows: int = READ_BLOCK_ROWS) -> GaussianCloud:
    """Read an Inria 3DGS PLY into a :class:`GaussianCloud`.

    Raises :class:`PlyFormatError` with one sentence for: a missing or unreadable
    file, a directory, a file that is not a PLY, a PlayCanvas compressed PLY, element
    counts that disagree with the data, no ``vertex`` element, zero vertices, missing
    3DGS properties or 3DGS properties that are not floats, an ``f_rest`` count that fits
    no SH degree 0-4, list properties, or non-finite values (how many, in which property,
    at which vertices). ``clamp_opacity`` sets infinite opacity logits (8-bit alpha 0 or
    255 converted to logits) to +-:data:`OPACITY_LOGIT_LIMIT`, as the RD harness does.

    A binary file is read ``block_rows`` vertices at a time straight into the cloud's
    arrays (memory: the cloud plus one block; the values do not depend on ``block_rows``);
    an ASCII file goes through ``plyfile``.
    """
    path = Path(path)
    if path.is_dir():
        raise PlyFormatError(f"{path}: is a directory, not a PLY file")
    if not path.is_file():
        raise PlyFormatError(f"{path}: no such file")
    with open(path, "rb") as handle:
        if handle.read(4) != b"ply\n" and not _starts_with_ply(path):
            raise PlyFormatError(f"{path}: not a PLY file (it does not start with 'ply')")
    layout = read_layout(path)
    if playcanvas_compressed(layout):
        raise PlyFormatError(
            f"{path}: a PlayCanvas/SuperSplat compressed PLY (quantised 'chunk' and packed 'vertex' elements), "
            f"not an Inria 3DGS PLY; decompress it first, e.g. `npx @playcanvas/splat-transform {path} decompressed.ply`"
        )
    check_layout(layout, path)
    vertex = layout.element("vertex")
    if vertex is not None:
        for prop in vertex.properties:
            if (prop.name in _REQUIRED or _F_REST.match(prop.name)) and not prop.count_type and prop.type not in FLOAT_TYPES:
                raise PlyFormatError(f"{path}: property {prop.name!r} is {prop.type}; an Inria 3DGS PLY stores it "
                                     "as float (or double)")
    offset = _binary_offset(layout)
    if offset is None:  # ASCII (or rows of varying size before the vertices): plyfile parses the file
        try:
            data = plyfile.PlyData.read(str(path))
        except Exception as exc:  # plyfile raises several types for malformed input
            raise PlyFormatError(f"{path}: malformed or truncated PLY ({_one_line(exc)})") from None
    names = [element.name for element in layout.elements]
    if vertex is None:
        raise PlyFormatError(f"{path}: no 'vertex' element (elements: {', '.join(names) or 'none'})")
    others = [n for n in names if n != "vertex"]
    if others:
        warnings.warn(f"{path}: PLY elements {others} are not Gaussians and are ignored", stacklevel=2)
    for prop in vertex.properties:
        if prop.count_type:
            raise PlyFormatError(f"{path}: list property {prop.name!r} is not supported in a 3DGS PLY")
    count = vertex.count
    if count == 0:
        raise PlyFormatError(f"{path}: the PLY has zero vertices")
    fields = [prop.name for prop in vertex.properties]
    missing = [name for name in _REQUIRED if name not in fields]
    if missing:
        raise PlyFormatError(f"{path}: not a 3DGS PLY, missing properties: {', '.join(missing)}")
    rest_ids = sorted(int(_F_REST.match(f).group(1)) for f in fields if _F_REST.match(f))
    if rest_ids != list(range(len(rest_ids))):
        raise PlyFormatError(f"{path}: f_rest_* properties are not numbered 0..{len(rest_ids) - 1}")
    if len(rest_ids) % 3:
        raise PlyFormatError(
            f"{path}: {len(rest_ids)} f_rest properties fit no SH degree "
            f"(degrees 0-4 need {_valid_rest_counts()})"
        )
    try:
        sh_index.degree_from_rest_count(len(rest_ids) // 3)
    except ValidationError:
        raise PlyFormatError(
            f"{path}: {len(rest_ids)} f_rest properties fit no SH degree "
            f"(degrees 0-4 need {_valid_rest_counts()})"
        ) from None

    arrays, columns = _destinations(vertex, len(rest_ids) // 3)
    with np.errstate(over="ignore", invalid="ignore"):  # doubles beyond float32 become inf: reported below
        if offset is None:
            table = data["vertex"].data
            for name, target in columns.items():
                target[...] = table[name]
        else:
            _read_rows(path, layout, offset, columns, block_rows)
    opacity = arrays["opacities"]
    if clamp_opacity:
        infinite = np.isinf(opacity)
        if infinite.any():
            from gscodec_shac.io.model_common import note

            note(f"{path}: {int(infinite.sum()):,} infinite opacity logit(s) (8-bit alpha 0 or 255) "
                 f"clamped to +-{OPACITY_LOGIT_LIMIT:g}")
            opacity[infinite] = np.sign(opacity[infinite]) * np.float32(OPACITY_LOGIT_LIMIT)
    # min and max propagate NaN and reach +-inf: allocation-free passes decide the common case
    if not all(_all_finite(arrays[name]) for name in _FLOAT_ARRAYS):
        checked = [c for c in _REQUIRED if c != "opacity"] + [f"f_rest_{i}" for i in rest_ids] + ["opacity"]
        _check_finite_columns(path, [(name, columns[name]) for name in checked])
    try:
        return GaussianCloud(**arrays)
    except ValidationError as exc:
        raise PlyFormatError(f"{path}: {exc}") from None


def _destinations(vertex: PlyElement, n_rest: int) -> tuple[dict, dict[str, np.ndarray]]:
    """The cloud's arrays for ``vertex`` (uninitialised) and, per PLY property, the column view it fills.

    ``f_rest`` is channel-major in the file: ``f_rest_{c * n_rest + k}`` is coefficient ``k`` of
    channel ``c``, i.e. ``sh_rest[:, k, c]``."""
    n = vertex.count
    arrays: dict = {
        "means": np.empty((n, 3), np.float32), "scales": np.empty((n, 3), np.float32),
        "quats": np.empty((n, 4), np.float32), "opacities": np.empty(n, np.float32),
        "sh_dc": np.empty((n, 3), np.float32), "sh_rest": np.empty((n, n_rest, 3), np.float32), "extra": {},
    }
    columns = {name: arrays["means"][:, i] for i, name in enumerate("xyz")}
    columns |= {f"scale_{i}": arrays["scales"][:, i] for i in range(3)}
    columns |= {f"rot_{i}": arrays["quats"][:, i] for i in range(4)}
    columns |= {f"f_dc_{i}": arrays["sh_dc"][:, i] for i in range(3)}
    columns |= {f"f_rest_{c * n_rest + k}": arrays["sh_rest"][:, k, c] for c in range(3) for k in range(n_rest)}
    columns["opacity"] = arrays["opacities"]
    for prop in vertex.properties:
        if prop.name not in columns:
            columns[prop.name] = arrays["extra"][prop.name] = np.empty(n, np.dtype(_NUMPY_TYPES[prop.type]))
    return arrays, columns


def _binary_offset(layout: PlyLayout) -> int | None:
    """Where the vertex rows of a binary file start; None for ASCII, or when they cannot be
    read as fixed-size rows (a list property, repeated property names, no vertex element)."""
    if layout.format == "ascii":
        return None
    offset = layout.header_bytes
    for element in layout.elements:
        if element.row_bytes is None:
            return None
        if element.name == "vertex":
            names = [prop.name for prop in element.properties]
            return offset if len(set(names)) == len(names) else None
        offset += element.count * element.row_bytes
    return None


def _read_rows(path: Path, layout: PlyLayout, offset: int, columns: dict[str, np.ndarray], block_rows: int) -> None:
    """Fill ``columns`` from the binary vertex rows at ``offset``, ``block_rows`` rows at a time; a file of
    at least :data:`SPLIT_READ_ROWS` vertices in two threads, each reading half of the rows."""
    count = layout.element("vertex").count
    block_rows = max(1, int(block_rows))
    if count < SPLIT_READ_ROWS:
        _read_row_range(path, layout, offset, columns, block_rows, 0, count)
        return
    middle = count // 2
    with ThreadPoolExecutor(1) as pool:  # file reads and column copies release the GIL
        other = pool.submit(_read_row_range, path, layout, offset, columns, block_rows, middle, count)
        _read_row_range(path, layout, offset, columns, block_rows, 0, middle)
        other.result()


def _read_row_range(path: Path, layout: PlyLayout, offset: int, columns: dict[str, np.ndarray], block_rows: int,
                    first: int, stop: int) -> None:
    """Fill rows ``first:stop`` of ``columns`` from the binary vertex rows at ``offset``."""
    vertex = layout.element("vertex")
    order = "<" if layout.format == "binary_little_endian" else ">"
    dtype = np.dtype([(prop.name, order + _NUMPY_TYPES[prop.type]) for prop in vertex.properties])
    buffer = np.empty(max(0, min(block_rows, stop - first)), dtype)
    # numpy's error state is per thread: doubles beyond float32 become inf quietly here, reported by the caller
    with open(path, "rb") as handle, np.errstate(over="ignore", invalid="ignore"):
        handle.seek(offset + first * dtype.itemsize)
        for start in range(first, stop, block_rows):
            rows = buffer[: min(block_rows, stop - start)]
            raw = rows.view(np.uint8)
            if handle.readinto(raw) != raw.size:
                raise PlyFormatError(f"{path}: malformed or truncated PLY (the vertex data ends early)")
            for name, target in columns.items():
                target[start : start + rows.size] = rows[name]


#: Rows per block when writing a PLY (the structured-array temporary, 1 MB at SH degree 3, stays in
#: the cache while the columns are copied in: 1M Gaussians 0.22 s against 0.45-0.88 s with 65,536
#: in a process that keeps freed memory; under the decode's heap trim the two take the same time).
WRITE_BLOCK_ROWS = 1 << 12


def write_ply(path: str | os.PathLike, cloud: GaussianCloud, *, write_normals: bool = True,
              block_rows: int = WRITE_BLOCK_ROWS) -> None:
    """Write ``cloud`` as a binary little-endian Inria 3DGS PLY, atomically.

    ``nx ny nz`` come from ``cloud.extra`` when present; otherwise zero normals are
    written (as the Inria trainer does) unless ``write_normals`` is false. Other
    extra properties follow the standard ones, in their stored order. The rows are
    interleaved and written ``block_rows`` at a time (the bytes do not depend on it),
    so the write needs no second copy of the whole model.
    """
    path = Path(path)
    n = cloud.num_gaussians
    first = _structured_rows(cloud, slice(0, 0), write_normals)
    element = plyfile.PlyElement.describe(first, "vertex")
    header = plyfile.PlyData([element], text=False, byte_order="<").header
    header = header.replace("\nelement vertex 0\n", f"\nelement vertex {n}\n", 1) + "\n"
    block_rows = max(1, int(block_rows))
    buffer = np.empty(min(block_rows, n), dtype=first.dtype)  # one block's rows, reused: no fresh pages per block
    with atomic_output(path, error=PlyFormatError) as handle:
        handle.write(header.encode("ascii"))
        for start in range(0, n, block_rows):
            rows = _structured_rows(cloud, slice(start, start + block_rows), write_normals,
                                    out=buffer[: min(block_rows, n - start)])
            handle.write(rows.view(np.uint8).data)


def cloud_to_structured(cloud: GaussianCloud, *, write_normals: bool = True) -> np.ndarray:
    """The PLY vertex table of ``cloud`` as a numpy structured array (Inria order)."""
    return _structured_rows(cloud, slice(0, cloud.num_gaussians), write_normals)


def _structured_rows(cloud: GaussianCloud, rows: slice, write_normals: bool, out: np.ndarray | None = None) -> np.ndarray:
    """Rows ``rows`` of the PLY vertex table of ``cloud`` as a structured array (Inria order), in
    ``out`` when given (a table of the same fields and length)."""
    n = len(range(cloud.num_gaussians)[rows])
    rest = cloud.sh_rest[rows]
    n_rest = rest.shape[1]
    means, sh_dc, scales, quats = cloud.means[rows], cloud.sh_dc[rows], cloud.scales[rows], cloud.quats[rows]
    columns: list[tuple[str, np.ndarray]] = [("x", means[:, 0]), ("y", means[:, 1]), ("z", means[:, 2])]
    if all(k in cloud.extra for k in _NORMALS):
        columns += [(k, cloud.extra[k][rows]) for k in _NORMALS]
    elif write_normals:
        columns += [(k, np.zeros(n, dtype=np.float32)) for k in _NORMALS]
    columns += [(f"f_dc_{i}", sh_dc[:, i]) for i in range(3)]
    # Inria channel-major: f_rest_{c * n_rest + k} is coefficient k of channel c
    columns += [(f"f_rest_{c * n_rest + k}", rest[:, k, c]) for c in range(3) for k in range(n_rest)]
    columns += [("opacity", cloud.opacities[rows])]
    columns += [(f"scale_{i}", scales[:, i]) for i in range(3)]
    columns += [(f"rot_{i}", quats[:, i]) for i in range(4)]
    written = {name for name, _ in columns}
    for key, value in cloud.extra.items():
        if key in written:
            continue
        if value.ndim != 1:
            raise PlyFormatError(f"extra property {key!r} has shape {value.shape}; PLY scalars must be 1-D")
        columns.append((key, value[rows]))
    dtype = np.dtype([(name, _ply_dtype(values)) for name, values in columns])
    table = out if out is not None and out.dtype == dtype and len(out) == n else np.empty(n, dtype=dtype)
    for name, values in columns:
        table[name] = values
    return table


def _ply_dtype(values: np.ndarray) -> str:
    kind = np.asarray(values).dtype
    if kind == np.float32:
        return "<f4"
    if kind == np.float64:
        return "<f8"
    if np.issubdtype(kind, np.integer) and kind.itemsize <= 4:
        return kind.newbyteorder("<").str
    if kind == np.bool_:
        return "u1"
    raise PlyFormatError(f"cannot store values of dtype {kind} in a PLY property")


def _all_finite(values: np.ndarray) -> bool:
    """No NaN or inf in ``values``: min and max propagate NaN and reach +-inf (no temporary array)."""
    return values.size == 0 or bool(np.isfinite(values.min()) and np.isfinite(values.max()))


def _check_finite_columns(path: Path, named: list[tuple[str, np.ndarray]]) -> None:
    """Refuse NaN/inf (after float32 conversion), saying how many, in which properties and where."""
    opacity = dict(named)["opacity"]
    bad = [(name, np.flatnonzero(~np.isfinite(values))) for name, values in named]
    bad = [(name, rows) for name, rows in bad if rows.size]
    if not bad:
        return
    total = sum(rows.size for _, rows in bad)
    vertices = np.unique(np.concatenate([rows for _, rows in bad]))
    shown = "; ".join(f"{name}: {rows.size} (vertex {', '.join(map(str, rows[:3]))}{', ...' if rows.size > 3 else ''})"
                      for name, rows in bad[:4]) + ("; ..." if len(bad) > 4 else "")
    if all(name == "opacity" for name, _ in bad) and np.isinf(opacity[bad[0][1]]).all():
        hint = (f"infinite opacity logits (8-bit alpha 0 or 255) can be clamped to +-{OPACITY_LOGIT_LIMIT:g} as the "
                "RD harness does: read_ply(path, clamp_opacity=True)")
    else:
        hint = "fix or remove those Gaussians (the codec needs finite values)"
    raise PlyFormatError(f"{path}: {total} non-finite value(s) (NaN, inf or beyond float32 range) in "
                         f"{vertices.size} vertices: {shown}; {hint}")


def _valid_rest_counts() -> str:
    return ", ".join(str(3 * sh_index.num_rest_coeffs(d)) for d in range(sh_index.MAX_SH_DEGREE + 1))


def _starts_with_ply(path: Path) -> bool:
    with open(path, "rb") as handle:
        head = handle.read(5)
    return head in (b"ply\r\n",)


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__
