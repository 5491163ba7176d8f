"""Sort each distinct cloud once per sweep: a file cache of :class:`~gscodec_shac.codec.GridOrder`.

Sorting (PLAS) is a third or more of an encode and depends only on the cloud and the
rate point's sort and prune settings, which are the same for every SH method and every
Table III rate point. :func:`cached_grid_order` stores the encoder's
:meth:`~gscodec_shac.codec.Encoder.grid_order` in ``cache_dir/sort-<hash>.npz`` (written
atomically, computed under a lock so parallel workers wait instead of sorting again);
``encoder.encode(cloud, grid=order)`` then gives the same bytes as an uncached encode.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np

from gscodec_shac.codec import Encoder, GridOrder
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.atomic import write_npz
from gscodec_shac.rd.cache import DURABLE, file_lock

_CACHE_VERSION = "sortcache-3"


def cloud_digest(cloud: GaussianCloud) -> str:
    """SHA-256 of the arrays sorting and pruning look at (means, scales, quaternions, opacities, DC)."""
    digest = hashlib.sha256(str(cloud.num_gaussians).encode())
    for array in (cloud.means, cloud.scales, cloud.quats, cloud.opacities, cloud.sh_dc):
        digest.update(np.ascontiguousarray(array, dtype=np.float32).tobytes())
    return digest.hexdigest()


def cached_grid_order(encoder: Encoder, cloud: GaussianCloud, cache_dir: str | Path) -> tuple[GridOrder, bool, float]:
    """``encoder.grid_order(cloud)``, from ``cache_dir`` when an earlier run computed it.

    Returns the order, whether it came from the cache, and the seconds the sort took
    when it was computed (now or by the earlier run).
    """
    cache_dir = Path(cache_dir)
    settings = json.dumps(encoder.rate_point.grid_settings(), sort_keys=True)
    key = hashlib.sha256(f"{_CACHE_VERSION}|{cloud_digest(cloud)}|{settings}".encode()).hexdigest()[:20]
    path = cache_dir / f"sort-{key}.npz"
    with file_lock(cache_dir / f"sort-{key}.lock"):
        if path.is_file():
            try:
                with np.load(path, allow_pickle=False) as data:
                    grid = GridOrder(tuple(int(v) for v in data["shape"]), data["order"].astype(np.int64),
                                     int(data["dropped"]), str(data["policy"]))
                    return grid, True, float(data["seconds"])
            except (OSError, KeyError, ValueError):
                pass  # unreadable entry: sort again and overwrite it
        tic = time.perf_counter()
        grid = encoder.grid_order(cloud)
        seconds = time.perf_counter() - tic
        write_npz(path, {"shape": np.asarray(grid.shape, np.int64), "order": np.asarray(grid.order, np.int64),
                         "dropped": np.asarray(grid.dropped), "policy": np.asarray(grid.policy),
                         "seconds": np.asarray(seconds)}, **DURABLE)
    return grid, False, seconds
