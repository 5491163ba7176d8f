"""How closely ``--target-psnr`` lands: one rate-controller fit, then each target (docs/rate_control.md).

The same choices and bytes as ``gscodec-shac encode MODEL OUT.gsc --target-psnr T --cameras
CAMERAS``, fitted once for all targets. One JSON line per target: the PSNR reached (against the
uncompressed model on the controller's views), the encodes it took, bits per Gaussian and each
encode's measured PSNR and bytes.

    python scripts/psnr_targets.py ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply \\
        ../shared/data/scenes/bonsai_cpu_sh3/cameras.json --targets 35,37.5,40,42.5,45
"""

from __future__ import annotations

import argparse
import json
import time

from gscodec_shac.codec.rate_control import PSNR_WINDOW, RateController, Target
from gscodec_shac.io.cameras import load_cameras
from gscodec_shac.io.models import read_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", help="a model file (PLY, SPZ, ...)")
    parser.add_argument("cameras", help="a camera file (the controller's views)")
    parser.add_argument("--targets", default="35,40,45", help="comma-separated PSNR targets in dB")
    parser.add_argument("--background", default="0,0,0", help="r,g,b in [0, 1] (1,1,1 for NeRF-synthetic)")
    args = parser.parse_args()
    cloud, _ = read_model(args.model)
    background = tuple(float(v) for v in args.background.split(","))
    tic = time.perf_counter()
    controller = RateController(cloud, views=load_cameras(args.cameras), background=background).fit()
    fit_seconds = time.perf_counter() - tic
    landed = 0
    for value in (float(v) for v in args.targets.split(",")):
        tic = time.perf_counter()
        outcome = controller.encode(Target("psnr", value))
        size = outcome.stream.total_bytes()
        inside = value <= outcome.measured_psnr <= value + PSNR_WINDOW
        landed += inside
        print(json.dumps({"target": value, "psnr": round(outcome.measured_psnr, 3), "in_window": inside,
                          "encodes": outcome.encodes, "bytes": size, "bits_per_gaussian": round(8 * size / cloud.num_gaussians, 1),
                          "trials": [[round(t["measured_psnr"], 2), t["bytes"], t["chunks_coded"]] for t in outcome.trials],
                          "chunks_coded": sum(t["chunks_coded"] for t in outcome.trials),
                          "seconds": round(time.perf_counter() - tic, 1), "fit_seconds": round(fit_seconds, 1)}), flush=True)
    print(f"{landed} of {len(args.targets.split(','))} targets in the window")


if __name__ == "__main__":
    main()
