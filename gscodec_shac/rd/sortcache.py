"""An :class:`~gscodec_shac.codec.pipeline.Encoder` that sorts each distinct cloud once per sweep.

Sorting (PLAS) is a third or more of an encode and depends only on the pruned cloud's
geometry/colour and the rate point's sort settings, which are the same for every SH
method and every Table III rate point. :class:`SortCachingEncoder` stores the grid order
in ``cache_dir/sort-<hash>.npz`` (written atomically, computed under a lock so parallel
workers wait instead of sorting again) and reuses it; the bitstream is byte-identical to
an uncached encode.

This overrides the pipeline's private ``Encoder._grid_order`` step. A public hook in the
pipeline (a precomputed order or a sort cache passed to ``Encoder``) would replace it;
if that method disappears the encoder silently sorts as usual (``sort_cached_`` is None).
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.codec.pipeline import Encoder
from gscodec_shac.rd.cache import file_lock, save_npz

_CACHE_VERSION = "sortcache-1"


def cloud_digest(cloud: GaussianCloud) -> str:
    """SHA-256 of the arrays sorting can look at (means, scales, quaternions, opacities, DC)."""
    digest = hashlib.sha256(str(cloud.num_gaussians).encode())
    for array in (cloud.means, cloud.scales, cloud.quats, cloud.opacities, cloud.sh_dc):
        digest.update(np.ascontiguousarray(array, dtype=np.float32).tobytes())
    return digest.hexdigest()


class SortCachingEncoder(Encoder):
    """:class:`Encoder` whose grid order is cached in ``cache_dir`` (None: no caching).

    After :meth:`encode`: ``sort_cached_`` (True when the order came from the cache, None
    when caching was off or unavailable) and ``sort_seconds_`` (seconds the sort took when
    it was computed, whether now or by an earlier run).
    """

    def __init__(self, *args: Any, cache_dir: str | Path | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.cache_dir = Path(cache_dir) if cache_dir is not None else None
        self.sort_cached_: bool | None = None
        self.sort_seconds_: float | None = None

    def _grid_order(self, cloud: GaussianCloud):  # type: ignore[override]
        parent = getattr(super(), "_grid_order", None)
        if parent is None:  # pragma: no cover - the pipeline changed shape
            raise AttributeError("Encoder._grid_order is gone; SortCachingEncoder needs updating")
        if self.cache_dir is None:
            tic = time.perf_counter()
            result = parent(cloud)
            self.sort_seconds_ = time.perf_counter() - tic
            return result
        spec = json.dumps(self.rate_point.sort.to_json(), sort_keys=True)
        key = hashlib.sha256(f"{_CACHE_VERSION}|{cloud_digest(cloud)}|{spec}".encode()).hexdigest()[:20]
        path = self.cache_dir / f"sort-{key}.npz"
        with file_lock(self.cache_dir / f"sort-{key}.lock"):
            if path.is_file():
                try:
                    with np.load(path, allow_pickle=False) as data:
                        shape = tuple(int(v) for v in data["shape"])
                        order = data["order"].astype(np.int64)
                        dropped, policy = int(data["dropped"]), str(data["policy"])
                        seconds = float(data["seconds"])
                    self.sort_cached_, self.sort_seconds_ = True, seconds
                    return shape, order, dropped, policy
                except (OSError, KeyError, ValueError):
                    pass  # unreadable entry: sort again and overwrite it
            tic = time.perf_counter()
            shape, order, dropped, policy = parent(cloud)
            seconds = time.perf_counter() - tic
            save_npz(path, shape=np.asarray(shape, np.int64), order=np.asarray(order, np.int64),
                     dropped=np.asarray(dropped), policy=np.asarray(policy), seconds=np.asarray(seconds))
        self.sort_cached_, self.sort_seconds_ = False, seconds
        return shape, order, dropped, policy
