"""The decoder: ``.gsc`` bytes (or a parsed :class:`Bitstream`) -> a :class:`GaussianCloud`.

The mirror of :mod:`gscodec_shac.codec.encoder`: the header's attribute entries name
their chunks; every chunk is decoded by the grid codec of its codec-table entry (in
threads, largest first), the planes of each attribute are assembled and dequantised,
the attribute transforms are inverted and the SH stage rebuilt from its stored state
inverts its features. Sizes in the header are checked against limits and against each
other before anything is allocated; any problem raises one :class:`BitstreamError`.
"""

from __future__ import annotations

import zlib
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from gscodec_shac import sh_index
from gscodec_shac.codec import quantize as qz
from gscodec_shac.codec.attributes import ATTRIBUTES
from gscodec_shac.codec.container import Bitstream, Chunk
from gscodec_shac.codec.encoder import default_workers
from gscodec_shac.codec.grid.base import GridCodec, get_codec
from gscodec_shac.codec.layout import occupied, occupied_cells, unpack_mask
from gscodec_shac.codec.positions import MAX_BITS as MAX_POSITION_BITS
from gscodec_shac.codec.positions import decode_sorted_codes, morton_decode
from gscodec_shac.errors import BitstreamError, CodecUnavailableError, GscodecError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.shac.base import StageState, stage_from_state
from gscodec_shac.validate import Where

#: Decoder limits: anything larger is treated as a corrupt header, before allocating.
MAX_GAUSSIANS = 1 << 26
MAX_SH_FEATURES = 128
MAX_STATE_BYTES = 256 << 20
#: How a chunk holds its channels: all bits, or the high / low byte of 9-16 bit data.
_PARTS = ("all", "hi", "lo")
#: Header checks raise this: "corrupt .gsc file: key 'k': problem".
HEADER = Where("corrupt .gsc file", BitstreamError)


class Decoder:
    """Decode ``.gsc`` bytes (or a parsed :class:`Bitstream`) into a :class:`GaussianCloud` (grid order)."""

    def __init__(self, progress: bool = False, workers: int | None = None) -> None:
        self.progress = progress
        self.workers = workers or default_workers()
        self._table: list = []
        self._codecs: dict[int, GridCodec] = {}

    def decode(self, data: bytes | Bitstream) -> GaussianCloud:
        stream = data if isinstance(data, Bitstream) else Bitstream.from_bytes(data)
        try:
            return self._decode(stream)
        except (BitstreamError, CodecUnavailableError):
            raise
        except GscodecError as exc:
            raise BitstreamError(f"corrupt .gsc file: {exc}") from None
        except (ValueError, KeyError, TypeError, IndexError, AttributeError, zlib.error, OverflowError) as exc:
            raise BitstreamError(f"corrupt .gsc file: {type(exc).__name__}: {exc}") from None

    def _decode(self, stream: Bitstream) -> GaussianCloud:
        header = stream.header
        self._table, self._codecs = header.get("codecs"), {}
        if not isinstance(self._table, list):
            raise BitstreamError("corrupt .gsc file: header has no codec table")
        n = HEADER.integer(header.get("num_gaussians"), "num_gaussians", 1, MAX_GAUSSIANS)
        degree = HEADER.integer(header.get("sh_degree"), "sh_degree", 0, sh_index.MAX_SH_DEGREE)
        grid = _object(header.get("grid"), "grid")
        shape = (HEADER.integer(grid.get("height"), "grid.height", 1, MAX_GAUSSIANS),
                 HEADER.integer(grid.get("width"), "grid.width", 1, MAX_GAUSSIANS))
        if not n <= shape[0] * shape[1] <= 2 * n + 4096:
            raise BitstreamError(f"corrupt .gsc file: a {shape[0]}x{shape[1]} grid cannot hold {n:,} Gaussians")
        sh = header.get("sh")
        if sh is not None and not isinstance(sh, dict):
            raise BitstreamError("corrupt .gsc file: sh is not an object")
        entries = self._attribute_entries(stream, header, sh)
        cells = self._cells(stream, grid.get("padding"), n, shape)
        sets = {name: entry for name, entry in entries.items() if entry.get("coding") == "set"}
        if set(sets) - {"positions"} or (sets and "positions_set" not in stream.features):
            raise BitstreamError("corrupt .gsc file: only positions can be set-coded, in a stream that says so")

        tasks = [task for name, entry in entries.items() if name not in sets
                 for task in self._chunk_tasks(stream, name, entry, shape)]
        # Largest chunks first (the SH grid dominates), so no worker is left with it at the end.
        biggest_first = sorted(range(len(tasks)), key=lambda i: -len(tasks[i].chunk.data))
        with ThreadPoolExecutor(self.workers) as pool:
            futures = {i: pool.submit(tasks[i].decode) for i in biggest_first}
            for _ in tqdm(as_completed(futures.values()), total=len(tasks), desc="decode", unit="chunk",
                          disable=not self.progress, leave=False):
                pass
            planes = [futures[i].result() for i in range(len(tasks))]
        values = {
            name: _assemble(entry, [(t, p) for t, p in zip(tasks, planes) if t.attribute == name], shape, cells)
            for name, entry in entries.items() if name not in sets
        }
        if sets:
            values["positions"] = _position_set(stream, sets["positions"], n)
        ycbcr = header.get("color") == "ycbcr"
        out = {name: ATTRIBUTES[name].inverse(values[name], ycbcr) for name in ATTRIBUTES if name in values}
        sh_dc = out.get("sh_dc")
        sh_rest = np.zeros((n, sh_index.num_rest_coeffs(degree), 3), dtype=np.float32)
        if sh:
            dc_and_ac = self._sh_reconstruction(stream, sh, values.get("sh", np.zeros((n, 0))))
            if sh.get("uses_dc"):
                sh_dc, dc_and_ac = dc_and_ac[:, :3], dc_and_ac[:, 3:]
            sh_rest = sh_index.sh_rest_from_ac(np.ascontiguousarray(dc_and_ac, dtype=np.float32))
            if sh_rest.shape[1] != sh_index.num_rest_coeffs(degree):
                raise BitstreamError("corrupt .gsc file: SH stage output does not match the SH degree")
        return GaussianCloud(
            means=out["positions"], scales=out["scale"], quats=out["rotation"], opacities=out["opacity"][:, 0],
            sh_dc=sh_dc, sh_rest=sh_rest,
        )

    def _attribute_entries(self, stream: Bitstream, header: dict, sh: dict | None) -> dict[str, dict]:
        """The header's attribute entries, checked against what the header promises and the chunks present."""
        attrs = _object(header.get("attributes"), "attributes")
        expected = [name for name in ATTRIBUTES if not (name == "sh_dc" and sh and sh.get("uses_dc"))]
        n_features = HEADER.integer(sh.get("features"), "sh.features", 0, MAX_SH_FEATURES) if sh else 0
        if n_features:
            expected.append("sh")
        if sorted(attrs) != sorted(expected):
            raise BitstreamError(f"corrupt .gsc file: attributes {sorted(attrs)}, expected {sorted(expected)}")
        entries = {name: _object(attrs[name], name) for name in expected}
        for name, entry in entries.items():
            HEADER.integer(entry.get("channels"), f"attributes.{name}.channels", 1, MAX_SH_FEATURES)
        if n_features and entries["sh"]["channels"] != n_features:
            raise BitstreamError("corrupt .gsc file: SH feature count does not match its attribute")
        listed = {str(c) for entry in entries.values() for c in entry.get("chunks", [])}
        listed |= {"sh_state"} if sh else set()
        listed |= {"grid_mask"} if _object(header.get("grid"), "grid").get("padding") == "mask" else set()
        named = {c.name for c in stream.chunks}
        if named != listed:
            raise BitstreamError(f"corrupt .gsc file: chunks {sorted(named ^ listed)} do not match the attributes")
        return entries

    def _sh_reconstruction(self, stream: Bitstream, sh: dict, features: np.ndarray) -> np.ndarray:
        """The stage's inverse transform of the decoded features: (N, K') or (N, 3 + K')."""
        state = StageState.from_bytes(inflate(stream.chunk("sh_state"), MAX_STATE_BYTES))
        if state.name != sh.get("stage"):
            raise BitstreamError("corrupt .gsc file: SH stage state does not match the header")
        stage = stage_from_state(state)
        if sh.get("ycbcr"):
            features = qz.triplets_from_ycbcr(features)
        if not sh.get("lossless"):
            features = features.astype(np.float32, copy=False)
        return np.asarray(stage.inverse_transform(features))

    def _codec(self, index: Any) -> GridCodec:
        """The codec of table entry ``index`` (built once per stream)."""
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(self._table):
            raise BitstreamError(f"corrupt .gsc file: codec index {index!r} is not in the codec table")
        if index not in self._codecs:
            info = _object(self._table[index], "codec table entry")
            options = _object(info.get("options", {}), "codec options")
            self._codecs[index] = get_codec(str(info.get("name")), **options)
        return self._codecs[index]

    def _cells(self, stream: Bitstream, padding: Any, n: int, shape: tuple[int, int]) -> np.ndarray:
        """The cells holding the ``n`` Gaussians, in grid order."""
        if padding not in ("tail", "mask", "zorder"):
            raise BitstreamError(f"corrupt .gsc file: unknown padding layout {padding!r}")
        mask = None
        if padding == "mask":
            count = shape[0] * shape[1]
            mask = unpack_mask(inflate(stream.chunk("grid_mask"), (count + 7) // 8), n, count)
        return occupied_cells(padding, shape, n, mask)

    def _chunk_tasks(self, stream: Bitstream, name: str, entry: dict, shape: tuple[int, int]) -> list["_ChunkTask"]:
        """One validated decode task per chunk of an attribute."""
        tasks = []
        for chunk_name in entry.get("chunks", []):
            chunk = stream.chunk(str(chunk_name))
            meta = chunk.meta
            start, stop = (int(v) for v in meta["channels"])
            part, bits = meta.get("part"), int(meta["bits"])
            if (
                part not in _PARTS or not 0 <= start < stop <= entry["channels"] or not 1 <= bits <= 16
                or list(meta["shape"]) != [stop - start, *shape]
                or (part == "lo" and bits != 8) or (part == "hi" and bits > 8)
            ):
                raise BitstreamError(f"corrupt .gsc file: chunk {chunk.name!r} has an inconsistent part, shape or bit depth")
            tasks.append(_ChunkTask(name, chunk, start, stop, part, bits, self._codec(meta.get("codec")), shape))
        return tasks


@dataclass(frozen=True)
class _ChunkTask:
    """A chunk to decode into planes ``[start, stop)`` (or their high / low bytes) of an attribute."""

    attribute: str
    chunk: Chunk
    start: int
    stop: int
    part: str
    bits: int
    codec: GridCodec
    shape: tuple[int, int]

    def decode(self) -> np.ndarray:
        try:
            return self.codec.decode(self.chunk.data, (self.stop - self.start, *self.shape), self.bits)
        except BitstreamError as exc:
            raise BitstreamError(f"corrupt .gsc file: chunk {self.chunk.name!r}: {exc}") from None


def _position_set(stream: Bitstream, entry: dict, n: int) -> np.ndarray:
    """Set-coded positions (:mod:`.positions`) -> (N, 3) transformed values, in Morton (grid) order."""
    chunk = stream.chunk("positions")
    bits = HEADER.integer(chunk.meta.get("bits"), "chunks.positions.bits", 1, MAX_POSITION_BITS)
    if entry.get("chunks") != ["positions"] or chunk.meta.get("encoding") != "morton_set" or entry["channels"] != 3:
        raise BitstreamError("corrupt .gsc file: the position set's entry is inconsistent")
    quantizer = qz.Quantizer.from_json(_object(entry.get("quantizer"), "quantizer"))
    if quantizer.bits != bits or quantizer.lo.shape != (3,):
        raise BitstreamError("corrupt .gsc file: the position set's quantiser does not match it")
    try:
        codes = decode_sorted_codes(chunk.data, n, bits)
    except BitstreamError as exc:
        raise BitstreamError(f"corrupt .gsc file: {exc}") from None
    return quantizer.dequantize(morton_decode(codes))


def _assemble(entry: dict, decoded: list, shape: tuple[int, int], cells: np.ndarray) -> np.ndarray:
    """Decoded planes of one attribute's chunks -> (N, C) values (floats; labels as floats)."""
    count = entry["channels"]
    q = np.zeros((count, *shape), dtype=np.uint16)
    parts = {part: np.zeros(count, dtype=np.int64) for part in _PARTS}
    for task, planes in decoded:
        q[task.start : task.stop] |= (planes << 8) if task.part == "hi" else planes
        parts[task.part][task.start : task.stop] += 1
    whole = (parts["all"] == 1) & (parts["hi"] == 0) & (parts["lo"] == 0)
    split = (parts["all"] == 0) & (parts["hi"] == 1) & (parts["lo"] == 1)
    if not np.all(whole | split):
        raise BitstreamError("corrupt .gsc file: an attribute's chunks do not cover each channel exactly once")
    if "quantizer" in entry:
        quantizer = qz.Quantizer.from_json(_object(entry["quantizer"], "quantizer"))
        if quantizer.lo.shape != (count,):
            raise BitstreamError("corrupt .gsc file: quantiser ranges do not match the channel count")
        return quantizer.dequantize_cells(q.reshape(count, -1), cells)
    rows = occupied(q.reshape(count, -1), cells)
    bits = HEADER.integer(entry.get("integer_bits"), "integer_bits", 1, 16)
    if rows.size and int(rows.max()) >= 1 << bits:
        raise BitstreamError(f"corrupt .gsc file: integer attribute exceeds {bits} bits")
    return rows.astype(np.float64)


def inflate(chunk: Chunk, limit: int) -> bytes:
    """A zlib chunk's bytes, checked against its recorded ``raw_size`` (at most ``limit``)."""
    raw_size = chunk.meta.get("raw_size")
    if chunk.meta.get("encoding") != "zlib" or not isinstance(raw_size, int) or not 0 <= raw_size <= limit:
        raise BitstreamError(f"corrupt .gsc file: chunk {chunk.name!r} has a bad encoding or size")
    inflater = zlib.decompressobj()
    out = inflater.decompress(chunk.data, raw_size + 1)
    if len(out) != raw_size or not inflater.eof or inflater.unused_data:
        raise BitstreamError(f"corrupt .gsc file: chunk {chunk.name!r} does not inflate to {raw_size} bytes")
    return out


def _object(value: Any, what: str) -> dict:
    if not isinstance(value, dict):
        raise BitstreamError(f"corrupt .gsc file: {what} is not an object")
    return value
