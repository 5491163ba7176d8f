"""Give freed heap memory back to the operating system promptly (glibc only).

glibc keeps up to ``M_TRIM_THRESHOLD`` bytes of freed memory at the top of each heap
and raises its threshold for ``mmap`` as large blocks are freed, so a process that
allocates and frees many blocks of a few MB (video frames, row blocks, worker threads'
arenas) keeps memory it no longer uses: a 4M-Gaussian decode peaked 0.48 GB higher than
with a trim threshold of 0 (docs/benchmarks.md, issue 25). :func:`trim_freed_memory`
sets that threshold to 0 for this process; the ``gscodec-shac`` command calls it at
start-up. It changes no result, only when memory is returned.
"""

from __future__ import annotations

import ctypes

#: glibc's ``mallopt`` parameter number of the trim threshold (``<malloc.h>``).
M_TRIM_THRESHOLD = -1


def trim_freed_memory() -> bool:
    """Set glibc's trim threshold to 0 (freed heap tops go back to the system); False without glibc."""
    try:  # the C library already loaded into this process (no library search at start-up)
        mallopt = getattr(ctypes.CDLL(None), "mallopt", None)
    except (OSError, TypeError):
        return False
    if mallopt is None:
        return False
    return bool(mallopt(M_TRIM_THRESHOLD, 0))
