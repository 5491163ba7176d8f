"""The rate controller's render sensitivities measured at other probe QPs than its own (30).

Fits the controller (SHAC-auto) once per QP of ``--qps`` with that QP as
``rate_control.SENSITIVITY_QP`` (the probe as decoded at it gives the rendered errors), and prints,
per attribute, the median ratio of the fitted error model at equal settings against the first QP's:
how far the sensitivity changes with the QP (docs/rate_control.md, "Render sensitivities at three
probe QPs"). The controller's views are the cameras that are not held out, as in ``gscodec-shac rd``.

    python scripts/sensitivity_qps.py ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply \\
        --cameras ../shared/data/scenes/bonsai_cpu_sh3/cameras.json --test-every 8
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from gscodec_shac.codec import rate_control
from gscodec_shac.errors import GscodecError
from held_out_scene import HeldOutScene, add_scene_arguments


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, bpg=55.0)
    parser.add_argument("--qps", type=int, nargs="+", default=[30, 18, 42],
                        help="probe QPs (of rate_control.PROBE_QPS); the first is the reference")
    args = parser.parse_args()
    if not set(args.qps) <= set(rate_control.PROBE_QPS):
        sys.exit(f"error: --qps must be among the probe's QPs {rate_control.PROBE_QPS}")
    try:
        scene = HeldOutScene.from_arguments(args)
    except (GscodecError, OSError, ValueError) as exc:
        sys.exit(f"error: {exc}")
    models = {}
    for qp in args.qps:
        rate_control.SENSITIVITY_QP = qp
        controller = rate_control.RateController(scene.cloud, views=scene.train, background=scene.background,
                                                 workers=2).fit()
        models[qp] = controller.models_
    first = args.qps[0]
    print("attribute " + " ".join(f"QP {qp:>2}" for qp in args.qps[1:]) + f"   (model MSE against QP {first}'s)")
    for name, model in models[first].items():
        ratios = [float(np.median(models[qp][name].mse / model.mse)) for qp in args.qps[1:]]
        print(f"{name:9s} " + " ".join(f"{r:5.2f}" for r in ratios))


if __name__ == "__main__":
    main()
