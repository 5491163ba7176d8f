"""Seconds per blend (the per-pixel pass of a render) of a model, from prepared frames.

The rate controller's calibration blends the same prepared frame many times (its variants), so
the blend kernel's time per call is what its renders cost beyond the per-Gaussian stages. For
each width this prepares orbit views of the model (``--views`` of them) and times ``--repeat``
blends of each; it prints and writes the median wall and CPU seconds per blend and per prepare.
Run it under two checkouts to compare them (the checkout first on ``PYTHONPATH``):

    PYTHONPATH=. python scripts/bench_blend.py ../out/bench/1M/s1M.ply --widths 192,800 --json blend.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np

from gscodec_shac.camera import orbit_views
from gscodec_shac.io.models import read_model
from gscodec_shac.render import Renderer


def timed(call) -> tuple[float, float]:
    """(wall, CPU) seconds of one ``call()``."""
    wall, cpu = time.perf_counter(), time.process_time()
    call()
    return time.perf_counter() - wall, time.process_time() - cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", help="a model file (e.g. `gscodec-shac synthetic -n 1000000` output)")
    parser.add_argument("--widths", default="192,800", help="comma-separated image widths (orbit views)")
    parser.add_argument("--views", type=int, default=3, help="orbit views per width")
    parser.add_argument("--repeat", type=int, default=5, help="timed blends per view (after one untimed)")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args()
    cloud, _ = read_model(args.model)
    renderer = Renderer(cloud)
    background = np.zeros(3)
    rows = []
    for width in (int(w) for w in args.widths.split(",")):
        blends, prepares = [], []
        for view in orbit_views(cloud.means, args.views, width, up=(0.0, 0.0, 1.0)):
            renderer.prepare(view)  # the first call of a size allocates the workspace
            prepares.append(timed(lambda: renderer.prepare(view)))
            frame = renderer.prepare(view)
            renderer.blend(frame.bins, view, background)
            blends += [timed(lambda: renderer.blend(frame.bins, view, background)) for _ in range(args.repeat)]
        row = {"width": width, "height": view.height, "pairs": frame.bins.n_pairs,
               "blend_wall_s": statistics.median(w for w, _ in blends),
               "blend_cpu_s": statistics.median(c for _, c in blends),
               "prepare_wall_s": statistics.median(w for w, _ in prepares),
               "prepare_cpu_s": statistics.median(c for _, c in prepares)}
        rows.append(row)
        print(f"{width:>5} x {view.height:<5} blend {row['blend_wall_s'] * 1e3:7.1f} ms wall {row['blend_cpu_s'] * 1e3:7.1f}"
              f" ms CPU; prepare {row['prepare_wall_s'] * 1e3:7.1f} ms wall {row['prepare_cpu_s'] * 1e3:7.1f} ms CPU"
              f" ({cloud.num_gaussians:,} Gaussians, {row['pairs']:,} tile entries in the last view)", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"model": str(args.model), "load": os.getloadavg()[0], "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
