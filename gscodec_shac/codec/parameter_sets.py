"""HEVC parameter sets stored once per file (format 2.4, feature ``hevc_parameter_sets``).

Every HEVC stream x265 writes starts with its parameter sets (VPS, SPS, PPS: about 80 bytes), and a
file holds one stream per chunk and layout group (30-50 on a rate-controlled scene), while the sets
of a file differ only by picture size, bit depth, chroma format and frame count: a few distinct ones.
:func:`share` moves each stream's leading parameter sets into one deflated table chunk
(:data:`CHUNK`) and records, in the chunk's entry, ``parameter_sets``: the table index of each of its
streams; :func:`restore` puts them back before the grid codec decodes the chunk, byte for byte.

An ``hevc`` chunk is the codec's layout head (:data:`HEAD_BYTES`: layout index and sample shift,
``grid/hevc.py``) followed by its streams, each preceded by its length (``grid/base.join_chunks``).
The split point of a stream is the start code of its first NAL unit that is not a parameter set
(:func:`parameter_sets_end`); a stream that does not begin with parameter sets shares an empty entry.
The encoder shares them in streams that need format 2 for another feature (set-coded positions:
the ladder, SHAC-auto); a stream without features stays format 1.0, byte for byte.
"""

from __future__ import annotations

import struct
import zlib

from gscodec_shac.codec.container import Bitstream
from gscodec_shac.codec.grid.base import join_chunks, split_chunks
from gscodec_shac.errors import BitstreamError

FEATURE = "hevc_parameter_sets"
CHUNK = "hevc_parameter_sets"
#: The chunk-table key listing, per stream of a chunk, its parameter sets' index in the table.
META_KEY = "parameter_sets"
#: The grid codec whose chunks share their parameter sets.
CODEC = "hevc"
#: Bytes of an ``hevc`` chunk's layout head, before its streams.
HEAD_BYTES = 2
#: NAL unit types of the parameter sets (H.265 table 7-1: VPS, SPS, PPS).
PARAMETER_SET_TYPES = frozenset({32, 33, 34})
#: The most table entries a stream may declare (a file has a handful).
MAX_SETS = 4096
#: The largest inflated table (its entries are about 80 bytes each).
MAX_TABLE_BYTES = 1 << 20


def parameter_sets_end(stream: bytes) -> int:
    """Where ``stream``'s leading VPS, SPS and PPS NAL units end: the offset of the start code (its
    leading zero byte included) of the first other NAL unit; 0 when it does not begin with them."""
    at = stream.find(b"\x00\x00\x01")
    if at not in (0, 1) or (at == 1 and stream[0] != 0):
        return 0
    while at != -1:
        start = at - 1 if at > 0 and stream[at - 1] == 0 else at
        if at + 3 >= len(stream) or (stream[at + 3] >> 1) & 0x3F not in PARAMETER_SET_TYPES:
            return start
        at = stream.find(b"\x00\x00\x01", at + 3)
    return len(stream)


def _streams(data: bytes) -> list[bytes]:
    """The length-prefixed streams after an ``hevc`` chunk's head, all of them."""
    count, offset = 0, HEAD_BYTES
    while offset + 4 <= len(data):
        (length,) = struct.unpack_from("<I", data, offset)
        offset += 4 + length
        count += 1
    return split_chunks(data[HEAD_BYTES:], count, CODEC)


def share(stream: Bitstream, hevc_codecs: set[int]) -> None:
    """Move the leading parameter sets of the streams of every chunk coded by a codec of
    ``hevc_codecs`` (indices into the codec table) into one table chunk; needs :data:`FEATURE`."""
    table: dict[bytes, int] = {}  # each distinct run of parameter sets -> its index, in order of appearance
    for chunk in stream.chunks:
        if chunk.meta.get("codec") not in hevc_codecs or "shape" not in chunk.meta:
            continue
        kept, indices = [], []
        for piece in _streams(chunk.data):
            end = parameter_sets_end(piece)
            indices.append(table.setdefault(piece[:end], len(table)))
            kept.append(piece[end:])
        chunk.data = chunk.data[:HEAD_BYTES] + join_chunks(kept)
        chunk.meta[META_KEY] = indices
    if table:
        raw = join_chunks(list(table))
        stream.add_chunk(CHUNK, zlib.compress(raw, 9), attribute=CHUNK, encoding="zlib", raw_size=len(raw),
                         sets=len(table))
        stream.require(FEATURE)


def read_table(raw: bytes, sets: int) -> list[bytes]:
    """The parameter-set table from its inflated chunk (``sets`` entries, as the header declares)."""
    return split_chunks(raw, sets, CHUNK)


def restore(data: bytes, indices: tuple[int, ...], table: list[bytes]) -> bytes:
    """An ``hevc`` chunk as its codec wrote it: each stream's parameter sets put back in front of it."""
    pieces = _streams(data)
    if len(pieces) != len(indices):
        raise BitstreamError(f"the chunk holds {len(pieces)} hevc streams but lists parameter sets for "
                             f"{len(indices)}")
    return data[:HEAD_BYTES] + join_chunks([table[i] + piece for i, piece in zip(indices, pieces)])
