"""x265 encodes in worker processes: one encoder per process, a crashed or hung one re-run.

libx265 has races between encoders of one process and inside an encoder's lookahead
(docs/reliability.md "Known gaps": a segfault in CI, a segfault and a hang in stress loops;
x265's tracker has an open lookahead race). The encode scheduler runs two x265 encodes at
once, so each runs in a worker process of its own: ``python -m
gscodec_shac.codec.grid.x265_worker``, started on first use, kept idle for the next piece
and ended when this process exits (or when its stdin closes). A request is a
:data:`LENGTH`-prefixed pickle followed by the frames' raw samples on the worker's stdin, a
reply a :data:`LENGTH`-prefixed pickle on its stdout; :func:`read_into` reads at both ends.
No ``multiprocessing``, so the caller's ``__main__`` is never imported again. A worker that
dies, a piece that runs far past its expected time, or an x265 that stops coming back while it
codes (the worker sends a :data:`TICK` after each frame and packet), is replaced and the piece coded again:
x265 at a fixed QP with one frame thread writes the same bytes (but for a rare run-to-run
difference inside x265: docs/reliability.md, "Known gaps"), so a re-run changes only the wall time.

``GSCODEC_X265_PROCESSES=0`` codes in the calling process instead (the same bytes).
"""

from __future__ import annotations

import atexit
import os
import pickle
import select
import struct
import subprocess
import sys
import threading
import time
import warnings
from typing import Any

import numpy as np

from gscodec_shac.errors import GscodecError

#: Environment variable: ``0`` (or ``off``/``no``/``false``) codes x265 streams in-process.
ENV = "GSCODEC_X265_PROCESSES"
#: Attempts per piece (the first and two re-runs).
ATTEMPTS = 3
#: Seconds a piece may run before its worker is thought hung: this much, plus PER_SAMPLE each, times
#: the machine's load per core when above 1 (:func:`piece_timeout`).
BASE_TIMEOUT = 30.0
PER_SAMPLE = 20e-6  # ~10x x265 `slow`'s time per sample on this 2-core machine
#: Seconds x265 may go without coming back (taking a frame or giving a packet) before its worker is
#: thought hung: this much, plus PER_SAMPLE per sample of the piece's largest frame, times the load
#: per core when above 1 (:func:`stall_timeout`). One step codes about one frame, so a hang at 1M
#: is found in ~30 s, not after the whole piece's allowance (~10 min for 29 frames of 1M samples).
STALL_BASE = 10.0
#: The length prefix of every message, request or reply (the worker reads and writes the same).
LENGTH = struct.Struct("<Q")
#: The worker's progress message: an empty reply, sent each time x265 comes back.
TICK = LENGTH.pack(0)


def read_into(fd: int, buffer: np.ndarray | bytearray, deadline: float | None = None) -> bool:
    """Fill ``buffer`` from ``fd``; False at end of input. With ``deadline`` (``time.monotonic()``
    seconds) the wait for data is bounded: :class:`TimeoutError` once it passes."""
    view, got = memoryview(buffer).cast("B"), 0
    while got < len(view):
        if deadline is not None:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise TimeoutError
        count = os.readv(fd, [view[got:]])
        if not count:
            return False
        got += count
    return True


class X265WorkerError(GscodecError):
    """x265 failed in its worker process on every attempt."""


class _WorkerDied(Exception):
    pass


class _Stalled(Exception):
    pass


def enabled() -> bool:
    """Whether x265 streams are coded in worker processes (the default; POSIX only: pipes are polled with select)."""
    return os.name == "posix" and os.environ.get(ENV, "1").strip().lower() not in ("0", "off", "no", "false")


class _Worker:
    """One ``x265_worker`` process and its pipes."""

    def __init__(self) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "gscodec_shac.codec.grid.x265_worker"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=None, close_fds=True,
        )
        self.ticks = 0  # the TICKs of the last piece

    def call(self, frames: list[np.ndarray], pix_fmt: str, options: dict[str, str], timeout: float,
             stall: float | None = None) -> Any:
        """Send one piece; the unpickled reply, or _WorkerDied / TimeoutError / _Stalled.

        The frames' samples go down the pipe straight from their arrays (no pickled copy),
        after a small pickle of their shapes and dtypes, the pixel format and the options.
        The whole piece has ``timeout`` seconds, each step of x265 (a :data:`TICK`) ``stall``.
        """
        frames = [np.ascontiguousarray(frame) for frame in frames]
        head = pickle.dumps(([(f.shape, f.dtype.str) for f in frames], pix_fmt, options),
                            protocol=pickle.HIGHEST_PROTOCOL)
        stdin = self.process.stdin
        try:
            stdin.write(LENGTH.pack(len(head)))  # type: ignore[union-attr]
            stdin.write(head)  # type: ignore[union-attr]
            for frame in frames:
                stdin.write(memoryview(frame).cast("B"))  # type: ignore[union-attr]
            stdin.flush()  # type: ignore[union-attr]
        except (BrokenPipeError, OSError) as exc:
            raise _WorkerDied(f"could not send the piece ({exc})") from None
        deadline = time.monotonic() + timeout
        self.ticks = 0
        while True:
            step = deadline if stall is None else min(deadline, time.monotonic() + stall)
            try:
                length = LENGTH.unpack(self._read(bytearray(LENGTH.size), step))[0]
            except TimeoutError:
                if step < deadline:
                    raise _Stalled(f"x265 did not come back for {stall:.0f} s") from None
                raise
            if length:
                return pickle.loads(self._read(bytearray(length), deadline))
            self.ticks += 1

    def _read(self, buffer: bytearray, deadline: float) -> bytearray:
        if not read_into(self.process.stdout.fileno(), buffer, deadline):  # type: ignore[union-attr]
            raise _WorkerDied(f"worker process ended (exit status {self.process.wait()})")
        return buffer

    def close(self, kill: bool = False) -> None:
        if kill:
            self.process.kill()
        else:
            try:
                self.process.stdin.close()  # type: ignore[union-attr]
            except OSError:
                pass
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self.process.stdout.close()  # type: ignore[union-attr]


_lock = threading.Lock()
_idle: list[_Worker] = []


def _take() -> _Worker:
    with _lock:
        if _idle:
            return _idle.pop()
    return _Worker()


def _give_back(worker: _Worker) -> None:
    with _lock:
        _idle.append(worker)


def prestart(count: int) -> None:
    """Start worker processes until ``count`` are idle (each starts Python on its own, while the
    caller reads and sorts its model on one core: ~0.2 s of CPU each, no longer on the coding's
    critical path). Nothing when x265 is coded in-process (:func:`enabled`)."""
    if not enabled():
        return
    with _lock:
        missing = count - len(_idle)
    for _ in range(max(0, missing)):
        _give_back(_Worker())


def encode(frames: list, pix_fmt: str, options: dict[str, str], timeout: float | None = None,
           stall: float | None = None) -> bytes:
    """:func:`.hevc.encode_frames` in a worker process, re-run on a fresh worker if one dies or hangs.

    A worker hangs when the whole piece takes over ``timeout`` seconds (:func:`piece_timeout` by
    default) or x265 does not come back for ``stall`` (:func:`stall_timeout`). Errors the encode
    itself raises (x265 refusing settings) come back as they are.
    """
    samples = sum(int(f.size) for f in frames)
    largest = max((int(f.size) for f in frames), default=0)
    failures = []
    for _ in range(ATTEMPTS):
        limit = timeout if timeout is not None else piece_timeout(samples)
        step = stall if stall is not None else stall_timeout(largest)
        worker = _take()
        try:
            status, value = worker.call(frames, pix_fmt, options, limit, step)
        except (_WorkerDied, _Stalled, TimeoutError) as exc:
            failures.append(f"no result after {limit:.0f} s" if isinstance(exc, TimeoutError) else str(exc))
            worker.close(kill=True)
            _say_retry(failures[-1])
            continue
        _give_back(worker)
        if status == "error":
            raise value
        return value
    raise X265WorkerError(f"x265 failed in its worker process {ATTEMPTS} times: {'; '.join(failures)}")


def piece_timeout(samples: int, load: float | None = None, cores: int | None = None) -> float:
    """Seconds a piece of ``samples`` may take before its worker is thought hung: BASE_TIMEOUT plus
    PER_SAMPLE each, stretched by the 1-minute load per core above 1 (``load``, ``cores``: the
    machine's by default), so that a loaded machine's slow piece is not taken for a hung one."""
    return (BASE_TIMEOUT + PER_SAMPLE * samples) * _load_factor(load, cores)


def stall_timeout(frame_samples: int, load: float | None = None, cores: int | None = None) -> float:
    """Seconds x265 may take for one step (a frame taken or a packet given) of a piece whose largest
    frame has ``frame_samples``: STALL_BASE plus PER_SAMPLE each, stretched like :func:`piece_timeout`."""
    return (STALL_BASE + PER_SAMPLE * frame_samples) * _load_factor(load, cores)


def _load_factor(load: float | None, cores: int | None) -> float:
    """The 1-minute load per core when above 1, else 1 (``load``, ``cores``: the machine's by default)."""
    load = os.getloadavg()[0] if load is None else load
    cores = (os.cpu_count() or 1) if cores is None else cores
    return max(1.0, load / max(cores, 1))


def _say_retry(reason: str) -> None:
    warnings.warn(f"x265 worker process failed ({reason}): coding the stream again", RuntimeWarning, stacklevel=3)


@atexit.register
def shutdown() -> None:
    """End the idle worker processes (new ones start on the next :func:`encode`)."""
    with _lock:
        workers, _idle[:] = list(_idle), []
    for worker in workers:
        worker.close()
