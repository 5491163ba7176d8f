"""CPU of an encode's grid placement (``Encoder.grid_order``: features, Morton start, PLAS) under
one or more checkouts, alternating, each in a fresh process, with the order's sha256.

    python scripts/time_grid_order.py ../out/lead/bench_final/1M/s1M.ply . ../main \
        --rate-point paper_table3:rp2 --threads 1 --repeat 2

Each process loads the model, sorts once untimed on a 300-Gaussian cloud (numba's kernels load),
then times ``grid_order`` of the model (CPU of the process: all numba threads). ``--wait-policy``
sets ``OMP_WAIT_POLICY`` for every process (``unset``: as the environment has it), so checkouts that
set it themselves and ones that do not are compared under the same policy.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

CHILD = """
import hashlib, sys, time
import numpy as np
from gscodec_shac.codec.encoder import Encoder
from gscodec_shac.io.ply import read_ply
cloud = read_ply(sys.argv[1])
encoder = Encoder(sys.argv[2], "pca")
encoder.grid_order(cloud.select(np.arange(min(300, cloud.num_gaussians))))
cpu, wall = time.process_time(), time.perf_counter()
grid = encoder.grid_order(cloud)
cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
sha = hashlib.sha256(np.ascontiguousarray(grid.order, np.int64).tobytes()).hexdigest()[:16]
print(f"{cpu:.2f} {wall:.2f} {sha}")
"""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ply", type=Path)
    parser.add_argument("checkouts", type=Path, nargs="+", help="repository folders, each first on PYTHONPATH")
    parser.add_argument("--rate-point", default="paper_table3:rp2")
    parser.add_argument("--threads", type=int, default=2, help="NUMBA_NUM_THREADS")
    parser.add_argument("--wait-policy", default="PASSIVE", help="OMP_WAIT_POLICY (PASSIVE, ACTIVE or unset)")
    parser.add_argument("--repeat", type=int, default=1)
    args = parser.parse_args()
    for round_ in range(args.repeat):
        order = args.checkouts if round_ % 2 == 0 else args.checkouts[::-1]
        for checkout in order:
            env = {**os.environ, "PYTHONPATH": str(checkout.resolve()), "NUMBA_NUM_THREADS": str(args.threads)}
            env.pop("OMP_WAIT_POLICY", None)
            if args.wait_policy != "unset":
                env["OMP_WAIT_POLICY"] = args.wait_policy
            load = os.getloadavg()[0]
            # cwd = the checkout: ``python -c`` puts the working directory first on sys.path
            out = subprocess.run([sys.executable, "-c", CHILD, str(args.ply.resolve()), args.rate_point], env=env,
                                 cwd=checkout, capture_output=True, text=True, check=True).stdout.split()
            print(f"{str(checkout):>12}  cpu {out[0]:>6} s  wall {out[1]:>6} s  order {out[2]}  load {load:.1f}",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
