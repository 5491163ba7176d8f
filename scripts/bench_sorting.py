"""Benchmark of the `sorting` package: time, peak memory, smoothness, and what it buys in HEVC bytes.

    python scripts/bench_sorting.py --out /tmp/bench_sorting \
        --md docs/benchmarks_sorting.md --plot docs/figures/sorting_convergence.png

Sections (each can be skipped):

* ``table``: random / Morton / ours (PLAS-like) on real and synthetic scenes at
  64x64 ... 1024x1024; every run is a fresh worker process, so its peak RSS
  (``ru_maxrss``) is the sort's own; wall and CPU seconds exclude numba's
  one-off compilation (a tiny warm-up sort first).
* ``reference``: ours against our numpy re-implementation of published PLAS
  (``scripts/plas_reference.py``) at 32x32, 64x64, 128x128 on the real bonsai scene.
* ``convergence``: neighbour distance after every blur radius against passes,
  for ours (default and PLAS schedules) and the reference, as a PNG.
* ``hevc``: bytes of the DC and scale grids (10 bit, per-channel min/max, one
  gray x265 stream per channel, QP 12, preset slow) for random / Morton / ours.

The 14 sorting channels: xyz (3), log-scales (3), opacity logit (1), rotation
(4, sign-canonical), DC (3), each attribute min/max-normalised as a whole
(``sorting.prepare_features``). Outputs (JSON, CSV, cached features and
orders) go to ``--out``, outside the repository.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

import sorting  # noqa: E402

SCENES = REPO.parent / "shared" / "data" / "scenes"
BONSAI = SCENES / "bonsai_cpu_sh3" / "point_cloud.ply"
GARDEN = SCENES / "garden_sfm_gsplat" / "test_garden.npz"
SYNTHETIC_N = 1024 * 1024
METHODS = ("random", "morton", "plas")
from sorting.plas import PLAS_REFERENCE as FAITHFUL  # noqa: E402  the published schedule


# ---------------------------------------------------------------- data


def cloud_attributes(cloud) -> dict[str, np.ndarray]:
    """The 14 sorting channels of a GaussianCloud, by attribute."""
    quats = np.asarray(cloud.normalized_quats(), dtype=np.float64)
    quats = quats * np.where(quats[:, :1] < 0, -1.0, 1.0)  # q and -q are the same rotation
    n = cloud.num_gaussians
    return {
        "xyz": cloud.means, "scale": cloud.scales, "opacity": cloud.opacities.reshape(n),
        "rotation": quats, "dc": cloud.sh_dc.reshape(n, -1),
    }


def dataset(name: str, cache: Path) -> dict[str, np.ndarray]:
    """Features (and DC/scale for the HEVC section) of a named data set, cached as .npz."""
    path = cache / f"{name}.npz"
    if path.exists():
        with np.load(path) as data:
            return dict(data)
    cache.mkdir(parents=True, exist_ok=True)
    if name == "bonsai":
        from gscodec_shac.io.ply import read_ply

        cloud = read_ply(BONSAI)
        attrs = cloud_attributes(cloud)
        out = {"features": sorting.prepare_features(attrs), "dc": attrs["dc"], "scale": attrs["scale"]}
    elif name == "garden":
        data = np.load(GARDEN)
        colours = data["colors"].astype(np.float32) / 255.0
        out = {"features": sorting.prepare_features({"xyz": data["means3d"], "rgb": colours}), "dc": colours}
    elif name == "synthetic":
        from gscodec_shac.synthetic import make_synthetic_scene

        print(f"generating a {SYNTHETIC_N:,}-Gaussian synthetic scene (minutes) ...", flush=True)
        cloud = make_synthetic_scene(SYNTHETIC_N, seed=0).cloud
        attrs = cloud_attributes(cloud)
        out = {"features": sorting.prepare_features(attrs), "dc": attrs["dc"], "scale": attrs["scale"]}
    else:
        raise SystemExit(f"unknown data set {name!r}")
    np.savez(path, **out)
    return out


def rows_for(data: dict[str, np.ndarray], count: int | None, seed: int = 0) -> np.ndarray:
    """Indices of a seeded random subset of ``count`` rows (all rows when None)."""
    n = len(data["features"])
    if count is None or count >= n:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, count, replace=False))


#: (label, data set, rows or None for all, grid shape or None for grid_shape(rows))
CASES = [
    ("bonsai 64x64", "bonsai", 64 * 64, (64, 64)),
    ("bonsai 128x128", "bonsai", 128 * 128, (128, 128)),
    ("bonsai all (75k)", "bonsai", None, None),
    ("garden SfM (139k, 6 ch)", "garden", None, None),
    ("synthetic 512x512", "synthetic", 512 * 512, (512, 512)),
    ("synthetic 1024x1024", "synthetic", None, (1024, 1024)),
]


def smoothness(features: np.ndarray, order: np.ndarray, shape: tuple[int, int]) -> tuple[float, float]:
    grid = sorting.apply_order(features, order, shape=shape)
    mask = (order >= 0).reshape(shape)
    return sorting.neighbour_distance(grid, mask), sorting.vad(grid, mask)


# ---------------------------------------------------------------- worker (one sort per process)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def current_rss_mb() -> float:
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def worker(args: argparse.Namespace) -> None:
    """Sort one case with one method; write a JSON row and the order."""
    case = next(c for c in CASES if c[0] == args.case)
    label, name, count, shape = case
    data = dataset(name, Path(args.out) / "cache")
    rows = rows_for(data, count)
    feats = np.ascontiguousarray(data["features"][rows])
    shape = shape or sorting.grid_shape(len(rows))
    warm_up(feats)
    base = current_rss_mb()
    load = os.getloadavg()[0]
    wall, cpu = time.perf_counter(), time.process_time()
    order = sorting.sort_to_grid(feats, shape, method=args.method, seed=0, progress=args.progress)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    nd, v = smoothness(feats, order, shape)
    row = {
        "case": label, "data": name, "n": int(len(rows)), "height": shape[0], "width": shape[1],
        "channels": int(feats.shape[1]), "method": args.method, "wall_s": wall, "cpu_s": cpu,
        "peak_rss_mb": peak_rss_mb(), "rss_before_mb": base, "neighbour_distance": nd, "vad": v,
        "threads": int(os.environ.get("NUMBA_NUM_THREADS", os.cpu_count() or 1)), "load_before": load,
        "load_after": os.getloadavg()[0],
    }
    np.save(Path(args.out) / "orders" / f"{slug(label)}_{args.method}.npy", order)
    Path(args.row).write_text(json.dumps(row))


def warm_up(features: np.ndarray) -> None:
    """Load (or compile) every numba kernel, parallel ones included, outside the timed region."""
    import sorting.blur
    import sorting.plas

    plas, blur = sorting.plas, sorting.blur
    saved = plas.PARALLEL_GROUPS, blur.PARALLEL_CELLS, plas.WARM_GRID, plas.BLOCKWISE_BLOCKS, plas.BLOCKWISE_GRID
    plas.PARALLEL_GROUPS = blur.PARALLEL_CELLS = plas.WARM_GRID = plas.BLOCKWISE_GRID = 1
    try:
        sample = np.ascontiguousarray(features[: 48 * 48])
        for blocks in (4, 1 << 40):  # block-by-block and whole-layout passes
            plas.BLOCKWISE_BLOCKS = blocks
            sorting.sort_to_grid(sample, (48, 48), tile_groups_above=256)
            sorting.sort_to_grid(sample, (48, 48))
    finally:
        plas.PARALLEL_GROUPS, blur.PARALLEL_CELLS, plas.WARM_GRID, plas.BLOCKWISE_BLOCKS, plas.BLOCKWISE_GRID = saved
    sorting.sort_to_grid(sample, (48, 48), method="morton")


def slug(text: str) -> str:
    return "".join(ch if ch.isalnum() else "_" for ch in text).strip("_")


def run_table(out: Path, cases: list[tuple], progress: bool) -> list[dict]:
    (out / "orders").mkdir(parents=True, exist_ok=True)
    rows = []
    for label, name, _, _ in cases:
        dataset(name, out / "cache")  # build the cache once, outside the timed workers
        for method in METHODS:
            row_path = out / "rows" / f"{slug(label)}_{method}.json"
            row_path.parent.mkdir(parents=True, exist_ok=True)
            cmd = [sys.executable, __file__, "--worker", "--case", label, "--method", method,
                   "--out", str(out), "--row", str(row_path)] + (["--progress"] if progress else [])
            subprocess.run(cmd, check=True)
            row = json.loads(row_path.read_text())
            print(f"{label:26s} {method:7s} {row['wall_s']:7.2f} s wall {row['cpu_s']:7.2f} s cpu "
                  f"{row['peak_rss_mb']:7.0f} MB  nd {row['neighbour_distance']:.4f}  vad {row['vad']:.5f}", flush=True)
            rows.append(row)
    return rows


# ---------------------------------------------------------------- reference and convergence


def run_reference(out: Path, sides: list[int]) -> list[dict]:
    from plas_reference import plas_reference

    data = dataset("bonsai", out / "cache")
    rows = []
    for side in sides:
        feats = np.ascontiguousarray(data["features"][rows_for(data, side * side)])
        shape = (side, side)
        warm_up(feats)
        runs = {
            "reference PLAS (numpy port)": lambda: plas_reference(feats, side, seed=0),
            "ours (default)": lambda: sorting.sort_to_grid(feats, shape, seed=0),
            "ours (PLAS schedule)": lambda: sorting.sort_to_grid(feats, shape, seed=0, **FAITHFUL),
        }
        for label, fn in runs.items():
            wall, cpu = time.perf_counter(), time.process_time()
            order = fn()
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            nd, v = smoothness(feats, order, shape)
            rows.append({"side": side, "method": label, "wall_s": wall, "cpu_s": cpu, "neighbour_distance": nd, "vad": v})
            print(f"{side:4d}  {label:30s} {wall:7.2f} s wall {cpu:7.2f} s cpu  nd {nd:.4f}  vad {v:.5f}", flush=True)
    return rows


def run_convergence(out: Path, side: int) -> dict[str, list]:
    """(passes, neighbour distance) after every radius for ours and the reference."""
    from plas_reference import plas_reference

    from sorting.plas import make_schedule, plas_sort

    data = dataset("bonsai", out / "cache")
    feats = np.ascontiguousarray(data["features"][rows_for(data, side * side)])
    shape = (side, side)
    curves: dict[str, list] = {}
    for label, overrides in (("ours (default)", {}), ("ours (PLAS schedule)", FAITHFUL),
                             ("ours (PLAS schedule, break 1e-5)", {**FAITHFUL, "improvement_break": 1e-5})):
        total = [0]
        curve: list = []

        def record(radius: int, passes: int, idx: np.ndarray, curve=curve, total=total) -> None:
            total[0] += passes
            curve.append((total[0], radius, smoothness(feats, idx, shape)[0]))

        plas_sort(feats, shape, np.random.default_rng(0), make_schedule(**overrides), callback=record)
        curves[label] = curve
    record_ref: list = []
    plas_reference(feats, side, seed=0, record=record_ref)
    curves["reference PLAS (numpy port)"] = [
        (passes, radius, smoothness(feats, order, shape)[0]) for passes, radius, order in record_ref
    ]
    return curves


def plot_convergence(curves: dict[str, list], path: Path, side: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=100)
    for label, curve in curves.items():
        passes = [c[0] for c in curve]
        dist = [c[2] for c in curve]
        ax.plot(passes, dist, label=f"{label}: {dist[-1]:.4f} after {passes[-1]:,.0f} passes", lw=1.4)
    ax.set_xscale("log")
    ax.set_xlabel("improvement passes, cumulative (one point per blur radius)")
    ax.set_ylabel("mean neighbour L2 distance")
    ax.set_title(f"Sorting {side}x{side} real bonsai Gaussians, 14 channels")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


# ---------------------------------------------------------------- HEVC bytes


def fill_empty(grid: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Empty cells take the value of the previous occupied cell in raster order."""
    flat = grid.reshape(-1, grid.shape[-1]).copy()
    occupied = mask.reshape(-1)
    last = np.maximum.accumulate(np.where(occupied, np.arange(occupied.size), 0))
    flat[~occupied] = flat[last[~occupied]]
    return flat.reshape(grid.shape)


def hevc_bytes(values: np.ndarray, order: np.ndarray, shape: tuple[int, int], qp: int = 12) -> int:
    """Bytes of (N, C) values as 10-bit per-channel min/max planes, one gray x265 stream per channel."""
    lo, hi = values.min(axis=0), values.max(axis=0)
    q = np.rint((values - lo) / np.where(hi > lo, hi - lo, 1.0) * 1023).astype(np.uint16)
    grid = fill_empty(sorting.apply_order(q, order, shape=shape), (order >= 0).reshape(shape))
    planes = np.ascontiguousarray(grid.transpose(2, 0, 1))
    try:
        from gscodec_shac.codec.grid import get_codec

        codec = get_codec("hevc", layout="gray", preset="slow")
        return len(codec.encode(planes, 10, qp))
    except ImportError:
        return sum(len(x265_gray10(plane, qp)) for plane in planes)


def x265_gray10(plane: np.ndarray, qp: int) -> bytes:
    """One 10-bit gray frame through PyAV/libx265 (fallback when the codec package is absent)."""
    import fractions

    import av

    h, w = plane.shape
    ctx = av.CodecContext.create("libx265", "w")
    ctx.width, ctx.height, ctx.pix_fmt = w, h, "gray10le"
    ctx.time_base = fractions.Fraction(1, 25)
    ctx.options = {"preset": "slow", "x265-params": f"qp={qp}:ipratio=1:info=0:log-level=error"}
    frame = av.VideoFrame(w, h, "gray10le")
    view = np.frombuffer(frame.planes[0], dtype=np.uint16).reshape(h, frame.planes[0].line_size // 2)
    view[:, :w] = plane
    frame.pts = 0
    return b"".join(bytes(p) for p in ctx.encode(frame) + ctx.encode(None))


def run_hevc(out: Path, labels: list[str]) -> list[dict]:
    rows = []
    for label, name, count, shape in CASES:
        if label not in labels:
            continue
        data = dataset(name, out / "cache")
        idx = rows_for(data, count)
        shape = shape or sorting.grid_shape(len(idx))
        for method in METHODS:
            order = np.load(out / "orders" / f"{slug(label)}_{method}.npy")
            row = {"case": label, "method": method}
            for attr in ("dc", "scale"):
                if attr in data:
                    row[f"{attr}_bytes"] = hevc_bytes(data[attr][idx].astype(np.float64), order, shape)
            rows.append(row)
            print(f"{label:26s} {method:7s} " + "  ".join(f"{k} {v:,}" for k, v in row.items() if k.endswith("bytes")), flush=True)
    return rows


# ---------------------------------------------------------------- report


REPRODUCE = (
    "python scripts/bench_sorting.py --out /tmp/bench_sorting "
    "--md docs/benchmarks_sorting.md --plot docs/figures/sorting_convergence.png"
)


def markdown(results: dict) -> str:
    lines = ["# Sorting benchmark (`sorting` package)", "",
             f"Reproduce: `{REPRODUCE}` (about 15 minutes; `--sections table,reference,convergence,hevc` "
             "runs a part, the others are kept from `--out`/results.json).", "",
             f"Machine: {os.cpu_count()} cores, no GPU, shared with other jobs: `load` is the 1-minute load "
             "average when a sort started; wall times grow with it, CPU seconds (this process's own, "
             "both threads) much less. Peak memory is the sorting process's peak RSS (Python, numpy, "
             "numba and the features included). Every sort is seed 0 and reproducible. Features: 14 "
             "channels (xyz, log-scales, opacity, rotation, DC; garden SfM: xyz + colour), each attribute "
             "min/max-normalised as a whole; neighbour distance = mean L2 distance between 4-neighbours "
             "of these features (lower is smoother), VAD = PLAS's variance of absolute neighbour "
             "differences. `morton` = Z-order of the feature vectors laid out in 2-D Z-order; `plas` = "
             "`sorting.sort_to_grid` with its defaults.", ""]
    if results.get("table"):
        lines += ["## Time, memory, smoothness", "",
                  "| case | N | grid | method | wall s | CPU s | peak RSS MB | neighbour dist. | VAD | load |",
                  "|---|---:|---|---|---:|---:|---:|---:|---:|---:|"]
        for r in results["table"]:
            lines.append(f"| {r['case']} | {r['n']:,} | {r['height']}x{r['width']} | {r['method']} | {r['wall_s']:.2f} | "
                         f"{r['cpu_s']:.2f} | {r['peak_rss_mb']:.0f} | {r['neighbour_distance']:.4f} | {r['vad']:.5f} | "
                         f"{r.get('load_before', float('nan')):.1f} |")
        lines.append("")
    if results.get("reference"):
        lines += ["## Against a faithful PLAS port (real bonsai subsets, 14 channels)", "",
                  "| grid | method | wall s | CPU s | neighbour dist. | VAD |", "|---|---|---:|---:|---:|---:|"]
        for r in results["reference"]:
            lines.append(f"| {r['side']}x{r['side']} | {r['method']} | {r['wall_s']:.2f} | {r['cpu_s']:.2f} | "
                         f"{r['neighbour_distance']:.4f} | {r['vad']:.5f} |")
        lines.append("")
    if results.get("hevc"):
        lines += ["## What it buys: HEVC bytes at QP 12 (10 bit, one gray x265 stream per channel, preset slow)", "",
                  "| case | method | DC bytes | scale bytes |", "|---|---|---:|---:|"]
        for r in results["hevc"]:
            scale = f"{r['scale_bytes']:,}" if "scale_bytes" in r else "-"
            lines.append(f"| {r['case']} | {r['method']} | {r.get('dc_bytes', 0):,} | {scale} |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="/tmp/bench_sorting", help="folder for JSON/CSV/caches (outside the repo)")
    parser.add_argument("--sections", default="table,reference,convergence,hevc")
    parser.add_argument("--cases", default="", help="comma-separated case labels (default: all)")
    parser.add_argument("--reference-sides", default="32,64,128")
    parser.add_argument("--convergence-side", type=int, default=128)
    parser.add_argument("--hevc-cases", default="bonsai all (75k),synthetic 1024x1024")
    parser.add_argument("--md", help="write the markdown tables here")
    parser.add_argument("--plot", help="write the convergence PNG here")
    parser.add_argument("--progress", action="store_true")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--case", help=argparse.SUPPRESS)
    parser.add_argument("--method", help=argparse.SUPPRESS)
    parser.add_argument("--row", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args)
        return
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sections = set(args.sections.split(","))
    results_path = out / "results.json"
    results = json.loads(results_path.read_text()) if results_path.exists() else {}
    cases = [c for c in CASES if not args.cases or c[0] in args.cases.split(",")]
    if "table" in sections:
        results["table"] = run_table(out, cases, args.progress)
        with open(out / "table.csv", "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(results["table"][0]))
            writer.writeheader()
            writer.writerows(results["table"])
    if "reference" in sections:
        results["reference"] = run_reference(out, [int(s) for s in args.reference_sides.split(",")])
    if "convergence" in sections:
        results["convergence"] = run_convergence(out, args.convergence_side)
    if args.plot and results.get("convergence"):  # also redraws from results.json alone
        plot_convergence(results["convergence"], Path(args.plot), args.convergence_side)
    if "hevc" in sections:
        results["hevc"] = run_hevc(out, args.hevc_cases.split(","))
    results_path.write_text(json.dumps(results, indent=1))
    if args.md:
        Path(args.md).write_text(markdown(results))
    print(f"results: {results_path}")


if __name__ == "__main__":
    main()
