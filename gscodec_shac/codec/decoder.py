"""The decoder: ``.gsc`` bytes (or a parsed :class:`Bitstream`) -> a :class:`GaussianCloud`.

The mirror of :mod:`gscodec_shac.codec.encoder`: :func:`~gscodec_shac.codec.header.read_header`
checks the whole header against itself and the chunks first (the one validator), the
estimated peak memory is compared with :func:`~gscodec_shac.limits.memory_budget`, then
every chunk is decoded by the grid codec of its codec-table entry (in threads, largest
first), the planes of each attribute are assembled and dequantised, the attribute
transforms are inverted and the SH stage rebuilt from its stored state inverts its
features. Any problem raises one :class:`BitstreamError` (a stream too large for the
memory budget: :class:`MemoryLimitError`).
"""

from __future__ import annotations

import threading
import zlib
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Callable

import numpy as np

from gscodec_shac import sh_index
from gscodec_shac.codec import parameter_sets, tiers
from gscodec_shac.codec import quantize as qz
from gscodec_shac.codec.attributes import ATTRIBUTES, transforms
from gscodec_shac.codec.container import Bitstream, Chunk
from gscodec_shac.codec.grid.base import GridCodec, get_codec
from gscodec_shac.codec.header import (
    AttributeEntry,
    ChunkPlan,
    StreamHeader,
    inflate,
    read_dc_only,
    read_header,
    read_stage,
)
from gscodec_shac.codec.layout import occupied, occupied_cells, unpack_mask
from gscodec_shac.codec.positions import decode_sorted_codes, morton_decode
from gscodec_shac.errors import BitstreamError, CodecUnavailableError, GscodecError, MemoryLimitError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.limits import MEMORY_ENV, default_workers, format_bytes, memory_budget
from gscodec_shac.progress import optional_bar
from gscodec_shac.shac.base import ShStage


class Decoder:
    """Decode ``.gsc`` bytes (or a parsed :class:`Bitstream`) into a :class:`GaussianCloud` (grid order)."""

    def __init__(self, progress: bool = False, workers: int | None = None) -> None:
        self.progress = progress
        self.workers = workers or default_workers()

    def decode(self, data: bytes | Bitstream) -> GaussianCloud:
        stream = data if isinstance(data, Bitstream) else Bitstream.from_bytes(data)
        if tiers.is_tiered(stream):  # importance tiers (codec/tiers.py): each a stream, decoded in turn
            parts = tiers.split(stream)
            views = [read_header(part) for part in parts]
            for view in views:
                self.check_memory(view)
            return GaussianCloud.concat([self._checked_decode(part, view, shared_state=True)
                                         for part, view in zip(parts, views)])
        view = read_header(stream)
        self.check_memory(view)
        return self._checked_decode(stream, view)

    def _checked_decode(self, stream: Bitstream, view: StreamHeader, shared_state: bool = False) -> GaussianCloud:
        """:meth:`_decode`, anything wrong raised as one :class:`BitstreamError`."""
        try:
            with np.errstate(all="ignore"):  # overflow shows up as non-finite values, refused below
                return self._decode(stream, view, shared_state)
        except (BitstreamError, CodecUnavailableError):
            raise
        except GscodecError as exc:
            raise BitstreamError(f"corrupt .gsc file: {exc}") from None
        except (ValueError, KeyError, TypeError, IndexError, AttributeError, zlib.error, OverflowError) as exc:
            raise BitstreamError(f"corrupt .gsc file: {type(exc).__name__}: {exc}") from None

    def check_memory(self, view: StreamHeader) -> None:
        """Refuse, before allocating, a stream whose decode would need more than the memory budget."""
        need, budget = view.peak_memory(self.workers), memory_budget()
        if need > budget:
            raise MemoryLimitError(
                f"decoding {view.num_gaussians:,} Gaussians ({view.grid_shape[0]}x{view.grid_shape[1]} grid) needs "
                f"about {format_bytes(need)}, more than the {format_bytes(budget)} this process may use "
                f"(physical memory, cgroup and address-space limits, ${MEMORY_ENV})"
            )

    def _decode(self, stream: Bitstream, view: StreamHeader, shared_state: bool = False) -> GaussianCloud:
        with ThreadPoolExecutor(self.workers) as pool:
            return self._decode_in(pool, stream, view, shared_state)

    def _decode_in(self, pool: ThreadPoolExecutor, stream: Bitstream, view: StreamHeader,
                   shared_state: bool = False) -> GaussianCloud:
        """The cloud of a checked stream; ``shared_state``: a tier's, whose SH stage state may hold more
        features than the tier codes (:mod:`.tiers`)."""
        n, degree, shape = view.num_gaussians, view.sh_degree, view.grid_shape
        ycbcr = view.color == "ycbcr"
        # Set-coded positions (LZMA and numpy, then their inverse transform: one thread) start first: beside the
        # grid codecs' imports (PyAV's), then beside the largest chunk, whose pictures FFmpeg decodes on several
        # threads (queued last, they were the only work left at the end of a 1M decode: 0.15 s of one core).
        set_futures = {name: pool.submit(_position_set, stream.chunk(e.chunks[0]), e, n, ycbcr)
                       for name, e in view.attributes.items() if e.coding == "set"}
        codecs = {i: get_codec(view.codecs[i].name, **view.codecs[i].options) for i in {p.codec for p in view.chunks}}
        mask = None
        if view.padding == "mask":
            mask = unpack_mask(inflate(stream.chunk("grid_mask"), view.zlib_sizes["grid_mask"]), n, view.cells)
        stage = read_stage(stream, view, shared_state) if view.sh is not None else None
        dc_only = read_dc_only(stream, view)  # Gaussians coded without AC coefficients (codec/sh_degree.py)

        # The occupied cells, computed once, when the first decoded picture needs them: a header
        # declaring a huge grid over small pictures fails the codec's picture-size check first.
        cells = _Once(lambda: occupied_cells(view.padding, shape, n, mask))
        grids = {name: (shape, n, cells, _cell_selector(view.padding, n, cells)) for name in view.attributes}
        if dc_only is not None:  # the SH features of the other Gaussians are on a grid of their own
            sh = view.sh
            coded = n - sh.dc_only  # type: ignore[union-attr]
            sh_cells = _Once(lambda: occupied_cells(sh.grid_padding, sh.grid, coded))
            grids["sh"] = (sh.grid, coded, sh_cells, _cell_selector(sh.grid_padding, coded, sh_cells))
        by_blocks = stage is not None and stage.inverts_row_blocks and not view.sh.lossless  # type: ignore[union-attr]
        streamed = {name: (_FeatureCodes if name == "sh" and by_blocks else _Dequantized)(
                        entry, grids[name][1], grids[name][3], ycbcr)
                    for name, entry in view.attributes.items()
                    if entry.coding == "planes" and entry.quantizer is not None
                    and all(p.part == "all" for p in view.chunks if p.attribute == name)}
        table = None
        if view.parameter_sets:  # the HEVC streams' parameter sets, stored once (codec/parameter_sets.py)
            raw = inflate(stream.chunk(parameter_sets.CHUNK), view.zlib_sizes[parameter_sets.CHUNK])
            table = parameter_sets.read_table(raw, view.parameter_sets)
        tasks = [_ChunkTask(plan, stream.chunk(plan.name), codecs[plan.codec], grids[plan.attribute][0],
                            streamed.get(plan.attribute), table)
                 for plan in view.chunks]
        # The chunks of most pictures first (the SH grid dominates), then the largest: a decode's time goes with
        # its pictures as much as with its bytes, and a single picture left for the end keeps a core idle for
        # less time than a 3-picture chunk (at 4M the 0.4 MB-per-1M DC chunk, queued last by its bytes, ran
        # alone for 0.6 s).
        costliest_first = sorted(range(len(tasks)), key=lambda i: (-(tasks[i].plan.stop - tasks[i].plan.start),
                                                                    -len(tasks[i].chunk.data)))
        futures = {i: pool.submit(tasks[i].decode) for i in costliest_first}
        for future in optional_bar(as_completed(futures.values()), self.progress, total=len(tasks), desc="decode",
                                   unit="chunk", leave=False):
            future.result()
        planes = [futures[i].result() for i in range(len(tasks))]
        out = {name: future.result() for name, future in set_futures.items()}
        features = streamed.get("sh") if isinstance(streamed.get("sh"), _FeatureCodes) else None
        values = {name: target.values() for name, target in streamed.items()
                  if target.done is None and target is not features}
        out = {**out, **{name: target.done for name, target in streamed.items() if target.done is not None}}
        values.update({
            name: _assemble(entry, [(t, p) for t, p in zip(tasks, planes) if t.plan.attribute == name],
                            grids[name][0], grids[name][2](), self.workers)
            for name, entry in view.attributes.items() if entry.coding == "planes" and name not in streamed
        })
        del planes, tasks, futures, streamed  # the coded planes are not needed past here (peak memory)
        out.update({name: _inverse(view.attributes[name])(values[name], ycbcr)
                    for name in ATTRIBUTES if name in values})
        sh_dc = out.get("sh_dc")
        if view.sh is None:
            sh_rest = np.zeros((n, sh_index.num_rest_coeffs(degree), 3), dtype=np.float32)
        else:
            if features is not None:  # dequantised and inverted block by block
                dc_and_ac = features.inverse(stage, view.sh.ycbcr, pool)
            else:
                features = values.pop("sh", np.zeros((grids["sh"][1] if "sh" in grids else n, 0)))
                dc_and_ac = np.asarray(stage.inverse_transform(_stage_input(features, view.sh.ycbcr,
                                                                            view.sh.lossless)))
            features = None  # freed before the cloud's float32 copies below (peak memory)
            if view.sh.uses_dc:
                sh_dc, dc_and_ac = dc_and_ac[:, :3], dc_and_ac[:, 3:]
            sh_rest = sh_index.sh_rest_from_ac(np.ascontiguousarray(dc_and_ac, dtype=np.float32))
            if dc_only is not None:  # the DC-only Gaussians' AC coefficients are zero
                coded, sh_rest = sh_rest, np.zeros((n, *sh_rest.shape[1:]), dtype=np.float32)
                sh_rest[~dc_only] = coded
        return GaussianCloud(
            means=out["positions"], scales=out["scale"], quats=out["rotation"], opacities=out["opacity"][:, 0],
            sh_dc=sh_dc, sh_rest=sh_rest,
        )


class _Once:
    """A value computed on first use, once, whichever thread asks first."""

    def __init__(self, compute: Callable[[], np.ndarray]) -> None:
        self._compute, self._value, self._lock = compute, None, threading.Lock()

    def __call__(self) -> np.ndarray:
        with self._lock:
            if self._value is None:
                self._value = self._compute()
            return self._value


def _cell_selector(padding: str, n: int, cells: _Once) -> Callable[[], slice | np.ndarray]:
    """The occupied cells as a slice where they are the first ``n`` (``tail`` padding: a view of a
    plane's codes, no gather), else the cells' indices."""
    return (lambda: slice(0, n)) if padding == "tail" else cells


def _inverse(entry: AttributeEntry) -> Callable[[np.ndarray, bool], np.ndarray]:
    """A cloud attribute's values from what was coded, by the transform its header records."""
    return transforms(entry.name)[entry.transform].inverse


def _stage_input(features: np.ndarray, ycbcr: bool, lossless: bool) -> np.ndarray:
    """Dequantised SH features as the stage inverts them: RGB triplets, float32 unless lossless."""
    if ycbcr:
        features = qz.triplets_from_ycbcr(features)
    return features if lossless else features.astype(np.float32, copy=False)


class _Dequantized:
    """An attribute's (C, N) float32 values, filled channel by channel as its pictures decode.

    Per channel the same two lookups as :meth:`Quantizer.dequantize_cells` (the occupied
    cells' codes, then their reconstructions), run by the thread that decoded the picture
    while the codec goes on with the next one.
    """

    def __init__(self, entry: AttributeEntry, n: int, cells: Callable[[], slice | np.ndarray], ycbcr: bool) -> None:
        self.tables = entry.quantizer.tables()  # type: ignore[union-attr]
        self.cells = cells
        self.out = np.empty((entry.channels, n), dtype=np.float32)
        self.inverse = _inverse(entry) if entry.name in ATTRIBUTES else None
        self.ycbcr, self.missing, self.done = ycbcr, entry.channels, None
        self._lock = threading.Lock()

    def put(self, channel: int, planes: np.ndarray) -> None:
        cells = self.cells()
        for k, plane in enumerate(planes):
            np.take(self.tables[channel + k], _codes(plane, cells), mode="clip", out=self.out[channel + k])
        with self._lock:
            self.missing -= len(planes)
            last = self.missing == 0
        if last and self.inverse is not None:  # a cloud attribute: its row-major values, in this thread
            self.done = np.ascontiguousarray(self.inverse(self.out.T, self.ycbcr), dtype=np.float32)

    def values(self) -> np.ndarray:
        """(N, C) values (a column-major view)."""
        return self.out.T


class _FeatureCodes:
    """The SH features' codes (C, N) uint16, kept as their pictures decode; :meth:`inverse` then
    dequantises them and inverts the stage (one with ``inverts_row_blocks``) block by block, so the
    (N, C) float features are never held whole and each block's values are still in cache."""

    #: Rows per block (of 8k, 32k and 64k the fastest on a 1M decode; at least some thousand rows,
    #: so that the BLAS never takes its small-matrix path for a block).
    block_rows = 1 << 16
    done = None

    def __init__(self, entry: AttributeEntry, n: int, cells: Callable[[], slice | np.ndarray], ycbcr: bool) -> None:
        self.tables = entry.quantizer.tables()  # type: ignore[union-attr]
        self.cells = cells
        self.codes = np.empty((entry.channels, n), dtype=np.uint16)

    def put(self, channel: int, planes: np.ndarray) -> None:
        cells = self.cells()
        for k, plane in enumerate(planes):
            self.codes[channel + k] = _codes(plane, cells)

    def inverse(self, stage: ShStage, ycbcr: bool, pool: ThreadPoolExecutor) -> np.ndarray:
        """(N, K_in) float32: ``stage.inverse_transform`` of the dequantised features, in row blocks
        (on the threads of ``pool``, one BLAS thread each).

        Every block is ``block_rows`` tall (the last one starts early and keeps only its new rows;
        fewer rows than that: one block, the whole matrix), so the BLAS runs the same kernel for
        every row and the result is the whole-matrix product's bit for bit.
        """
        from threadpoolctl import threadpool_limits

        channels, n = self.codes.shape
        width = stage.inverse_transform(np.zeros((0, channels), np.float32)).shape[1]  # the stage's output columns
        out = np.empty((n, width), np.float32)
        rows = min(self.block_rows, n)

        def invert(start: int) -> None:
            first = min(start, n - rows)
            block = np.empty((channels, rows), dtype=np.float32)
            for c in range(channels):
                np.take(self.tables[c], self.codes[c, first : first + rows], mode="clip", out=block[c])
            into = out[start : start + rows] if first == start else np.empty((rows, width), np.float32)
            stage.inverse_transform_into(_stage_input(block.T, ycbcr, lossless=False), into)
            if first != start:
                out[start:] = into[start - first :]

        with threadpool_limits(1, user_api="blas"):
            list(pool.map(invert, range(0, n, rows or 1)))
        return out


def _codes(plane: np.ndarray, cells: slice | np.ndarray) -> np.ndarray:
    """The occupied cells' codes of a decoded plane (a view for a slice)."""
    flat = plane.reshape(-1)
    return flat[cells] if isinstance(cells, slice) else np.take(flat, cells)


@dataclass(frozen=True)
class _ChunkTask:
    """A chunk to decode into planes ``[start, stop)`` (or their high / low bytes) of an attribute;
    with ``target``, straight into that attribute's dequantised values (returns None)."""

    plan: ChunkPlan
    chunk: Chunk
    codec: GridCodec
    shape: tuple[int, int]
    target: _Dequantized | None = None
    #: The file's HEVC parameter sets (feature ``hevc_parameter_sets``), put back before decoding.
    parameter_sets: list[bytes] | None = None

    def decode(self) -> np.ndarray | None:
        plan, target = self.plan, self.target
        shape = (plan.stop - plan.start, *self.shape)
        try:
            data = self.chunk.data
            if plan.parameter_sets is not None:
                data = parameter_sets.restore(data, plan.parameter_sets, self.parameter_sets or [])
            if target is None:
                return self.codec.decode(data, shape, plan.bits)
            self.codec.decode_into(data, shape, plan.bits,
                                   lambda first, planes: target.put(plan.start + first, planes))
            return None
        except BitstreamError as exc:
            raise BitstreamError(f"corrupt .gsc file: chunk {self.chunk.name!r}: {exc}") from None


def _position_set(chunk: Chunk, entry: AttributeEntry, n: int, ycbcr: bool) -> np.ndarray:
    """Set-coded positions (:mod:`.positions`) -> (N, 3) means, in Morton (grid) order."""
    try:
        codes = decode_sorted_codes(chunk.data, n, entry.bits)
    except BitstreamError as exc:
        raise BitstreamError(f"corrupt .gsc file: chunk {chunk.name!r}: {exc}") from None
    return _inverse(entry)(entry.quantizer.dequantize(morton_decode(codes)), ycbcr)


def _assemble(entry: AttributeEntry, decoded: list, shape: tuple[int, int], cells: np.ndarray,
              workers: int = 1) -> np.ndarray:
    """Decoded planes of one attribute's chunks -> (N, C) values of the occupied ``cells`` (floats; labels as floats)."""
    count = entry.channels
    whole = len(decoded) == 1 and decoded[0][0].plan.part == "all" and decoded[0][1].shape[0] == count
    if whole:  # one chunk holds every plane as it is: no copy
        q = decoded[0][1]
    else:
        q = np.zeros((count, *shape), dtype=np.uint16)
        for task, planes in decoded:
            plan = task.plan
            q[plan.start : plan.stop] |= (planes << 8) if plan.part == "hi" else planes
    if entry.quantizer is not None:
        return entry.quantizer.dequantize_cells(q.reshape(count, -1), cells, workers)
    rows = occupied(q.reshape(count, -1), cells)
    bits = entry.bits
    if rows.size and int(rows.max()) >= 1 << bits:
        raise BitstreamError(f"corrupt .gsc file: attribute {entry.name!r} exceeds {bits} bits")
    return rows.astype(np.float64)
