"""Grid codecs: registry, lossless round trips, HEVC rate behaviour and layouts, robustness."""

from __future__ import annotations

import re
import zlib

import numpy as np
import pytest

from gscodec_shac.codec.grid import available_codecs, get_codec
from gscodec_shac.codec.grid.hm import find_hm
from gscodec_shac.codec.grid.raw import pack_bits, unpack_bits
from gscodec_shac.errors import BitstreamError, CodecUnavailableError, ValidationError

SHAPE = (3, 64, 48)


def smooth_planes(shape: tuple[int, int, int], bit_depth: int, seed: int = 0) -> np.ndarray:
    """Correlated smooth planes with a little noise, like sorted attribute grids."""
    rng = np.random.default_rng(seed)
    c, h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.stack([np.sin(xx / 9 + k) + np.cos(yy / 7 - 0.5 * k) for k in range(c)])
    top = 2**bit_depth - 1
    values = (base + 2) / 4 * top + rng.normal(0, top / 400, base.shape)
    return np.clip(np.rint(values), 0, top).astype(np.uint16)


def random_planes(shape: tuple[int, int, int], bit_depth: int, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 2**bit_depth, shape).astype(np.uint16)


LOSSLESS = [
    ("raw", {"entropy": "none"}, (1, 3, 8, 10, 16)),
    ("raw", {"entropy": "zlib"}, (8, 10, 16)),
    ("raw", {"entropy": "lzma"}, (8, 10, 16)),
    ("png", {}, (8, 10, 16)),
    ("jpegls", {}, (8, 10, 16)),
    ("hevc", {"layout": "gray"}, (8, 10, 12)),
    ("hevc", {"layout": "yuv444"}, (10,)),
    ("hevc", {"layout": "frames"}, (10,)),
]
LOSSLESS_CASES = [(name, opts, depth) for name, opts, depths in LOSSLESS for depth in depths]


def case_id(case) -> str:
    name, opts, depth = case
    return f"{name}-{'-'.join(map(str, opts.values())) or 'default'}-{depth}bit"


# ------------------------------------------------------------------ registry
def test_registry_finds_every_builtin_codec():
    assert {"raw", "png", "jpegls", "hevc"} <= set(available_codecs())
    for name in ("raw", "png", "jpegls", "hevc"):
        codec = get_codec(name)
        assert codec.name == name
        assert codec.version().strip()
        assert codec.describe()["name"] == name


def test_unknown_codec_and_bad_options_are_validation_errors():
    with pytest.raises(ValidationError, match="unknown grid codec 'webp'.*hevc"):
        get_codec("webp")
    with pytest.raises(ValidationError, match="entropy"):
        get_codec("raw", entropy="brotli")
    with pytest.raises(ValidationError, match="layout"):
        get_codec("hevc", layout="rgb")
    with pytest.raises(ValidationError, match="preset"):
        get_codec("hevc", preset="fastest")
    with pytest.raises(ValidationError, match="bad options"):
        get_codec("png", colour=True)


def test_hevc_version_names_x265_and_pyav():
    version = get_codec("hevc").version()
    assert version.startswith("x265 ") and "PyAV" in version and "unknown" not in version


# ------------------------------------------------------------ lossless codecs
@pytest.mark.parametrize("case", LOSSLESS_CASES, ids=case_id)
@pytest.mark.parametrize("kind", ["smooth", "random"])
def test_lossless_round_trip_is_exact(case, kind):
    name, opts, depth = case
    make = smooth_planes if kind == "smooth" else random_planes
    planes = make(SHAPE, depth)
    codec = get_codec(name, **opts)
    data = codec.encode(planes, depth, None)
    decoded = codec.decode(data, SHAPE, depth)
    assert decoded.dtype == np.uint16 and decoded.shape == SHAPE
    np.testing.assert_array_equal(decoded, planes)


def test_lossless_codecs_compress_smooth_grids():
    planes = smooth_planes(SHAPE, 10)
    raw_bytes = planes.size * 10 / 8
    for name in ("png", "jpegls", "raw"):
        assert len(get_codec(name).encode(planes, 10, None)) < raw_bytes, name


def test_raw_bit_packing_is_msb_first_and_tight():
    assert pack_bits(np.array([1, 2, 3], np.uint16), 3) == bytes([0b00101001, 0b10000000])
    values = np.arange(1000, dtype=np.uint16) % 1024
    packed = pack_bits(values, 10)
    assert len(packed) == 1250
    np.testing.assert_array_equal(unpack_bits(packed, 1000, 10), values)


def test_lossless_only_codecs_refuse_a_qp():
    for name in ("raw", "png", "jpegls"):
        with pytest.raises(ValidationError, match="lossless only"):
            get_codec(name).encode(smooth_planes(SHAPE, 10), 10, 22)


@pytest.mark.parametrize("name", ["raw", "png", "jpegls", "hevc"])
def test_bad_inputs_are_validation_errors(name):
    codec = get_codec(name)
    with pytest.raises(ValidationError, match="exceed 10 bits"):
        codec.encode(np.full(SHAPE, 1024, np.uint16), 10, None)
    with pytest.raises(ValidationError, match=r"\(C, H, W\)"):
        codec.encode(np.zeros((64, 48), np.uint16), 10, None)
    with pytest.raises(ValidationError, match="integers"):
        codec.encode(np.zeros(SHAPE, np.float32), 10, None)
    with pytest.raises(ValidationError, match="shape"):
        codec.decode(b"\x00" * 16, (3, 0, 48), 10)


def test_hevc_refuses_16_bit_and_bad_qp():
    codec = get_codec("hevc")
    with pytest.raises(ValidationError, match="at most 12 bits.*8-bit planes"):
        codec.encode(smooth_planes(SHAPE, 16), 16, None)
    with pytest.raises(ValidationError, match="qp"):
        codec.encode(smooth_planes(SHAPE, 10), 10, 52)


# --------------------------------------------------------------- HEVC lossy
def test_hevc_error_is_bounded_and_grows_with_qp():
    planes = smooth_planes(SHAPE, 10)
    codec = get_codec("hevc")
    rmse, sizes = [], []
    for qp in (7, 17, 27, 37):
        data = codec.encode(planes, 10, qp)
        decoded = codec.decode(data, SHAPE, 10).astype(float)
        rmse.append(float(np.sqrt(np.mean((decoded - planes) ** 2))))
        sizes.append(len(data))
        # HEVC's quantiser step is 2**((QP-4)/6) at 8 bits, 4x that in 10-bit units.
        step = 4 * 2 ** ((qp - 4) / 6)
        assert rmse[-1] < step / 2, (qp, rmse[-1], step)
    assert rmse == sorted(rmse) and rmse[0] < rmse[-1] / 4
    assert sizes == sorted(sizes, reverse=True)


def test_hevc_lossy_is_deterministic_for_every_layout():
    planes = smooth_planes((4, 40, 56), 10)
    for layout in ("gray", "yuv444", "frames"):
        first = get_codec("hevc", layout=layout).encode(planes, 10, 22)
        again = get_codec("hevc", layout=layout, threads=1).encode(planes, 10, 22)
        assert first == again, layout


@pytest.mark.parametrize("name", ["raw", "png", "jpegls"])
def test_lossless_codecs_are_deterministic(name):
    planes = smooth_planes(SHAPE, 10)
    assert get_codec(name).encode(planes, 10, None) == get_codec(name).encode(planes, 10, None)


@pytest.mark.parametrize("layout", ["gray", "yuv444", "frames"])
@pytest.mark.parametrize("shape", [(1, 64, 48), (2, 37, 45), (4, 24, 40), (5, 9, 13)])
def test_hevc_layouts_round_trip_any_shape(layout, shape):
    planes = smooth_planes(shape, 10)
    codec = get_codec("hevc", layout=layout, preset="fast")
    np.testing.assert_array_equal(codec.decode(codec.encode(planes, 10, None), shape, 10), planes)
    decoded = codec.decode(codec.encode(planes, 10, 12), shape, 10)
    assert decoded.shape == shape and np.abs(decoded.astype(int) - planes).max() < 40


def test_hevc_frames_layout_exploits_correlated_channels():
    rng = np.random.default_rng(3)
    base = smooth_planes((1, 64, 64), 10)[0].astype(int)
    planes = np.stack([np.clip(base + rng.integers(-2, 3, base.shape), 0, 1023) for _ in range(6)]).astype(np.uint16)
    gray = len(get_codec("hevc", layout="gray").encode(planes, 10, 17))
    frames = len(get_codec("hevc", layout="frames").encode(planes, 10, 17))
    assert frames < 0.6 * gray, (frames, gray)


@pytest.mark.parametrize("shape", [(4, 128, 64), (5, 32, 32), (4, 40, 16)])
def test_hevc_frames_layout_is_exact_and_reproducible_on_narrow_grids(shape):
    """Regression: x265 4.2 inter streams 16/32/64 samples wide were irreproducible or inexact."""
    planes = smooth_planes(shape, 10)
    codec = get_codec("hevc", layout="frames", preset="fast")
    streams = {codec.encode(planes, 10, None) for _ in range(3)}
    assert len(streams) == 1
    np.testing.assert_array_equal(codec.decode(streams.pop(), shape, 10), planes)


def _frame_types(codec, planes: np.ndarray) -> str:
    """The picture types (I, P, B) of a ``frames``-layout stream, in display order."""
    from av.video.frame import PictureType

    from gscodec_shac.codec.grid.base import split_chunks
    from gscodec_shac.codec.grid.hevc import _decoded_frames

    (stream,) = split_chunks(codec.encode(planes, 10, 30)[2:], 1, "hevc")
    return "".join(PictureType(frame.pict_type).name for frame in _decoded_frames(stream, 0))


def test_hevc_frames_layout_fixes_the_frame_types():
    """x265's adaptive B frames and weighted P frames now and then wrote other bytes for the same
    input (docs/reliability.md): the layout codes P frames, or B frames at fixed places whatever
    the content, with no weighted prediction."""
    rng = np.random.default_rng(5)
    smooth = smooth_planes((7, 64, 96), 10)
    noise = rng.integers(0, 1024, smooth.shape).astype(np.uint16)
    assert _frame_types(get_codec("hevc", layout="frames"), smooth) == "IPPPPPP"
    with_b = get_codec("hevc", layout="frames", bframes=2)
    assert _frame_types(with_b, smooth) == _frame_types(with_b, noise) and "B" in _frame_types(with_b, smooth)


def test_hevc_long_frames_streams_take_the_narrower_analysis(tmp_path, monkeypatch):
    """The frames are different channels on one grid, not a moving picture: streams of
    LONG_STREAM_MIN_FRAMES frames or more (the SH ones) use x265's diamond search and the medium
    preset's analysis (LONG_STREAM_PARAMS), and at QP RECT_OFF_MAX_QP or finer no rectangular
    partitions (docs/benchmarks.md). Shorter ones (rotation, scale, DC) and single pictures keep the
    preset's. Read back from the options x265 was given (``GSCODEC_X265_DUMP``)."""
    import json

    from gscodec_shac.codec.grid.hevc import LONG_STREAM_MIN_FRAMES, LONG_STREAM_PARAMS, RECT_OFF_MAX_QP

    monkeypatch.setenv("GSCODEC_X265_PROCESSES", "0")  # coded here, so this process writes the records
    monkeypatch.setenv("GSCODEC_X265_DUMP", str(tmp_path))
    many = smooth_planes((LONG_STREAM_MIN_FRAMES, 40, 80), 10)
    frames = get_codec("hevc", layout="frames").encode(many, 10, RECT_OFF_MAX_QP + 1)
    get_codec("hevc", layout="frames").encode(many[::-1], 10, RECT_OFF_MAX_QP)
    get_codec("hevc", layout="frames").encode(many[: LONG_STREAM_MIN_FRAMES - 1], 10, RECT_OFF_MAX_QP)
    get_codec("hevc", layout="gray").encode(many[:2], 10, RECT_OFF_MAX_QP)
    records = [json.loads(line) for path in tmp_path.glob("x265-*.jsonl") for line in path.read_text().splitlines()]
    seen = {(len(r["shape"]), int(re.search(r"qp=(\d+)", r["options"]["x265-params"]).group(1))):
            (LONG_STREAM_PARAMS in r["options"]["x265-params"], ":rect=0" in r["options"]["x265-params"])
            for r in records}
    assert seen == {(LONG_STREAM_MIN_FRAMES, RECT_OFF_MAX_QP + 1): (True, False),
                    (LONG_STREAM_MIN_FRAMES, RECT_OFF_MAX_QP): (True, True),
                    (LONG_STREAM_MIN_FRAMES - 1, RECT_OFF_MAX_QP): (False, False),
                    (1, RECT_OFF_MAX_QP): (False, False)}, records
    assert not any(":me=" in r["options"]["x265-params"] for r in records if len(r["shape"]) < LONG_STREAM_MIN_FRAMES)
    decoded = get_codec("hevc", layout="frames").decode(frames, many.shape, 10)
    assert np.abs(decoded.astype(int) - many).max() < 40


def test_hevc_shifts_narrow_data_to_the_coding_depth():
    planes = smooth_planes(SHAPE, 8)
    codec = get_codec("hevc", depth=10)
    lossy = codec.encode(planes, 8, 17)
    assert lossy[1] == 2  # shift byte
    assert np.abs(codec.decode(lossy, SHAPE, 8).astype(int) - planes).max() <= 8
    lossless = codec.encode(planes, 8, None)
    assert lossless[1] == 0
    np.testing.assert_array_equal(codec.decode(lossless, SHAPE, 8), planes)


# --------------------------------------------------------------- robustness
ROBUST = [("raw", {"entropy": "none"}), ("raw", {"entropy": "zlib"}), ("raw", {"entropy": "lzma"}), ("png", {}),
          ("jpegls", {}), ("hevc", {"layout": "gray"}), ("hevc", {"layout": "yuv444"}), ("hevc", {"layout": "frames"})]  # fmt: skip


def robust_id(case) -> str:
    return "-".join([case[0], *map(str, case[1].values())])


@pytest.mark.parametrize("name,opts", ROBUST, ids=[robust_id(c) for c in ROBUST])
def test_random_and_truncated_streams_raise_bitstream_error(name, opts):
    codec = get_codec(name, **opts)
    planes = smooth_planes(SHAPE, 10)
    data = codec.encode(planes, 10, None)
    rng = np.random.default_rng(7)
    for size in (0, 1, 5, 64, len(data)):
        with pytest.raises(BitstreamError):
            codec.decode(rng.bytes(size), SHAPE, 10)
    for cut in sorted({1, 2, 6, 30, len(data) // 2, len(data) - 1}):
        with pytest.raises(BitstreamError):
            codec.decode(data[:cut], SHAPE, 10)
    with pytest.raises(BitstreamError):
        codec.decode(data + b"\x00", SHAPE, 10)


@pytest.mark.parametrize("name,opts", ROBUST, ids=[robust_id(c) for c in ROBUST])
def test_flipped_bytes_never_escape_as_other_errors(name, opts):
    """A damaged payload may decode to wrong values (the container's CRC catches that) but
    must never crash, hang, or return the wrong shape."""
    codec = get_codec(name, **opts)
    planes = smooth_planes(SHAPE, 10)
    data = codec.encode(planes, 10, None)
    for position in np.linspace(0, len(data) - 1, 40).astype(int):
        damaged = bytearray(data)
        damaged[position] ^= 0x5A
        try:
            decoded = codec.decode(bytes(damaged), SHAPE, 10)
        except BitstreamError:
            continue
        assert decoded.shape == SHAPE and decoded.dtype == np.uint16 and int(decoded.max()) < 1024


@pytest.mark.parametrize("name,opts", ROBUST, ids=[robust_id(c) for c in ROBUST])
@pytest.mark.parametrize("wrong", [(2, 24, 80), (4, 24, 80), (3, 24, 88), (3, 24, 79), (3, 32, 80), (3, 23, 80)])
def test_shape_mismatch_raises_bitstream_error(name, opts, wrong):
    # 80 wide: the hevc frames layout pads narrower grids to 72 columns, which hides width errors below 72.
    codec = get_codec(name, **opts)
    data = codec.encode(smooth_planes((3, 24, 80), 10), 10, None)
    with pytest.raises(BitstreamError):
        codec.decode(data, wrong, 10)


def test_hevc_yuv444_tells_channel_counts_apart():
    codec = get_codec("hevc", layout="yuv444")
    data = codec.encode(smooth_planes((5, 32, 32), 10), 10, 22)
    for wrong in (4, 6):
        with pytest.raises(BitstreamError):
            codec.decode(data, (wrong, 32, 32), 10)


def test_decoders_refuse_streams_larger_than_the_shape():
    bomb = b"\x01" + zlib.compress(bytes(20_000_000))
    with pytest.raises(BitstreamError, match="more samples"):
        get_codec("raw").decode(bomb, (1, 8, 8), 10)
    big = np.zeros((1, 512, 512), np.uint16)
    for name in ("png", "jpegls", "hevc"):
        data = get_codec(name).encode(big, 10, None)
        with pytest.raises(BitstreamError, match="512"):
            get_codec(name).decode(data, (1, 16, 16), 10)


# ----------------------------------------------------------------------- hm
def test_hm_missing_says_how_to_get_it(monkeypatch, tmp_path):
    monkeypatch.setenv("GSCODEC_HM_DIR", str(tmp_path))
    with pytest.raises(CodecUnavailableError, match="TAppEncoder.*HM 18.0.*cmake.*GSCODEC_HM_DIR"):
        get_codec("hm")
    monkeypatch.delenv("GSCODEC_HM_DIR")
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(CodecUnavailableError, match="on PATH"):
        get_codec("hm")
    assert "hm" not in available_codecs()


def test_hm_round_trip_when_installed():
    try:
        find_hm()
    except CodecUnavailableError as exc:
        pytest.skip(f"HM not installed: {exc}")
    planes = smooth_planes((2, 32, 40), 10)
    codec = get_codec("hm")
    assert codec.version().startswith("HM ")
    np.testing.assert_array_equal(codec.decode(codec.encode(planes, 10, None), planes.shape, 10), planes)
    lossy = codec.encode(planes, 10, 22)
    # HM writes standard HEVC: the in-process decoder reads it too, and both agree.
    np.testing.assert_array_equal(codec.decode(lossy, planes.shape, 10), get_codec("hevc").decode(lossy, planes.shape, 10))


def test_x265_encoders_opened_at_once_in_a_fresh_process_give_the_serial_bytes():
    """x265 sets up process-wide tables when an encoder opens: threads opening at once must not race.

    A fresh interpreter (nothing set up yet) starts eight encodes of three bit depths
    at the same moment; each must give the bytes of the same encode run alone.
    """
    import subprocess
    import sys

    script = """
import threading, numpy as np
from gscodec_shac.codec.grid.hevc import HevcCodec, _X265_LIFECYCLE
rng = np.random.default_rng(1)
jobs = [(rng.integers(0, 2 ** b, size=(1, 48, 40), dtype=np.uint16), b) for b in (8, 10, 12) * 3][:8]
barrier, out = threading.Barrier(len(jobs)), {}
def run(i):
    planes, bits = jobs[i]
    barrier.wait()
    out[i] = HevcCodec().encode(planes, bits, 24)
threads = [threading.Thread(target=run, args=(i,)) for i in range(len(jobs))]
[t.start() for t in threads]; [t.join() for t in threads]
assert not _X265_LIFECYCLE.locked()
print(all(out[i] == HevcCodec().encode(*jobs[i], 24) for i in range(len(jobs))))
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "True"


# ------------------------------------------------------------ x265 worker processes
def _x265_planes() -> np.ndarray:
    rng = np.random.default_rng(7)
    ramp = np.add.outer(np.arange(64), np.arange(80))[None] * 5
    return ((ramp + rng.integers(0, 60, size=(4, 64, 80))) % 1024).astype(np.uint16)


@pytest.mark.parametrize("layout", ["gray", "yuv444", "frames"])
def test_x265_worker_processes_write_the_in_process_bytes(layout, monkeypatch):
    from gscodec_shac.codec.grid import x265_processes

    planes = _x265_planes()
    import signal

    monkeypatch.setenv(x265_processes.ENV, "1")
    handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    in_workers = get_codec("hevc", layout=layout).encode(planes, 10, 26)
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == handlers  # the caller's are untouched
    monkeypatch.setenv(x265_processes.ENV, "0")
    assert get_codec("hevc", layout=layout).encode(planes, 10, 26) == in_workers


def test_a_dead_x265_worker_is_replaced_and_the_piece_coded_again(monkeypatch):
    from gscodec_shac.codec.grid import x265_processes
    from gscodec_shac.codec.grid.hevc import encode_frames

    frames = list(_x265_planes()[:1])
    options = {"preset": "fast", "x265-params": "qp=30:info=0:log-level=error:frame-threads=1"}
    expected = encode_frames(frames, "gray10le", options)
    x265_processes.shutdown()  # earlier tests' idle workers (parallel encodes leave several) would die too
    assert x265_processes.encode(frames, "gray10le", options) == expected
    with x265_processes._lock:  # the worker waiting for the next piece dies (as when x265 crashes)
        idle = list(x265_processes._idle)
    assert idle
    for worker in idle:
        worker.process.kill()
        worker.process.wait()
    with pytest.warns(RuntimeWarning, match="x265 worker process failed .*coding the stream again"):
        assert x265_processes.encode(frames, "gray10le", options) == expected


def test_prestarted_x265_workers_code_the_next_pieces(monkeypatch):
    from gscodec_shac.codec.grid import x265_processes
    from gscodec_shac.codec.grid.hevc import encode_frames

    x265_processes.shutdown()
    monkeypatch.setenv(x265_processes.ENV, "0")
    x265_processes.prestart(2)  # x265 in-process: nothing to start
    assert not x265_processes._idle
    monkeypatch.setenv(x265_processes.ENV, "1")
    x265_processes.prestart(2)
    x265_processes.prestart(2)  # already idle: none more
    with x265_processes._lock:
        started = list(x265_processes._idle)
    assert len(started) == 2 and all(worker.process.poll() is None for worker in started)
    frames = list(_x265_planes()[:1])
    options = {"preset": "fast", "x265-params": "qp=30:info=0:log-level=error:frame-threads=1"}
    assert x265_processes.encode(frames, "gray10le", options) == encode_frames(frames, "gray10le", options)
    with x265_processes._lock:
        assert {id(worker) for worker in x265_processes._idle} == {id(worker) for worker in started}


def test_a_hung_x265_worker_is_killed_and_reported_after_the_last_attempt():
    from gscodec_shac.codec.grid import x265_processes

    frames = list(_x265_planes()[:1])
    options = {"preset": "slow", "x265-params": "qp=30:info=0:log-level=error:frame-threads=1"}
    with pytest.raises(x265_processes.X265WorkerError, match="3 times: no result after 0 s"), \
            pytest.warns(RuntimeWarning, match="no result after 0 s"):
        x265_processes.encode(frames, "gray10le", options, timeout=1e-4)


def test_an_x265_that_stops_coming_back_is_killed_long_before_the_piece_allowance():
    from gscodec_shac.codec.grid import x265_processes

    frames = list(_x265_planes()[:1])
    options = {"preset": "slow", "x265-params": "qp=30:info=0:log-level=error:frame-threads=1"}
    with pytest.raises(x265_processes.X265WorkerError, match="3 times: x265 did not come back for 0 s"), \
            pytest.warns(RuntimeWarning, match="did not come back for 0 s"):
        x265_processes.encode(frames, "gray10le", options, timeout=600, stall=1e-4)


def test_a_silent_x265_worker_is_replaced_after_its_stall_limit_and_the_piece_coded_again(monkeypatch):
    import os
    import signal
    import time

    from gscodec_shac.codec.grid import x265_processes
    from gscodec_shac.codec.grid.hevc import encode_frames

    frames = list(_x265_planes())
    options = {"preset": "fast", "x265-params": "qp=30:info=0:log-level=error:frame-threads=1"}
    expected = encode_frames(frames, "gray10le", options)
    monkeypatch.setenv(x265_processes.ENV, "1")
    x265_processes.shutdown()
    x265_processes.prestart(2)
    with x265_processes._lock:
        spare, silent = x265_processes._idle  # the next piece takes the last one
    for worker in (spare, silent):  # both started and answering
        assert worker.call(frames[:1], "gray10le", options, timeout=600)[0] == "ok"
    os.kill(silent.process.pid, signal.SIGSTOP)  # alive but silent, as an x265 spinning on a lock
    started = time.monotonic()
    with pytest.warns(RuntimeWarning, match="x265 did not come back for 3 s"):
        assert x265_processes.encode(frames, "gray10le", options, timeout=600, stall=3.0) == expected
    assert time.monotonic() - started < 60  # the stall limit, not the piece's allowance
    assert silent.process.poll() is not None  # killed
    with x265_processes._lock:
        assert spare in x265_processes._idle


def test_the_x265_worker_reports_each_frame_taken_and_each_packet_flushed():
    from gscodec_shac.codec.grid import x265_processes
    from gscodec_shac.codec.grid.hevc import encode_frames

    frames = list(_x265_planes())
    options = {"preset": "fast", "x265-params": "qp=30:info=0:log-level=error:frame-threads=1"}
    calls = []
    expected = encode_frames(frames, "gray10le", options, progress=lambda: calls.append(1))
    assert expected == encode_frames(frames, "gray10le", options)  # reporting changes nothing
    assert len(frames) + 1 <= len(calls) <= 2 * len(frames)  # every frame taken, then the flushed packets
    x265_processes.shutdown()
    assert x265_processes.encode(frames, "gray10le", options) == expected
    with x265_processes._lock:
        (worker,) = x265_processes._idle
    assert worker.ticks == len(calls)


def test_a_step_of_x265_may_take_its_largest_frame_times_the_load():
    from gscodec_shac.codec.grid.x265_processes import PER_SAMPLE, STALL_BASE, piece_timeout, stall_timeout

    idle = stall_timeout(10**6, load=0.3, cores=2)
    assert idle == STALL_BASE + PER_SAMPLE * 10**6 == stall_timeout(10**6, load=2.0, cores=2)
    assert stall_timeout(10**6, load=13.0, cores=2) == pytest.approx(6.5 * idle)
    assert stall_timeout(10**6, load=1.0, cores=2) < piece_timeout(10**6, load=1.0, cores=2)


def test_a_loaded_machine_gives_a_piece_longer_before_its_worker_is_thought_hung():
    from gscodec_shac.codec.grid.x265_processes import BASE_TIMEOUT, PER_SAMPLE, piece_timeout

    idle = piece_timeout(10**6, load=0.3, cores=2)
    assert idle == BASE_TIMEOUT + PER_SAMPLE * 10**6 == piece_timeout(10**6, load=2.0, cores=2)
    assert piece_timeout(10**6, load=13.0, cores=2) == pytest.approx(6.5 * idle)
    assert piece_timeout(0, load=1.0, cores=0) == BASE_TIMEOUT


def test_x265_refusing_its_settings_in_a_worker_is_the_same_clear_error(monkeypatch):
    from gscodec_shac.codec.grid import x265_processes

    monkeypatch.setenv(x265_processes.ENV, "1")
    with pytest.raises(ValidationError, match="x265 refused the settings"):
        x265_processes.encode(list(_x265_planes()[:1]), "gray10le", {"preset": "no-such-preset", "x265-params": "qp=30:log-level=error"})


@pytest.mark.parametrize("in_workers", [True, False])
def test_x265_dump_records_each_stream_input_and_output(in_workers, tmp_path, monkeypatch):
    """GSCODEC_X265_DUMP: one record per stream whose hashes and kept frames re-code to the same bytes."""
    import hashlib
    import json

    from gscodec_shac.codec.grid import x265_dump, x265_processes
    from gscodec_shac.codec.grid.hevc import encode_frames

    planes = _x265_planes()
    monkeypatch.setenv(x265_processes.ENV, "1" if in_workers else "0")
    x265_processes.shutdown()  # workers copy the environment when they start
    monkeypatch.delenv(x265_dump.ENV, raising=False)
    plain = get_codec("hevc", layout="gray").encode(planes, 10, 26)
    assert not list(tmp_path.iterdir())
    x265_processes.shutdown()
    monkeypatch.setenv(x265_dump.ENV, str(tmp_path / "dump"))
    assert get_codec("hevc", layout="gray").encode(planes, 10, 26) == plain  # the hook changes no byte
    x265_processes.shutdown()
    rows = [json.loads(line) for path in (tmp_path / "dump").glob("x265-*.jsonl") for line in path.read_text().splitlines()]
    assert len(rows) == len(planes)  # gray: one stream per channel
    assert sorted(r["input"] for r in rows) == sorted(x265_dump.input_digest([p << 0]) for p in planes)
    monkeypatch.delenv(x265_dump.ENV)
    for row in rows:
        frames = x265_dump.load_frames(str(tmp_path / "dump" / f"frames-{row['input'][:16]}.npz"))
        assert x265_dump.input_digest(frames) == row["input"]
        stream = encode_frames(frames, row["pix_fmt"], row["options"])
        assert (hashlib.sha256(stream).hexdigest(), len(stream)) == (row["output"], row["bytes"])
        assert stream in plain
