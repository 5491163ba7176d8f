"""The one validator of a parsed ``.gsc`` container: :func:`read_header` -> :class:`StreamHeader`.

Every reader of a stream (the decoder, ``gscodec-shac info``, the gsplat drop-in) calls
:func:`read_header` and then uses only the typed, checked view it returns; nothing reads
``Bitstream.header`` directly. A check that fails raises one :class:`BitstreamError`
naming the key (``corrupt .gsc file: key 'grid.height': must be an integer in 1..67108864,
got -1``). What is checked, before anything is decoded or allocated:

* types and ranges of every field a reader uses, every enum by name (padding, colour,
  chunk part, SH stage, grid codec, attribute transform, chunk encoding); the rotation's
  transform ``rotation_vector`` (3 channels) only with the feature ``rotation_vector``;
* counts: Gaussians (at most :data:`~gscodec_shac.limits.MAX_GAUSSIANS`), the grid shape
  against the Gaussian count, channels per attribute, SH features against the SH stage;
* the chunk table: each chunk named by an attribute exactly once, its plane shape equal
  to ``(channels, H, W)``, its bit depth equal to the attribute's, every channel covered
  exactly once, codec indices inside the codec table, no unlisted chunk;
* per-Gaussian SH degree (feature ``sh_dc_only``): the count ``sh.dc_only`` (fewer than the
  Gaussians, a stage that codes the DC apart) comes with the feature, the zlib chunk
  ``sh_dc_only`` of one bit per Gaussian and the SH planes' own grid ``sh.grid`` (shape against
  the coded Gaussians, padding ``tail`` or ``zorder``); :func:`read_dc_only` checks the flags
  against the count;
* zlib chunks (``grid_mask``, ``sh_state``, ``sh_dc_only``, ``hevc_parameter_sets``): the declared
  inflated size against its limit and against what deflate can produce from the stored bytes (at
  most 1032:1);
* HEVC parameter sets stored once (feature ``hevc_parameter_sets``): the feature, the table chunk
  (its entry count ``sets``) and every hevc chunk's ``parameter_sets`` indices (each below ``sets``)
  come together; the stream count of a chunk is checked when it is decoded;
* dynamic models (feature ``deformation``): the ``deformation`` header entry (architecture
  within :mod:`gscodec_shac.deform_arch`'s bounds, dtype float16, or uint8 with 2..8 bits and
  the feature ``deformation_quantised``, the bits a list of one per matrix exactly with the
  feature ``deformation_mixed_bits``) comes with the feature and the zlib chunk
  ``deformation``, whose inflated size must be what that architecture and dtype need
  (:func:`gscodec_shac.codec.deformation.raw_size`);
* the peak memory a decode needs (:meth:`StreamHeader.peak_memory`) is the decoder's to
  compare with :func:`gscodec_shac.limits.memory_budget` before the first allocation.

:func:`read_stage` rebuilds the SH stage from the ``sh_state`` chunk and checks its arrays
against the declared shapes (features in, AC columns out) on one row before any decode.
Unknown keys are ignored: minor versions may add information an older reader skips.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from gscodec_shac import sh_index
from gscodec_shac.codec import parameter_sets as ps
from gscodec_shac.codec.attributes import ATTRIBUTES, ROTATION_VECTOR_FEATURE, SH_FEATURES_TRANSFORM, transforms
from gscodec_shac.codec.container import Bitstream, Chunk
from gscodec_shac.codec.grid.base import CODECS
from gscodec_shac.codec.quantize import Quantizer
from gscodec_shac.deform_arch import DeformArch, weight_count
from gscodec_shac.errors import BitstreamError, GscodecError
from gscodec_shac.limits import MAX_GAUSSIANS
from gscodec_shac.io.bounded import Inflater
from gscodec_shac.shac.base import _STATE_MAGIC as STATE_MAGIC, STAGES, ShStage, StageState, stage_from_state
from gscodec_shac.validate import Where

#: Header checks raise this: "corrupt .gsc file: key 'k': problem".
HEADER = Where("corrupt .gsc file", BitstreamError)
#: The most SH features (and channels of any attribute) a stream may declare.
MAX_SH_FEATURES = 128
#: The largest inflated SH stage state (a real one: 1 KiB-3 MiB): 16 MiB plus 256 bytes per grid
#: cell (a vq codebook of one float32 SH-3 vector per Gaussian needs 180), at most 256 MiB.
MAX_STATE_BYTES = 256 << 20
STATE_BASE_BYTES = 16 << 20
STATE_BYTES_PER_CELL = 256
#: Deflate never expands more than 1032:1 (258-byte matches in 2-bit codes), zlib framing included.
ZLIB_MAX_RATIO = 1032
#: The most entries of the codec table.
MAX_CODECS = 64
PADDINGS = ("tail", "mask", "zorder")
#: How an attribute is coded: as planes of a grid codec, or (positions) as a Morton-sorted set.
CODINGS = ("planes", "set")
COLORS = ("rgb", "ycbcr")
PARTS = ("all", "hi", "lo")
SORT_POLICIES = ("pad", "drop", "geometry")
_MAX_QP = 51
_OPTION_TYPES = (str, int, float, bool, type(None))


@dataclass(frozen=True)
class ShEntry:
    """The SH stage: its name, feature count and how its features were coded."""

    stage: str
    features: int
    lossless: bool
    uses_dc: bool
    ycbcr: bool
    #: How many Gaussians are coded DC-only (feature ``sh_dc_only``; None: none, the feature is absent).
    dc_only: int | None = None
    #: With DC-only Gaussians: the SH planes' grid (H, W) and how the coded Gaussians fill it.
    grid: tuple[int, int] | None = None
    grid_padding: str = "tail"


@dataclass(frozen=True)
class AttributeEntry:
    """One coded attribute: channels, sample bits, quantiser (None: integers) and its chunks."""

    name: str
    channels: int
    bits: int
    transform: str
    chunks: tuple[str, ...]
    quantizer: Quantizer | None
    coding: str = "planes"


@dataclass(frozen=True)
class ChunkPlan:
    """A chunk of planes: channels ``[start, stop)`` of ``attribute`` (or their high/low byte)."""

    name: str
    attribute: str
    start: int
    stop: int
    part: str
    bits: int
    codec: int
    qp: int | None
    #: Per stream of the chunk, the index of its parameter sets in the file's table (feature
    #: ``hevc_parameter_sets``); None: the chunk's streams hold their own.
    parameter_sets: tuple[int, ...] | None = None


@dataclass(frozen=True)
class CodecEntry:
    """An entry of the codec table: registry name, library version, options."""

    name: str
    version: str | None
    options: dict[str, Any]


@dataclass(frozen=True)
class DeformationEntry:
    """The deformation network of a dynamic model: its architecture and stored weight type."""

    arch: DeformArch
    dtype: str
    weights: int
    #: Bits per quantised weight (``uint8``): one for every matrix, or one per matrix in order
    #: (feature ``deformation_mixed_bits``); 16 for ``float16``.
    bits: int | tuple[int, ...] = 16


@dataclass(frozen=True)
class StreamHeader:
    """The checked view of a ``.gsc`` header (see the module docstring)."""

    version: tuple[int, int]
    total_bytes: int
    num_gaussians: int
    sh_degree: int
    grid_shape: tuple[int, int]
    padding: str
    color: str
    sh: ShEntry | None
    attributes: dict[str, AttributeEntry]
    chunks: tuple[ChunkPlan, ...]
    codecs: tuple[CodecEntry, ...]
    chunk_bytes: dict[str, int]
    chunk_attributes: dict[str, str]
    #: Declared inflated size of each zlib chunk (``grid_mask``, ``sh_state``).
    zlib_sizes: dict[str, int]
    #: Entries of the HEVC parameter-set table (feature ``hevc_parameter_sets``; 0: none).
    parameter_sets: int = 0
    # what the writer recorded for people (``info``); None when absent
    producer: str | None = None
    input_gaussians: int | None = None
    pruned: int = 0
    dropped: int = 0
    sort_method: str | None = None
    rate_point: str | None = None
    #: The rate-control target the stream was made for (``{"kind", "value"}``), if any.
    target: dict[str, Any] | None = None
    #: The deformation network of a dynamic model (None: a static model).
    deformation: DeformationEntry | None = None

    @property
    def cells(self) -> int:
        return self.grid_shape[0] * self.grid_shape[1]

    @property
    def channels(self) -> int:
        """Coded channels over all attributes."""
        return sum(entry.channels for entry in self.attributes.values())

    def decoded_bytes(self) -> int:
        """Bytes of the decoded cloud's float32 arrays (what the decode produces)."""
        floats = 3 + 3 + 4 + 1 + 3 + 3 * sh_index.num_rest_coeffs(self.sh_degree)
        return 4 * floats * self.num_gaussians

    def peak_memory(self, workers: int = 1) -> int:
        """An upper bound of the decoder's extra peak memory for this stream, in bytes.

        The decoded planes (uint16, all held until assembly), each attribute's copies on
        the way to float32 values, the SH reconstruction (float64 where the stage works in
        it) and the cloud, plus one grid codec's working copies per worker and the inflated
        stage state with its arrays (a vq codebook of bytes becomes float32); calibrated on
        real decodes (docs/reliability.md, "Memory").
        """
        n, cells = self.num_gaussians, self.cells
        widest = max((plan.stop - plan.start for plan in self.chunks), default=0)
        ac = 3 * sh_index.num_rest_coeffs(self.sh_degree)
        planes = 2 * cells * self.channels
        codec = 4 * 2 * cells * widest * max(1, min(workers, len(self.chunks)))
        values = n * self.channels * (2 + 4 + 8)
        sh = n * (ac + 3) * (8 + 8 + 4) if self.sh else 0
        state = 6 * sum(self.zlib_sizes.values())
        if self.deformation is not None:  # float16 -> float32 weights and the torch network (+ unpacked bits)
            state += (10 if self.deformation.dtype == "float16" else 20) * self.deformation.weights
        position_set = 48 * n if any(e.coding == "set" for e in self.attributes.values()) else 0
        return planes + codec + values + sh + state + position_set + 2 * self.decoded_bytes()


def read_header(stream: Bitstream) -> StreamHeader:
    """Check ``stream``'s header completely against itself and its chunks; the checked view. A tiered
    stream has one view per tier: :func:`gscodec_shac.codec.tiers.read_headers`."""
    if "tiers" in stream.features:
        raise BitstreamError("a tiered .gsc stream has one header per tier: read them with read_headers")
    header = stream.header
    n = HEADER.integer(header.get("num_gaussians"), "num_gaussians", 1, MAX_GAUSSIANS)
    degree = HEADER.integer(header.get("sh_degree"), "sh_degree", 0, sh_index.MAX_SH_DEGREE)
    grid = HEADER.mapping(header.get("grid"), "grid", optional=False)
    shape = (HEADER.integer(grid.get("height"), "grid.height", 1, MAX_GAUSSIANS),
             HEADER.integer(grid.get("width"), "grid.width", 1, MAX_GAUSSIANS))
    if not n <= shape[0] * shape[1] <= 2 * n + 4096:
        raise HEADER.error("grid", f"a {shape[0]}x{shape[1]} grid cannot hold {n:,} Gaussians")
    padding = HEADER.choice(grid.get("padding"), PADDINGS, "grid.padding")
    color = HEADER.choice(header.get("color", "rgb"), COLORS, "color")
    sh = _sh_entry(header.get("sh"), degree, n, stream.features)
    codecs = _codec_table(header.get("codecs"))
    attributes = _attributes(header.get("attributes"), sh)
    if (attributes["rotation"].transform == "rotation_vector") != (ROTATION_VECTOR_FEATURE in stream.features):
        raise HEADER.error("attributes.rotation.transform", "rotation vectors and the rotation_vector feature "
                           "come together")
    as_set = attributes["positions"].coding == "set"
    if as_set != ("positions_set" in stream.features) or as_set != (padding == "zorder"):
        raise HEADER.error("grid.padding", "set-coded positions, the zorder padding and the positions_set "
                           "feature come together")
    chunks = _chunk_plans(stream, attributes, shape, len(codecs), sh.grid if sh else None)
    deformation = _deformation(header.get("deformation"), stream.features)
    sets = _parameter_sets(stream, chunks, codecs)
    zlib_sizes = _zlib_chunks(stream, attributes, sh, padding, shape[0] * shape[1], deformation, n, sets > 0)

    prune = HEADER.mapping(header.get("prune"), "prune")
    policy = grid.get("policy")
    if policy is not None:
        HEADER.choice(policy, SORT_POLICIES, "grid.policy")
    sort = HEADER.mapping(grid.get("sort"), "grid.sort")
    rate_point = HEADER.mapping(header.get("rate_point"), "rate_point")
    control = HEADER.mapping(header.get("rate_control"), "rate_control")
    target = HEADER.mapping(control.get("target"), "rate_control.target") or None
    return StreamHeader(
        version=stream.version,
        total_bytes=stream.total_bytes(),
        num_gaussians=n,
        sh_degree=degree,
        grid_shape=shape,
        padding=padding,
        color=color,
        sh=sh,
        attributes=attributes,
        chunks=chunks,
        codecs=codecs,
        chunk_bytes={c.name: len(c.data) for c in stream.chunks},
        chunk_attributes={c.name: _optional_string(c.meta.get("attribute"), f"chunks.{c.name}.attribute") or c.name
                          for c in stream.chunks},
        zlib_sizes=zlib_sizes,
        parameter_sets=sets,
        producer=_optional_string(header.get("producer"), "producer"),
        input_gaussians=_optional_integer(header.get("input_gaussians"), "input_gaussians", n, 1 << 40),
        pruned=_optional_integer(prune.get("pruned"), "prune.pruned", 0, 1 << 40) or 0,
        dropped=_optional_integer(grid.get("dropped"), "grid.dropped", 0, 1 << 40) or 0,
        sort_method=_optional_string(sort.get("method"), "grid.sort.method"),
        rate_point=_optional_string(rate_point.get("name"), "rate_point.name"),
        target=target,
        deformation=deformation,
    )


def read_deformation(stream: Bitstream, view: StreamHeader) -> dict[str, np.ndarray]:
    """The float32 weights of a dynamic stream's network (sizes checked by :func:`read_header`)."""
    from gscodec_shac.codec.deformation import decode_weights

    if view.deformation is None:
        raise BitstreamError("corrupt .gsc file: the stream has no deformation network")
    raw = inflate(stream.chunk("deformation"), view.zlib_sizes["deformation"])
    weights = decode_weights(raw, view.deformation.arch, view.deformation.dtype, view.deformation.bits)
    bad = [name for name, value in weights.items() if not np.all(np.isfinite(value))]
    if bad:
        raise BitstreamError(f"corrupt .gsc file: chunk 'deformation': weight {bad[0]} holds NaN or infinity")
    return weights


def read_dc_only(stream: Bitstream, view: StreamHeader) -> np.ndarray | None:
    """The DC-only flag of each Gaussian in grid order (None: every Gaussian has its AC coefficients)."""
    from gscodec_shac.codec.sh_degree import CHUNK, read_flags

    if view.sh is None or view.sh.dc_only is None:
        return None
    return read_flags(inflate(stream.chunk(CHUNK), view.zlib_sizes[CHUNK]), view.num_gaussians, view.sh.dc_only)


def read_stage(stream: Bitstream, view: StreamHeader, shared: bool = False) -> ShStage:
    """The SH stage rebuilt from ``sh_state``, checked against the header on one row. ``shared``: the
    state of an importance tier (:mod:`.tiers`), which may hold more features than the tier codes: the
    stage then keeps the first of them."""
    sh = view.sh
    if sh is None:
        raise BitstreamError("corrupt .gsc file: the stream has no SH stage")
    try:
        state = StageState.from_bytes(_inflate_state(stream.chunk("sh_state"), view.zlib_sizes["sh_state"]))
    except BitstreamError:
        raise
    except GscodecError as exc:
        raise BitstreamError(f"corrupt .gsc file: chunk 'sh_state': {exc}") from None
    if state.name != sh.stage:
        raise BitstreamError(f"corrupt .gsc file: chunk 'sh_state' holds stage {state.name!r}, "
                             f"the header says {sh.stage!r}")
    try:
        stage = stage_from_state(state)
        if shared and 0 < sh.features < getattr(stage, "n_features", 0):
            stage.keep_features(sh.features)
        probe = np.asarray(stage.inverse_transform(np.zeros((1, sh.features), dtype=np.float32)))
    except GscodecError as exc:
        raise BitstreamError(f"corrupt .gsc file: chunk 'sh_state': {exc}") from None
    except (ValueError, TypeError, KeyError, IndexError, AttributeError, OverflowError) as exc:
        raise BitstreamError(f"corrupt .gsc file: chunk 'sh_state' is inconsistent "
                             f"({type(exc).__name__}: {exc})") from None
    columns = 3 * sh_index.num_rest_coeffs(view.sh_degree) + (3 if sh.uses_dc else 0)
    if probe.shape != (1, columns):
        raise BitstreamError(f"corrupt .gsc file: the {sh.stage!r} stage state gives {probe.shape[-1]} SH columns "
                             f"from {sh.features} features, SH degree {view.sh_degree} needs {columns}")
    return stage


def inflate(chunk: Chunk, raw_size: int) -> bytes:
    """A zlib chunk's bytes, exactly ``raw_size`` of them (checked by :func:`read_header`);
    inflation stops at the first byte past them."""
    inflater = Inflater(chunk.data, f"corrupt .gsc file: chunk {chunk.name!r}", error=BitstreamError)
    out = inflater.read(raw_size)
    inflater.finish()
    return out


def _inflate_state(chunk: Chunk, raw_size: int) -> bytes:
    """The SH stage state: its 8-byte preamble (magic, JSON length) is inflated and checked
    first, so a zlib bomb of the declared size is refused after 8 bytes, not after all of it."""
    inflater = Inflater(chunk.data, f"corrupt .gsc file: chunk {chunk.name!r}", error=BitstreamError)
    head = inflater.read(min(8, raw_size))
    length = int.from_bytes(head[4:8], "little")
    if head[:4] != STATE_MAGIC or 8 + length > raw_size:
        raise BitstreamError(f"corrupt .gsc file: chunk {chunk.name!r} does not hold an SH stage state "
                             "(bad magic or header length)")
    out = head + inflater.read(raw_size - 8)
    inflater.finish()
    return out


# ------------------------------------------------------------------ parts
def _sh_entry(value: Any, degree: int, n: int, features: set[str]) -> ShEntry | None:
    from gscodec_shac.codec.sh_degree import FEATURE

    if value is None:
        if FEATURE in features:
            raise HEADER.error("sh", f"the {FEATURE!r} feature needs an SH stage entry")
        if degree > 0:
            raise HEADER.error("sh", f"SH degree {degree} needs an SH stage entry, got none")
        return None
    if degree == 0:
        raise HEADER.error("sh", "SH degree 0 has no SH stage, but the header names one")
    sh = HEADER.mapping(value, "sh", optional=False)
    entry = ShEntry(
        stage=HEADER.choice(sh.get("stage"), STAGES.names(), "sh.stage"),
        features=HEADER.integer(sh.get("features"), "sh.features", 0, MAX_SH_FEATURES),
        lossless=HEADER.boolean(sh.get("lossless"), "sh.lossless"),
        uses_dc=HEADER.boolean(sh.get("uses_dc"), "sh.uses_dc"),
        ycbcr=HEADER.boolean(sh.get("ycbcr"), "sh.ycbcr"),
        dc_only=_optional_integer(sh.get("dc_only"), "sh.dc_only", 0, n - 1),
    )
    if (entry.dc_only is not None) != (FEATURE in features):
        raise HEADER.error("sh.dc_only", f"the DC-only count and the {FEATURE!r} feature come together")
    if entry.dc_only is None:
        return entry
    if entry.uses_dc:
        raise HEADER.error("sh.dc_only", "a stage coding the DC inside its features has no DC-only Gaussians")
    coded = n - entry.dc_only
    grid = HEADER.mapping(sh.get("grid"), "sh.grid", optional=False)
    shape = (HEADER.integer(grid.get("height"), "sh.grid.height", 1, MAX_GAUSSIANS),
             HEADER.integer(grid.get("width"), "sh.grid.width", 1, MAX_GAUSSIANS))
    if not coded <= shape[0] * shape[1] <= 2 * coded + 4096:
        raise HEADER.error("sh.grid", f"a {shape[0]}x{shape[1]} grid cannot hold the {coded:,} Gaussians with SH")
    padding = HEADER.choice(grid.get("padding"), ("tail", "zorder"), "sh.grid.padding")
    return dataclasses.replace(entry, grid=shape, grid_padding=padding)


def _codec_table(value: Any) -> tuple[CodecEntry, ...]:
    table = HEADER.sequence(value, "codecs")
    if len(table) > MAX_CODECS:
        raise HEADER.error("codecs", f"{len(table)} entries (at most {MAX_CODECS})")
    entries = []
    for index, raw in enumerate(table):
        key = f"codecs[{index}]"
        entry = HEADER.mapping(raw, key, optional=False)
        options = HEADER.mapping(entry.get("options"), f"{key}.options")
        for name, option in options.items():
            if not isinstance(option, _OPTION_TYPES):
                raise HEADER.error(f"{key}.options.{name}", f"must be a string, number, boolean or null, got {option!r}")
        entries.append(CodecEntry(HEADER.choice(entry.get("name"), CODECS.names(), f"{key}.name"),
                                  _optional_string(entry.get("version"), f"{key}.version"), options))
    return tuple(entries)


def _attributes(value: Any, sh: ShEntry | None) -> dict[str, AttributeEntry]:
    attrs = HEADER.mapping(value, "attributes", optional=False)
    expected = [name for name in ATTRIBUTES if not (name == "sh_dc" and sh and sh.uses_dc)]
    if sh and sh.features:
        expected.append("sh")
    if sorted(attrs) != sorted(expected):
        raise HEADER.error("attributes", f"names {sorted(map(str, attrs))}, expected {sorted(expected)}")
    out = {}
    for name in expected:
        key = f"attributes.{name}"
        entry = HEADER.mapping(attrs[name], key, optional=False)
        channels = HEADER.integer(entry.get("channels"), f"{key}.channels", 1, MAX_SH_FEATURES)
        forms = {SH_FEATURES_TRANSFORM: None} if name == "sh" else transforms(name)
        transform = HEADER.choice(entry.get("transform"), tuple(forms), f"{key}.transform")
        wanted = sh.features if name == "sh" else forms[transform].channels
        if channels != wanted:
            raise HEADER.error(f"{key}.channels", f"must be {wanted}, got {channels}")
        chunks = HEADER.sequence(entry.get("chunks"), f"{key}.chunks")
        names = tuple(HEADER.string(c, f"{key}.chunks[{i}]") for i, c in enumerate(chunks))
        if len(set(names)) != len(names):
            raise HEADER.error(f"{key}.chunks", "names a chunk twice")
        quantizer = _quantizer(entry.get("quantizer"), channels, f"{key}.quantizer")
        coding = HEADER.choice(entry.get("coding", "planes"), CODINGS, f"{key}.coding")
        if coding == "set" and (name != "positions" or quantizer is None or len(names) != 1):
            raise HEADER.error(f"{key}.coding", "only positions, with a quantizer and one chunk, are set-coded")
        integer_bits = entry.get("integer_bits")
        if integer_bits is None and quantizer is None:
            raise HEADER.error(key, "has neither a quantizer nor integer_bits")
        if integer_bits is not None:
            HEADER.integer(integer_bits, f"{key}.integer_bits", 1, 16)
            if quantizer is not None and quantizer.bits != integer_bits:
                raise HEADER.error(f"{key}.integer_bits", f"{integer_bits} differs from the quantizer's {quantizer.bits}")
        bits = integer_bits if integer_bits is not None else quantizer.bits
        out[name] = AttributeEntry(name, channels, bits, transform, names, quantizer, coding)
    return out


def _quantizer(value: Any, channels: int, key: str) -> Quantizer | None:
    if value is None:
        return None
    entry = HEADER.mapping(value, key, optional=False)
    bits = HEADER.integer(entry.get("bits"), f"{key}.bits", 1, 16)
    float32_max = float(np.finfo(np.float32).max)
    ranges = []
    for side in ("min", "max"):
        values = entry.get(side)
        if not isinstance(values, list) or len(values) != channels:
            raise HEADER.error(f"{key}.{side}", f"must be a list of {channels} numbers, got {values!r}")
        ranges.append([HEADER.number(v, f"{key}.{side}[{i}]", -float32_max, float32_max) for i, v in enumerate(values)])
    lo, hi = (np.asarray(r, dtype=np.float32) for r in ranges)
    bad = np.flatnonzero(hi < lo)
    if bad.size:
        raise HEADER.error(f"{key}.max[{bad[0]}]", f"{hi[bad[0]]} is below min {lo[bad[0]]}")
    return Quantizer(bits, lo, hi)


def _chunk_plans(stream: Bitstream, attributes: dict[str, AttributeEntry], shape: tuple[int, int],
                 n_codecs: int, sh_shape: tuple[int, int] | None = None) -> tuple[ChunkPlan, ...]:
    present = {c.name: c for c in stream.chunks}
    plans, owner = [], {}
    for attribute in attributes.values():
        cover = {part: np.zeros(attribute.channels, dtype=np.int64) for part in PARTS}
        for name in attribute.chunks:
            if name in owner or name in ("grid_mask", "sh_state", "sh_dc_only", ps.CHUNK):
                raise HEADER.error(f"attributes.{attribute.name}.chunks", f"chunk {name!r} is listed twice")
            owner[name] = attribute.name
            if name not in present:
                raise HEADER.error(f"attributes.{attribute.name}.chunks", f"chunk {name!r} is not in the chunk table")
            if attribute.coding == "set":
                _check_set_chunk(present[name].meta, name, attribute)
                cover["all"][:] = 1
                continue
            plane_shape = sh_shape if attribute.name == "sh" and sh_shape else shape
            plan = _chunk_plan(present[name].meta, name, attribute, plane_shape, n_codecs)
            cover[plan.part][plan.start : plan.stop] += 1
            plans.append(plan)
        whole = (cover["all"] == 1) & (cover["hi"] == 0) & (cover["lo"] == 0)
        split = (cover["all"] == 0) & (cover["hi"] == 1) & (cover["lo"] == 1)
        if not np.all(whole | split):
            raise HEADER.error(f"attributes.{attribute.name}.chunks", "do not cover each channel exactly once")
    return tuple(plans)


def _check_set_chunk(meta: dict, name: str, attribute: AttributeEntry) -> None:
    """The chunk of set-coded positions: its encoding and bit depth (the quantiser's)."""
    key = f"chunks.{name}"
    if meta.get("attribute", attribute.name) != attribute.name:
        raise HEADER.error(f"{key}.attribute", f"must be {attribute.name!r}, got {meta.get('attribute')!r}")
    HEADER.choice(meta.get("encoding"), ("morton_set",), f"{key}.encoding")
    HEADER.choice(meta.get("bits"), (attribute.bits,), f"{key}.bits")


def _chunk_plan(meta: dict, name: str, attribute: AttributeEntry, shape: tuple[int, int], n_codecs: int) -> ChunkPlan:
    key = f"chunks.{name}"
    if meta.get("attribute", attribute.name) != attribute.name:
        raise HEADER.error(f"{key}.attribute", f"must be {attribute.name!r}, got {meta.get('attribute')!r}")
    channels = meta.get("channels")
    if not isinstance(channels, list) or len(channels) != 2:
        raise HEADER.error(f"{key}.channels", f"must be [start, stop], got {channels!r}")
    start = HEADER.integer(channels[0], f"{key}.channels[0]", 0, attribute.channels - 1)
    stop = HEADER.integer(channels[1], f"{key}.channels[1]", start + 1, attribute.channels)
    part = HEADER.choice(meta.get("part"), PARTS, f"{key}.part")
    bits = HEADER.integer(meta.get("bits"), f"{key}.bits", 1, 16)
    wanted = {"all": attribute.bits, "hi": attribute.bits - 8, "lo": 8}[part]
    if part != "all" and attribute.bits <= 8:
        raise HEADER.error(f"{key}.part", f"{attribute.bits}-bit samples are not split into bytes")
    if bits != wanted:
        raise HEADER.error(f"{key}.bits", f"must be {wanted} for a {part!r} chunk of {attribute.bits}-bit samples, "
                           f"got {bits}")
    plane_shape = meta.get("shape")
    if plane_shape != [stop - start, *shape]:
        raise HEADER.error(f"{key}.shape", f"must be {[stop - start, *shape]}, got {plane_shape!r}")
    codec = HEADER.integer(meta.get("codec"), f"{key}.codec", 0, n_codecs - 1)
    qp = meta.get("qp")
    if qp is not None:
        HEADER.integer(qp, f"{key}.qp", 0, _MAX_QP)
    indices = meta.get(ps.META_KEY)
    if indices is not None:
        indices = tuple(HEADER.integer(i, f"{key}.{ps.META_KEY}[{k}]", 0, ps.MAX_SETS - 1)
                        for k, i in enumerate(HEADER.sequence(indices, f"{key}.{ps.META_KEY}")))
    return ChunkPlan(name, attribute.name, start, stop, part, bits, codec, qp, indices)


def _parameter_sets(stream: Bitstream, chunks: tuple[ChunkPlan, ...], codecs: tuple[CodecEntry, ...]) -> int:
    """The entries of the HEVC parameter-set table: the feature, the table chunk (its ``sets``) and
    every hevc chunk's indices come together, each index inside the table; 0 without the feature."""
    if ps.FEATURE not in stream.features:
        listed = next((plan.name for plan in chunks if plan.parameter_sets is not None), None)
        if listed is not None:
            raise HEADER.error(f"chunks.{listed}.{ps.META_KEY}", f"needs the {ps.FEATURE} feature")
        return 0
    if not any(c.name == ps.CHUNK for c in stream.chunks):
        raise HEADER.error("chunks", f"chunk {ps.CHUNK!r} is missing")
    sets = HEADER.integer(stream.chunk(ps.CHUNK).meta.get("sets"), f"chunks.{ps.CHUNK}.sets", 1, ps.MAX_SETS)
    for plan in chunks:
        hevc = codecs[plan.codec].name == ps.CODEC
        if (plan.parameter_sets is not None) != hevc:
            raise HEADER.error(f"chunks.{plan.name}.{ps.META_KEY}", "is listed exactly for the hevc chunks of a "
                               f"stream with the {ps.FEATURE} feature")
        if hevc and (not plan.parameter_sets or max(plan.parameter_sets) >= sets):
            raise HEADER.error(f"chunks.{plan.name}.{ps.META_KEY}", f"must list indices below {sets}, "
                               f"got {list(plan.parameter_sets)}")
    return sets


def _deformation(value: Any, features: set[str]) -> DeformationEntry | None:
    """The ``deformation`` entry: present exactly when the stream needs the ``deformation`` feature;
    quantised (uint8) exactly when it also needs ``deformation_quantised``."""
    from gscodec_shac.codec.deformation import DTYPES, MIXED_FEATURE, QUANTISED_FEATURE

    if (value is not None) != ("deformation" in features):
        raise HEADER.error("deformation", "the deformation entry and the 'deformation' feature come together")
    if value is None:
        for feature in (QUANTISED_FEATURE, MIXED_FEATURE):
            if feature in features:
                raise HEADER.error("deformation", f"the {feature!r} feature needs a deformation entry")
        return None
    entry = HEADER.mapping(value, "deformation", optional=False)
    dtype = HEADER.choice(entry.get("dtype"), DTYPES, "deformation.dtype")
    if (dtype == "uint8") != (QUANTISED_FEATURE in features):
        raise HEADER.error("deformation.dtype", f"dtype uint8 and the {QUANTISED_FEATURE!r} feature come together")
    if MIXED_FEATURE in features and dtype != "uint8":
        raise HEADER.error("deformation.dtype", f"the {MIXED_FEATURE!r} feature needs the quantised form (uint8)")
    try:
        arch = DeformArch.from_dict(entry.get("arch"))
    except GscodecError as exc:
        raise HEADER.error("deformation.arch", str(exc)) from None
    except TypeError as exc:
        raise HEADER.error("deformation.arch", f"malformed ({exc})") from None
    bits = _deformation_bits(entry.get("bits"), arch, features) if dtype == "uint8" else 16
    return DeformationEntry(arch, dtype, weight_count(arch), bits)


def _deformation_bits(value: Any, arch: DeformArch, features: set[str]) -> int | tuple[int, ...]:
    """``deformation.bits``: one count (2..8), or with ``deformation_mixed_bits`` a list of one per matrix."""
    from gscodec_shac.codec.deformation import MAX_BITS, MIN_BITS, MIXED_FEATURE, matrix_bits

    if (MIXED_FEATURE in features) != isinstance(value, list):
        raise HEADER.error("deformation.bits", f"a list of bits and the {MIXED_FEATURE!r} feature come together")
    if not isinstance(value, list):
        return HEADER.integer(value, "deformation.bits", MIN_BITS, MAX_BITS)
    count = len(matrix_bits(arch, MIN_BITS))
    if len(value) != count:
        raise HEADER.error("deformation.bits", f"{len(value)} values for the architecture's {count} matrices")
    return tuple(HEADER.integer(v, "deformation.bits", MIN_BITS, MAX_BITS) for v in value)


def _zlib_chunks(stream: Bitstream, attributes: dict[str, AttributeEntry], sh: ShEntry | None, padding: str,
                 cells: int, deformation: DeformationEntry | None = None, n: int = 0,
                 parameter_sets: bool = False) -> dict[str, int]:
    """``{name: raw size}`` of the zlib chunks; checks no chunk is unaccounted for."""
    expected: dict[str, int | None] = {}
    limits = {ps.CHUNK: ps.MAX_TABLE_BYTES}
    if parameter_sets:
        expected[ps.CHUNK] = None
    if padding == "mask":
        expected["grid_mask"] = (cells + 7) // 8
    if sh is not None:
        expected["sh_state"] = None
        if sh.dc_only is not None:
            expected["sh_dc_only"] = (n + 7) // 8
    if deformation is not None:
        from gscodec_shac.codec.deformation import raw_size

        expected["deformation"] = raw_size(deformation.arch, deformation.dtype, deformation.bits)
    listed = {name for entry in attributes.values() for name in entry.chunks}
    named = {c.name for c in stream.chunks}
    stray = sorted(named - listed - set(expected))
    missing = sorted(set(expected) - named)
    if stray or missing:
        what = f"chunk {stray[0]!r} belongs to no attribute" if stray else f"chunk {missing[0]!r} is missing"
        raise HEADER.error("chunks", what)
    sizes = {}
    for name, exact in expected.items():
        chunk = stream.chunk(name)
        key = f"chunks.{name}"
        HEADER.choice(chunk.meta.get("encoding"), ("zlib",), f"{key}.encoding")
        limit = exact if exact is not None else limits.get(
            name, min(MAX_STATE_BYTES, STATE_BASE_BYTES + STATE_BYTES_PER_CELL * cells))
        raw_size = HEADER.integer(chunk.meta.get("raw_size"), f"{key}.raw_size", exact or 0, limit)
        if raw_size > ZLIB_MAX_RATIO * len(chunk.data):
            raise HEADER.error(f"{key}.raw_size", f"{raw_size:,} bytes cannot come from {len(chunk.data):,} "
                               f"deflated bytes (at most {ZLIB_MAX_RATIO}:1)")
        sizes[name] = raw_size
    return sizes


def _optional_string(value: Any, key: str) -> str | None:
    return None if value is None else HEADER.string(value, key)


def _optional_integer(value: Any, key: str, lo: int, hi: int) -> int | None:
    return None if value is None else HEADER.integer(value, key, lo, hi)


def describe(view: StreamHeader) -> dict[str, Any]:
    """A JSON-serialisable summary of a checked header (``gscodec-shac info`` of a ``.gsc``)."""
    n = view.num_gaussians
    # bits per *input* Gaussian, as encode and rd report them; a stream older than the
    # input count (format 1.x before input_gaussians) falls back to the decoded count
    per = view.input_gaussians if view.input_gaussians is not None else n
    sizes: dict[str, int] = {"header": view.total_bytes - sum(view.chunk_bytes.values())}
    for name, size in view.chunk_bytes.items():
        attribute = view.chunk_attributes[name]
        sizes[attribute] = sizes.get(attribute, 0) + size
    plans = {plan.name: plan for plan in view.chunks}
    return {
        "bytes": view.total_bytes,
        "format_version": "%d.%d" % view.version,
        "producer": view.producer,
        "num_gaussians": n,
        "input_gaussians": view.input_gaussians if view.input_gaussians is not None else n,
        "pruned": view.pruned,
        "dropped": view.dropped,
        "sh_degree": view.sh_degree,
        "sh_stage": view.sh.stage if view.sh else None,
        "sh_features": view.sh.features if view.sh else None,
        "sh_dc_only": view.sh.dc_only if view.sh else None,
        "grid": f"{view.grid_shape[0]}x{view.grid_shape[1]}",
        "sort": "positions (set-coded)" if view.padding == "zorder" else view.sort_method,
        "padding": view.padding,
        "color": view.color,
        "rate_point": view.rate_point,
        "target": view.target,
        "deformation": ({"arch": view.deformation.arch.to_dict(), "weights": view.deformation.weights,
                         "dtype": view.deformation.dtype, "bits": view.deformation.bits,
                         "bytes": view.chunk_bytes.get("deformation", 0)}
                        if view.deformation else None),
        "bits_per_gaussian": 8.0 * view.total_bytes / per,
        "bits_per_gaussian_of": "input" if view.input_gaussians is not None else "decoded",
        "decoded_bytes": view.decoded_bytes(),
        "attributes": {name: {"bytes": size, "bits_per_gaussian": 8.0 * size / per} for name, size in sizes.items()},
        "chunks": [
            {"name": name, "bytes": size, "attribute": view.chunk_attributes[name],
             "bits": plans[name].bits if name in plans else None, "qp": plans[name].qp if name in plans else None,
             "codec": view.codecs[plans[name].codec].name if name in plans else None}
            for name, size in view.chunk_bytes.items()
        ],
    }
