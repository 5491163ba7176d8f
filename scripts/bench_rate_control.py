"""Benchmark rate control against a plain encode: seconds, ratios and where the time goes.

For each scene: a plain encode at the rate controller's template (``shac_auto:template``,
cloud in memory -> bytes, sorting included) and its decode, then ``encode --target-bpg``
at each target (the controller's fit, probes and renders included) — medians over
``--repeats`` runs, with the ratio to the plain encode. The machine's load average is
recorded at the start and the end; on a shared machine compare the ratios, not seconds.

Scenes: ``synthetic-1m`` (:func:`gscodec_shac.synthetic.make_synthetic_scene`, made once
into ``--work``), ``bonsai`` (../shared/data/scenes/bonsai_cpu_sh3) or a PLY path.

    python scripts/bench_rate_control.py --scenes synthetic-1m bonsai --targets 60 120 \\
        --json /tmp/bench_rc.json --markdown docs/benchmarks_rate_control.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GSCODEC_SHARED_SCENES", REPO.parent / "shared" / "data" / "scenes"))


def load_scene(name: str, work: Path):
    from gscodec_shac.io.ply import read_ply, write_ply
    from gscodec_shac.synthetic import make_synthetic_scene

    if name == "synthetic-1m":
        path = work / "synthetic_1m.ply"
        if not path.exists():
            work.mkdir(parents=True, exist_ok=True)
            write_ply(path, make_synthetic_scene(1_000_000, seed=0, n_cameras=4).cloud)
        return read_ply(path), "synthetic 1M (seed 0)"
    if name == "bonsai":
        return read_ply(SHARED / "bonsai_cpu_sh3" / "point_cloud.ply"), "../shared/data/scenes/bonsai_cpu_sh3"
    return read_ply(name), name


def median_seconds(run, repeats: int) -> tuple[float, object]:
    times, result = [], None
    for _ in range(repeats):
        tic = time.perf_counter()
        result = run()
        times.append(time.perf_counter() - tic)
    return statistics.median(times), result


def bench_scene(name: str, targets: list[float], repeats: int, work: Path) -> list[dict]:
    from gscodec_shac.codec import Decoder, Encoder
    from gscodec_shac.codec.rate_control import TEMPLATE, RateController, Target

    cloud, source = load_scene(name, work)
    n = cloud.num_gaussians
    rows = []
    plain_s, stream = median_seconds(lambda: Encoder(TEMPLATE).encode(cloud), repeats)
    data = stream.to_bytes()
    decode_s, _ = median_seconds(lambda: Decoder().decode(data), repeats)
    rows.append({"scene": name, "source": source, "n": n, "what": f"plain encode ({TEMPLATE})", "seconds": plain_s,
                 "ratio": 1.0, "bits_per_gaussian": 8 * len(data) / n, "decode_s": decode_s})
    for bpg in targets:
        def controlled():
            controller = RateController(cloud)
            outcome = controller.encode(Target("bytes", bpg * n / 8))
            return controller, outcome

        seconds, (controller, outcome) = median_seconds(controlled, repeats)
        rows.append({"scene": name, "source": source, "n": n, "what": f"--target-bpg {bpg:g}", "seconds": seconds,
                     "ratio": seconds / plain_s, "bits_per_gaussian": 8 * outcome.stream.total_bytes() / n,
                     "encodes": outcome.encodes, "steps": {k: round(v, 2) for k, v in controller.seconds_.items()}})
    return rows


def markdown(rows: list[dict], meta: dict) -> str:
    lines = [
        "# Rate-control benchmark (`scripts/bench_rate_control.py`)", "",
        f"Machine: {meta['machine']}; load average at start {meta['load_start']}, at end {meta['load_end']}.",
        f"Command: `{meta['command']}`. Medians of {meta['repeats']} run(s); encode = cloud in memory -> bytes "
        "(sorting, SH stage, grid codecs); a rate-controlled encode includes the controller's probes, render "
        "calibration and every encode it makes; decode = bytes -> cloud.", "",
        "| scene | N | what | seconds | x plain encode | bits/G | encodes | decode s | where the time goes (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        decode = f"{r['decode_s']:.2f}" if "decode_s" in r else "-"
        lines.append(f"| {r['scene']} | {r['n']:,} | {r['what']} | {r['seconds']:.1f} | {r['ratio']:.2f} | "
                     f"{r['bits_per_gaussian']:.1f} | {r.get('encodes', 1)} | {decode} | {r.get('steps', '')} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=["synthetic-1m"])
    parser.add_argument("--targets", nargs="+", type=float, default=[60.0, 120.0], help="bits per Gaussian")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--work", type=Path, default=Path("/tmp/gscodec-bench"), help="scratch folder (outside the repo)")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--markdown", type=Path)
    args = parser.parse_args()
    meta = {"machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
            "load_start": " ".join(f"{v:.1f}" for v in os.getloadavg()), "repeats": args.repeats,
            "command": "python scripts/bench_rate_control.py " + " ".join(
                f"--scenes {' '.join(args.scenes)} --targets {' '.join(f'{t:g}' for t in args.targets)} "
                f"--repeats {args.repeats}".split())}
    rows = [row for scene in args.scenes for row in bench_scene(scene, args.targets, args.repeats, args.work)]
    meta["load_end"] = " ".join(f"{v:.1f}" for v in os.getloadavg())
    text = markdown(rows, meta)
    print(text)
    if args.json:
        args.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    if args.markdown:
        args.markdown.write_text(text)


if __name__ == "__main__":
    main()
