"""The x265 worker process of :mod:`.x265_processes`: encodes the pieces it reads on stdin.

Each request is a length-prefixed pickle ``([(shape, dtype), ...], pix_fmt, options)``
followed by each frame's samples (C order), read straight into its array; each reply a
length-prefixed pickle ``("ok", stream bytes)`` or ``("error", exception)``, after a
:data:`.TICK` (an empty message) each time x265 takes a frame or gives back a packet. The process
ends quietly when its stdin closes or its reader is gone (the caller ended or was killed);
it ignores SIGINT (a Ctrl-C reaches the whole process group: the caller handles it and closes
the pipes). Its file descriptor 1 is pointed at stderr, so nothing a library prints can
corrupt the replies.
"""

from __future__ import annotations

import os
import pickle
import signal
import sys

import numpy as np

from gscodec_shac.codec.grid.x265_processes import LENGTH, TICK, read_into


def _read_message(fd: int) -> bytearray | None:
    """One length-prefixed message; None at end of input."""
    head = bytearray(LENGTH.size)
    if not read_into(fd, head):
        return None
    body = bytearray(LENGTH.unpack(head)[0])
    return body if read_into(fd, body) else None


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

    while (payload := _read_message(requests)) is not None:
        layout, pix_fmt, options = pickle.loads(payload)
        frames = [np.empty(shape, dtype=np.dtype(dtype)) for shape, dtype in layout]
        if not all(read_into(requests, frame) for frame in frames):
            break
        try:
            reply: tuple = ("ok", encode_frames(frames, pix_fmt, options, progress=lambda: _write_all(replies, TICK)))
        except OSError:  # a tick found the caller gone (BrokenPipeError) or its pipe broken
            return 0
        except Exception as exc:  # sent back and raised in the caller
            reply = ("error", exc)
        data = pickle.dumps(reply, protocol=pickle.HIGHEST_PROTOCOL)
        try:
            _write_all(replies, LENGTH.pack(len(data)) + data)
        except OSError:  # the caller is gone (BrokenPipeError) or its pipe broke: nothing to answer
            return 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
