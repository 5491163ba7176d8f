"""Atomic file output: write a temporary file in the target folder, then rename it.

A reader sees the whole new file or the old one, never a half-written file, and a failed
write (an exception, Ctrl-C) leaves nothing behind. Every writer of user-facing outputs
(PLY, ``.gsc``, cameras, checkpoints, sweep results) goes through here.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import tempfile
from pathlib import Path
from typing import Any, BinaryIO, Iterator

import numpy as np

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


def write_atomic(path: str | os.PathLike, data: bytes | str, **options: Any) -> Path:
    """Write ``data`` (text as UTF-8) to ``path`` atomically; ``options`` as for :func:`atomic_output`."""
    with atomic_output(path, **options) as handle:
        handle.write(data.encode("utf-8") if isinstance(data, str) else data)
    return Path(path)


def write_json(path: str | os.PathLike, value: Any, **options: Any) -> Path:
    """``value`` as indented JSON (numpy scalars and arrays, paths allowed), written atomically."""
    return write_atomic(path, json.dumps(value, indent=1, default=_json_default) + "\n", **options)


def write_npz(path: str | os.PathLike, arrays: dict[str, np.ndarray], **options: Any) -> Path:
    """``np.savez`` of ``arrays``, written atomically."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return write_atomic(path, buffer.getvalue(), **options)


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")
