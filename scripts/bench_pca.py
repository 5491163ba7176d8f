"""Benchmark SHAC-PCA fit / transform / inverse on an N x 45 float32 AC matrix.

    python scripts/bench_pca.py [-n 1000000] [--repeats 5] [--blas-threads 1] [--json OUT.json] [--markdown OUT.md]
    python scripts/bench_pca.py --side-dtype-effect SCENE.ply ... [--synthetic N]

The second form measures what float16 side information (P, mu, sigma) costs in
reconstruction error against float32, beside the error of 10-bit features.

The matrix is a seeded low-rank-plus-noise float32 matrix with a decaying
spectrum (the cost of the Gram route does not depend on the values). Reports the
median wall time of ``--repeats`` runs per configuration, as JSON rows and a
markdown table, plus a reference: a thin SVD of the standardised matrix (the
route we do not take) and the Table-I analysis of the same matrix.

Wall times on a shared 2-core machine depend on its load: the load average
and the process CPU time are recorded with every run. ``--blas-threads 1``
pins OpenBLAS to one thread (set before numpy is imported); on a busy machine
its spinning worker threads otherwise cost up to 10x.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import sys

if __name__ == "__main__" and "--blas-threads" in sys.argv:  # must precede the numpy import
    _threads = sys.argv[sys.argv.index("--blas-threads") + 1]
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[_var] = _threads

import numpy as np  # noqa: E402

from gscodec_shac.shac import analysis  # noqa: E402
from gscodec_shac.shac.pca import ShacPCA  # noqa: E402


def make_matrix(n: int, k: int = 45, seed: int = 0) -> np.ndarray:
    """Low-rank (rank 12) signal with a decaying spectrum plus 5% isotropic noise."""
    rng = np.random.default_rng(seed)
    basis = rng.normal(size=(12, k)) * (0.7 ** np.arange(12))[:, None]
    out = (rng.normal(size=(n, 12)).astype(np.float32) @ basis.astype(np.float32)) * np.float32(0.02)
    out += rng.normal(scale=0.001, size=(n, k)).astype(np.float32)
    return out


_CPU: list[float] = []


def _time(fn) -> float:
    """Wall seconds of ``fn()``; its process CPU seconds are appended to ``_CPU``."""
    start, cpu = time.perf_counter(), time.process_time()
    fn()
    _CPU.append(time.process_time() - cpu)
    return time.perf_counter() - start


def bench_config(ac: np.ndarray, params: dict, repeats: int) -> dict:
    """Median seconds of fit, transform, inverse_transform and their sum."""
    fits, transforms, inverses, totals, cpus = [], [], [], [], []
    for _ in range(repeats):
        del _CPU[:]
        pca = ShacPCA(**params)
        t_fit = _time(lambda: pca.fit(ac))
        holder = {}
        t_tr = _time(lambda: holder.setdefault("f", pca.transform(ac)))
        t_inv = _time(lambda: pca.inverse_transform(holder["f"]))
        fits.append(t_fit), transforms.append(t_tr), inverses.append(t_inv), totals.append(t_fit + t_tr + t_inv)
        cpus.append(sum(_CPU))
    return {
        "config": ", ".join(f"{k}={v}" for k, v in params.items()),
        "n_components": pca.n_components_,
        "fit_s": statistics.median(fits),
        "transform_s": statistics.median(transforms),
        "inverse_s": statistics.median(inverses),
        "total_s": statistics.median(totals),
        "total_cpu_s": statistics.median(cpus),
        "side_bytes": pca.state().nbytes(),
    }


def bench_reference(ac: np.ndarray, repeats: int) -> list[dict]:
    """The full thin SVD of A' (not used) and the Table-I analysis (used by `analyze`)."""
    rows = []
    svd_times = []
    for _ in range(max(1, repeats // 2)):
        svd_times.append(_time(lambda: np.linalg.svd((ac - ac.mean(0)) / ac.std(0), full_matrices=False)))
    rows.append({"config": "reference: np.linalg.svd of A' (float32, thin)", "total_s": statistics.median(svd_times)})
    table_times = [_time(lambda: analysis.table_row("bench", ac)) for _ in range(repeats)]
    rows.append({"config": "analysis.table_row (Table I row)", "total_s": statistics.median(table_times)})
    return rows


def side_dtype_effect(name: str, ac: np.ndarray) -> list[dict]:
    """RMSE of A~ with float32 vs float16 side info (M = 24 and ER = 99%), and with 10-bit features."""
    ac = ac.astype(np.float64)
    rms = float(np.sqrt((ac**2).mean()))
    rows = []
    for params in ({"n_components": 24}, {"energy_retention": 0.99}):
        rec, nbytes = {}, {}
        for side in ("float32", "float16"):
            pca = ShacPCA(side_dtype=side, **params).fit(ac)
            features = pca.transform(ac)
            rec[side] = pca.inverse_transform(features)
            nbytes[side] = pca.state().nbytes()
            if side == "float32":  # per-feature min/max 10-bit uniform quantisation, for scale
                lo, hi = features.min(0), features.max(0)
                step = np.where(hi > lo, (hi - lo) / 1023, 1.0)
                rec["q10"] = pca.inverse_transform(np.round((features - lo) / step) * step + lo)
        err = {key: float(np.sqrt(((ac - value) ** 2).mean())) for key, value in rec.items()}
        rows.append({
            "scene": name, "config": ", ".join(f"{k}={v}" for k, v in params.items()), "M": pca.n_components_,
            "ac_rms": rms, "rmse_f32": err["float32"], "rmse_f16": err["float16"],
            "rel_increase": err["float16"] / err["float32"] - 1.0,
            "max_abs_diff_f16_f32": float(np.abs(rec["float16"] - rec["float32"]).max()),
            "rmse_10bit_features": err["q10"], "bytes_f32": nbytes["float32"], "bytes_f16": nbytes["float16"],
        })
    return rows


def side_dtype_markdown(rows: list[dict]) -> str:
    lines = [
        "| scene | config | M | RMS of A | RMSE f32 side | RMSE f16 side | increase | max abs diff "
        "| RMSE 10-bit F | side bytes f32 / f16 |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['config']} | {r['M']} | {r['ac_rms']:.4g} | {r['rmse_f32']:.4g} | "
            f"{r['rmse_f16']:.4g} | "
            f"{100 * r['rel_increase']:+.3f}% | {r['max_abs_diff_f16_f32']:.2g} | {r['rmse_10bit_features']:.4g} | "
            f"{r['bytes_f32']:,} / {r['bytes_f16']:,} |"
        )
    return "\n".join(lines)


def markdown(result: dict) -> str:
    lines = [
        f"N = {result['n']:,}, K' = {result['k']}, float32, median of {result['repeats']} runs, "
        f"{result['machine']}, BLAS threads {result['blas_threads']}, load average {result['load_before']:.1f} "
        f"before / {result['load_after']:.1f} after",
        "",
        "| configuration | M | fit [s] | transform [s] | inverse [s] | total [s] | total CPU [s] | side info [B] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in result["rows"]:
        if "fit_s" in row:
            lines.append(
                f"| {row['config']} | {row['n_components']} | {row['fit_s']:.3f} | {row['transform_s']:.3f} | "
                f"{row['inverse_s']:.3f} | **{row['total_s']:.3f}** | {row['total_cpu_s']:.3f} | "
                f"{row['side_bytes']:,} |"
            )
        else:
            lines.append(f"| {row['config']} | | | | | {row['total_s']:.3f} | | |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-n", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", help="write the JSON result here")
    parser.add_argument("--markdown", help="write the markdown table here")
    parser.add_argument("--no-reference", action="store_true", help="skip the full-SVD reference")
    parser.add_argument("--blas-threads", help="pin BLAS to this many threads (set before numpy is imported)")
    parser.add_argument("--side-dtype-effect", nargs="*", metavar="PLY",
                        help="instead of timing: float16 vs float32 side-info error on these scenes")
    parser.add_argument("--synthetic", type=int, nargs="?", const=100_000,
                        help="with --side-dtype-effect: add a synthetic scene of N Gaussians (seed 0)")
    args = parser.parse_args()
    if args.side_dtype_effect is not None:
        run_side_dtype_effect(args)
        return
    load_before = os.getloadavg()[0]

    ac = make_matrix(args.n)
    configs = [
        {"energy_retention": 0.99},
        {"energy_retention": 0.95},
        {"n_components": 24},
        {"n_components": 24, "joint_rgb": False},
        {"n_components": 24, "side_dtype": "float16"},
    ]
    rows = [bench_config(ac, params, args.repeats) for params in configs]
    if not args.no_reference:
        rows += bench_reference(ac, args.repeats)
    result = {
        "benchmark": "shac_pca",
        "n": args.n,
        "k": ac.shape[1],
        "repeats": args.repeats,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, numpy {np.__version__}",
        "blas_threads": args.blas_threads or "default",
        "load_before": load_before,
        "load_after": os.getloadavg()[0],
        "rows": rows,
    }
    text = markdown(result)
    print(text)
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(result, handle, indent=2)
    if args.markdown:
        with open(args.markdown, "w") as handle:
            handle.write(text + "\n")


def run_side_dtype_effect(args: argparse.Namespace) -> None:
    from pathlib import Path

    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.synthetic import make_synthetic_scene

    rows = []
    for path in args.side_dtype_effect:
        name = Path(path).parent.name if Path(path).stem == "point_cloud" else Path(path).stem
        rows += side_dtype_effect(name, read_ply(path).ac_matrix())
    if args.synthetic:
        ac = make_synthetic_scene(args.synthetic).cloud.ac_matrix()
        rows += side_dtype_effect(f"synthetic_{args.synthetic}_s0", ac)
    text = side_dtype_markdown(rows)
    print(text)
    if args.json:
        with open(args.json, "w") as handle:
            json.dump({"benchmark": "shac_pca_side_dtype", "rows": rows}, handle, indent=2)
    if args.markdown:
        with open(args.markdown, "w") as handle:
            handle.write(text + "\n")


if __name__ == "__main__":
    main()
