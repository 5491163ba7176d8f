"""Give freed heap memory back to the operating system promptly (glibc only).

glibc keeps up to ``M_TRIM_THRESHOLD`` bytes of freed memory at the top of each heap
and raises its threshold for ``mmap`` as large blocks are freed, so a process that
allocates and frees many blocks of a few MB (video frames, row blocks, worker threads'
arenas) keeps memory it no longer uses: a 4M-Gaussian decode peaked 0.48 GB higher than
with a trim threshold of 0 (docs/benchmarks.md, issue 25). :func:`trim_freed_memory`
sets that threshold to 0 for this process. It changes no result, only when memory is
returned, and what that costs: with the threshold set, glibc stops raising its ``mmap``
threshold, so every block of 128 kB or more is mapped afresh and faulted in page by page
each time it is allocated. A one-pass encode barely notices (a 1M ladder encode: 0.69 against
0.75 GB, 1.4% slower); a run that renders the same cloud over and over does (the calibration of a
1M ``--target-bpg`` run: 15.1-15.6 s against 12.9-13.4 s), and so does a decode since it
dequantises and inverts its SH features in blocks (a 1M decode to PLY: 1.65 against 1.33 s,
0.40 against 0.51 GB peak; 4M: 1.37 against 1.69 GB). :func:`returns_freed_memory` says which
commands the ``gscodec-shac`` command sets it for.
"""

from __future__ import annotations

import argparse
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


def returns_freed_memory(args: argparse.Namespace) -> bool:
    """Whether the command of ``args`` should :func:`trim_freed_memory`: the one-pass commands whose
    peak memory issue 25 bounds (``convert``, an ``encode`` at a rate point), not ``decode`` (its
    peak without the trim, 1.69 GB at 4M, is well inside the 2.5 GB bar, and the trim cost it 20%
    of its time) nor the ones that render a cloud many times (an ``encode`` to a target, ``render``,
    ``rd``, training)."""
    if args.command == "convert":
        return True
    if args.command == "encode":
        return all(getattr(args, name, None) is None for name in ("target_size", "target_bpg", "target_psnr"))
    return False
