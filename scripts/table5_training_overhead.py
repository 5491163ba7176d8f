"""Small-scale paper Table V: training overhead of SHAC-LST against the same trainer with full SH
(docs/paper.md).

For each model size N, two trainers (``--sh full`` and ``--sh lst``, same capture, same N
initial Gaussians, same seed) are stepped in interleaved blocks (full, lst, full, lst, ...) so
that both see the same machine load; per-iteration wall and process CPU seconds are recorded
after a warm-up (numba compilation) and their medians compared. The SH degree is 3 from the
first iterations (``sh_interval=1``) and the run is nominally 30,000 iterations long, so no
densification or MCMC refinement happens inside the timed window: N stays fixed, as in the
paper's fixed-N rows. Quality at equal schedule is not measured here (see
docs/training.md, Table II small scale, and the ablation runs of scripts/table_lst_ablations.py).

    python scripts/table5_training_overhead.py --json table5.json --md table5.md \\
        --capture ../shared/data/scenes/snowmiku_capture --images images_8 --sizes 25000 100000
    python scripts/table5_training_overhead.py --quick
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numba  # noqa: E402
import torch  # noqa: E402

from gscodec_shac.train.data import load_capture, synthetic_capture  # noqa: E402
from gscodec_shac.train.trainer import TrainConfig, Trainer  # noqa: E402

#: The paper's Table V (truck, RTX 3090, 30k iterations): minutes of training.
PAPER = [
    {"method": "gsplat", "n": "0.36M", "psnr": 25.27, "ssim": 0.875, "lpips": 0.159, "minutes": 6.5},
    {"method": "gsplat+SHAC-LST", "n": "0.36M", "psnr": 25.29, "ssim": 0.875, "lpips": 0.159, "minutes": 8.2},
    {"method": "gsplat", "n": "1.00M", "psnr": 26.02, "ssim": 0.891, "lpips": 0.126, "minutes": 11.6},
    {"method": "gsplat+SHAC-LST", "n": "1.00M", "psnr": 26.07, "ssim": 0.891, "lpips": 0.125, "minutes": 15.6},
]


def timed_steps(trainer: Trainer, count: int, wall: list[float], cpu: list[float], phases: list[dict]) -> None:
    for _ in range(count):
        c0 = time.process_time()
        info = trainer.step()
        cpu.append(time.process_time() - c0)
        wall.append(info.seconds)
        phases.append(info.phases)


def measure(capture, n: int, args: argparse.Namespace) -> list[dict]:
    trainers = {}
    for sh in ("full", "lst"):
        config = TrainConfig(iterations=30_000, sh=sh, strategy="mcmc", max_gaussians=n, seed=0, sh_interval=1,
                             log_every=10**9)
        trainers[sh] = Trainer(capture, config)
    n_actual = trainers["full"].model.num_gaussians
    for trainer in trainers.values():  # warm-up: numba compilation, SH degree up to 3
        for _ in range(args.warmup):
            trainer.step()
    data = {sh: ([], [], []) for sh in trainers}
    for _ in range(args.rounds):
        for sh, trainer in trainers.items():
            timed_steps(trainer, args.block, *data[sh])
    rows = []
    for sh, (wall, cpu, phases) in data.items():
        model = trainers[sh].model
        rows.append({
            "n": n_actual, "method": "full SH (Train-L3-D45)" if sh == "full" else "SHAC-LST-L3-D21", "sh": sh,
            "steps": len(wall), "wall_s_per_it": statistics.median(wall), "cpu_s_per_it": statistics.median(cpu),
            "phases": {k: statistics.median(p[k] for p in phases) for k in phases[0]},
            "active_degree": trainers[sh].active_degree, "n_end": model.num_gaussians,
            "minutes_per_30k": statistics.median(wall) * 30_000 / 60,
        })
    full, lst = rows
    lst["wall_overhead"] = lst["wall_s_per_it"] / full["wall_s_per_it"] - 1.0
    lst["cpu_overhead"] = lst["cpu_s_per_it"] / full["cpu_s_per_it"] - 1.0
    print(f"N = {n_actual:,}: full {full['wall_s_per_it']:.3f} s/it ({full['cpu_s_per_it']:.3f} CPU), "
          f"LST {lst['wall_s_per_it']:.3f} s/it ({lst['cpu_s_per_it']:.3f} CPU): overhead "
          f"{100 * lst['wall_overhead']:+.1f}% wall, {100 * lst['cpu_overhead']:+.1f}% CPU", flush=True)
    return rows


def markdown(rows: list[dict], setup: dict) -> str:
    lines = [f"{setup['capture']} at {setup['width']}x{setup['height']}, numba/torch 1 thread, "
             f"{setup['rounds']} interleaved blocks of {setup['block']} iterations per method after "
             f"{setup['warmup']} warm-up iterations; medians; load average {setup['load'][0]:.1f} -> "
             f"{setup['load_end'][0]:.1f}.", "",
             "| N | method | s/it (wall) | s/it (CPU) | overhead wall | overhead CPU | forward | backward | optimizer |",
             "|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        over = (lambda k: "-" if k not in r else f"{100 * r[k]:+.1f}%")
        p = r["phases"]
        lines.append(f"| {r['n']:,} | {r['method']} | {r['wall_s_per_it']:.3f} | {r['cpu_s_per_it']:.3f} | "
                     f"{over('wall_overhead')} | {over('cpu_overhead')} | {p['forward']:.3f} | {p['backward']:.3f} | "
                     f"{p['optimizer']:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--capture", type=Path, default=Path("../shared/data/scenes/snowmiku_capture"))
    parser.add_argument("--images", default="images_8")
    parser.add_argument("--resolution-scale", type=float, default=None)
    parser.add_argument("--sizes", type=int, nargs="+", default=[25_000, 100_000])
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--block", type=int, default=8)
    parser.add_argument("--json", type=Path)
    parser.add_argument("--md", type=Path)
    parser.add_argument("--quick", action="store_true", help="smoke test on a synthetic capture, tiny sizes")
    args = parser.parse_args(argv)
    numba.set_num_threads(1)
    torch.set_num_threads(1)
    if args.quick:
        args.sizes, args.rounds, args.block, args.warmup = [500, 1500], 2, 2, 1
    rows: list[dict] = []
    load_start = list(os.getloadavg())
    for n in args.sizes:
        if args.quick:
            capture = synthetic_capture(2000, n_cameras=8, width=48, height=36, init_points=n, seed=3)
        else:
            # SfM points plus random background points so that N initial Gaussians exist
            probe = load_capture(args.capture, images=args.images, resolution_scale=args.resolution_scale,
                                 progress=False) if not rows else capture
            extra = max(0, n - len(probe.points))
            capture = probe if extra == 0 else load_capture(
                args.capture, images=args.images, resolution_scale=args.resolution_scale, random_points=extra,
                seed=0, progress=False)
        rows += measure(capture, n, args)
        first = capture.train_cameras[0]
        setup = {"capture": "synthetic (quick)" if args.quick else args.capture.name, "width": first.width,
                 "height": first.height, "sizes": args.sizes, "warmup": args.warmup, "rounds": args.rounds,
                 "block": args.block, "load": load_start, "load_end": list(os.getloadavg()), "quick": args.quick}
        text = markdown(rows, setup)  # written after every size, so a stopped run keeps what it measured
        if args.json:
            args.json.write_text(json.dumps({"setup": setup, "paper": PAPER, "rows": rows}, indent=1) + "\n")
        if args.md:
            args.md.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
