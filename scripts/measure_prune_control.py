"""The rate controller with and without importance pruning among its choices, at a few sizes.

Two controllers on the same scene and views (the training cameras, every ``--test-every``-th
held out; orbit views without cameras): one with the default candidates (opacity thresholds and
importance keep shares, :data:`IMPORTANCE_SHARES`), one with the opacity thresholds only. For each
target size (bits per input Gaussian): bytes, the pruning chosen, Gaussians kept, PSNR against the
uncompressed model's renders on the held-out views (and against the photos with ``--images``).

    python scripts/measure_prune_control.py ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply \\
        --cameras ../shared/data/scenes/bonsai_cpu_sh3/cameras.json \\
        --images ../shared/data/scenes/mipnerf360_bonsai/images --bpg 50,80,120 --out bonsai_control.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

from gscodec_shac.codec import Decoder  # noqa: E402
from gscodec_shac.codec.rate_control import IMPORTANCE_SHARES, RateController, make_target  # noqa: E402
from gscodec_shac.io.models import read_model  # noqa: E402
from measure_prune import mean_psnr, record, renders, save, scene_arguments, scene_views  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    scene_arguments(ap)
    ap.add_argument("--bpg", default="60,90,130")
    args = ap.parse_args()
    cloud, _ = read_model(args.model)
    n = cloud.num_gaussians
    train, test, gt = scene_views(cloud, args.cameras, args.images, args.test_every)
    reference = renders(cloud, test)
    result: dict = {"model": args.model, "n": n, "rows": [], "fit_s": {}}
    for label, shares in (("with importance", IMPORTANCE_SHARES), ("opacity only", ())):
        tic = time.perf_counter()
        controller = RateController(cloud, views=train, importance_shares=shares).fit()
        result["fit_s"][label] = time.perf_counter() - tic
        for bpg in (float(b) for b in args.bpg.split(",")):
            outcome = controller.encode(make_target(n, bpg=bpg))
            decoded = Decoder().decode(outcome.stream.to_bytes())
            images = renders(decoded, test)
            size = outcome.stream.total_bytes()
            row = {"controller": label, "target_bpg": bpg, "bytes": size, "bpg": 8 * size / n,
                   "kept": decoded.num_gaussians, "prune": outcome.plan.rate_point.prune_json(),
                   "settings": outcome.summary()["settings"], "encodes": outcome.encodes,
                   "psnr_ref": mean_psnr(images, reference), "measured_psnr": outcome.measured_psnr}
            record(result, row, images, gt)
    save(result, args.out)


if __name__ == "__main__":
    main()
