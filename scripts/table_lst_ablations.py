"""Trained SHAC-LST ablations at small scale: paper Tables VII, VIII, IX and Fig. 12-13 (docs/paper.md).

Every variant is *trained* from scratch with ``gscodec-shac train --sh lst`` (S and T learnt
together with the geometry, as the paper does; not a post-hoc fit), all with the same capture,
resolution, Gaussian budget (MCMC), iterations and seed, and evaluated on the held-out views
(every 8th view in name order, never trained on) against the photos. One variant differs from
the paper's model (lowest-degree subset, block-diagonal matrix, joint RGB, zero-initialised T,
lambda_t = 5e-3) in one setting only:

* Table VII: ``--lst-subset highest``;
* Table VIII: ``--lst-operator vector | linear | mlp``;
* Table IX: ``--lst-structure dense``, ``--lst-rgb separate``, ``--lst-init identity``;
* Fig. 12 (subset dimension): ``--sh-degree 2`` (L = 2, d = 15); L = 4 is beyond the trainer (SH 0-3);
* Fig. 13 (scale regulariser): ``--lambda-t 0``.

With ``--seeds`` every variant is trained at each seed and the tables show the mean, each seed,
and the paired difference to the paper's model of the same seed (the seed-to-seed spread is the
yardstick for every difference); a full-SH Train-L3-D45 model with the same schedule is the
anchor, and ``paper_seed1`` is the paper's model at seed 1 (the same run as ``paper`` at seed 1).
Runs are sequential, one thread each, and resumable: a run whose ``metrics.json`` says complete
is read, not retrained (``--retrain`` forces). Results: ``lst_ablations.json`` and
``lst_ablations.md`` in OUT_DIR.

    python scripts/table_lst_ablations.py ../outputs/lst_ablations \\
        --capture ../shared/data/scenes/snowmiku_capture --images images_8 --resolution-scale 0.5 \\
        --iterations 400 --max-gaussians 10000 --seeds 0 1 2 3 --rd
    python scripts/table_lst_ablations.py /tmp/lst_quick --quick     # a smoke run (minutes)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

#: name -> (extra ``train`` flags, tables/figures it belongs to, label)
VARIANTS: dict[str, tuple[list[str], tuple[str, ...], str]] = {
    "paper": ([], ("VII", "VIII", "IX", "Fig12", "Fig13"), "paper's model (lowest, matrix, block, joint, zero, lambda_t 5e-3)"),
    "paper_seed1": (["--seed", "1"], ("seed",), "paper's model, seed 1"),
    "full_l3": (["--sh", "full"], ("anchor",), "Train-L3-D45 (full SH, anchor)"),
    "highest": (["--lst-subset", "highest"], ("VII",), "highest degree l per order m"),
    "vector": (["--lst-operator", "vector"], ("VIII",), "vector operator"),
    "linear": (["--lst-operator", "linear"], ("VIII",), "linear operator (with bias)"),
    "mlp": (["--lst-operator", "mlp"], ("VIII",), "MLP operator (2 hidden layers)"),
    "dense": (["--lst-structure", "dense"], ("IX",), "w/o block-diagonal structure (dense T)"),
    "separate": (["--lst-rgb", "separate"], ("IX",), "w/o RGB joint processing"),
    "identity": (["--lst-init", "identity"], ("IX",), "w/o zero initialisation (identity)"),
    "lambda0": (["--lambda-t", "0"], ("Fig13",), "w/o scale regularisation (lambda_t = 0)"),
    "l2": (["--sh-degree", "2"], ("Fig12",), "L = 2 (d = 15)"),
}

#: The paper's numbers (Tables VII-IX: Tanks and Temples means, PSNR / SSIM / LPIPS).
PAPER = {
    "VII": {"highest": (23.73, 0.851, 0.170), "paper": (23.92, 0.854, 0.168)},
    "VIII": {"vector": (24.13, 0.858, 0.159), "linear": (24.24, 0.860, 0.156), "mlp": (24.23, 0.860, 0.157),
             "paper": (24.31, 0.862, 0.155)},
    "IX": {"dense": (24.20, 0.859, 0.157), "separate": (24.15, 0.858, 0.159), "identity": (24.18, 0.859, 0.158),
           "paper": (24.31, 0.862, 0.155)},
}
TABLE_ROWS = {
    "VII": ("highest", "paper"),
    "VIII": ("vector", "linear", "mlp", "paper"),
    "IX": ("dense", "separate", "identity", "paper"),
    "Fig12": ("l2", "paper"),
    "Fig13": ("lambda0", "paper"),
}


def python() -> list[str]:
    return [sys.executable, "-m", "gscodec_shac"]


def run_dir_of(out_dir: Path, name: str, seed: int) -> Path:
    """``NAME`` for seed 0, ``NAME_s<seed>`` otherwise (the paper's model at seed 1 is ``paper_seed1``)."""
    if seed == 0:
        return out_dir / name
    return out_dir / ("paper_seed1" if (name, seed) == ("paper", 1) else f"{name}_s{seed}")


def run_variant(name: str, args: argparse.Namespace, out_dir: Path, seed: int = 0) -> dict:
    """Train one variant at one seed (unless already complete) and return its metrics.json."""
    flags, _, _ = VARIANTS[name]
    if seed:
        flags = [*flags, "--seed", str(seed)]
    run_dir = run_dir_of(out_dir, name, seed)
    metrics_path = run_dir / "metrics.json"
    if metrics_path.exists() and not args.retrain:
        metrics = json.loads(metrics_path.read_text())
        if metrics.get("complete") and metrics.get("iterations_done") == args.iterations:
            return metrics
    sh = [] if "--sh" in flags else ["--sh", "lst"]
    size = ["--resolution-scale", str(args.resolution_scale)] if args.resolution_scale else []
    images = ["--images", args.images] if args.images else []
    command = python() + ["train", str(args.capture), str(run_dir), *sh, *flags, *size, *images,
                          "--iterations", str(args.iterations), "--max-gaussians", str(args.max_gaussians),
                          "--threads", str(args.threads), "--checkpoint-every", str(max(100, args.iterations // 4)),
                          "-q"]
    resume = (run_dir / "checkpoint.npz").exists() and not args.retrain
    command += ["--resume"] if resume else ["--force"]
    print(f"[{time.strftime('%H:%M:%S')}] {run_dir.name}: {' '.join(command[3:])}", flush=True)
    log = (out_dir / f"{run_dir.name}.log").open("a")
    subprocess.run(command, check=True, stdout=log, stderr=subprocess.STDOUT)
    return json.loads(metrics_path.read_text())


RD_VARIANTS = ("paper", "lambda0", "l2", "full_l3")
RD_RATE_POINTS = ("paper_table3:rp1", "paper_table3:rp2", "paper_table3:rp3", "paper_table3:rp4")


def rd_points(name: str, out_dir: Path, args: argparse.Namespace, seed: int = 0) -> list[dict]:
    """Code a trained model at the Table III rate points (trained LST: its own S and T, not refitted;
    full SH: stage ``none``), decode, render the held-out views and score against the photos."""
    import numpy as np

    from gscodec_shac.camera import test_split
    from gscodec_shac.codec import Decoder, Encoder
    from gscodec_shac.io.cameras import load_cameras
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.metrics import load_image, psnr, ssim
    from gscodec_shac.render import Renderer
    from gscodec_shac.train.finetune import load_finetuned

    run_dir = run_dir_of(out_dir, name, seed)
    if (run_dir / "point_cloud.lst.npz").exists():
        cloud, stage = load_finetuned(run_dir / "point_cloud.ply")
    else:
        cloud, stage = read_ply(run_dir / "point_cloud.ply"), "none"
    _, test = test_split(load_cameras(run_dir / "cameras.json", args.capture / args.images))
    truth = [load_image(c.image_path, size=(c.width, c.height)) for c in test]
    points = []
    for rp in RD_RATE_POINTS:
        data = Encoder(rp, sh_stage=stage, fit_stage=False, workers=1).encode(cloud).to_bytes()
        renderer = Renderer(Decoder(workers=1).decode(data))
        images = [renderer.render(c).image for c in test]
        points.append({"rate_point": rp, "bytes": len(data), "bits_per_gaussian": 8 * len(data) / cloud.num_gaussians,
                       "psnr": float(np.mean([psnr(i, t) for i, t in zip(images, truth)])),
                       "ssim": float(np.mean([ssim(i, t) for i, t in zip(images, truth)]))})
        print(f"  rd {run_dir.name} {rp}: {len(data):,} B, PSNR {points[-1]['psnr']:.3f} dB", flush=True)
    return points


def rd_over_seeds(name: str, out_dir: Path, args: argparse.Namespace) -> list[dict]:
    """:func:`rd_points` of every seed, averaged per rate point (bytes and PSNR/SSIM means)."""
    per_seed = {seed: rd_points(name, out_dir, args, seed) for seed in args.seeds}
    out = []
    for i, rp in enumerate(RD_RATE_POINTS):
        values = [points[i] for points in per_seed.values()]
        out.append({"rate_point": rp, **{k: sum(v[k] for v in values) / len(values)
                                         for k in ("bytes", "bits_per_gaussian", "psnr", "ssim")},
                    "per_seed": {seed: points[i] for seed, points in per_seed.items()}})
    return out


def rd_markdown(rd: dict[str, list[dict]]) -> str:
    lines = ["#### Fig. 12 / Fig. 13 as RD points (trained models coded with their own S and T at Table III rate "
             "points; MB and PSNR vs photos, means over the seeds)", "",
             "| model | rp1 MB / dB | rp2 MB / dB | rp3 MB / dB | rp4 MB / dB |", "|---|---|---|---|---|"]
    for name, points in rd.items():
        cells = [f"{p['bytes'] / 1e6:.3f} / {p['psnr']:.2f}" for p in points]
        lines.append(f"| {VARIANTS[name][2]} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def summarise(name: str, m: dict) -> dict:
    test = m.get("test") or {}
    return {
        "variant": name, "label": VARIANTS[name][2], "flags": VARIANTS[name][0], "method": m.get("method"),
        "psnr": test.get("mean_psnr"), "ssim": test.get("mean_ssim"),
        "num_gaussians": m["sizes"]["num_gaussians"], "sh_ac_dims": m["sizes"]["sh_ac_dims"],
        "transform_params": m["sizes"]["transform_params"], "size_mb": m["sizes"]["size_mb"],
        "train_seconds": m.get("train_seconds"), "seconds_per_iteration_median": median_s_per_it(m),
        "width": m.get("width"), "height": m.get("height"), "iterations": m.get("iterations_done"),
        "n_test_views": m.get("n_test_views"),
    }


def t_norm(run_dir: Path) -> float | None:
    """Largest singular value of the trained T (error gain S -> A~), matrix operators only."""
    if not (run_dir / "point_cloud.lst.npz").exists():
        return None
    import numpy as np

    from gscodec_shac.train.finetune import load_finetuned

    return float(np.linalg.norm(load_finetuned(run_dir / "point_cloud.ply")[1].transform_matrix(), 2))


def median_s_per_it(m: dict) -> float | None:
    values = sorted(e["s_per_it"] for e in m.get("log", []) if "s_per_it" in e)
    return values[len(values) // 2] if values else None


def paired(rows: dict[str, dict], name: str) -> str:
    """PSNR of ``name`` minus the paper's model's, seed by seed (same seed = same views order and
    initial subset), and their mean: the comparison with the least seed noise."""
    if name == "paper" or "paper" not in rows:
        return "-"
    mine, ref = rows[name]["per_seed"], rows["paper"]["per_seed"]
    common = sorted(set(mine) & set(ref))
    if not common:
        return "-"
    deltas = [mine[k]["psnr"] - ref[k]["psnr"] for k in common]
    return ", ".join(f"{d:+.2f}" for d in deltas) + f" ({sum(deltas) / len(deltas):+.2f})"


def markdown(rows: dict[str, dict], setup: dict) -> str:
    def fmt(v, spec):
        return "-" if v is None else format(v, spec)

    lines = [f"Setup: {setup['capture_name']}, {setup['width']}x{setup['height']}, {setup['iterations']} iterations, "
             f"{setup['max_gaussians']:,} Gaussians (MCMC), seeds {', '.join(map(str, setup['seeds']))}, "
             f"{setup['n_test_views']} held-out views vs photos. "
             f"Command: `{setup['command']}`", ""]
    paper_seeds = dict(rows["paper"]["per_seed"]) if "paper" in rows else {}
    if "paper_seed1" in rows and 1 not in paper_seeds:
        paper_seeds[1] = rows["paper_seed1"]["per_seed"][0]
    if len(paper_seeds) > 1:
        values = [v["psnr"] for _, v in sorted(paper_seeds.items())]
        lines += [f"Seed spread of the paper's model (seeds {', '.join(map(str, sorted(paper_seeds)))}): PSNR "
                  f"{', '.join(f'{v:.2f}' for v in values)} dB, range {max(values) - min(values):.2f} dB.", ""]
    for table, names in TABLE_ROWS.items():
        present = [n for n in names if n in rows]
        if not present:
            continue
        title = {"Fig12": "Fig. 12 (subset dimension, one point each)",
                 "Fig13": "Fig. 13 (scale regulariser, one point each)"}.get(table, f"Table {table}")
        lines += [f"#### {title}", "", "| variant | AC dims | P_T | size (MB) | PSNR (mean) | per seed | Δ vs paper's "
                  "model, per seed (mean) | SSIM (mean) | ‖T‖₂ | paper PSNR / SSIM / LPIPS |",
                  "|---|---:|---:|---:|---:|---|---|---:|---:|---|"]
        for n in present:
            r = rows[n]
            paper = PAPER.get(table, {}).get(n)
            paper_text = " / ".join(str(v) for v in paper) if paper else "-"
            per_seed = ", ".join(f"{v['psnr']:.2f}" for _, v in sorted(r["per_seed"].items()))
            lines.append(f"| {r['label']} | {r['sh_ac_dims']} | {r['transform_params']} | {r['size_mb']:.2f} | "
                         f"{fmt(r['psnr'], '.2f')} | {per_seed} | {paired(rows, n)} | {fmt(r['ssim'], '.4f')} | "
                         f"{fmt(r['t_norm'], '.2f')} | {paper_text} |")
        lines.append("")
    other = [n for n in ("paper_seed1", "full_l3") if n in rows]
    if other:
        lines += ["#### References", "", "| run | AC dims | size (MB) | PSNR (mean) | per seed | Δ vs paper's model | "
                  "SSIM (mean) | s/iteration (median, seed 0) |", "|---|---:|---:|---:|---|---|---:|---:|"]
        for n in other + ["paper"]:
            if n in rows:
                r = rows[n]
                per_seed = ", ".join(f"{v['psnr']:.2f}" for _, v in sorted(r["per_seed"].items()))
                lines.append(f"| {r['label']} | {r['sh_ac_dims']} | {r['size_mb']:.2f} | {fmt(r['psnr'], '.2f')} | "
                             f"{per_seed} | {paired(rows, n)} | {fmt(r['ssim'], '.4f')} | "
                             f"{fmt(r['seconds_per_iteration_median'], '.3f')} |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out_dir", type=Path, help="folder of the runs and of lst_ablations.{json,md}")
    parser.add_argument("--capture", type=Path, default=Path("../shared/data/scenes/snowmiku_capture"))
    parser.add_argument("--images", default="images_8")
    parser.add_argument("--resolution-scale", type=float, default=0.5)
    parser.add_argument("--iterations", type=int, default=400)
    parser.add_argument("--max-gaussians", type=int, default=10000)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--only", nargs="+", choices=sorted(VARIANTS), help="train only these variants")
    parser.add_argument("--retrain", action="store_true", help="train again even when a complete run exists")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="train every variant at each seed; "
                        "tables show the mean over the seeds (default 0)")
    parser.add_argument("--rd", action="store_true", help="also code the paper / lambda_t = 0 / L = 2 / full-SH "
                        "models at the Table III rate points (Fig. 12-13 as RD points)")
    parser.add_argument("--quick", action="store_true", help="smoke test: 20 iterations, 2,000 Gaussians, "
                        "scale 0.25, three variants")
    args = parser.parse_args(argv)
    names = list(args.only or VARIANTS)
    if args.quick:
        args.iterations, args.max_gaussians, args.resolution_scale = 20, 2000, 0.25
        names = args.only or ["paper", "mlp", "lambda0", "full_l3"]
    out_dir = args.out_dir
    out_dir.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    rows: dict[str, dict] = {}
    for seed in args.seeds:  # all variants at one seed before the next seed
        for name in names:
            if name == "paper_seed1" and seed:
                continue
            metrics = run_variant(name, args, out_dir, seed)
            row = summarise(name, metrics)
            rows.setdefault(name, {**row, "per_seed": {}})["per_seed"][seed] = {
                "psnr": row["psnr"], "ssim": row["ssim"], "t_norm": t_norm(run_dir_of(out_dir, name, seed))}
            print(f"  {name} seed {seed}: PSNR {row['psnr']:.3f} dB, SSIM {row['ssim']:.4f}", flush=True)
    for row in rows.values():  # PSNR / SSIM of a row = the mean over its seeds
        seeds = row["per_seed"]
        row["psnr"] = sum(v["psnr"] for v in seeds.values()) / len(seeds)
        row["ssim"] = sum(v["ssim"] for v in seeds.values()) / len(seeds)
        row["psnr_range"] = max(v["psnr"] for v in seeds.values()) - min(v["psnr"] for v in seeds.values())
        norms = [v["t_norm"] for v in seeds.values() if v["t_norm"] is not None]
        row["t_norm"] = sum(norms) / len(norms) if norms else None
    first = next(iter(rows.values()))
    command = ("python scripts/table_lst_ablations.py OUT_DIR --capture " + str(args.capture) +
               f" --images {args.images} --resolution-scale {args.resolution_scale} --iterations {args.iterations}"
               f" --max-gaussians {args.max_gaussians} --seeds {' '.join(map(str, args.seeds))}" + (" --rd" if args.rd else ""))
    setup = {"capture": str(args.capture), "capture_name": args.capture.name, "images": args.images,
             "resolution_scale": args.resolution_scale, "width": first["width"], "height": first["height"],
             "iterations": args.iterations, "max_gaussians": args.max_gaussians, "threads": args.threads,
             "n_test_views": first["n_test_views"], "command": command, "quick": args.quick, "seeds": args.seeds}
    result = {"setup": setup, "paper": PAPER, "rows": rows}
    text = markdown(rows, setup)
    if args.rd:
        result["rd"] = {name: rd_over_seeds(name, out_dir, args) for name in RD_VARIANTS if name in rows}
        text += "\n" + rd_markdown(result["rd"])
    (out_dir / "lst_ablations.json").write_text(json.dumps(result, indent=1) + "\n")
    (out_dir / "lst_ablations.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
