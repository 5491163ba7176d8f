"""Small-scale paper Table II from ``gscodec-shac train`` runs (docs/training.md).

For one capture, reads the three trained runs (Train-L3-D45, Train-L2-D24, SHAC-LST-L3-D21,
all with the same Gaussians budget and iterations) and adds the paper's post-hoc rows computed
from the Train-L3-D45 model without retraining: Trunc.-L3-D24 (AC up to degree 2), SHAC-PCA-L3-D24
(24 components, eq. 28-29) and SHAC-LST post-hoc D21 (closed-form ridge fit of T, eq. 32-34).
Every model is rendered at the held-out test views (every 8th view, never trained on) and
scored against the capture's photos, loaded exactly as the trainer loads them.

Size (MB) counts float32 parameters as the paper's Table II does: N x (14 + D) x 4 bytes plus
side information (PCA basis + mean + std, LST blocks of T).

    python scripts/table_train.py ../shared/data/scenes/snowmiku_capture \\
        --runs ../outputs/train --prefix snowmiku --images images_8 --json snowmiku_table.json
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from gscodec_shac.gaussians import GaussianCloud  # noqa: E402
from gscodec_shac.io.ply import read_ply  # noqa: E402
from gscodec_shac.metrics import psnr, ssim  # noqa: E402
from gscodec_shac.render import Renderer  # noqa: E402
from gscodec_shac.shac.base import make_stage  # noqa: E402
from gscodec_shac.train.data import load_capture  # noqa: E402

TRAINED = (("train_l3_d45", "Train-L3-D45", "Training"), ("train_l2_d24", "Train-L2-D24", "Training"),
           ("lst_l3_d21", "SHAC-LST-L3-D21", "Training"))
POST_HOC = (("trunc", {"degree": 2}, "Trunc.-L3-D24"), ("pca", {"n_components": 24}, "SHAC-PCA-L3-D24"),
            ("lst", {}, "SHAC-LST-posthoc-L3-D21"))
NON_SH_FLOATS = 14  # position 3, log-scale 3, rotation 4, opacity 1, DC 3


def score(cloud: GaussianCloud, cameras, images, background) -> tuple[float, float]:
    """Mean PSNR and SSIM over the test views."""
    renderer = Renderer(cloud)
    values = [(psnr(im, gt), ssim(im, gt)) for im, gt in
              ((renderer.render(cam, background=background).image, gt) for cam, gt in zip(cameras, images))]
    return float(np.mean([v[0] for v in values])), float(np.mean([v[1] for v in values]))


def size_mb(n: int, ac_dims: int, side_bytes: int = 0) -> float:
    return (n * (NON_SH_FLOATS + ac_dims) * 4 + side_bytes) / 1e6


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("capture", type=Path)
    parser.add_argument("--runs", type=Path, default=Path(__file__).resolve().parents[2] / "outputs" / "train",
                        help="folder of the run folders (default: ../outputs/train beside the repository)")
    parser.add_argument("--prefix", required=True, help="run folders are PREFIX_train_l3_d45 etc.")
    parser.add_argument("--images", default=None, help="image folder inside the capture, as given to train")
    parser.add_argument("--width", type=int, default=None, help="image width, as given to train")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)

    capture = load_capture(args.capture, images=args.images, width=args.width)
    cams, images, bg = capture.test_cameras, capture.test_images, capture.background
    rows = []
    anchor = None
    for suffix, label, category in TRAINED:
        run = args.runs / f"{args.prefix}_{suffix}"
        if not (run / "metrics.json").exists():
            print(f"{label}: no run at {run}, skipped", file=sys.stderr)
            continue
        metrics = json.loads((run / "metrics.json").read_text())
        cloud = read_ply(run / "point_cloud.ply")
        p, s = score(cloud, cams, images, bg)
        sizes = metrics["sizes"]
        side = 4 * int(sizes.get("transform_params", 0))
        rows.append({"category": category, "method": label, "psnr": p, "ssim": s, "n": len(cloud),
                     "ac_dims": sizes["sh_ac_dims"], "size_mb": size_mb(len(cloud), sizes["sh_ac_dims"], side),
                     "iterations": metrics["iterations_done"], "train_s": metrics["train_seconds"],
                     "trainer_psnr": metrics["test"]["mean_psnr"]})
        if suffix == "train_l3_d45":
            anchor = cloud
        print(f"{label}: PSNR {p:.2f} SSIM {s:.4f}", file=sys.stderr)
    if anchor is None:
        raise SystemExit(f"error: the Train-L3-D45 run {args.prefix}_train_l3_d45 is needed for the post-hoc rows")
    for name, params, label in POST_HOC:
        ac = anchor.ac_matrix()
        stage = make_stage(name, **params).fit(ac)
        features = stage.transform(ac)
        rebuilt = anchor.with_ac_matrix(stage.inverse_transform(features).astype(np.float32))
        p, s = score(rebuilt, cams, images, bg)
        side = stage.side_info_bytes()
        rows.append({"category": "Post-hoc", "method": label, "psnr": p, "ssim": s, "n": len(anchor),
                     "ac_dims": int(features.shape[1]), "size_mb": size_mb(len(anchor), int(features.shape[1]), side),
                     "iterations": None, "train_s": None, "trainer_psnr": None})
        print(f"{label}: PSNR {p:.2f} SSIM {s:.4f}", file=sys.stderr)

    command = "python scripts/table_train.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    print(f"Capture `{args.capture.name}`: {len(cams)} held-out test views at {cams[0].width}x{cams[0].height}, "
          f"scored against the photos. Command: `{command}`\n")
    print("| category | method | AC dims | N | size (MB, float32) | PSNR | SSIM | iterations | train s |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        its = f"{r['iterations']:,}" if r["iterations"] else "(from Train-L3-D45)"
        secs = f"{r['train_s']:,.0f}" if r["train_s"] else "-"
        print(f"| {r['category']} | {r['method']} | {r['ac_dims']} | {r['n']:,} | {r['size_mb']:.2f} | "
              f"{r['psnr']:.2f} | {r['ssim']:.4f} | {its} | {secs} |")
    if args.json:
        args.json.write_text(json.dumps({"command": command, "capture": str(args.capture), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
