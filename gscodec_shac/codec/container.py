"""The ``.gsc`` container: one self-describing file per compressed scene.

Layout (all integers little-endian)::

    offset  size  field
    0       8     magic  b"\\x89GSC\\r\\n\\x1a\\n"  (catches text-mode mangling, like PNG's)
    8       2     format major version (a decoder refuses majors it does not know)
    10      2     format minor version (additions an older decoder may ignore)
    12      4     header length H in bytes
    16      4     CRC32 of the header bytes
    20      H     header: UTF-8 JSON object; ``header["chunks"]`` is the chunk table
    20+H    ...   chunk payloads, back to back, in chunk-table order; nothing after

Versions. A stream is written with the oldest version that can hold it: 1.0 when it
uses no optional feature (so files that 1.0 decoders read stay byte-identical), else
the newest version any of its features needs (:data:`FEATURE_VERSIONS`: 2.0, 2.1 for a
quantised deformation network, 2.2 for one with a bit count per matrix, 2.3 for DC-only
Gaussians, 2.4 for rotation vectors and shared HEVC parameter sets, 2.5 for spatial SH bases with
unit-weight features, 2.6 for importance tiers). Version 2 headers are
deflated (zlib; the header length and CRC are of the stored bytes) and list in
``header["features"]`` the sorted names of the features the stream needs (see :data:`FEATURES`).
A decoder refuses a feature it does not know, naming it, instead of decoding the stream wrongly.

Each chunk-table entry is ``{"name", "size", "crc32", ...}`` plus whatever the
writer records about the chunk (codec name/version/options, plane shape, bit
depth, QP, attribute). The payload sizes must add up to the file length exactly,
so a truncated file or trailing bytes are detected before any payload is used.

:meth:`Bitstream.from_bytes` raises exactly one :class:`BitstreamError` for
anything wrong (foreign file, unknown version, truncation, CRC mismatch,
malformed table) and allocates nothing larger than the file itself. The JSON header is at
most :data:`~gscodec_shac.limits.MAX_HEADER_BYTES` long and
:data:`~gscodec_shac.limits.MAX_NESTING` levels deep (checked before parsing), without
NaN, Infinity or repeated keys. What the header says is checked by
:func:`gscodec_shac.codec.header.read_header` (every reader of a stream calls it).
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gscodec_shac.atomic import write_atomic
from gscodec_shac.errors import BitstreamError, StreamFileError
from gscodec_shac.limits import MAX_HEADER_BYTES, MAX_NESTING, json_nesting

MAGIC = b"\x89GSC\r\n\x1a\n"
#: The newest format this code writes and reads; it reads every older major too.
FORMAT_MAJOR = 2
FORMAT_MINOR = 6
#: What a version-2 stream may ask for in ``header["features"]``: name -> what it adds.
FEATURES: dict[str, str] = {
    "positions_set": "positions coded as a Morton-sorted set; the grid order follows from them (codec/positions.py)",
    "deformation": "a dynamic model: the canonical Gaussians plus a deformation network in chunk 'deformation' "
                   "(codec/deformation.py); it decodes to a model directory",
    "deformation_quantised": "the deformation network's weight matrices quantised per row to at most 8 bits "
                             "(codec/deformation.py)",
    "deformation_mixed_bits": "the quantised deformation network with its own bit count per weight matrix "
                              "(codec/deformation.py)",
    "sh_dc_only": "per-Gaussian SH degree: Gaussians flagged in chunk 'sh_dc_only' keep their DC colour only, "
                  "their AC coefficients are zero (codec/sh_degree.py)",
    "rotation_vector": "the rotation coded as a rotation vector angle * axis, three channels where the quaternion "
                       "takes four (codec/attributes.py)",
    "hevc_parameter_sets": "the HEVC streams' parameter sets (VPS, SPS, PPS) stored once, in chunk "
                           "'hevc_parameter_sets' (codec/parameter_sets.py)",
    "sh_spatial_unit_weights": "the pca-spatial SH stage's features scaled per region by the gains in its state "
                               "(shac/spatial_pca.py)",
    "tiers": "the Gaussians in importance tiers, each coded with its own grid and QPs: header 'tiers' holds their "
             "headers, chunk 't<k>.<name>' their chunks (codec/tiers.py)",
}
#: The version a stream needing the feature is written as (2.0 unless listed).
FEATURE_VERSIONS: dict[str, tuple[int, int]] = {"deformation_quantised": (2, 1), "deformation_mixed_bits": (2, 2),
                                                 "sh_dc_only": (2, 3), "rotation_vector": (2, 4),
                                                 "hevc_parameter_sets": (2, 4), "sh_spatial_unit_weights": (2, 5),
                                                 "tiers": (2, 6)}
_PREAMBLE = struct.Struct("<8sHHII")
PREAMBLE_SIZE = _PREAMBLE.size  # 20
_MAX_CHUNKS = 4096


@dataclass
class Chunk:
    """One named payload and what the writer records about it."""

    name: str
    data: bytes
    meta: dict[str, Any] = field(default_factory=dict)

    def table_entry(self) -> dict[str, Any]:
        return {"name": self.name, "size": len(self.data), "crc32": zlib.crc32(self.data), **self.meta}


@dataclass
class Bitstream:
    """A header (JSON-serialisable dict) and an ordered list of named chunks."""

    header: dict[str, Any] = field(default_factory=dict)
    chunks: list[Chunk] = field(default_factory=list)
    #: (major, minor) format version read from a file (new streams: see :meth:`write_version`).
    version: tuple[int, int] = (1, 0)
    #: Optional features the stream needs (names from :data:`FEATURES`).
    features: set[str] = field(default_factory=set)

    # ----------------------------------------------------------- building
    def add_chunk(self, name: str, data: bytes, **meta: Any) -> Chunk:
        """Append a chunk; names are unique."""
        if any(c.name == name for c in self.chunks):
            raise ValueError(f"duplicate chunk name {name!r}")
        chunk = Chunk(name, bytes(data), meta)
        self.chunks.append(chunk)
        return chunk

    def chunk(self, name: str) -> Chunk:
        """The chunk called ``name``; :class:`BitstreamError` when absent."""
        for chunk in self.chunks:
            if chunk.name == name:
                return chunk
        raise BitstreamError(f"corrupt .gsc file: chunk {name!r} is missing")

    def has_chunk(self, name: str) -> bool:
        return any(c.name == name for c in self.chunks)

    # ------------------------------------------------------- serialisation
    def require(self, feature: str) -> None:
        """Mark the stream as needing an optional feature (it is then written as version 2)."""
        if feature not in FEATURES:
            raise ValueError(f"unknown stream feature {feature!r}; known: {', '.join(sorted(FEATURES))}")
        self.features.add(feature)

    def write_version(self) -> tuple[int, int]:
        """The oldest version that holds this stream: 1.0 without optional features, else the newest
        its features need (2.0 to 2.3)."""
        return max((FEATURE_VERSIONS.get(f, (2, 0)) for f in self.features), default=(1, 0))

    def header_bytes(self) -> bytes:
        header = dict(self.header)
        if self.features:
            header["features"] = sorted(self.features)
        header["chunks"] = [c.table_entry() for c in self.chunks]
        return json.dumps(header, separators=(",", ":"), sort_keys=False, allow_nan=False).encode("utf-8")

    def stored_header(self) -> bytes:
        """The header as written: the JSON (version 1), deflated with zlib (version 2)."""
        header = self.header_bytes()
        return zlib.compress(header, 9) if self.write_version()[0] >= 2 else header

    def to_bytes(self) -> bytes:
        header = self.stored_header()
        preamble = _PREAMBLE.pack(MAGIC, *self.write_version(), len(header), zlib.crc32(header))
        return b"".join([preamble, header, *(c.data for c in self.chunks)])

    @classmethod
    def from_bytes(cls, data: bytes | bytearray | memoryview) -> "Bitstream":
        """Parse and verify a container (see module docstring); one BitstreamError on failure."""
        data = bytes(data)
        if len(data) < PREAMBLE_SIZE:
            if data[: len(MAGIC)] == MAGIC[: len(data)] and data:
                raise BitstreamError(f"truncated .gsc file ({len(data)} bytes, shorter than its preamble)")
            raise BitstreamError("not a .gsc file (too short to hold a preamble)")
        magic, major, minor, header_len, header_crc = _PREAMBLE.unpack_from(data)
        if magic != MAGIC:
            raise BitstreamError("not a .gsc file (bad magic)")
        if not 1 <= major <= FORMAT_MAJOR:
            raise BitstreamError(
                f"unsupported .gsc format version {major}.{minor}; this decoder reads 1.x to {FORMAT_MAJOR}.x"
            )
        if header_len > MAX_HEADER_BYTES:
            raise BitstreamError(f"corrupt .gsc file: header length {header_len} exceeds {MAX_HEADER_BYTES}")
        if PREAMBLE_SIZE + header_len > len(data):
            raise BitstreamError(
                f"truncated .gsc file: header needs {header_len} bytes, {len(data) - PREAMBLE_SIZE} remain"
            )
        raw_header = data[PREAMBLE_SIZE : PREAMBLE_SIZE + header_len]
        if zlib.crc32(raw_header) != header_crc:
            raise BitstreamError("corrupt .gsc file: header CRC32 mismatch")
        header = parse_header_json(_inflate_header(raw_header) if major >= 2 else raw_header)
        table = header.pop("chunks", None)
        features = _check_features(header.pop("features", None) if major >= 2 else None, major)
        entries = _check_table(table)
        offset = PREAMBLE_SIZE + header_len
        payload_total = sum(size for _, size, _, _ in entries)
        remaining = len(data) - offset
        if payload_total > remaining:
            raise BitstreamError(
                f"truncated .gsc file: chunks need {payload_total:,} bytes, {remaining:,} remain"
            )
        if payload_total < remaining:
            raise BitstreamError(f"corrupt .gsc file: {remaining - payload_total:,} unexpected bytes after the last chunk")
        chunks = []
        for name, size, crc, meta in entries:
            payload = data[offset : offset + size]
            if zlib.crc32(payload) != crc:
                raise BitstreamError(f"corrupt .gsc file: CRC32 mismatch in chunk {name!r}")
            chunks.append(Chunk(name, payload, meta))
            offset += size
        return cls(header, chunks, (major, minor), features)

    # ------------------------------------------------------------- files
    def write(self, path: str | os.PathLike) -> int:
        """Write atomically (temporary file renamed into place); returns the byte count."""
        data = self.to_bytes()
        write_atomic(path, data, error=BitstreamError)
        return len(data)

    @classmethod
    def read(cls, path: str | os.PathLike) -> "Bitstream":
        path = Path(path)
        if path.is_dir():
            raise StreamFileError(f"{path}: is a directory, not a .gsc file")
        if not path.is_file():
            raise StreamFileError(f"{path}: no such file")
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise StreamFileError(f"{path}: cannot be read ({exc.strerror or exc})") from None
        try:
            return cls.from_bytes(data)
        except BitstreamError as exc:
            raise BitstreamError(f"{path}: {exc}") from None

    # ------------------------------------------------------------- sizes
    def total_bytes(self) -> int:
        return PREAMBLE_SIZE + len(self.stored_header()) + sum(len(c.data) for c in self.chunks)

    def sizes(self) -> dict[str, int]:
        """Bytes per part: ``"header"`` (preamble + stored header) then each chunk by name."""
        out = {"header": PREAMBLE_SIZE + len(self.stored_header())}
        out.update({c.name: len(c.data) for c in self.chunks})
        return out

    def attribute_sizes(self) -> dict[str, int]:
        """Bytes per attribute (chunks grouped by their ``attribute`` entry), header included."""
        out: dict[str, int] = {"header": PREAMBLE_SIZE + len(self.stored_header())}
        for chunk in self.chunks:
            key = str(chunk.meta.get("attribute", chunk.name))
            out[key] = out.get(key, 0) + len(chunk.data)
        return out


def is_gsc(path: str | os.PathLike) -> bool:
    """True when the file starts with the ``.gsc`` magic."""
    try:
        with open(path, "rb") as handle:
            return handle.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def _inflate_header(stored: bytes) -> bytes:
    """A version-2 header's JSON: ``stored`` inflated, at most :data:`MAX_HEADER_BYTES` of it."""
    inflater = zlib.decompressobj()
    try:
        raw = inflater.decompress(stored, MAX_HEADER_BYTES + 1)
    except zlib.error as exc:
        raise BitstreamError(f"corrupt .gsc file: the deflated header does not inflate ({exc})") from None
    if len(raw) > MAX_HEADER_BYTES:
        raise BitstreamError(f"corrupt .gsc file: the header inflates to more than {MAX_HEADER_BYTES} bytes")
    if not inflater.eof or inflater.unused_data:
        raise BitstreamError("corrupt .gsc file: the deflated header is truncated or has trailing bytes")
    return raw


def parse_header_json(raw: bytes) -> dict[str, Any]:
    """The header object of ``raw`` JSON: nesting checked before parsing (no deep recursion),
    no NaN/Infinity, no repeated key; one :class:`BitstreamError` otherwise."""
    depth = json_nesting(raw)
    if depth > MAX_NESTING:
        raise BitstreamError(f"corrupt .gsc file: header nests {depth} levels deep (at most {MAX_NESTING})")
    try:
        header = json.loads(raw.decode("utf-8"), parse_constant=_no_constant, object_pairs_hook=_unique_keys)
    except (UnicodeDecodeError, ValueError) as exc:
        detail = f" ({exc})" if isinstance(exc, _HeaderValueError) else ""
        raise BitstreamError(f"corrupt .gsc file: header is not valid JSON{detail}") from None
    if not isinstance(header, dict):
        raise BitstreamError("corrupt .gsc file: header is not a JSON object")
    return header


class _HeaderValueError(ValueError):
    """JSON that parses but is not allowed in a header (NaN, a repeated key)."""


def _no_constant(name: str) -> Any:
    raise _HeaderValueError(f"{name} is not a number a header may hold")


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _HeaderValueError(f"key {key!r} appears twice")
        out[key] = value
    return out


def _check_features(features: Any, major: int) -> set[str]:
    """The features a version-2 stream needs, each one this decoder knows."""
    if major < 2:
        return set()
    if not isinstance(features, list) or not features or not all(isinstance(f, str) for f in features):
        raise BitstreamError("corrupt .gsc file: a version 2 header must list its features")
    unknown = sorted(set(features) - set(FEATURES))
    if unknown:
        raise BitstreamError(f"this .gsc file needs {', '.join(unknown)}, which this version of gscodec-shac "
                             "does not support; update gscodec-shac")
    return set(features)


def _check_table(table: Any) -> list[tuple[str, int, int, dict[str, Any]]]:
    """Validate the chunk table; returns (name, size, crc, meta) per entry."""
    if not isinstance(table, list):
        raise BitstreamError("corrupt .gsc file: header has no chunk table")
    if len(table) > _MAX_CHUNKS:
        raise BitstreamError(f"corrupt .gsc file: {len(table)} chunks (at most {_MAX_CHUNKS})")
    entries, seen = [], set()
    for index, entry in enumerate(table):
        if not isinstance(entry, dict):
            raise BitstreamError(f"corrupt .gsc file: chunk table entry {index} is not an object")
        name, size, crc = entry.get("name"), entry.get("size"), entry.get("crc32")
        if not isinstance(name, str) or not name or name in seen:
            raise BitstreamError(f"corrupt .gsc file: chunk table entry {index} has a bad or repeated name")
        for key, value, top in (("size", size, 1 << 40), ("crc32", crc, 1 << 32)):
            if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < top:
                raise BitstreamError(f"corrupt .gsc file: chunk {name!r} has a bad {key}")
        seen.add(name)
        meta = {k: v for k, v in entry.items() if k not in ("name", "size", "crc32")}
        entries.append((name, size, crc, meta))
    return entries
