"""The rate controller with and without importance pruning among its choices, at a few sizes.

Two controllers on the same scene and views (the training cameras, every ``--test-every``-th
held out; orbit views without cameras): one with the default candidates (opacity thresholds and
importance keep shares, :data:`IMPORTANCE_SHARES`), one with the opacity thresholds only. For each
target size (bits per input Gaussian): bytes, the pruning chosen, Gaussians kept, PSNR against the
uncompressed model's renders on the held-out views (and against the photos with ``--images``).

    python scripts/measure_prune_control.py ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply \\
        --cameras ../shared/data/scenes/bonsai_cpu_sh3/cameras.json \\
        --images ../shared/data/scenes/mipnerf360_bonsai/images --bpg 60,90,130 --out ../out/prune/control.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gscodec_shac.camera import orbit_views, test_split  # noqa: E402
from gscodec_shac.codec import Decoder  # noqa: E402
from gscodec_shac.codec.rate_control import IMPORTANCE_SHARES, RateController, make_target  # noqa: E402
from gscodec_shac.io.cameras import load_cameras  # noqa: E402
from gscodec_shac.io.models import read_model  # noqa: E402
from gscodec_shac.metrics import load_image, psnr  # noqa: E402
from gscodec_shac.render import Renderer  # noqa: E402


def renders(cloud, views) -> list[np.ndarray]:
    renderer = Renderer(cloud)
    return [renderer.render(v).image for v in views]


def mean_psnr(images, references) -> float:
    return float(np.mean([psnr(np.clip(a, 0, 1), np.clip(b, 0, 1)) for a, b in zip(images, references)]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--cameras")
    ap.add_argument("--images")
    ap.add_argument("--test-every", type=int, default=8)
    ap.add_argument("--bpg", default="60,90,130")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    cloud, _ = read_model(args.model)
    n = cloud.num_gaussians
    gt = None
    if args.cameras:
        cameras = load_cameras(args.cameras, args.images) if args.images else load_cameras(args.cameras)
        train, test = test_split(cameras, args.test_every)
        if args.images:
            gt = [load_image(c.image_path, size=(c.width, c.height)) for c in test]
    else:
        train, test = None, orbit_views(cloud.means, 12, 320, elevations=(0.0, 25.0),
                                        opacities=cloud.activated_opacities())
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
            if gt is not None:
                row["psnr_gt"] = mean_psnr(images, gt)
            result["rows"].append(row)
            print(json.dumps(row), flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
