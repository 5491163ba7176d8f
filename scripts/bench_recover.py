"""What ``encode --recover`` costs beside a plain rate-controlled encode (issues 25 and 29).

For each size target B (bits per Gaussian) two commands run, each in its own process and
measured as ``scripts/bench_speed.py`` measures (wall, CPU with the x265 workers, peak RSS):

* ``plain``: ``gscodec-shac encode MODEL OUT --target-bpg B --cameras CAMERAS --json``;
* ``recover``: the same with ``--recover`` (the model pruned by importance and recovered by a
  short fine-tune towards its own renders, then the better file on the judges is kept).

``--repeat R`` runs each pair R times, ``plain`` first in odd rounds and ``recover`` first in even
ones (the load of a shared machine drifts). Each row records the file's size, bits per Gaussian,
PSNR against the uncompressed model, the source kept and its fit's seconds (``--json``'s
``rate_control.recovery``); the script prints, per target, the median wall and CPU seconds and
the ratio recover / plain, and writes every row to ``OUT/bench_recover.json`` and ``.csv``.

    python scripts/bench_recover.py ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply \\
        --cameras ../shared/data/scenes/bonsai_cpu_sh3/cameras.json --bpg 40,100 --repeat 2 \\
        --out ../out/bench_recover
"""

from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from bench_speed import measured, write_results  # noqa: E402

KINDS = ("plain", "recover")
COLUMNS = ("bpg_target", "kind", "round", "wall_s", "cpu_s", "peak_rss_gb", "peak_tree_rss_gb", "load", "bytes",
           "bits_per_gaussian", "measured_psnr", "keep", "encodes", "recovery_seconds", "sha256")


def encode_command(model: str, out: Path, bpg: float, cameras: str, background: str | None,
                   recover: bool) -> list[str]:
    """The ``gscodec-shac encode`` command line of one measured run."""
    command = [sys.executable, "-m", "gscodec_shac", "encode", model, str(out), "--target-bpg", f"{bpg:g}",
               "--cameras", cameras, "--json", "--force"]
    if background:
        command += ["--background", background]
    return command + (["--recover"] if recover else [])


def summary_row(run: dict, out: Path) -> dict:
    """The fields of one run's ``--json`` summary kept in the results (and the file's sha256)."""
    summary = json.loads(run["stdout"])
    control = summary["rate_control"]
    recovery = control.get("recovery") or {}
    return {"bytes": summary["bytes"], "bits_per_gaussian": round(summary["bits_per_gaussian"], 2),
            "measured_psnr": control.get("measured_psnr"), "keep": recovery.get("keep", 1.0),
            "encodes": control.get("encodes"), "recovery_seconds": recovery.get("seconds"),
            "sha256": hashlib.sha256(out.read_bytes()).hexdigest()}


def ratios(rows: list[dict]) -> dict[float, dict]:
    """Per target: the median wall and CPU seconds of each kind and recover / plain of those medians."""
    out = {}
    for bpg in sorted({row["bpg_target"] for row in rows}):
        medians = {kind: {key: statistics.median(r[key] for r in rows if r["bpg_target"] == bpg and r["kind"] == kind)
                          for key in ("wall_s", "cpu_s")} for kind in KINDS}
        out[bpg] = medians | {"ratio_wall": medians["recover"]["wall_s"] / medians["plain"]["wall_s"],
                              "ratio_cpu": medians["recover"]["cpu_s"] / medians["plain"]["cpu_s"]}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", help="a trained model (PLY)")
    parser.add_argument("--cameras", required=True, help="its camera file (the controller's and the recovery's views)")
    parser.add_argument("--background", help="R,G,B in [0, 1] of the renders (default black)")
    parser.add_argument("--bpg", default="40,100", help="comma-separated bits-per-Gaussian targets")
    parser.add_argument("--repeat", type=int, default=1, help="pairs of runs per target")
    parser.add_argument("--nice", type=int, default=0, help="niceness of the measured processes")
    parser.add_argument("--out", type=Path, required=True, help="work and result folder")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    targets = [float(value) for value in args.bpg.split(",") if value.strip()]
    rows: list[dict] = []
    for bpg in targets:
        for round_ in range(1, args.repeat + 1):
            for kind in (KINDS if round_ % 2 else KINDS[::-1]):
                out = args.out / f"bpg{bpg:g}_{kind}.gsc"
                run = measured(encode_command(args.model, out, bpg, args.cameras, args.background, kind == "recover"),
                               args.nice, keep_output=True)
                row = {"bpg_target": bpg, "kind": kind, "round": round_} | {key: run[key] for key in COLUMNS if key in run}
                row |= summary_row(run, out)
                rows.append(row)
                print(f"{bpg:6g} bits/G {kind:8s} round {round_}: wall {row['wall_s']:7.2f} s  cpu {row['cpu_s']:7.2f} s  "
                      f"peak {row['peak_rss_gb']:.2f} GB  load {row['load']:.1f}  {row['bytes']:,} bytes, "
                      f"{row['measured_psnr']} dB, kept {row['keep']:g}", flush=True)
    summary = ratios(rows)
    for bpg, line in summary.items():
        print(f"{bpg:6g} bits/G: plain {line['plain']['wall_s']:.2f} s, --recover {line['recover']['wall_s']:.2f} s: "
              f"{line['ratio_wall']:.2f}x wall, {line['ratio_cpu']:.2f}x CPU (medians of {args.repeat})")
    write_results(args.out / "bench_recover", {"rows": rows, "medians": summary}, rows, list(COLUMNS))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
