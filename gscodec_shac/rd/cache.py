"""What the sweep's processes share: durable atomic writes and a cross-process lock.

Caches (sort orders, reference renders) and results are written with
:mod:`gscodec_shac.atomic` and :data:`DURABLE` (a reader sees a whole file or none, also
after a crash); a lock file (``fcntl.flock``) makes the first of several workers compute a
cache entry while the others wait for it instead of computing it again.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Iterator


#: How the sweep writes its files: folders created, data on disk before the rename.
DURABLE = {"make_dirs": True, "fsync": True}


@contextlib.contextmanager
def file_lock(path: str | os.PathLike) -> Iterator[None]:
    """Hold an exclusive advisory lock on ``path`` (created) for the ``with`` block."""
    import fcntl

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+b") as handle:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle.fileno(), fcntl.LOCK_UN)
