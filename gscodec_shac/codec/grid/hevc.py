"""``hevc``: x265 through PyAV at a fixed QP (or lossless), decoded in-process by FFmpeg.

Stream layout: two bytes, ``layout id`` (0 gray, 1 yuv444, 2 frames) and the
left ``shift`` applied to the samples, then length-prefixed Annex-B HEVC
elementary streams (:func:`~gscodec_shac.codec.grid.base.join_chunks`):

* ``gray``: one single-frame 4:0:0 stream per channel;
* ``yuv444``: one single-frame 4:4:4 stream per group of three channels, channel
  ``3g`` in Y, ``3g+1`` in Cb, ``3g+2`` in Cr; when C is not a multiple of 3 the
  last one or two channels are coded as ``gray`` streams;
* ``frames``: one 4:0:0 stream whose C frames are the C channels, so inter
  prediction can exploit their correlation (one I frame, ``keyint=C``,
  ``scenecut=0``; P frames only unless ``bframes`` is given, at fixed places:
  ``b-adapt=0``; no weighted prediction: ``weightp=0``; with 5 frames or more,
  a narrower analysis: :data:`LONG_STREAM_PARAMS`, see below). With the presets' adaptive
  B frames or weighted P frames x265 now and then wrote other bytes for the same
  input in a worker that had coded other streams before (docs/reliability.md,
  "x265 run-to-run differences"); with these settings it never did in the loops
  measured there, and the attribute channels take 0.3-0.8% fewer bytes at the same
  QP than with the preset's B frames (bonsai, chair). The frames are different attributes
  of the same Gaussians, not a moving picture, so on the long SH streams the preset's wide
  star search finds nothing the diamond search misses: ``me=dia`` took 28% less x265 CPU
  for a 29-frame SH stream, at 0.03% fewer bytes and the same PSNR. Nor, at fine QPs, do the
  slow preset's rectangular partitions, 4 references, RD level 4, sub-pixel level 3 and full
  intra search: without them (the medium preset's analysis, the slow preset's RDOQ kept)
  the SH stream of a 1M encode at QPs 9-13 took 21% less x265 CPU again, at a BD-rate of
  +0.01% over its samples. At coarser QPs the rectangular partitions pay (0.2-0.3% BD-rate at
  16-21, up to 3% above), so only streams at QP 21 or finer drop them (:data:`RECT_OFF_MAX_QP`:
  the ladder's rp5-rp9 SH streams, where the encode takes longest; docs/benchmarks.md, "A narrower
  x265 analysis for the long SH streams").
  On the 3- and 4-frame streams (rotation, scale, DC) the diamond search moved bonsai's
  renders at the top rate points by up to -0.19 dB and ``rect=0`` cost 3-4% BD-rate over
  their samples, so those keep the preset's analysis (docs/benchmarks.md, "Diamond motion
  search for the frames layout").

Every stream uses ``qp=Q:ipratio=1:pbratio=1`` (all frames at exactly QP Q; without
``ipratio=1`` x265 codes an intra frame ~3 QP finer), ``info=0`` (no 2 KB settings
text in each stream) and ``frame-threads=1`` (the output does not depend on how
many cores the machine has); ``qp=None`` selects ``lossless=1``.

Samples are coded at ``depth`` bits (8, 10 or 12; by default the smallest that
holds ``bit_depth``). In lossy mode data of fewer bits is shifted up to ``depth``
so a QP means the same relative error at every bit depth; lossless streams
store the values as they are. x265 pads pictures to its 8-sample coding grid itself
(edge replication) and writes the true size into the SPS conformance window, so
any H, W >= 16 is coded as is; smaller planes are edge-padded to 16 here (the
``frames`` layout: narrower than 72, see :func:`codable_size`) and cropped on
decode. The sequence parameter set is read before decoding, so a stream that
claims a different size, chroma format or bit depth is rejected unallocated.
"""

from __future__ import annotations

import fractions
import functools
import os
import re
import reprlib
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterator

import av
import numpy as np

from gscodec_shac.codec.effort import ANALYSES
from gscodec_shac.codec.grid import x265_dump, x265_processes
from gscodec_shac.codec.grid.base import EncodeParts, GridCodec, PlaneSink, join_chunks, register_codec, split_chunks
from gscodec_shac.errors import BitstreamError, CodecUnavailableError, ValidationError

LAYOUTS = ("gray", "yuv444", "frames")
PRESETS = ("ultrafast", "superfast", "veryfast", "faster", "fast", "medium", "slow", "slower", "veryslow", "placebo")
TUNES = ("psnr", "ssim", "grain", "fastdecode", "zerolatency", "animation")
_GRAY_FMT = {8: "gray", 10: "gray10le", 12: "gray12le"}
_YUV444_FMT = {8: "yuv444p", 10: "yuv444p10le", 12: "yuv444p12le"}
_QUIET = "info=0:log-level=error"
#: Frames layout streams of at least this many frames (the SH features, the AC bands) are
#: analysed with :data:`LONG_STREAM_PARAMS`.
LONG_STREAM_MIN_FRAMES = 5
#: x265 parameters of the long frames streams, on top of the preset: diamond motion search, and
#: the medium preset's analysis (early skip, RD level 3, sub-pixel level 2, 3 references, no mode
#: limiting) with a fast intra search, the slow preset's RDOQ kept.
LONG_STREAM_PARAMS = ":me=dia:early-skip=1:rd=3:subme=2:ref=3:limit-modes=0:fast-intra=1"
#: Long frames streams at this QP or finer also go without rectangular partitions (``rect=0``), most of
#: the CPU saved: BD-rate over the samples +-0.03% at QPs 5-15, +0.17-0.31% at 16-21, 0.3-3% above.
RECT_OFF_MAX_QP = 21
#: x265 parameters of the full analysis: RD level 6 (full rate-distortion decisions). On bonsai's and the
#: chair's streams 2-3.7% smaller at equal sample PSNR, for 1.3-3.5x x265's CPU (docs/benchmarks.md,
#: "The full x265 analysis for small scenes"); the encoder chooses it for small scenes (:mod:`..effort`).
FULL_ANALYSIS_PARAMS = ":rd=6"
#: x265 parameters without the in-loop filters (sample adaptive offset and deblocking; option
#: ``loop_filters=False``). They are made for pictures; on an attribute grid the cells across a block
#: edge hold other Gaussians. Measured: up to +0.3 dB at equal bytes on some plans, nothing through the
#: rate controller, so no shipped rate point uses it (docs/rate_control.md, "Is the plan the best
#: allocation on held-out views?"). The decoder reads the choice from the streams' parameter sets.
NO_LOOP_FILTER_PARAMS = ":sao=0:no-deblock=1"


@register_codec
class HevcCodec(GridCodec):
    """x265 HEVC at a fixed QP or lossless, one of three layouts.

    Options: ``layout`` (``"gray"``, ``"yuv444"`` or ``"frames"``), ``preset``
    (x265 preset, default ``"slow"``; ``"medium"`` is 2-3x faster and 1-4% larger
    in BD-rate), ``tune`` (x265 tune or ``None``; default ``"psnr"``, 3-12% smaller
    than no tune at equal PSNR on attribute grids: docs/benchmarks_codecs.md),
    ``depth`` (8, 10, 12 or ``None`` = smallest holding the data), ``bframes``
    (``frames`` layout only: B frames between P frames, at fixed places; default 0;
    ``None`` = the preset's count) and ``threads`` (x265
    worker threads; ``None`` = all cores; the bytes do not depend on it) and ``analysis``
    (``"preset"``, default, or ``"full"``: RD level 6 for every lossy stream, a few percent smaller
    for 1.3-3.5x the CPU; the decoder does not need it) and ``loop_filters`` (x265's SAO and
    deblocking on lossy streams, default ``True``; ``False`` codes without them).
    """

    name = "hevc"

    def __init__(
        self,
        layout: str = "gray",
        preset: str = "slow",
        tune: str | None = "psnr",
        depth: int | None = None,
        bframes: int | None = 0,
        threads: int | None = None,
        analysis: str = "preset",
        loop_filters: bool = True,
    ) -> None:
        if layout not in LAYOUTS:
            raise ValidationError(f"hevc: layout must be one of {', '.join(LAYOUTS)}, got {reprlib.repr(layout)}")
        if preset not in PRESETS:
            raise ValidationError(f"hevc: preset must be one of {', '.join(PRESETS)}, got {reprlib.repr(preset)}")
        if tune is not None and tune not in TUNES:
            raise ValidationError(f"hevc: tune must be None or one of {', '.join(TUNES)}, got {reprlib.repr(tune)}")
        if depth is not None and depth not in _GRAY_FMT:
            raise ValidationError(f"hevc: depth must be 8, 10, 12 or None, got {reprlib.repr(depth)}")
        if bframes is not None and not (isinstance(bframes, int) and 0 <= bframes <= 16):
            raise ValidationError(f"hevc: bframes must be an integer 0-16 or None, got {reprlib.repr(bframes)}")
        if threads is not None and not (isinstance(threads, int) and threads >= 1):
            raise ValidationError(f"hevc: threads must be a positive integer or None, got {reprlib.repr(threads)}")
        if analysis not in ANALYSES:
            raise ValidationError(f"hevc: analysis must be one of {', '.join(ANALYSES)}, got {reprlib.repr(analysis)}")
        if not isinstance(loop_filters, bool):
            raise ValidationError(f"hevc: loop_filters must be true or false, got {reprlib.repr(loop_filters)}")
        # the defaults of these two are not recorded: files coded with them keep the codec options of earlier versions
        recorded = {"analysis": analysis} if analysis != "preset" else {}
        if not loop_filters:
            recorded["loop_filters"] = False
        super().__init__(layout=layout, preset=preset, tune=tune, depth=depth, bframes=bframes, threads=threads,
                         **recorded)
        self.layout, self.preset, self.tune = layout, preset, tune
        self.depth, self.bframes, self.threads, self.analysis = depth, bframes, threads, analysis
        self.loop_filters = loop_filters

    @classmethod
    def check_available(cls) -> None:
        if "libx265" not in av.codecs_available or "hevc" not in av.codecs_available:
            raise CodecUnavailableError(
                "hevc needs PyAV built with libx265 and the hevc decoder: `pip install av` "
                "(the PyPI wheels bundle both)"
            )

    def version(self) -> str:
        libavcodec = ".".join(map(str, av.library_versions["libavcodec"]))
        return f"{x265_version()} (PyAV {av.__version__}, libavcodec {libavcodec})"

    # ------------------------------------------------------------------ encode
    def encode(self, planes: np.ndarray, bit_depth: int, qp: int | None) -> bytes:
        parts, join = self.encode_parts(planes, bit_depth, qp)
        return join([work() for _, work in parts])

    def encode_parts(self, planes: np.ndarray, bit_depth: int, qp: int | None) -> EncodeParts:
        """One piece per stream of the layout (x265 runs each independently; cost: its samples)."""
        planes = self._check_planes(planes, bit_depth, qp)
        check_qp(self.name, qp)
        depth = coding_depth(self.name, bit_depth, self.depth)
        shift = 0 if qp is None else depth - bit_depth
        grid = pad_to_codable(planes << shift if shift else planes, self.layout)
        parts = []
        for first, n_frames, chroma in stream_plan(self.layout, len(grid)):
            if chroma:
                frames, pix_fmt, extra = [grid[first : first + 3]], _YUV444_FMT[depth], ""
            else:
                frames, pix_fmt, extra = list(grid[first : first + n_frames]), _GRAY_FMT[depth], ""
                if n_frames > 1:  # the frames layout: one I frame, then inter frames of fixed types
                    extra = f":keyint={n_frames}:min-keyint={n_frames}:scenecut=0:b-adapt=0:weightp=0"
                    if n_frames >= LONG_STREAM_MIN_FRAMES:
                        extra += LONG_STREAM_PARAMS + (":rect=0" if qp is not None and qp <= RECT_OFF_MAX_QP else "")
                    extra += f":bframes={self.bframes}" if self.bframes is not None else ""
            if self.analysis == "full" and qp is not None:
                extra += FULL_ANALYSIS_PARAMS
            if not self.loop_filters and qp is not None:
                extra += NO_LOOP_FILTER_PARAMS
            parts.append((sum(f.size for f in frames), functools.partial(self._encode_stream, frames, pix_fmt, qp, extra)))
        head = bytes([LAYOUTS.index(self.layout), shift])
        return parts, lambda streams: head + join_chunks(streams)

    def _encode_stream(self, frames: list[np.ndarray], pix_fmt: str, qp: int | None, extra: str) -> bytes:
        """Encode frames ((H, W) or (3, H, W) arrays) into one Annex-B stream, in an x265 worker
        process (:mod:`.x265_processes`) unless ``GSCODEC_X265_PROCESSES=0``."""
        rate = f"qp={int(qp)}:ipratio=1:pbratio=1" if qp is not None else "lossless=1"
        params = f"{rate}:{_QUIET}:frame-threads=1{extra}"
        if self.threads is not None:
            params += f":pools={self.threads}"
        options = {"preset": self.preset, "x265-params": params}
        if self.tune is not None:
            options["tune"] = self.tune
        if x265_processes.enabled():
            return x265_processes.encode(frames, pix_fmt, options)
        return encode_frames(frames, pix_fmt, options)

    # ------------------------------------------------------------------ decode
    def decode(self, data: bytes, shape: tuple[int, int, int], bit_depth: int) -> np.ndarray:
        out = np.empty(self._check_shape(shape, bit_depth), dtype=np.uint16)

        def put(first: int, planes: np.ndarray) -> None:
            out[first : first + len(planes)] = planes

        self.decode_into(data, shape, bit_depth, put)
        return out

    def decode_into(self, data: bytes, shape: tuple[int, int, int], bit_depth: int, sink: PlaneSink) -> None:
        """Hand every decoded picture's channels to ``sink`` as FFmpeg outputs it (no frame is held)."""
        channels, height, width = self._check_shape(shape, bit_depth)
        if len(data) < 2 or data[0] >= len(LAYOUTS):
            raise BitstreamError("hevc stream is corrupt (unknown layout byte)")
        layout, shift = LAYOUTS[data[0]], data[1]
        coded_h, coded_w = codable_size(height, width, layout)
        plan = stream_plan(layout, channels)
        streams = split_chunks(data[2:], len(plan), self.name)
        depths = {check_sps(stream, coded_w, coded_h, chroma, i) for i, (stream, (_, _, chroma)) in enumerate(zip(streams, plan))}
        depth = check_depth(depths, shift, bit_depth)

        def decode_stream(index: int) -> None:
            first, n_frames, chroma = plan[index]
            step = 3 if chroma else 1
            count = 0
            for frame in _decoded_frames(streams[index], index, frame_threads if n_frames > 1 else 1):
                if count == n_frames:
                    raise BitstreamError(f"hevc stream {index} holds more than the {n_frames} frames expected")
                planes = _planes_from_frame(frame, index, coded_h, coded_w, chroma)[:, :height, :width]
                sink(first + count * step, restore_samples(planes, depth, shift, bit_depth))
                count += 1
            if count != n_frames:
                raise BitstreamError(f"hevc stream {index} holds {count} frames, expected {n_frames}")

        # FFmpeg decodes without the GIL: the streams of a multi-channel grid go to
        # parallel threads (one 1024x1024 plane is ~30 ms; 38 of them in series were
        # the critical path of a 1M-Gaussian decode); a multi-frame stream decodes with
        # FFmpeg's frame threads. The sink gets disjoint channels from each thread.
        frame_threads = os.cpu_count() or 1
        if len(streams) == 1:
            decode_stream(0)
            return
        with ThreadPoolExecutor(min(len(streams), os.cpu_count() or 1)) as pool:
            list(pool.map(decode_stream, range(len(streams))))


# ------------------------------------------------- helpers (shared with ``hm``)
def check_qp(name: str, qp: int | None) -> None:
    """HEVC QPs are integers 0-51; ``None`` means lossless."""
    if qp is not None and not (isinstance(qp, (int, np.integer)) and not isinstance(qp, bool) and 0 <= qp <= 51):
        raise ValidationError(f"{name}: qp must be an integer 0-51 or None (lossless), got {qp!r}")


def coding_depth(name: str, bit_depth: int, depth: int | None) -> int:
    """The bit depth to code at: ``depth``, or the smallest of 8/10/12 holding ``bit_depth``."""
    if bit_depth > 12:
        raise ValidationError(
            f"{name} codes at most 12 bits per sample, got {bit_depth}; split wider data into 8-bit planes"
        )
    chosen = depth or min(d for d in _GRAY_FMT if d >= bit_depth)
    if chosen < bit_depth:
        raise ValidationError(f"{name}: depth {chosen} cannot hold {bit_depth}-bit samples")
    return chosen


def check_depth(depths: set[int], shift: int, bit_depth: int) -> int:
    """The one coding depth of a chunk's streams, checked against its shift and the header's bit depth."""
    depth = next(iter(depths)) if len(depths) == 1 else None
    if depth is None or depth < bit_depth or shift not in (0, depth - bit_depth):
        raise BitstreamError(f"hevc stream at {depth} bits with shift {shift} cannot hold {bit_depth}-bit samples")
    return depth


def restore_samples(planes: np.ndarray, depth: int, shift: int, bit_depth: int) -> np.ndarray:
    """Undo the encoder's left shift (rounding, clipping) and check the value range: a new uint16 array."""
    if shift:
        return np.minimum((planes.astype(np.uint32) + (1 << (shift - 1))) >> shift, 2**bit_depth - 1).astype(np.uint16)
    if depth > bit_depth and int(planes.max()) >= 2**bit_depth:  # no shift although depth > bit_depth: lossless
        raise BitstreamError(f"hevc stream holds values above {bit_depth} bits")
    return np.array(planes, dtype=np.uint16, order="C")


def stream_plan(layout: str, channels: int) -> list[tuple[int, int, int]]:
    """The streams a layout makes: (first channel, frames, chroma format 0 or 3) each."""
    if layout == "frames":
        return [(0, channels, 0)]
    full = channels // 3 if layout == "yuv444" else 0
    return [(3 * g, 1, 3) for g in range(full)] + [(c, 1, 0) for c in range(3 * full, channels)]


def codable_size(height: int, width: int, layout: str = "gray") -> tuple[int, int]:
    """The picture size coded for (height, width) planes: at least 16 x 16 (x265's minimum).

    Other sizes need no padding here: x265 pads to its coding-unit grid itself
    (replicating edges) and signals the true size in the SPS conformance window,
    which the decoder crops to; the SPS check then verifies the exact size.
    The ``frames`` layout is at least 72 wide: inter-coded x265 4.2 streams of
    pictures 16, 32 or 64 samples wide were not reproducible and sometimes did
    not decode to the encoder's pictures (found by tests/test_codecs.py; widths
    from 72 up were always exact).
    """
    return max(16, height), max(72 if layout == "frames" else 16, width)


def pad_to_codable(planes: np.ndarray, layout: str = "gray") -> np.ndarray:
    """Edge-replicate (C, H, W) planes to :func:`codable_size`."""
    height, width = planes.shape[1:]
    coded_h, coded_w = codable_size(height, width, layout)
    if (coded_h, coded_w) == (height, width):
        return planes
    return np.pad(planes, ((0, 0), (0, coded_h - height), (0, coded_w - width)), mode="edge")


def _plane_view(plane: "av.video.plane.VideoPlane", itemsize: int) -> np.ndarray:
    """Writable (height, width) view of a frame plane (skipping the line padding)."""
    dtype = np.uint16 if itemsize == 2 else np.uint8
    rows = np.frombuffer(plane, dtype=dtype).reshape(plane.height, plane.line_size // itemsize)
    return rows[:, : plane.width]


def _frame_from_planes(planes: np.ndarray, pix_fmt: str) -> av.VideoFrame:
    """A VideoFrame whose planes (Y or Y/Cb/Cr) are filled from (1 or 3, H, W) arrays."""
    frame = av.VideoFrame(planes.shape[2], planes.shape[1], pix_fmt)
    itemsize = 1 if pix_fmt in ("gray", "yuv444p") else 2
    for plane, source in zip(frame.planes, planes):
        _plane_view(plane, itemsize)[...] = source
    return frame


def _planes_from_frame(frame: av.VideoFrame, index: int, height: int, width: int, chroma: int) -> np.ndarray:
    """(1 or 3, H, W) views of a decoded frame's samples (no copy), checking its format and size."""
    expected = _YUV444_FMT if chroma else _GRAY_FMT
    if frame.format.name not in expected.values() or (frame.height, frame.width) != (height, width):
        raise BitstreamError(
            f"hevc stream {index} decodes to {frame.width}x{frame.height} {frame.format.name}, "
            f"expected {width}x{height}"
        )
    itemsize = 1 if frame.format.name in ("gray", "yuv444p") else 2
    views = [_plane_view(plane, itemsize) for plane in frame.planes]
    return views[0][None] if len(views) == 1 else np.stack(views)


def _decoded_frames(stream: bytes, index: int, threads: int = 1) -> Iterator[av.VideoFrame]:
    """The frames of one Annex-B stream, in output order, each as soon as FFmpeg gives it
    (``threads`` > 1: FFmpeg's frame threads, the same pictures on several cores)."""
    try:
        ctx = av.CodecContext.create("hevc", "r")
        if threads > 1:
            ctx.thread_type, ctx.thread_count = "FRAME", threads
        for packet in ctx.parse(stream) + ctx.parse(None):
            yield from ctx.decode(packet)
        yield from ctx.decode(None)
    except (av.FFmpegError, ValueError) as exc:
        raise BitstreamError(f"hevc stream {index} is corrupt: {exc}") from None


def encode_frames(
    frames: list[np.ndarray], pix_fmt: str, options: dict[str, str], progress: Callable[[], None] | None = None
) -> bytes:
    """One x265 stream of ``frames`` ((H, W) or (3, H, W) arrays) with the codec ``options``.

    ``progress`` is called each time x265 comes back: after every frame it takes and every packet
    of the flush, so a caller can tell a slow piece from a hung encoder (:mod:`.x265_processes`).
    """
    height, width = frames[0].shape[-2:]
    tick = progress if progress is not None else (lambda: None)
    try:
        with X265Encoder(width, height, pix_fmt, options) as encoder:
            packets = []
            for index, array in enumerate(frames):
                frame = _frame_from_planes(array.reshape((-1, height, width)), pix_fmt)
                frame.pts = index
                packets += encoder.encode(frame)
                tick()
            for packet in encoder.flush():
                packets.append(packet)
                tick()
    except av.FFmpegError as exc:
        raise ValidationError(
            f"hevc: x265 refused the settings {options} for a {width}x{height} {pix_fmt} frame: {exc}"
        ) from None
    stream = b"".join(bytes(packet) for packet in packets)
    x265_dump.record(frames, pix_fmt, options, stream)  # GSCODEC_X265_DUMP=DIR only
    return stream


# x265_encoder_open fills process-wide tables (x265_setup_primitives: "if the SAD
# primitive is unset, set up every primitive", one table per bit depth) with no lock.
# Two encoders of the encode scheduler opened at the same moment in a fresh process
# could both run that set-up while one of them already encoded: a rare segfault in
# x265 (seen once in CI). Opening and closing are serialised; encoding stays parallel.
_X265_LIFECYCLE = threading.Lock()


class X265Encoder:
    """One libx265 encoder context, opened and freed under the process-wide x265 lock.

    Use as a context manager; only this object holds the PyAV context, so leaving
    the ``with`` block frees x265's encoder inside the lock.
    """

    def __init__(self, width: int, height: int, pix_fmt: str, options: dict[str, str]) -> None:
        ctx = av.CodecContext.create("libx265", "w")
        ctx.width, ctx.height, ctx.pix_fmt = width, height, pix_fmt
        ctx.time_base = fractions.Fraction(1, 25)
        ctx.options = options
        with _X265_LIFECYCLE:
            ctx.open()
        self._ctx: av.CodecContext | None = ctx

    def encode(self, frame: av.VideoFrame | None) -> list[av.Packet]:
        """Packets x265 gives back for ``frame`` (``None`` flushes)."""
        return self._ctx.encode(frame)

    def flush(self) -> Iterator[av.Packet]:
        """The packets x265 still holds, one at a time as it codes them."""
        return self._ctx.encode_lazy(None)

    def __enter__(self) -> "X265Encoder":
        return self

    def __exit__(self, *exc: object) -> None:
        with _X265_LIFECYCLE:
            self._ctx = None


@functools.lru_cache(maxsize=1)
def x265_version() -> str:
    """x265's version as it writes it into a stream's info SEI (encodes one 16x16 frame once)."""
    frame = _frame_from_planes(np.zeros((1, 16, 16), np.uint16), "gray")
    with X265Encoder(16, 16, "gray", {"preset": "ultrafast", "x265-params": "log-level=error"}) as encoder:
        stream = b"".join(bytes(p) for p in encoder.encode(frame) + encoder.encode(None))
    match = re.search(rb"x265 \(build \d+\) - ([0-9][\w.+-]*)", stream)
    return f"x265 {match.group(1).decode()}" if match else "x265 (version unknown)"


# ------------------------------------------------------------- SPS inspection
class _Bits:
    """MSB-first bit reader over an RBSP with Exp-Golomb codes."""

    def __init__(self, data: bytes) -> None:
        self.data, self.pos = data, 0

    def u(self, n: int) -> int:
        value = 0
        for _ in range(n):
            if self.pos >= 8 * len(self.data):
                raise BitstreamError("hevc sequence parameter set is truncated")
            value = (value << 1) | ((self.data[self.pos >> 3] >> (7 - (self.pos & 7))) & 1)
            self.pos += 1
        return value

    def ue(self) -> int:
        zeros = 0
        while self.u(1) == 0:
            zeros += 1
            if zeros > 31:
                raise BitstreamError("hevc sequence parameter set is corrupt (bad Exp-Golomb code)")
        return (1 << zeros) - 1 + self.u(zeros)


def check_sps(stream: bytes, width: int, height: int, chroma: int, index: int) -> int:
    """Check every SPS in an Annex-B stream against the expected picture; return its bit depth."""
    depths = []
    for nal in re.split(b"\x00\x00\x01", stream)[1:]:
        if len(nal) < 2 or (nal[0] >> 1) & 0x3F != 33:  # 33: sequence parameter set
            continue
        bits = _Bits(nal[2:].replace(b"\x00\x00\x03", b"\x00\x00"))
        bits.u(4)  # sps_video_parameter_set_id
        sub_layers = bits.u(3)
        bits.u(1)
        bits.u(88 + 8)  # general profile/tier/flags and level
        present = [(bits.u(1), bits.u(1)) for _ in range(sub_layers)]
        if sub_layers:
            bits.u(2 * (8 - sub_layers))
        for profile, level in present:
            bits.u(88 * profile + 8 * level)
        bits.ue()  # sps_seq_parameter_set_id
        chroma_format = bits.ue()
        if chroma_format == 3:
            bits.u(1)  # separate_colour_plane_flag
        coded_w, coded_h = bits.ue(), bits.ue()
        if bits.u(1):  # conformance window (4:0:0 and 4:4:4 crop in luma samples)
            left, right, top, bottom = bits.ue(), bits.ue(), bits.ue(), bits.ue()
            coded_w, coded_h = coded_w - left - right, coded_h - top - bottom
        depth = bits.ue() + 8
        if (coded_w, coded_h, chroma_format) != (width, height, chroma) or depth not in _GRAY_FMT:
            raise BitstreamError(
                f"hevc stream {index} is a {coded_w}x{coded_h} picture (chroma format {chroma_format}, "
                f"{depth} bits), expected {width}x{height} with chroma format {chroma}"
            )
        depths.append(depth)
    if not depths or len(set(depths)) != 1:
        raise BitstreamError(f"hevc stream {index} has no usable sequence parameter set")
    return depths[0]
