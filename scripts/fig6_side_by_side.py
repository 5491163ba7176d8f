"""Small-scale paper Fig. 6: side-by-side renders of the baseline codec and ours at a similar
size, with residual maps (docs/paper.md).

Per scene: the baseline is our codec with every SH AC coefficient coded (stage ``none``) at one
rate point (default the coarsest Table III point, ``paper_table3:rp1``); ours is the same codec
with a low-rank SH stage at the *largest* rate point whose file is not larger than the
baseline's (so ours is never given more bytes). With ``lst_model`` (a model trained with
``gscodec-shac train --sh lst``) ours codes that model's trained S and T (no refit); the
``snowmiku`` preset uses the LST-trained model for both, so the two files differ only in how the
SH are coded (45 expanded AC coefficients vs the 21 of S). Without one, ours is SHAC-PCA at
ER 0.99 on the baseline's model. Both are decoded, rendered at the held-out views (every 8th in
name order) and scored against the photos; the figure shows one held-out view (``--view``, by
default the first, not chosen by result): photo, the two renders, and |render - photo| x
``--gain``. Writes a PNG (and with ``--json`` every number).

    python scripts/fig6_side_by_side.py --preset bonsai --preset snowmiku --out docs/figures/fig6_side_by_side.png
    python scripts/fig6_side_by_side.py --quick --out /tmp/fig6_quick.png
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from gscodec_shac.camera import test_split  # noqa: E402
from gscodec_shac.codec import Decoder, Encoder  # noqa: E402
from gscodec_shac.gaussians import GaussianCloud  # noqa: E402
from gscodec_shac.metrics import load_image, psnr, ssim  # noqa: E402
from gscodec_shac.render import Renderer  # noqa: E402

RATE_POINTS = ["paper_table3:rp1", "paper_table3:rp2", "paper_table3:rp3", "paper_table3:rp4"]

#: Scenes known to this script (paths relative to the repository root, with ../shared and ../outputs beside it).
PRESETS = {
    "bonsai": {"label": "bonsai_cpu_sh3 (Mip-NeRF 360 bonsai, 75k, 200x133)",
               "ply": "../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply",
               "cameras": "../shared/data/scenes/bonsai_cpu_sh3/cameras.json",
               "images": "../shared/data/scenes/mipnerf360_bonsai/images", "lst_model": None},
    "snowmiku": {"label": "snowmiku (trained as SHAC-LST, 20k, 248x186, 800 iterations)",
                 "ply": "../outputs/paper-doc/lst_ablations/paper/point_cloud.ply",
                 "cameras": "../outputs/paper-doc/lst_ablations/paper/cameras.json",
                 "images": "../shared/data/scenes/snowmiku_capture/images_8",
                 "lst_model": "../outputs/paper-doc/lst_ablations/paper/point_cloud.ply"},
}


@dataclass
class Coded:
    name: str
    rate_point: str
    size: int
    cloud: GaussianCloud


def code(cloud: GaussianCloud, rate_point: str, stage, fit: bool = True, params: dict | None = None
         ) -> tuple[int, GaussianCloud]:
    encoder = Encoder(rate_point, sh_stage=stage, fit_stage=fit, sh_params=params, workers=1)
    data = encoder.encode(cloud).to_bytes()
    return len(data), Decoder(workers=1).decode(data)


def evaluate(cloud: GaussianCloud, cameras, images, background) -> tuple[list[np.ndarray], float, float]:
    renderer = Renderer(cloud)
    renders = [np.clip(renderer.render(c, background=background).image, 0.0, 1.0) for c in cameras]
    return (renders, float(np.mean([psnr(r, g) for r, g in zip(renders, images)])),
            float(np.mean([ssim(r, g) for r, g in zip(renders, images)])))


def scene_panel(name: str, spec: dict, args: argparse.Namespace) -> dict:
    """Code, decode, render and score one scene; returns the numbers and the images of one view."""
    from gscodec_shac.io.cameras import load_cameras
    from gscodec_shac.io.ply import read_ply

    background = (0.0, 0.0, 0.0)
    if spec.get("synthetic"):
        from gscodec_shac.synthetic import make_synthetic_scene

        scene = make_synthetic_scene(spec["synthetic"], seed=0)
        model = scene.cloud
        _, test = test_split(scene.cameras)
        test = test[:3]
        r = Renderer(model)
        images = [np.clip(r.render(c, background=background).image, 0, 1) for c in test]  # "photos" = uncompressed
        lst_cloud = lst_stage = None
    else:
        model = read_ply(spec["ply"])
        _, test = test_split(load_cameras(spec["cameras"], spec["images"]))
        images = [load_image(c.image_path, size=(c.width, c.height)) for c in test]
        lst_cloud = lst_stage = None
        if spec.get("lst_model") and Path(spec["lst_model"]).exists():
            from gscodec_shac.train.finetune import load_finetuned

            lst_cloud, lst_stage = load_finetuned(spec["lst_model"])
    size_b, base = code(model, args.baseline_rp, "none")
    ours = None
    for rp in RATE_POINTS:
        size, cloud = (code(lst_cloud, rp, lst_stage, fit=False) if lst_stage is not None
                       else code(model, rp, "pca", params={"energy_retention": 0.99}))
        if size <= size_b:
            ours = Coded("SHAC-LST (trained)" if lst_stage is not None else "SHAC-PCA ER 0.99", rp, size, cloud)
        else:
            break
    if ours is None:
        raise SystemExit(f"{name}: even {RATE_POINTS[0]} of ours is larger than the baseline at {args.baseline_rp}")
    base_renders, base_psnr, base_ssim = evaluate(base, test, images, background)
    our_renders, our_psnr, our_ssim = evaluate(ours.cloud, test, images, background)
    model_psnr = evaluate(model, test, images, background)[1]
    lst_model_psnr = evaluate(lst_cloud, test, images, background)[1] if lst_cloud is not None else None
    k = min(args.view, len(test) - 1)
    print(f"{name}: baseline {args.baseline_rp} {size_b:,} B {base_psnr:.2f} dB; {ours.name} {ours.rate_point} "
          f"{ours.size:,} B {our_psnr:.2f} dB; view {test[k].name}", flush=True)
    return {
        "scene": name, "label": spec.get("label", name), "view": test[k].name, "n_test_views": len(test),
        "baseline": {"rate_point": args.baseline_rp, "bytes": size_b, "psnr": base_psnr, "ssim": base_ssim,
                     "view_psnr": psnr(base_renders[k], images[k])},
        "ours": {"method": ours.name, "rate_point": ours.rate_point, "bytes": ours.size, "psnr": our_psnr,
                 "ssim": our_ssim, "view_psnr": psnr(our_renders[k], images[k])},
        "uncompressed_psnr": model_psnr, "lst_model_uncompressed_psnr": lst_model_psnr,
        "_images": (images[k], base_renders[k], our_renders[k]),
    }


def figure(panels: list[dict], out: Path, gain: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(panels), 5, figsize=(11, 2.0 * len(panels) + 0.2), squeeze=False)
    for row, p in zip(axes, panels):
        gt, base, ours = p["_images"]
        b, o = p["baseline"], p["ours"]
        cells = [
            (gt, f"{p['scene']}: photo ({p['view']})"),
            (base, f"baseline {b['rate_point'].split(':')[-1]}: {b['bytes'] / 1e6:.2f} MB, {b['view_psnr']:.2f} dB"),
            (ours, f"{o['method']} {o['rate_point'].split(':')[-1]}: {o['bytes'] / 1e6:.2f} MB, {o['view_psnr']:.2f} dB"),
            (np.clip(np.abs(base - gt) * gain, 0, 1), f"|baseline - photo| x{gain:g}"),
            (np.clip(np.abs(ours - gt) * gain, 0, 1), f"|ours - photo| x{gain:g}"),
        ]
        for ax, (image, title) in zip(row, cells):
            ax.imshow(image, interpolation="nearest")
            ax.set_title(title, fontsize=6.5)
            ax.axis("off")
    fig.tight_layout(pad=0.3)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=72)
    plt.close(fig)
    from PIL import Image  # 256 colours keep the PNG near 100 KB (docs/figures stays small)

    Image.open(out).convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT,
                                            dither=Image.Dither.NONE).save(out, optimize=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", action="append", choices=sorted(PRESETS), default=[])
    parser.add_argument("--scene", action="append", default=[], metavar="NAME=PLY,CAMERAS,IMAGES[,LST_PLY]",
                        help="another scene: its PLY, cameras, photo folder and optionally an LST-trained PLY")
    parser.add_argument("--baseline-rp", default="paper_table3:rp1")
    parser.add_argument("--view", type=int, default=0, help="index of the held-out view shown (default 0)")
    parser.add_argument("--gain", type=float, default=4.0, help="residual amplification (default 4)")
    parser.add_argument("--out", type=Path, required=True, help="PNG path")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--quick", action="store_true", help="smoke test on a 5,000-Gaussian synthetic scene")
    args = parser.parse_args(argv)
    specs: list[tuple[str, dict]] = [(p, PRESETS[p]) for p in args.preset]
    for item in args.scene:
        name, _, rest = item.partition("=")
        parts = rest.split(",")
        specs.append((name, {"ply": parts[0], "cameras": parts[1], "images": parts[2],
                             "lst_model": parts[3] if len(parts) > 3 else None}))
    if args.quick:
        specs = [("synthetic-5k", {"synthetic": 5000, "label": "synthetic 5k (vs uncompressed renders)"})]
    if not specs:
        parser.error("give --preset, --scene or --quick")
    panels = [scene_panel(name, spec, args) for name, spec in specs]
    figure(panels, args.out, args.gain)
    if args.json:
        args.json.write_text(json.dumps([{k: v for k, v in p.items() if not k.startswith("_")} for p in panels],
                                        indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
