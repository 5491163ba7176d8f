"""What pruning with recovery restores, on held-out views (docs/rate_control.md, "Pruning with recovery").

For each keep share and step count: the model pruned to its most important share and fine-tuned to
its own renders (:func:`gscodec_shac.train.recover.prune_and_recover`) on the training views (all but
every ``--test-every``-th camera in name order); PSNR on the held-out cameras against the uncompressed
model's renders and, with ``--images``, against the photos. Step 0 is importance pruning alone.

    python scripts/recover_check.py ../outputs/train/lego_train_l3_d45/point_cloud.ply \\
        --cameras ../outputs/train/lego_train_l3_d45/cameras.json --images ../data/nerf_synthetic/lego/train \\
        --background 1,1,1 --shares 0.6,0.45,0.3 --steps 0,200,400 --out recover_lego.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gscodec_shac.camera import test_split  # noqa: E402
from gscodec_shac.io.cameras import load_cameras  # noqa: E402
from gscodec_shac.io.ply import read_ply  # noqa: E402
from gscodec_shac.metrics import load_image, psnr  # noqa: E402
from gscodec_shac.render import Renderer  # noqa: E402
from gscodec_shac.train.recover import prune_and_recover  # noqa: E402


def mean_psnr(images: list[np.ndarray], references: list[np.ndarray]) -> float:
    """Mean over the views of each view's PSNR (:func:`gscodec_shac.metrics.psnr`, as the rd sweep scores)."""
    return float(np.mean([psnr(a, b) for a, b in zip(images, references)]))


def parse_rates(parser: argparse.ArgumentParser, text: str) -> dict[str, float]:
    """``NAME=VALUE,...`` -> {name: value}; a malformed item stops with one argparse error naming it."""
    rates = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        name, _, value = item.partition("=")
        try:
            rates[name.strip()] = float(value)
        except ValueError:
            parser.error(f"--rates: {item!r} is not NAME=VALUE with a number (e.g. lr_opacity=0.015)")
    return rates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("ply")
    parser.add_argument("--cameras", required=True)
    parser.add_argument("--images", help="photos of the cameras (PSNR against them too)")
    parser.add_argument("--background", default="0,0,0")
    parser.add_argument("--test-every", type=int, default=8)
    parser.add_argument("--shares", default="0.6,0.45,0.3")
    parser.add_argument("--steps", default="0,200")
    parser.add_argument("--rates", default="",
                        help="learning rates instead of the recovery's, NAME=VALUE,... (e.g. the reference's: "
                        "lr_means=1.6e-5,lr_means_final=1.6e-6,lr_opacity=0.05,lr_scales=5e-3)")
    parser.add_argument("--out", required=True, help="JSON results")
    args = parser.parse_args()
    rates = parse_rates(parser, args.rates)
    background = tuple(float(v) for v in args.background.split(","))
    cloud = read_ply(args.ply)
    train, test = test_split(load_cameras(args.cameras, args.images), args.test_every)
    model_images = [Renderer(cloud).render(c, background=background).image for c in test]
    photos = ([load_image(c.image_path, background=background, size=(c.width, c.height)) for c in test]
              if args.images else None)
    rows = [{"keep": 1.0, "steps": 0, "kept": cloud.num_gaussians, "psnr_model": math.inf,
             "psnr_photos": mean_psnr(model_images, photos) if photos else None, "seconds": 0.0}]
    for share in (float(v) for v in args.shares.split(",")):
        for steps in (int(v) for v in args.steps.split(",")):
            result = prune_and_recover(cloud, train, keep_share=share, iterations=steps, background=background,
                                       measure=False, progress=False, learning_rates=rates)
            renderer = Renderer(result.cloud)
            images = [renderer.render(c, background=background).image for c in test]
            rows.append({"keep": share, "steps": steps, "kept": result.kept,
                         "psnr_model": mean_psnr(images, model_images),
                         "psnr_photos": mean_psnr(images, photos) if photos else None,
                         "seconds": round(result.seconds, 1)})
            print(json.dumps(rows[-1]), flush=True)
    Path(args.out).write_text(json.dumps({"ply": args.ply, "train_views": len(train), "test_views": len(test),
                                          "learning_rates": rates, "rows": rows}, indent=2))
    print("| keep | steps | Gaussians kept | PSNR vs model (dB) | PSNR vs photos (dB) | seconds |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        photo = f"{r['psnr_photos']:.2f}" if r["psnr_photos"] is not None else "-"
        print(f"| {r['keep']:g} | {r['steps']} | {r['kept']:,} | {r['psnr_model']:.2f} | {photo} | {r['seconds']} |")


if __name__ == "__main__":
    main()
