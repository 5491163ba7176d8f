"""The x265 worker process of :mod:`.x265_processes`: encodes the pieces it reads on stdin.

Each request is a length-prefixed pickle ``([(shape, dtype), ...], pix_fmt, options)``
followed by each frame's samples (C order), read straight into its array; each reply a
length-prefixed pickle ``("ok", stream bytes)`` or ``("error", exception)``. The process
ends quietly when its stdin closes or its reader is gone (the caller ended or was killed);
it ignores SIGINT (a Ctrl-C reaches the whole process group: the caller handles it and closes
the pipes). Its file descriptor 1 is pointed at stderr, so nothing a library prints can
corrupt the replies.
"""

from __future__ import annotations

import os
import pickle
import signal
import struct
import sys

import numpy as np

_LENGTH = struct.Struct("<Q")


def _read_exactly(fd: int, size: int) -> bytes | None:
    parts, got = [], 0
    while got < size:
        data = os.read(fd, min(size - got, 1 << 22))
        if not data:
            return None
        parts.append(data)
        got += len(data)
    return b"".join(parts)


def _read_into(fd: int, array: np.ndarray) -> bool:
    """Fill ``array`` from ``fd``; False at end of input."""
    view, got = memoryview(array).cast("B"), 0
    while got < len(view):
        count = os.readv(fd, [view[got:]])
        if not count:
            return False
        got += count
    return True


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def main() -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    requests = sys.stdin.fileno()
    replies = os.dup(sys.stdout.fileno())
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())

    from gscodec_shac.codec.grid.hevc import encode_frames

    while (head := _read_exactly(requests, _LENGTH.size)) is not None:
        payload = _read_exactly(requests, _LENGTH.unpack(head)[0])
        if payload is None:
            break
        layout, pix_fmt, options = pickle.loads(payload)
        frames = [np.empty(shape, dtype=np.dtype(dtype)) for shape, dtype in layout]
        if not all(_read_into(requests, frame) for frame in frames):
            break
        try:
            reply: tuple = ("ok", encode_frames(frames, pix_fmt, options))
        except Exception as exc:  # sent back and raised in the caller
            reply = ("error", exc)
        data = pickle.dumps(reply, protocol=pickle.HIGHEST_PROTOCOL)
        try:
            _write_all(replies, _LENGTH.pack(len(data)) + data)
        except OSError:  # the caller is gone (BrokenPipeError) or its pipe broke: nothing to answer
            return 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
