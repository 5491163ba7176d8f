"""A PLY header read and checked against the file before ``plyfile`` touches the data.

:func:`read_layout` parses the header (format, elements, their counts and property
types; at most :data:`MAX_PLY_HEADER_BYTES`) and :func:`check_layout` compares the
counts with the bytes that follow, so that a vertex count that disagrees with the data
(too few rows, or data left over), a count no file could hold, or trailing garbage is
one :class:`PlyFormatError` naming the element, before anything is allocated for it.
:func:`playcanvas_compressed` recognises PlayCanvas/SuperSplat ``compressed.ply`` files,
which are PLYs but not Inria 3DGS PLYs.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from gscodec_shac.errors import PlyFormatError

#: The largest PLY header read (an Inria header with SH degree 4 is ~2 KiB).
MAX_PLY_HEADER_BYTES = 1 << 16
#: Bytes per value of each PLY scalar type (both spellings of each).
TYPE_BYTES = {
    "char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
    "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8,
}
FLOAT_TYPES = ("float", "float32", "double", "float64")
FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
#: Properties of the vertex element of a PlayCanvas compressed PLY.
_PLAYCANVAS_PACKED = {"packed_position", "packed_rotation", "packed_scale", "packed_color"}


@dataclass(frozen=True)
class PlyProperty:
    """One property: name, value type, and for a list property the type of its length."""

    name: str
    type: str
    count_type: str | None = None


@dataclass(frozen=True)
class PlyElement:
    """One element: name, row count and properties."""

    name: str
    count: int
    properties: tuple[PlyProperty, ...]

    @property
    def row_bytes(self) -> int | None:
        """Bytes per binary row, None when a list property makes rows vary."""
        if any(p.count_type for p in self.properties):
            return None
        return sum(TYPE_BYTES[p.type] for p in self.properties)

    def property(self, name: str) -> PlyProperty | None:
        return next((p for p in self.properties if p.name == name), None)


@dataclass(frozen=True)
class PlyLayout:
    """A parsed header and where the data starts."""

    format: str
    elements: tuple[PlyElement, ...]
    header_bytes: int
    file_bytes: int

    def element(self, name: str) -> PlyElement | None:
        return next((e for e in self.elements if e.name == name), None)


def read_layout(path: str | os.PathLike) -> PlyLayout:
    """Parse the header of the PLY ``path`` (its first bytes must be ``ply``)."""
    path = Path(path)
    with open(path, "rb") as handle:
        head = handle.read(MAX_PLY_HEADER_BYTES)
    end = _header_end(head)
    if end is None:
        if len(head) >= MAX_PLY_HEADER_BYTES:
            raise PlyFormatError(f"{path}: no 'end_header' in the first {MAX_PLY_HEADER_BYTES:,} bytes")
        raise PlyFormatError(f"{path}: truncated PLY header (no 'end_header')")
    try:
        lines = head[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise PlyFormatError(f"{path}: the PLY header is not ASCII text") from None
    fmt, elements = None, []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info", "end_header"):
            continue
        where = f"{path}: header line {number}"
        if words[0] == "format":
            if len(words) != 3 or words[1] not in FORMATS or words[2] != "1.0":
                raise PlyFormatError(f"{where}: unsupported format {' '.join(words[1:])!r} "
                                     f"(one of {', '.join(FORMATS)}, version 1.0)")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise PlyFormatError(f"{where}: 'element' needs a name and a non-negative count, got {line.strip()!r}")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise PlyFormatError(f"{where}: a property before any element")
            elements[-1][2].append(_property(words, where))
        else:
            raise PlyFormatError(f"{where}: unknown keyword {words[0]!r}")
    if fmt is None:
        raise PlyFormatError(f"{path}: the PLY header has no 'format' line")
    return PlyLayout(fmt, tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements), end, path.stat().st_size)


def check_layout(layout: PlyLayout, path: str | os.PathLike) -> None:
    """Refuse a file whose element counts disagree with its size (binary) or its lines (ASCII)."""
    body = layout.file_bytes - layout.header_bytes
    if layout.format != "ascii":
        exact = all(e.row_bytes is not None for e in layout.elements)
        least = sum(e.count * (e.row_bytes if e.row_bytes is not None else _least_row_bytes(e))
                    for e in layout.elements)
        if body < least:
            raise PlyFormatError(f"{path}: malformed or truncated PLY: the header's element counts "
                                 f"({_counts(layout)}) need {least:,} bytes of data, the file holds {body:,}")
        if exact and body > least:
            raise PlyFormatError(f"{path}: {body - least:,} bytes after the last element: the header's element "
                                 f"counts ({_counts(layout)}) disagree with the data")
        return
    rows = sum(e.count for e in layout.elements)
    if body < 2 * rows:  # every row is at least one character and a line break
        raise PlyFormatError(f"{path}: malformed or truncated PLY: the header's element counts ({_counts(layout)}) need "
                             f"{rows:,} lines, the file holds {body:,} bytes")
    with open(path, "rb") as handle:
        handle.seek(layout.header_bytes)
        lines = sum(1 for line in handle if line.strip())
    if lines != rows:
        raise PlyFormatError(f"{path}: the file holds {lines:,} data lines, the header's element counts "
                             f"say {rows:,} ({_counts(layout)})")


def playcanvas_compressed(layout: PlyLayout) -> bool:
    """True for a PlayCanvas/SuperSplat ``compressed.ply`` (``chunk`` + packed ``vertex`` elements)."""
    vertex = layout.element("vertex")
    return (layout.element("chunk") is not None and vertex is not None
            and _PLAYCANVAS_PACKED <= {p.name for p in vertex.properties})


def _property(words: list[str], where: str) -> PlyProperty:
    if len(words) == 5 and words[1] == "list":
        count_type, item_type, name = words[2], words[3], words[4]
        if count_type not in TYPE_BYTES or item_type not in TYPE_BYTES or count_type in FLOAT_TYPES:
            raise PlyFormatError(f"{where}: bad list property types {count_type!r} {item_type!r}")
        return PlyProperty(name, item_type, count_type)
    if len(words) != 3 or words[1] not in TYPE_BYTES:
        raise PlyFormatError(f"{where}: bad property line {' '.join(words)!r} "
                             f"(types: {', '.join(sorted(TYPE_BYTES))})")
    return PlyProperty(words[2], words[1])


def _least_row_bytes(element: PlyElement) -> int:
    """The smallest binary row of an element with list properties (every list empty)."""
    return sum(TYPE_BYTES[p.count_type] if p.count_type else TYPE_BYTES[p.type] for p in element.properties)


def _header_end(head: bytes) -> int | None:
    for marker in (b"end_header\n", b"end_header\r\n"):
        index = head.find(marker)
        if index >= 0 and (index == 0 or head[index - 1 : index] in (b"\n", b"\r")):
            return index + len(marker)
    return None


def _counts(layout: PlyLayout) -> str:
    return ", ".join(f"{e.name} {e.count:,}" for e in layout.elements)
