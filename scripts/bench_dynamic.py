"""Seconds per iteration of the CPU deformable trainer for two network sizes on one D-NeRF scene.

Runs ``--steps`` iterations with the deformation network active (warm-up 0) from the random
initialisation (``--init-points`` Gaussians, no densification) for each ``DEPTHxWIDTH`` and
reports the median wall and CPU seconds per iteration and the median of each phase. The machine is
shared, so the load average before and after is recorded too.

Example::

    python scripts/bench_dynamic.py ../shared/data/scenes/dnerf/jumpingjacks --json bench_dynamic.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("--archs", nargs="+", default=["4x128", "8x256"])
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--init-points", type=int, default=20_000)
    parser.add_argument("--resolution-scale", type=float, default=0.5)
    parser.add_argument("--json", type=Path, required=True)
    args = parser.parse_args(argv)
    from gscodec_shac.atomic import write_atomic
    from gscodec_shac.train.dynamic import DynamicConfig, DynamicTrainer, load_dnerf_capture

    capture = load_dnerf_capture(args.scene, resolution_scale=args.resolution_scale)
    out = {"scene": args.scene.name, "size": [capture.train_cameras[0].width, capture.train_cameras[0].height],
           "init_points": args.init_points, "steps": args.steps, "load_before": os.getloadavg()[0], "archs": {}}
    for arch in args.archs:
        depth, width = (int(v) for v in arch.split("x"))
        config = DynamicConfig(iterations=10_000, warm_up=0, init_points=args.init_points, depth=depth, width=width,
                               densify_until=0)
        trainer = DynamicTrainer(capture, config)
        trainer.step()  # compile / warm caches
        wall, cpu, phases = [], [], []
        for _ in range(args.steps):
            c0, w0 = time.process_time(), time.perf_counter()
            info = trainer.step()
            wall.append(time.perf_counter() - w0)
            cpu.append(time.process_time() - c0)
            phases.append(info.phases)
        out["archs"][arch] = {
            "network_weights": trainer.net.n_params, "gaussians": trainer.model.num_gaussians,
            "median_wall_s_per_it": float(np.median(wall)), "median_cpu_s_per_it": float(np.median(cpu)),
            "phases": {k: float(np.median([p[k] for p in phases])) for k in phases[0]},
        }
        print(arch, json.dumps(out["archs"][arch]), file=sys.stderr, flush=True)
    out["load_after"] = os.getloadavg()[0]
    write_atomic(args.json, json.dumps(out, indent=1))
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
