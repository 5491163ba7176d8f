"""Benchmark the codec: encode/decode time, peak memory and bytes per attribute.

Each measurement runs in a fresh child process (so peak RSS is that run's own);
times are medians over ``--repeats`` runs inside the child, from a cloud already
in memory to bytes (encode) and from bytes to a cloud (decode); PLY reading and
writing are reported separately. Scenes are made or converted into ``--work``
(never into the repository):

* ``synthetic-100k``, ``synthetic-1m``: :func:`gscodec_shac.synthetic.make_synthetic_scene`;
* ``playbot``: the 500k SOG scene in ../shared/data/scenes/playbot_sog_sh2, decoded
  to PLY with ``splat-transform meta.json out.ply`` (npm ``@playcanvas/splat-transform``).

Usage::

    python scripts/bench_codec.py                       # default matrix -> docs/benchmarks_codec.md
    python scripts/bench_codec.py --scenes synthetic-100k --rate-points paper_table3:rp1 --sh none pca
    python scripts/bench_codec.py --vq-only             # k-means codebook fit times (100k, 1M)
    python scripts/bench_codec.py --from-json a.json b.json   # one report from several runs
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PLAYBOT = REPO.parent / "shared" / "data" / "scenes" / "playbot_sog_sh2" / "meta.json"
NPM_PREFIX = Path.home() / ".cache" / "gscodec-shac" / "npm"
SCENES = {"synthetic-100k": 100_000, "synthetic-1m": 1_000_000, "playbot": 500_000}
DEFAULT_POINTS = [
    "paper_table3:rp1", "paper_table3:rp2", "paper_table3:rp3", "paper_table3:rp4",
    "mpeg_ctc_video:rp01", "mpeg_ctc_video:rp02", "mpeg_ctc_video:rp03", "mpeg_ctc_video:rp04",
    "gscodec_studio:rp0", "gscodec_studio:rp3", "gsplat_png",
]


# ------------------------------------------------------------------ children
def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def child_encode(args: argparse.Namespace) -> dict:
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.codec import Encoder

    tic = time.perf_counter()
    cloud = read_ply(args.ply)
    read_s = time.perf_counter() - tic
    times, steps, stream = [], [], None
    for _ in range(args.repeats):
        encoder = Encoder(args.rate_point, sh_stage=None if args.sh == "default" else args.sh,
                          sort=args.sort, sh_params=json.loads(args.sh_params))
        tic = time.perf_counter()
        stream = encoder.encode(cloud)
        data = stream.to_bytes()
        times.append(time.perf_counter() - tic)
        steps.append(encoder.timings_)
    Path(args.gsc).write_bytes(data)
    return {
        "n": cloud.num_gaussians, "read_ply_s": read_s, "encode_s": statistics.median(times), "encode_runs": times,
        "steps": {k: statistics.median(s[k] for s in steps) for k in steps[0]},
        "bytes": len(data), "sizes": stream.attribute_sizes(), "peak_mb": _peak_mb(),
        "sh_features": (stream.header.get("sh") or {}).get("features"),
        "grid": [stream.header["grid"]["height"], stream.header["grid"]["width"]],
    }


def child_decode(args: argparse.Namespace) -> dict:
    from gscodec_shac.io.ply import write_ply
    from gscodec_shac.codec import Decoder

    data = Path(args.gsc).read_bytes()
    times, cloud = [], None
    for _ in range(args.repeats):
        tic = time.perf_counter()
        cloud = Decoder().decode(data)
        times.append(time.perf_counter() - tic)
    tic = time.perf_counter()
    write_ply(Path(args.gsc).with_suffix(".decoded.ply"), cloud)
    write_s = time.perf_counter() - tic
    Path(args.gsc).with_suffix(".decoded.ply").unlink()
    return {"decode_s": statistics.median(times), "decode_runs": times, "write_ply_s": write_s, "peak_mb": _peak_mb()}


def child_vq(args: argparse.Namespace) -> dict:
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.shac.vq import VectorQuantizer

    ac = read_ply(args.ply).ac_matrix()
    tic = time.perf_counter()
    stage = VectorQuantizer().fit(ac)
    fit_s = time.perf_counter() - tic
    mse = float(((ac - stage.codebook_[stage.labels_]) ** 2).mean())
    return {"n": int(ac.shape[0]), "columns": int(ac.shape[1]), "fit_s": fit_s, "mse": mse,
            "variance": float(ac.var(axis=0).mean()), "peak_mb": _peak_mb()}


def run_child(kind: str, blas_threads: int | None = None, **options) -> dict:
    argv = [sys.executable, __file__, "--child", kind]
    for key, value in options.items():
        argv += [f"--{key.replace('_', '-')}", str(value)]
    env = dict(os.environ)
    if blas_threads:
        env.update(OPENBLAS_NUM_THREADS=str(blas_threads), OMP_NUM_THREADS=str(blas_threads))
    result = subprocess.run(argv, capture_output=True, text=True, cwd=REPO, env=env)
    if result.returncode != 0:
        return {"error": (result.stderr.strip().splitlines() or ["failed"])[-1]}
    return json.loads(result.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------- scenes
def prepare_scene(name: str, work: Path) -> Path | None:
    path = work / f"{name}.ply"
    if path.exists():
        return path
    if name == "playbot":
        tool = shutil.which("splat-transform") or NPM_PREFIX / "node_modules" / ".bin" / "splat-transform"
        if not PLAYBOT.exists() or not Path(tool).exists():
            print(f"skip playbot: need {PLAYBOT} and splat-transform ({NPM_PREFIX})", file=sys.stderr)
            return None
        subprocess.run([str(tool), "-w", "-q", str(PLAYBOT), str(path)], check=True, capture_output=True)
        return path
    from gscodec_shac.io.ply import write_ply
    from gscodec_shac.synthetic import make_synthetic_scene

    write_ply(path, make_synthetic_scene(SCENES[name], seed=0, n_cameras=4).cloud)
    return path


# ------------------------------------------------------------------- report
ATTRS = ("positions", "rotation", "scale", "opacity", "sh_dc", "sh", "sh_state", "header")


def report(rows: list[dict], vq: list[dict], meta: dict) -> str:
    lines = [
        "# Codec benchmarks (`scripts/bench_codec.py`)",
        "",
        f"Machine: {meta['machine']}; load average at start {meta['load_start']}, at end {meta['load_end']} "
        f"(other jobs shared the CPU: treat times as upper bounds); BLAS threads: {meta.get('blas_threads', 'default')}.",
        f"Command: `{meta['command']}`. Times are medians of {meta['repeats']} runs in one child process; "
        "encode = cloud in memory -> .gsc bytes (sorting, SH stage, quantisation, grid codecs, container), "
        "decode = bytes -> cloud; PLY reading/writing listed apart. Peak = the child's max RSS (includes the PLY).",
        "",
        "| scene | N | rate point | SH | features | bytes | bits/G | encode s (sort / SH / code) | decode s | read / write PLY s | peak MB enc / dec |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['scene']} | | {r['rate_point']} | {r['sh']} | error: {r['error']} | | | | | | |")
            continue
        s = r["steps"]
        lines.append(
            f"| {r['scene']} | {r['n']:,} | {r['rate_point']} | {r['sh']} | {r['sh_features'] or '-'} | {r['bytes']:,} | "
            f"{8 * r['bytes'] / r['n']:.2f} | {r['encode_s']:.1f} ({s['sort']:.1f} / {s['sh_stage']:.1f} / {s['code']:.1f}) | "
            f"{r['decode_s']:.2f} | {r['read_ply_s']:.1f} / {r['write_ply_s']:.1f} | {r['peak_mb']:.0f} / {r['decode_peak_mb']:.0f} |"
        )
    lines += ["", "Bytes per attribute (bits per Gaussian):", "",
              "| scene | rate point | SH | " + " | ".join(ATTRS) + " |", "|---|---|---|" + "---|" * len(ATTRS)]
    for r in rows:
        if "error" in r:
            continue
        cells = [f"{8 * r['sizes'].get(a, 0) / r['n']:.2f}" for a in ATTRS]
        lines.append(f"| {r['scene']} | {r['rate_point']} | {r['sh']} | " + " | ".join(cells) + " |")
    if vq:
        lines += ["", "SH k-means codebook (`vq` stage: 65,536 entries, 6-bit centroids, K' = AC columns), one fit each:", "",
                  "| scene | N | K' | fit s | MSE / variance | peak MB |", "|---|---|---|---|---|---|"]
        for v in vq:
            if "error" in v:
                lines.append(f"| {v['scene']} | error: {v['error']} | | | | |")
                continue
            lines.append(f"| {v['scene']} | {v['n']:,} | {v['columns']} | {v['fit_s']:.1f} | {v['mse'] / v['variance']:.4f} | {v['peak_mb']:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--child", choices=("encode", "decode", "vq"), help=argparse.SUPPRESS)
    parser.add_argument("--ply", help=argparse.SUPPRESS)
    parser.add_argument("--gsc", help=argparse.SUPPRESS)
    parser.add_argument("--rate-point", help=argparse.SUPPRESS)
    parser.add_argument("--sh-params", default="{}", help=argparse.SUPPRESS)
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--rate-points", nargs="+", default=DEFAULT_POINTS)
    parser.add_argument("--sh", nargs="+", default=["default", "pca"], help="SH stages ('default' = the rate point's)")
    parser.add_argument("--sort", default=None, help="override the sort method (default: the rate point's)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--blas-threads", type=int, default=None,
                        help="OPENBLAS_NUM_THREADS/OMP_NUM_THREADS for the children (default: inherited)")
    parser.add_argument("--vq", action="store_true", help="also time the k-means codebook fit")
    parser.add_argument("--vq-only", action="store_true")
    parser.add_argument("--work", default="/tmp/gscodec-bench", help="scratch folder for scenes and bitstreams")
    parser.add_argument("--out", default=str(REPO / "docs" / "benchmarks_codec.md"))
    parser.add_argument("--json", default=None, help="raw results (default: WORK/results.json)")
    parser.add_argument("--from-json", nargs="+", help="only write the report, merging these saved results")
    args = parser.parse_args(argv)

    if args.from_json:
        runs = [json.loads(Path(p).read_text()) for p in args.from_json]
        meta = dict(runs[0]["meta"])
        meta["command"] = "; ".join(r["meta"]["command"] for r in runs)
        meta["load_end"] = runs[-1]["meta"]["load_end"]
        meta["repeats"] = "/".join(str(r["meta"]["repeats"]) for r in runs)
        Path(args.out).write_text(report([x for r in runs for x in r["rows"]], [x for r in runs for x in r["vq"]], meta))
        print(f"wrote {args.out}", file=sys.stderr)
        return 0

    if args.child:
        sh = args.sh[0] if isinstance(args.sh, list) else args.sh
        args.sh = sh
        result = {"encode": child_encode, "decode": child_decode, "vq": child_vq}[args.child](args)
        print(json.dumps(result))
        return 0

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    meta = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
        "load_start": " ".join(f"{v:.1f}" for v in os.getloadavg()),
        "command": "python scripts/bench_codec.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "repeats": args.repeats,
        "blas_threads": args.blas_threads or os.environ.get("OPENBLAS_NUM_THREADS", "default"),
    }
    rows, vq = [], []
    for scene in args.scenes:
        ply = prepare_scene(scene, work)
        if ply is None:
            continue
        if args.vq or args.vq_only:
            result = run_child("vq", args.blas_threads, ply=ply, repeats=1)
            vq.append({"scene": scene, **result})
            print(f"vq {scene}: {result}", file=sys.stderr)
        if args.vq_only:
            continue
        for point in args.rate_points:
            for sh in args.sh:
                gsc = work / f"{scene}-{Path(point).name.replace(':', '-')}-{sh}.gsc"
                options = {"ply": ply, "gsc": gsc, "rate_point": point, "sh": sh, "repeats": args.repeats}
                if args.sort:
                    options["sort"] = args.sort
                encoded = run_child("encode", args.blas_threads, **options)
                row = {"scene": scene, "rate_point": point, "sh": sh, **encoded}
                if "error" not in encoded:
                    decoded = run_child("decode", args.blas_threads, gsc=gsc, repeats=args.repeats)
                    if "error" in decoded:
                        row = {**row, "error": "decode: " + decoded["error"]}
                    else:
                        row.update(decode_s=decoded["decode_s"], write_ply_s=decoded["write_ply_s"], decode_peak_mb=decoded["peak_mb"])
                    gsc.unlink(missing_ok=True)
                rows.append(row)
                print(json.dumps({k: v for k, v in row.items() if k not in ("sizes", "encode_runs")}), file=sys.stderr)
    meta["load_end"] = " ".join(f"{v:.1f}" for v in os.getloadavg())
    Path(args.json or work / "results.json").write_text(json.dumps({"meta": meta, "rows": rows, "vq": vq}, indent=1))
    Path(args.out).write_text(report(rows, vq, meta))
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
