"""Atomic file output: write a temporary file in the target folder, then rename it.

A reader sees the whole new file or the old one, never a half-written file, and a failed
write (an exception, Ctrl-C) leaves nothing behind. Every writer of user-facing outputs
(PLY, ``.gsc``, cameras, checkpoints, sweep results) goes through here.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Iterator

from gscodec_shac.errors import GscodecError


@contextlib.contextmanager
def atomic_output(
    path: str | os.PathLike, *, error: type[Exception] = GscodecError, make_dirs: bool = False, fsync: bool = False
) -> Iterator[BinaryIO]:
    """A binary handle whose content replaces ``path`` when the block ends without error.

    A missing output folder raises ``error`` naming it, unless ``make_dirs`` creates it;
    ``fsync`` flushes the data to disk before the rename (for caches shared by processes).
    """
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    if make_dirs:
        directory.mkdir(parents=True, exist_ok=True)
    elif not directory.is_dir():
        raise error(f"{path}: output directory {directory} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "wb") as handle:
            yield handle
            if fsync:
                handle.flush()
                os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes, **options) -> Path:
    """Write ``data`` to ``path`` atomically; ``options`` as for :func:`atomic_output`."""
    with atomic_output(path, **options) as handle:
        handle.write(data)
    return Path(path)
