"""Encoder and Decoder: a :class:`GaussianCloud` <-> a ``.gsc`` :class:`Bitstream`.

Encode (decode is the mirror)::

    prune -> sort onto an (H, W) grid -> SH stage -> per-attribute transform
          -> per-channel quantiser -> (C, H, W) planes -> grid codec -> chunks

Every attribute is one row of :data:`ATTRIBUTES` (forward and inverse
transform, channel count); a chunk is a run of an attribute's channels that
share a QP (and, for 9-16 bit lossless data in the ``split8`` layout, one of
its two 8-bit halves). The decoded cloud is in grid order: the Gaussians of the
occupied cells, row by row.

Integer SH features (the ``vq`` stage, ``stage.lossless_features``) skip the
quantiser: they are coded losslessly at ``stage.feature_bits`` bits with the
rate point's ``sh_labels`` settings.
"""

from __future__ import annotations

import json
import os
import time
import zlib
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, NamedTuple

import numpy as np
from tqdm.auto import tqdm

import gscodec_shac
from gscodec_shac.codec import quantize as qz
from gscodec_shac import sh_index
from gscodec_shac.codec.container import Bitstream
from gscodec_shac.codec.grid.base import GridCodec, get_codec
from gscodec_shac.errors import BitstreamError, CodecUnavailableError, GscodecError, ValidationError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.codec.rate_points import AttributeSpec, RatePoint, load_rate_point
from gscodec_shac.shac.base import ShStage, StageState, make_stage, stage_from_state

#: Decoder limits: anything larger is treated as a corrupt header, before allocating.
MAX_GAUSSIANS = 1 << 26
MAX_SH_FEATURES = 128
MAX_STATE_BYTES = 256 << 20
#: Stages whose features are whole (l, m) RGB triplets (YCbCr applies to them).
TRIPLET_STAGES = ("none", "trunc", "lst")


def default_workers() -> int:
    """Grid-codec calls run in this many threads (x265, PNG and FFmpeg release the GIL)."""
    return max(1, min(8, os.cpu_count() or 1))


@dataclass
class _Job:
    """One chunk to code: its planes, codec and the chunk-table entry it will get."""

    name: str
    codec: GridCodec
    planes: np.ndarray
    bits: int
    qp: int | None
    meta: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------- attribute table
class GridOrder(NamedTuple):
    """Where the (pruned) Gaussians go: grid ``shape`` (H, W), ``order`` (H*W cells ->
    row or -1), how many were ``dropped`` to fill the grid, and the ``policy`` used."""

    shape: tuple[int, int]
    order: np.ndarray
    dropped: int
    policy: str


@dataclass(frozen=True)
class _Attr:
    """One coded attribute: how to get its (N, C) values from a cloud and back."""

    name: str
    forward: Callable[[GaussianCloud, bool], np.ndarray]
    inverse: Callable[[np.ndarray, bool], np.ndarray]
    groups: tuple[tuple[int, int], ...] | None = None  # fixed channel groups (else by QP)


def _dc_forward(cloud: GaussianCloud, ycbcr: bool) -> np.ndarray:
    return qz.triplets_to_ycbcr(cloud.sh_dc) if ycbcr else cloud.sh_dc


def _dc_inverse(values: np.ndarray, ycbcr: bool) -> np.ndarray:
    return qz.triplets_from_ycbcr(values) if ycbcr else values


ATTRIBUTES: dict[str, _Attr] = {
    a.name: a
    for a in (
        _Attr("positions", lambda c, _: qz.log_transform(c.means), lambda v, _: qz.inverse_log_transform(v)),
        _Attr("rotation", lambda c, _: qz.canonical_quaternions(c.quats), lambda v, _: v, groups=((0, 1), (1, 4))),
        _Attr("scale", lambda c, _: c.scales, lambda v, _: v),
        _Attr("opacity", lambda c, _: c.opacities[:, None], lambda v, _: v),
        _Attr("sh_dc", _dc_forward, _dc_inverse),
    )
}
_TRANSFORMS = {
    "positions": "sign_log1p",
    "rotation": "unit_w_nonnegative",
    "scale": "log_scale",
    "opacity": "logit",
    "sh_dc": "color",
    "sh": "sh_stage_features",
}


# ------------------------------------------------------------------------ encoder
class Encoder:
    """Encode clouds with one rate point.

    ``sh_stage``: a stage name (fitted on each cloud) or a :class:`ShStage`
    instance; with ``fit_stage=False`` an instance is used as already fitted
    (e.g. SHAC-LST's trained T). ``sh_params`` go to :func:`make_stage`;
    ``sort`` overrides the rate point's sort method; ``workers`` is the number
    of threads coding chunks (the bytes do not depend on it). After
    :meth:`encode`, ``order_`` holds the input row of each decoded Gaussian and
    ``timings_`` the seconds per step.
    """

    def __init__(
        self,
        rate_point: str | Path | RatePoint,
        sh_stage: str | ShStage | None = None,
        sort: str | None = None,
        *,
        sh_params: dict[str, Any] | None = None,
        fit_stage: bool = True,
        progress: bool = False,
        workers: int | None = None,
    ) -> None:
        point = load_rate_point(rate_point)
        name = sh_stage if isinstance(sh_stage, str) else None
        self.rate_point = point.with_overrides(sh_stage=name, sh_params=sh_params, sort_method=sort)
        self._stage_instance = sh_stage if isinstance(sh_stage, ShStage) else None
        if self._stage_instance is not None:
            self.rate_point = self.rate_point.with_overrides(sh_stage=self._stage_instance.name)
        self.fit_stage = fit_stage
        self.progress = progress
        self.workers = workers or default_workers()
        self.order_: np.ndarray | None = None
        self.timings_: dict[str, float] = {}
        self._codecs: dict[tuple, tuple[GridCodec, int]] = {}
        self._jobs: list[_Job] = []

    # ---------------------------------------------------------------- main
    def encode(self, cloud: GaussianCloud, grid: GridOrder | None = None) -> Bitstream:
        """Compress ``cloud`` into a :class:`Bitstream` (deterministic for equal input).

        ``grid``: a placement from :meth:`grid_order` for the same cloud and sort
        settings, to sort once for many encodes (the bytes are the same).
        """
        rp = self.rate_point
        self._codecs, self._jobs, self.timings_ = {}, [], {}
        with self._timed("prune"):
            kept = self._kept_rows(cloud)
            work = cloud if kept.size == cloud.num_gaussians else cloud.select(kept)
        with self._timed("sort"):
            shape, order, dropped, policy = self._grid_order(work) if grid is None else _checked_grid(grid, work)
            rows = order[order >= 0]
            grid_cloud = work.select(rows)
            self.order_ = kept[rows]
        with self._timed("sh_stage"):
            stage, features = self._sh_features(grid_cloud)

        stream = Bitstream()
        n = grid_cloud.num_gaussians
        padding = "tail" if bool(np.all(order[:n] >= 0)) else "mask"
        if padding == "mask":  # empty cells inside the grid: store which cells are occupied
            mask = np.packbits(order >= 0)
            stream.add_chunk("grid_mask", zlib.compress(mask.tobytes(), 9), attribute="grid", encoding="zlib", raw_size=mask.size)
        cell_rows = _cell_rows(order)
        ycbcr = rp.color == "ycbcr"
        attributes: dict[str, Any] = {}
        with self._timed("quantize"):
            for name, attr in ATTRIBUTES.items():
                if name == "sh_dc" and stage is not None and stage.uses_dc:
                    continue  # the DC travels inside the stage's features
                values = attr.forward(grid_cloud, ycbcr)
                attributes[name] = self._code_values(name, values, rp.attributes[name], cell_rows, shape, attr.groups)
            if features is not None and features.shape[1]:
                attributes["sh"] = self._code_sh(stage, features, grid_cloud.sh_degree, cell_rows, shape)
        with self._timed("code"):
            self._run_jobs(stream)

        sh_header = None
        if stage is not None:
            raw = stage.state().to_bytes()
            stream.add_chunk("sh_state", zlib.compress(raw, 9), attribute="sh_state", encoding="zlib", raw_size=len(raw))
            sh_header = {
                "stage": stage.name,
                "features": int(features.shape[1]),
                "lossless": bool(getattr(stage, "lossless_features", False)),
                "uses_dc": bool(stage.uses_dc),
                "ycbcr": bool(ycbcr and _triplet_features(stage, features.shape[1])),
            }
        stream.header = {
            "producer": f"gscodec-shac {gscodec_shac.__version__}",
            "num_gaussians": n,
            "input_gaussians": cloud.num_gaussians,
            "sh_degree": cloud.sh_degree,
            "grid": {"height": shape[0], "width": shape[1], "padding": padding, "policy": policy,
                     "dropped": dropped, "sort": rp.sort.to_json()},
            "prune": {"min_opacity": rp.min_opacity, "pruned": int(cloud.num_gaussians - kept.size)},
            "color": rp.color,
            "sh": sh_header,
            "attributes": attributes,
            "codecs": [codec.describe() for codec, _ in sorted(self._codecs.values(), key=lambda item: item[1])],
            "rate_point": rp.to_json(),
        }
        return stream

    def grid_order(self, cloud: GaussianCloud) -> GridOrder:
        """The grid placement :meth:`encode` would compute for ``cloud`` (after pruning)."""
        kept = self._kept_rows(cloud)
        return GridOrder(*self._grid_order(cloud if kept.size == cloud.num_gaussians else cloud.select(kept)))

    @contextmanager
    def _timed(self, step: str) -> Iterator[None]:
        tic = time.perf_counter()
        yield
        self.timings_[step] = time.perf_counter() - tic

    def _kept_rows(self, cloud: GaussianCloud) -> np.ndarray:
        """Rows surviving the rate point's opacity pruning (all rows when it is 0)."""
        min_opacity = self.rate_point.min_opacity
        if min_opacity <= 0:
            return np.arange(cloud.num_gaussians)
        kept = np.flatnonzero(qz.prune_mask(cloud, min_opacity))
        if kept.size == 0:
            raise ValidationError(f"pruning at opacity {min_opacity} removes every Gaussian")
        return kept

    # -------------------------------------------------------------- steps
    def _grid_order(self, cloud: GaussianCloud) -> tuple[tuple[int, int], np.ndarray, int, str]:
        """Grid shape, order (cells -> rows of ``cloud``, -1 empty), count dropped, policy used.

        The drop policy falls back to padding when the cloud fills less than one
        ``multiple`` x ``multiple`` block.
        """
        import sorting

        spec = self.rate_point.sort
        n = cloud.num_gaussians
        try:
            policy = spec.policy if not (spec.policy == "drop" and n < spec.multiple**2) else "pad"
            shape = sorting.grid_shape(n, multiple=spec.multiple, policy=policy)
            keep = np.arange(n)
            if policy == "drop" and shape[0] * shape[1] < n:
                keep = sorting.select_for_grid(_importance(cloud), shape[0] * shape[1])
            attributes = {
                "xyz": cloud.means, "scale": cloud.scales, "opacity": cloud.opacities,
                "dc": cloud.sh_dc, "rotation": qz.canonical_quaternions(cloud.quats),
            }
            attributes = {k: v[keep] for k, v in attributes.items() if spec.weights.get(k, 0) > 0}
            if spec.method == "none":
                local = sorting.sort_to_grid(np.zeros((keep.size, 1), np.float32), shape, method="none")
            else:
                weights = {k: spec.weights[k] for k in attributes}
                features = sorting.prepare_features(attributes, weights, spec.normalize)
                schedule = spec.schedule if spec.method == "plas" else {}
                local = sorting.sort_to_grid(
                    features, shape, method=spec.method, seed=spec.seed, progress=self.progress, **schedule
                )
        except sorting.SortingError as exc:
            raise ValidationError(f"sorting: {exc}") from None
        order = np.where(local >= 0, keep[np.maximum(local, 0)], -1)
        return shape, order, int(n - keep.size), policy

    def _sh_features(self, cloud: GaussianCloud) -> tuple[ShStage | None, np.ndarray | None]:
        if cloud.sh_degree == 0:
            return None, None
        stage = self._stage_instance or make_stage(self.rate_point.sh_stage, **self.rate_point.sh_params)
        ac = cloud.ac_matrix()
        if stage.uses_dc:
            ac = np.concatenate([cloud.sh_dc, ac], axis=1)
        features = stage.fit_transform(ac) if (self.fit_stage or self._stage_instance is None) else stage.transform(ac)
        return stage, np.asarray(features)

    def _code_sh(self, stage: ShStage, features: np.ndarray, degree: int, cell_rows: np.ndarray, shape: tuple[int, int]) -> dict:
        rp = self.rate_point
        if getattr(stage, "lossless_features", False):
            bits = int(stage.feature_bits)
            spec = rp.attributes["sh_labels"]
            labels = np.rint(features).astype(np.int64)
            if labels.size and (labels.min() < 0 or labels.max() >= 1 << bits):
                raise ValidationError(f"SH stage {stage.name!r} gave labels outside 0..2^{bits}-1")
            return self._code_integers("sh", labels.astype(np.uint16), bits, spec, cell_rows, shape)
        spec = rp.attributes["sh_ac"] if stage.name in ("none", "trunc") else rp.attributes["sh_features"]
        values = features
        if rp.color == "ycbcr" and _triplet_features(stage, features.shape[1]):
            values = qz.triplets_to_ycbcr(features)
        qps = [spec.qp_for_degree(d) for d in feature_degrees(stage, features.shape[1], degree)]
        return self._code_values("sh", values, spec, cell_rows, shape, None, qps)

    def _code_values(
        self, name: str, values: np.ndarray, spec: AttributeSpec,
        cell_rows: np.ndarray, shape: tuple[int, int], groups: tuple | None, qps: list | None = None,
    ) -> dict:
        """Quantise (N, C) floats and queue their chunks; returns the attribute's header entry."""
        quantizer = qz.Quantizer.fit(values, spec.bits)
        q = quantizer.quantize(values)
        if spec.lossless:
            entry = self._code_integers(name, q, spec.bits, spec, cell_rows, shape)
        else:
            channels = q.shape[1]
            qps = qps or [spec.qp_for_degree(1)] * channels
            runs = groups or _runs(qps)
            entry = {"chunks": []}
            for index, (start, stop) in enumerate(runs):
                chunk = f"{name}_{index}" if len(runs) > 1 else name
                planes = _planes(q[:, start:stop], cell_rows, shape)
                self._queue(chunk, name, planes, spec.bits, qps[start], spec, (start, stop), "all")
                entry["chunks"].append(chunk)
        entry.update(transform=_TRANSFORMS[name], channels=int(values.shape[1]), quantizer=quantizer.to_json())
        return entry

    def _code_integers(
        self, name: str, q: np.ndarray, bits: int, spec: AttributeSpec,
        cell_rows: np.ndarray, shape: tuple[int, int],
    ) -> dict:
        """Code (N, C) integers of ``bits`` bits losslessly (split into two 8-bit halves or not)."""
        channels = (0, q.shape[1])
        if spec.layout == "split8" and bits > 8:
            high, low = qz.split_planes(q, bits)
            self._queue(f"{name}_hi", name, _planes(high, cell_rows, shape), bits - 8, None, spec, channels, "hi")
            self._queue(f"{name}_lo", name, _planes(low, cell_rows, shape), 8, None, spec, channels, "lo")
            chunks = [f"{name}_hi", f"{name}_lo"]
        else:
            self._queue(name, name, _planes(q, cell_rows, shape), bits, None, spec, channels, "all")
            chunks = [name]
        return {"chunks": chunks, "channels": int(q.shape[1]), "integer_bits": bits, "transform": _TRANSFORMS[name]}

    def _queue(
        self, chunk: str, attribute: str, planes: np.ndarray, bits: int,
        qp: int | None, spec: AttributeSpec, channels: tuple[int, int], part: str,
    ) -> None:
        codec, index = self._codec(spec.codec, spec.options)
        meta = {"attribute": attribute, "channels": list(channels), "part": part,
                "shape": list(planes.shape), "bits": bits, "qp": qp, "codec": index}
        self._jobs.append(_Job(chunk, codec, planes, bits, qp, meta))

    def _run_jobs(self, stream: Bitstream) -> None:
        """Code the queued chunks in threads; chunks enter the stream in queue order."""
        with ThreadPoolExecutor(self.workers) as pool:
            futures = [pool.submit(job.codec.encode, job.planes, job.bits, job.qp) for job in self._jobs]
            for job, future in tqdm(list(zip(self._jobs, futures)), desc="encode", unit="chunk",
                                    disable=not self.progress, leave=False):
                stream.add_chunk(job.name, future.result(), **job.meta)
        self._jobs = []

    def _codec(self, name: str, options: dict) -> tuple[GridCodec, int]:
        """A codec instance and its index in the header's codec table."""
        key = (name, json.dumps(options, sort_keys=True))
        if key not in self._codecs:
            self._codecs[key] = (get_codec(name, **options), len(self._codecs))
        return self._codecs[key]


# ------------------------------------------------------------------------ decoder
class Decoder:
    """Decode ``.gsc`` bytes (or a parsed :class:`Bitstream`) into a :class:`GaussianCloud`.

    Any problem with the data raises one :class:`BitstreamError`; sizes in the
    header are checked against limits and against each other before anything
    is allocated.
    """

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
        n = _int_field(header, "num_gaussians", 1, MAX_GAUSSIANS)
        degree = _int_field(header, "sh_degree", 0, sh_index.MAX_SH_DEGREE)
        grid = _dict_field(header, "grid")
        shape = (_int_field(grid, "height", 1, MAX_GAUSSIANS), _int_field(grid, "width", 1, MAX_GAUSSIANS))
        if not n <= shape[0] * shape[1] <= 2 * n + 4096:
            raise BitstreamError(f"corrupt .gsc file: a {shape[0]}x{shape[1]} grid cannot hold {n:,} Gaussians")
        sh = header.get("sh")
        if sh is not None and not isinstance(sh, dict):
            raise BitstreamError("corrupt .gsc file: sh is not an object")
        entries = self._attribute_entries(stream, header, sh)
        mask = self._mask(stream, grid.get("padding"), n, shape[0] * shape[1])

        tasks = [task for name, entry in entries.items() for task in self._chunk_tasks(stream, name, entry, shape)]
        # Largest chunks first (the SH grid dominates), so no worker is left with it at the end.
        biggest_first = sorted(range(len(tasks)), key=lambda i: -len(tasks[i].chunk.data))
        with ThreadPoolExecutor(self.workers) as pool:
            futures = {i: pool.submit(tasks[i].decode) for i in biggest_first}
            for _ in tqdm(as_completed(futures.values()), total=len(tasks), desc="decode", unit="chunk",
                          disable=not self.progress, leave=False):
                pass
            planes = [futures[i].result() for i in range(len(tasks))]
        values = {
            name: _assemble(entry, [(t, p) for t, p in zip(tasks, planes) if t.attribute == name], shape, mask, n)
            for name, entry in entries.items()
        }
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
        attrs = _dict_field(header, "attributes")
        expected = [name for name in ATTRIBUTES if not (name == "sh_dc" and sh and sh.get("uses_dc"))]
        n_features = _int_field(sh, "features", 0, MAX_SH_FEATURES) if sh else 0
        if n_features:
            expected.append("sh")
        if sorted(attrs) != sorted(expected):
            raise BitstreamError(f"corrupt .gsc file: attributes {sorted(attrs)}, expected {sorted(expected)}")
        entries = {name: _dict_check(attrs[name], name) for name in expected}
        for entry in entries.values():
            _int_field(entry, "channels", 1, MAX_SH_FEATURES)
        if n_features and entries["sh"]["channels"] != n_features:
            raise BitstreamError("corrupt .gsc file: SH feature count does not match its attribute")
        listed = {str(c) for entry in entries.values() for c in entry.get("chunks", [])}
        listed |= {"sh_state"} if sh else set()
        listed |= {"grid_mask"} if _dict_field(header, "grid").get("padding") == "mask" else set()
        named = {c.name for c in stream.chunks}
        if named != listed:
            raise BitstreamError(f"corrupt .gsc file: chunks {sorted(named ^ listed)} do not match the attributes")
        return entries

    def _sh_reconstruction(self, stream: Bitstream, sh: dict, features: np.ndarray) -> np.ndarray:
        """The stage's inverse transform of the decoded features: (N, K') or (N, 3 + K')."""
        state = StageState.from_bytes(_inflate(stream.chunk("sh_state"), MAX_STATE_BYTES))
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
            info = _dict_check(self._table[index], "codec table entry")
            options = _dict_check(info.get("options", {}), "codec options")
            self._codecs[index] = get_codec(str(info.get("name")), **options)
        return self._codecs[index]

    def _mask(self, stream: Bitstream, padding: Any, n: int, cells: int) -> np.ndarray | None:
        """Occupied cells (None: the first ``n`` cells in raster order)."""
        if padding == "tail":
            return None
        if padding != "mask":
            raise BitstreamError(f"corrupt .gsc file: unknown padding layout {padding!r}")
        bits = np.frombuffer(_inflate(stream.chunk("grid_mask"), (cells + 7) // 8), dtype=np.uint8)
        if bits.size != (cells + 7) // 8:
            raise BitstreamError("corrupt .gsc file: grid mask has the wrong size")
        mask = np.unpackbits(bits, count=cells).astype(bool)
        if int(mask.sum()) != n:
            raise BitstreamError("corrupt .gsc file: grid mask does not match the Gaussian count")
        return mask

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
    chunk: Any
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


# ----------------------------------------------------------------------- helpers
_PARTS = ("all", "hi", "lo")


def _assemble(entry: dict, decoded: list, shape: tuple[int, int], mask: np.ndarray | None, n: int) -> np.ndarray:
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
    flat = q.reshape(count, -1)
    rows = (flat[:, :n] if mask is None else flat[:, mask]).T
    if "quantizer" in entry:
        quantizer = qz.Quantizer.from_json(_dict_check(entry["quantizer"], "quantizer"))
        if quantizer.lo.shape != (count,):
            raise BitstreamError("corrupt .gsc file: quantiser ranges do not match the channel count")
        return quantizer.dequantize(rows)
    bits = _int_field(entry, "integer_bits", 1, 16)
    if rows.size and int(rows.max()) >= 1 << bits:
        raise BitstreamError(f"corrupt .gsc file: integer attribute exceeds {bits} bits")
    return rows.astype(np.float64)


def feature_degrees(stage: ShStage, n_features: int, sh_degree: int) -> list[int]:
    """SH degree whose QP each feature column takes (the QP ladder).

    Stages that keep AC columns (none, trunc, lst) use each column's own degree;
    a rank-ordered stage (pca) takes the MPEG PCA rule: its first 9 components
    get the degree-1 QP, the next 15 degree 2, then degree 3 (the column counts
    3(2l+1) of each degree, in order).
    """
    explicit = getattr(stage, "feature_degrees_", None)
    if explicit is not None:
        return [int(d) for d in explicit]
    columns: np.ndarray | None = None
    if stage.name in ("none", "trunc"):
        columns = np.arange(n_features)
    elif stage.name == "lst" and getattr(stage, "layout_", None) is not None:
        columns = np.asarray(stage.layout_.subset_columns)
    if columns is not None and columns.size == n_features:
        return [sh_index.degree_order(int(c) // 3 + 1)[0] for c in columns]
    bounds = np.cumsum([3 * (2 * l + 1) for l in range(1, sh_index.MAX_SH_DEGREE + 2)])
    return [int(np.searchsorted(bounds, i, side="right")) + 1 for i in range(n_features)]


def _checked_grid(grid: GridOrder, cloud: GaussianCloud) -> GridOrder:
    """A caller's placement, checked against the cloud it is used for."""
    from sorting.grid import check_order
    from sorting.errors import SortingError

    shape, order, dropped, policy = grid
    order = np.asarray(order)
    if len(shape) != 2 or int(shape[0]) * int(shape[1]) != order.size:
        raise ValidationError(f"grid order has {order.size} cells, shape {tuple(shape)} has a different count")
    try:
        order = check_order(order.reshape(-1), cloud.num_gaussians)
    except SortingError as exc:
        raise ValidationError(f"grid order does not fit this cloud: {exc}") from None
    return GridOrder((int(shape[0]), int(shape[1])), order, int(dropped), str(policy))


def _triplet_features(stage: ShStage, n_features: int) -> bool:
    return stage.name in TRIPLET_STAGES and not stage.uses_dc and n_features % 3 == 0


def _importance(cloud: GaussianCloud) -> np.ndarray:
    """What the drop policy keeps: opacity times footprint area (exp of twice the mean log-scale)."""
    return cloud.activated_opacities() * np.exp(2.0 * cloud.scales.astype(np.float64).mean(axis=1))


def _cell_rows(order: np.ndarray) -> np.ndarray:
    """For each grid cell, the grid-order row it shows: its own, or the previous row for an empty cell."""
    return np.maximum(np.cumsum(order >= 0) - 1, 0)


def _planes(values: np.ndarray, cell_rows: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(N, C) grid-order values -> (C, H, W) planes; empty cells repeat the previous value."""
    return np.ascontiguousarray(values[cell_rows].T.reshape(values.shape[1], *shape))


def _runs(qps: list) -> list[tuple[int, int]]:
    """Maximal runs of equal QP: [(start, stop), ...]."""
    runs, start = [], 0
    for i in range(1, len(qps) + 1):
        if i == len(qps) or qps[i] != qps[start]:
            runs.append((start, i))
            start = i
    return runs


def _inflate(chunk, limit: int) -> bytes:
    raw_size = chunk.meta.get("raw_size")
    if chunk.meta.get("encoding") != "zlib" or not isinstance(raw_size, int) or not 0 <= raw_size <= limit:
        raise BitstreamError(f"corrupt .gsc file: chunk {chunk.name!r} has a bad encoding or size")
    inflater = zlib.decompressobj()
    out = inflater.decompress(chunk.data, raw_size + 1)
    if len(out) != raw_size or not inflater.eof or inflater.unused_data:
        raise BitstreamError(f"corrupt .gsc file: chunk {chunk.name!r} does not inflate to {raw_size} bytes")
    return out


def _dict_field(header: dict, key: str) -> dict:
    return _dict_check(header.get(key), key)


def _dict_check(value: Any, what: str) -> dict:
    if not isinstance(value, dict):
        raise BitstreamError(f"corrupt .gsc file: {what} is not an object")
    return value


def _int_field(mapping: dict, key: str, lo: int, hi: int) -> int:
    value = mapping.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise BitstreamError(f"corrupt .gsc file: {key} = {value!r} is outside {lo}..{hi}")
    return value


# ------------------------------------------------------------------- file API
def encode_file(
    in_ply: str | os.PathLike,
    out_gsc: str | os.PathLike,
    rate_point: str | Path | RatePoint,
    sh: str | None = None,
    *,
    sort: str | None = None,
    seed: int | None = None,
    preset: str | None = None,
    progress: bool = False,
    **stage_params: Any,
) -> dict[str, Any]:
    """PLY -> ``.gsc`` (written atomically); returns a summary (bytes, bits per Gaussian, seconds).

    ``sh`` picks the SH stage (default: the rate point's), ``stage_params`` its
    parameters (e.g. ``energy_retention=0.99``); ``preset`` sets the lossy
    codecs' speed preset (x265's ``preset`` option).
    """
    from gscodec_shac.io.ply import read_ply

    tic = time.perf_counter()
    _check_output_dir(out_gsc)
    point = load_rate_point(rate_point)
    point = point.with_overrides(seed=seed, codec_options={"preset": preset} if preset else None)
    cloud = read_ply(in_ply)
    encoder = Encoder(point, sh_stage=sh, sort=sort, sh_params={k: v for k, v in stage_params.items() if v is not None}, progress=progress)
    stream = encoder.encode(cloud)
    size = stream.write(out_gsc)
    seconds = time.perf_counter() - tic
    return {
        "input": str(in_ply),
        "output": str(out_gsc),
        "rate_point": encoder.rate_point.name,
        "sh_stage": encoder.rate_point.sh_stage,
        "input_gaussians": cloud.num_gaussians,
        "num_gaussians": stream.header["num_gaussians"],
        "bytes": size,
        "bits_per_gaussian": 8.0 * size / cloud.num_gaussians,
        "seconds": seconds,
        "timings": encoder.timings_,
        "sizes": stream.attribute_sizes(),
    }


def decode_file(in_gsc: str | os.PathLike, out_ply: str | os.PathLike, *, progress: bool = False) -> dict[str, Any]:
    """``.gsc`` -> Inria PLY (written atomically); returns a summary."""
    from gscodec_shac.io.ply import write_ply

    tic = time.perf_counter()
    _check_output_dir(out_ply)
    stream = Bitstream.read(in_gsc)
    cloud = Decoder(progress=progress).decode(stream)
    write_ply(out_ply, cloud)
    return {
        "input": str(in_gsc),
        "output": str(out_ply),
        "num_gaussians": cloud.num_gaussians,
        "sh_degree": cloud.sh_degree,
        "bytes": Path(in_gsc).stat().st_size,
        "seconds": time.perf_counter() - tic,
    }


def _check_output_dir(path: str | os.PathLike) -> None:
    """Fail before the work, not after it, when the output cannot be written."""
    directory = Path(path).parent
    if not directory.is_dir():
        raise GscodecError(f"{path}: output directory {directory} does not exist")
