"""``gscodec-shac demo``: the README's main job, end to end on a scene made in code.

Generates the built-in synthetic SH-3 scene, encodes it at four points of the SHAC rate
ladder (about 40 to 220 bits per Gaussian) with the baseline codec (every SH AC coefficient
coded) and with SHAC-PCA at 97% energy retention, and with SHAC-auto (the rate controller)
at four sizes in the same range, decodes, renders the held-out orbit views (every 8th),
scores them against ground truth (the same scene generated without the white SH noise
that mimics optimisation noise) and against the uncompressed model's renders, and
writes the RD plot, the BD-rate table (Markdown and JSON) and the per-run results into
OUT_DIR. It is an RD sweep (:mod:`gscodec_shac.rd`) with a fixed specification, so a
repeated call reuses finished runs.

To stay within a few minutes on a busy 2-core machine it codes with x265's ``medium``
preset (``--preset``; the rate points' own is ``slow``, about 2-3x slower) and 30,000
Gaussians.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

from gscodec_shac.commands._options import add_command, add_output, add_quiet

RATE_POINTS = ["shac_ladder:rp1", "shac_ladder:rp3", "shac_ladder:rp5", "shac_ladder:rp7"]
#: Sizes (bits per Gaussian) SHAC-auto is asked for: the range the ladder points span.
AUTO_TARGETS = [40, 75, 130, 220]


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "demo",
        help="end-to-end demo: synthetic scene, baseline vs SHAC-PCA and SHAC-auto, RD plot + BD-rate",
        description="Generate the synthetic SH-3 scene, code it with the baseline and SHAC-PCA (ER 0.97) at four "
        "points of the SHAC rate ladder and with SHAC-auto at four sizes, render the held-out views and write the "
        "RD plot and the BD-rate table into OUT_DIR (default demo-output). A repeated call reuses finished runs.",
        examples=["gscodec-shac demo demo-output"],
    )
    add_output(parser, "OUT_DIR", "output directory (created; reused to resume; default demo-output)",
               default="demo-output", required=False)
    parser.add_argument("-n", "--num-gaussians", type=int, default=30_000, metavar="N",
                        help="Gaussians in the scene, 1000-1000000 (default 30000)")
    parser.add_argument("--preset", default="medium",
                        help="x265 speed preset (default medium; the rate points use slow)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the synthetic scene (default 0)")
    parser.add_argument("--workers", type=int, default=2, metavar="N", help="runs executing at once (default 2)")
    parser.add_argument("--force", action="store_true", help="recompute finished runs; use a folder that holds "
                        "other files")
    add_quiet(parser)
    parser.set_defaults(func=run)


def demo_sweep(n: int, seed: int, preset: str | None = "medium") -> dict[str, Any]:
    """The demo's sweep specification (a plain dict, validated by :func:`parse_sweep`)."""
    return {
        "name": "demo",
        "description": "synthetic SH-3 scene, baseline vs SHAC-PCA (ER 0.97) and SHAC-auto, SHAC rate ladder",
        "rate_points": RATE_POINTS,
        "settings": {"anchor": "baseline", "preset": preset},
        "scenes": [{
            "name": "synthetic",
            "synthetic": {"n": n, "seed": seed, "n_cameras": 32, "width": 320, "height": 240},
            "test_every": 8,
        }],
        "methods": ["baseline", {"name": "shac-pca-er0.97", "recipe": "pca", "energy_retention": 0.97},
                    {"name": "shac-auto", "recipe": "auto", "bpg": AUTO_TARGETS}],
    }


def run(args: argparse.Namespace) -> int:
    import json
    import time

    from gscodec_shac.errors import GscodecError
    from gscodec_shac.atomic import write_atomic
    from gscodec_shac.rd.cache import DURABLE
    from gscodec_shac.rd.report import bd_markdown, bd_table, short_rate_point, write_report
    from gscodec_shac.rd.spec import parse_sweep
    from gscodec_shac.rd.sweep import run_sweep

    if not 1_000 <= args.num_gaussians <= 1_000_000:
        raise GscodecError(f"--num-gaussians must be 1000-1000000, got {args.num_gaussians}")
    if args.workers < 1:
        raise GscodecError(f"--workers must be at least 1, got {args.workers}")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from gscodec_shac.commands._options import check_results_folder

    tic = time.perf_counter()
    out = Path(args.out)
    check_results_folder(out, args.force)
    spec = parse_sweep(demo_sweep(args.num_gaussians, args.seed, args.preset), source="demo")
    executor = "serial" if args.workers == 1 else "local"
    outcome = run_sweep(spec, out, executor=executor, workers=args.workers, force=args.force, progress=not args.quiet)
    paths = write_report(out, out / "report", title="gscodec-shac demo: baseline vs SHAC on the synthetic scene")
    table = bd_table(outcome.rows, "baseline")
    bd_md = "\n".join(["# BD-rates of SHAC-PCA (ER 0.97) and SHAC-auto against the baseline, synthetic scene", ""]
                      + bd_markdown(table, "synthetic")) + "\n"
    write_atomic(out / "bd_table.md", bd_md, **DURABLE)
    write_atomic(out / "bd_table.json", json.dumps(table, indent=1) + "\n", **DURABLE)

    print()
    print(f"{'method':<17}{'point':<6}{'MB':>7}{'bits/G':>8}{'PSNR gt':>9}{'SSIM gt':>9}{'PSNR ref':>9}{'enc s':>7}")
    for row in outcome.rows:
        if row.get("status") != "ok":
            print(f"{row['method']:<17}{short_rate_point(row['rate_point']):<6}  {row['status']}: {row.get('error')}")
            continue
        print(f"{row['method']:<17}{short_rate_point(row['rate_point']):<6}{row['bytes'] / 1e6:>7.3f}"
              f"{row['bits_per_gaussian']:>8.1f}{_num(row.get('psnr_gt')):>9.2f}{_num(row.get('ssim_gt')):>9.4f}"
              f"{_num(row.get('psnr_ref')):>9.2f}{row['encode_s']:>7.1f}")
    first = next((r for r in outcome.rows if r.get("status") == "ok"), {})
    print(f"uncompressed model: {_num(first.get('uncompressed_bytes')) / 1e6:.2f} MB, PSNR gt "
          f"{_num(first.get('uncompressed_psnr_gt')):.2f} dB, SSIM gt {_num(first.get('uncompressed_ssim_gt')):.4f}")
    print("(gt: the noise-free synthetic scene's renders; ref: the uncompressed model's renders; "
          f"{first.get('n_views', '?')} held-out orbit views)")
    for entry in table:
        if entry["metric"] in ("psnr_gt", "psnr_ref"):
            against = "ground truth" if entry["metric"] == "psnr_gt" else "the uncompressed model"
            same = (f"{entry['size_change_pct']:+.1f}% bytes and {entry['quality_change']:+.2f} dB at equal rate point"
                    if entry["size_change_pct"] is not None else "no common rate point")
            rate = (f"BD-rate {entry['bd_rate_pct']:+.1f}%" if entry["bd_rate_pct"] is not None
                    else "BD-rate undefined (the PSNR ranges do not overlap)")
            gain = f"BD-PSNR {entry['bd_quality']:+.2f} dB" if entry["bd_quality"] is not None else "BD-PSNR undefined"
            notes = [n for n in entry["note"].split("; ") if "monotone hulls" in n or "disagree" in n]
            print(f"{entry['method']} vs baseline, PSNR against {against}: {same}; {rate}; {gain}"
                  + "".join(f" ({n})" for n in notes))
    figure = paths.get("figure:synthetic")
    print(f"RD plot: {figure}" if figure else "RD plot: none (no finished runs)")
    print(f"BD table: {out / 'bd_table.md'}; results: {out / 'results.csv'}; report: {paths['markdown']}")
    print(f"open in a browser: {paths['html']} (RD plots, BD table, decoded renders next to the uncompressed one)")
    print(f"demo finished in {time.perf_counter() - tic:.0f} s "
          f"({outcome.executed} runs executed, {outcome.reused} reused)")
    return 1 if outcome.failed else 0


def _num(value: Any) -> float:
    return float(value) if isinstance(value, (int, float)) else float("nan")
