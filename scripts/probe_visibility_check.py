"""PSNR targets with and without the probe-visibility weighting (rate control version 11), on a
synthetic scene whose probe is made more visible than the rest of the cloud.

The cloud is ``gscodec-shac synthetic``'s scene of N Gaussians with a probe of ``--probe``
Gaussians; every Gaussian outside the probe's rows has its log-scales lowered by ``--shrink``
(smaller, so less visible), which makes the probe's mean importance 1.3-1.5x the cloud's. For each
target: the PSNR reached, the encodes and the bytes, once with the sensitivities weighed by the
probe's visibility (``"visibility": "weighed"``, version 11 on) and once with it forced to 1
(``"not weighed"``). docs/rate_control.md, "Controller version 11".

    python scripts/probe_visibility_check.py --shrink 0.7,1.2 --targets 33,34,36,38,40
"""

from __future__ import annotations

import argparse
import json

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-n", type=int, default=6000, help="Gaussians of the synthetic scene")
    parser.add_argument("--probe", type=int, default=1000, help="Gaussians of the controller's probe")
    parser.add_argument("--shrink", default="0.7,1.2", help="comma-separated log-scale reductions outside the probe")
    parser.add_argument("--targets", default="33,34,36,38,40", help="comma-separated PSNR targets in dB")
    args = parser.parse_args()

    from gscodec_shac.codec import rate_control as rc
    from gscodec_shac.synthetic import make_synthetic_scene

    scene = make_synthetic_scene(args.n, seed=0, n_cameras=8, width=96, height=72)
    rc.PROBE_MIN = args.probe
    rows = rc._probe_rows(scene.cloud)
    outside = np.ones(scene.cloud.num_gaussians, dtype=bool)
    outside[rows] = False
    measured_visibility = rc.RateController._probe_visibility
    for shrink in (float(v) for v in args.shrink.split(",")):
        scales = scene.cloud.scales.copy()
        scales[outside] -= shrink
        cloud = scene.cloud.replace(scales=scales)
        for label, visibility in (("weighed", measured_visibility), ("not weighed", lambda self, rows: 1.0)):
            rc.RateController._probe_visibility = visibility
            try:
                controller = rc.RateController(cloud, views=scene.cameras, workers=2).fit()
            finally:
                rc.RateController._probe_visibility = measured_visibility
            probe = controller._probe_decoded[0]
            ratio = float(np.mean(controller.importance_[probe]) / np.mean(controller.importance_))
            runs = []
            for target in (float(v) for v in args.targets.split(",")):
                outcome = controller.encode(rc.Target("psnr", target))
                runs.append({"target": target, "psnr": round(outcome.measured_psnr, 2), "encodes": outcome.encodes,
                             "bytes": outcome.stream.total_bytes()})
            print(json.dumps({"shrink": shrink, "visibility": label, "probe_importance_ratio": round(ratio, 3),
                              "encodes": sum(r["encodes"] for r in runs), "runs": runs}), flush=True)


if __name__ == "__main__":
    main()
