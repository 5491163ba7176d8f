"""The SH stage alone with and without the cameras' view metric (rate controller version 18).

Fits the rate controller without the metric, takes its plan at ``--bpg`` and, with every other
setting fixed, codes the SH features at each water-filling base of ``--bases`` with SHAC-PCA fitted
three ways: the paper's (no metric), in the controller's view metric (footprint-weighted, cameras
that frame the Gaussian) and in the unweighted metric of the camera centres. PSNR against the
uncompressed model on the held-out cameras (every ``--test-every``-th) and on the controller's own
views; prints the BD-rates of the whole file and of the SH bytes against the paper's, and writes
one CSV row per encode (docs/rate_control.md, "Controller version 18").

With ``--ladder ER`` it codes the fixed points ``shac_ladder:rp1``-``rp9`` with SHAC-PCA at that
energy retention instead (what ``gscodec-shac encode IN OUT --cameras C`` does to the default encode);
with ``--time-metric`` it only times the metric the controller computes (docs/benchmarks.md).

    python scripts/sh_view_metric.py ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply \\
        --cameras ../shared/data/scenes/bonsai_cpu_sh3/cameras.json --test-every 8 --csv bonsai.csv
    python scripts/sh_view_metric.py ... --ladder 0.99
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
from tqdm import tqdm

from gscodec_shac.codec import rate_control as rc_module
from gscodec_shac.codec.decoder import Decoder
from gscodec_shac.codec.encoder import Encoder
from gscodec_shac.codec.rate_points import load_rate_point
from gscodec_shac.errors import GscodecError
from gscodec_shac.rd.bd import bd_rate
from held_out_scene import HeldOutScene, add_scene_arguments, write_rows
from gscodec_shac.shac.view_metric import IDENTITY_SHARE, cloud_view_metric, footprints, view_metric


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, bpg=75.0, model="an SH-3 model (PLY)",
                        cameras="the scene's cameras (the metric needs them)")
    parser.add_argument("--bases", type=float, nargs="+", default=[8, 12, 16, 20, 24, 28, 32])
    parser.add_argument("--identity-share", type=float, default=IDENTITY_SHARE,
                        help=f"the identity's share in the metrics (default {IDENTITY_SHARE})")
    parser.add_argument("--ladder", type=float, metavar="ER",
                        help="code shac_ladder:rp1-rp9 with SHAC-PCA at this energy retention instead")
    parser.add_argument("--time-metric", action="store_true",
                        help="only time the controller's metric of the training cameras (median of 5) and stop")
    args = parser.parse_args()
    try:
        scene = HeldOutScene.from_arguments(args)
        cloud, train, background = scene.cloud, scene.train, scene.background
        if args.time_metric:
            seconds = []
            for _ in range(5):
                tic = time.perf_counter()
                cloud_view_metric(cloud, train)
                seconds.append(time.perf_counter() - tic)
            print(f"view metric of {cloud.num_gaussians:,} Gaussians and {len(train)} cameras: "
                  f"median {statistics.median(seconds):.3f} s of 5 ({min(seconds):.3f}-{max(seconds):.3f})")
            return
        controller = rc_module.RateController(cloud, views=train, background=background, workers=2,
                                              view_metric=False).fit()
    except (GscodecError, OSError, ValueError) as exc:
        sys.exit(f"error: {exc}")
    if args.ladder is None:
        settings = controller.encode(rc_module.Target("bytes", args.bpg * cloud.num_gaussians / 8)).plan.settings
        print("plan", settings)
        steps = [(base, controller._rate_point(dict(settings, sh=base))) for base in args.bases]
    else:
        steps = [(index, load_rate_point(f"shac_ladder:rp{index}").with_overrides(
            sh_stage="pca", sh_params={"energy_retention": args.ladder})) for index in range(1, 10)]
    references = scene.references()
    weights = footprints(cloud.scales, cloud.activated_opacities())
    metrics = {
        "paper": None,
        "view metric": view_metric(cloud.means, train, cloud.sh_degree, footprints=weights,
                                   identity_share=args.identity_share),
        "unweighted centres": view_metric(cloud.means, np.array([c.center for c in train]), cloud.sh_degree,
                                          identity_share=args.identity_share),
    }
    rows = []
    with tqdm(total=len(metrics) * len(steps), desc="SH curves", unit="encode") as bar:
        for name, metric in metrics.items():
            stage = rc_module.fitted_stage(controller.template, cloud, metric)
            for base, point in steps:
                if args.ladder is None:
                    encoder = Encoder(point, sh_stage=stage, fit_stage=False, workers=2,
                                      importance=controller.importance_)
                else:  # the stage fitted with the rate point's energy retention, as an encode does
                    encoder = Encoder(point, workers=2, sh_metric=metric)
                stream = encoder.encode(cloud)
                sizes = stream.attribute_sizes()
                data = stream.to_bytes()
                decoded = Decoder().decode(data)
                step = "base" if args.ladder is None else "rate_point"
                rows.append({"variant": name, step: base, "bytes": len(data),
                             "sh_bytes": sizes.get("sh", 0) + sizes.get("sh_state", 0),
                             "psnr_held_out": scene.mean_psnr(decoded, references),
                             "psnr_controller_views": controller.measured_psnr(stream)})
                bar.update(1)
    write_rows(args.csv, rows)
    paper = [r for r in rows if r["variant"] == "paper"]
    for name in list(metrics)[1:]:
        other = [r for r in rows if r["variant"] == name]
        parts = []
        for quality in ("psnr_held_out", "psnr_controller_views"):
            for rate in ("bytes", "sh_bytes"):
                value = bd_rate([r[rate] for r in paper], [r[quality] for r in paper],
                                [r[rate] for r in other], [r[quality] for r in other]).value
                parts.append(f"{quality} {rate} {value:+.2f}%")
        print(f"{name} vs paper: " + ", ".join(parts))


if __name__ == "__main__":
    main()
