"""Rate and test PSNR of a dynamic model's network stored as float16 or quantised (``encode --network-bits``).

For each ``--bits`` value the model is encoded with the same rate point and SH stage
(``gscodec-shac encode MODEL out.gsc -r RATE_POINT --sh pca --er 0.96 --network-bits B``),
decoded, and the decoded model rendered on the scene's test frames
(``gscodec-shac render DEC frames/ --cameras transforms_test.json --resolution-scale S``),
whose ``metrics.json`` gives the mean per-frame PSNR and SSIM against the ground truth; the
8-bit PNG renders are also compared with the float16 variant's (what the quantisation changes
in the picture, apart from how good the model is).
The canonical Gaussians are coded identically in every variant, so the differences are the
network's. Writes a JSON summary and prints one markdown row per variant.

Example::

    python scripts/network_bits.py ../outputs/dynamic/mutant ../shared/data/scenes/dnerf/mutant \\
        --work nb_work --bits 16 8 6 5 4 3 8p 4p --json network_bits.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path


def plain_network(gsc: Path, model: Path, bits: int) -> None:
    """Replace the network chunk of ``gsc`` by ``bits``-bit codes of every matrix by plain rounding
    (the 2.1 form as written before quantisation-aware rounding and 8-bit heads)."""
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.deformation import add_deformation
    from gscodec_shac.deform import load_dynamic_model

    stream = Bitstream.read(gsc)
    stream.chunks = [c for c in stream.chunks if c.name != "deformation"]
    stream.features -= {"deformation_quantised", "deformation_mixed_bits"}
    dynamic = load_dynamic_model(model)
    add_deformation(stream, dynamic.arch, dynamic.net.weights(), bits)
    stream.write(gsc)


def run_variant(model: Path, scene: Path, work: Path, variant: str, args: argparse.Namespace) -> dict:
    from gscodec_shac.cli import main
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.header import read_header

    bits, plain = int(variant.rstrip("p")), variant.endswith("p")
    gsc, dec, frames = work / f"b{variant}.gsc", work / f"b{variant}_dec", work / f"b{variant}_frames"
    tic = time.perf_counter()
    if main(["encode", str(model), str(gsc), "-r", args.rate_point, "--sh", "pca", "--er", str(args.er),
             "--network-bits", str(16 if plain else bits), "-q", "--force"]) != 0:
        raise SystemExit(f"encode failed for {bits} bits")
    if plain:
        plain_network(gsc, model, bits)
    if main(["decode", str(gsc), str(dec), "-q", "--force"]) != 0:
        raise SystemExit(f"decode failed for {bits} bits")
    if main(["render", str(dec), str(frames), "--cameras", str(scene / "transforms_test.json"),
             "--resolution-scale", str(args.resolution_scale), "-q", "--force"]) != 0:
        raise SystemExit(f"render failed for {bits} bits")
    metrics = json.loads((frames / "metrics.json").read_text())
    view = read_header(Bitstream.read(gsc))
    return {"variant": variant, "bits": bits, "plain": plain, "file_bytes": gsc.stat().st_size, "network_bytes": view.chunk_bytes["deformation"],
            "weights": view.deformation.weights, "psnr": metrics["mean"]["psnr"], "ssim": metrics["mean"]["ssim"],
            "seconds": time.perf_counter() - tic}


def psnr_between_renders(a_dir: Path, b_dir: Path) -> tuple[float, float]:
    """(mean, min) PSNR of ``b_dir``'s PNGs against ``a_dir``'s (same names; 8-bit images)."""
    import cv2
    import numpy as np

    values = []
    for a in sorted(a_dir.glob("*.png")):
        x = cv2.imread(str(a)).astype(np.float64) / 255.0
        y = cv2.imread(str(b_dir / a.name)).astype(np.float64) / 255.0
        mse = float(np.mean((x - y) ** 2))
        values.append(99.0 if mse == 0 else -10.0 * np.log10(mse))
    return float(np.mean(values)), float(np.min(values))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("model", type=Path, help="dynamic model directory (or Deformable-3DGS output folder)")
    parser.add_argument("scene", type=Path, help="D-NeRF scene folder (transforms_test.json)")
    parser.add_argument("--work", type=Path, required=True, help="folder for the streams, decodes and renders")
    parser.add_argument("--bits", nargs="+", default=["16", "8", "6", "5", "4", "3", "8p", "4p"],
                        help="variants: 16 (float16), B (what encode --network-bits B writes: quantisation-aware "
                        "rounding, heads at 8 below 8), Bp (every matrix at B bits, plain rounding: format 2.1 as "
                        "written before)")
    parser.add_argument("--rate-point", default="paper_table3:rp2")
    parser.add_argument("--er", type=float, default=0.96)
    parser.add_argument("--resolution-scale", type=float, default=0.5)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()
    rows = [run_variant(args.model, args.scene, args.work, variant, args) for variant in args.bits]
    base = next((r for r in rows if r["bits"] == 16), rows[0])
    print("| network | network chunk (bytes) | vs float16 | file (bytes) | test PSNR (dB) | vs float16 (dB) | SSIM "
          "| renders vs float16's: mean / min PSNR (dB) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        r["psnr_vs_float16"] = r["psnr"] - base["psnr"]
        r["size_ratio_vs_float16"] = base["network_bytes"] / r["network_bytes"]
        r["render_psnr_vs_float16"] = psnr_between_renders(args.work / f"b{base['variant']}_frames",
                                                           args.work / f"b{r['variant']}_frames")
        name = ("float16" if r["bits"] == 16 else f"{r['bits']}-bit, plain rounding" if r["plain"]
                else f"{r['bits']}-bit as `encode` codes it" + (" (heads, time layer 8; after the skip +1)" if r["bits"] < 8 else ""))
        mean, low = r["render_psnr_vs_float16"]
        print(f"| {name} | {r['network_bytes']:,} | {r['size_ratio_vs_float16']:.2f}x smaller | {r['file_bytes']:,} | "
              f"{r['psnr']:.3f} | {r['psnr_vs_float16']:+.3f} | {r['ssim']:.4f} | {mean:.1f} / {low:.1f} |")
    summary = {"model": str(args.model), "scene": str(args.scene), "rate_point": args.rate_point, "er": args.er,
               "load_before": load, "load_after": os.getloadavg(), "rows": rows}
    print(f"load average before {load[0]:.1f}, after {summary['load_after'][0]:.1f}")
    if args.json:
        args.json.write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
