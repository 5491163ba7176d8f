"""Every table and figure of the SHAC paper and the command that reproduces it here (docs/paper.md).

    python scripts/paper.py                      # list: item, doc, full command
    python scripts/paper.py --run "Table V"      # run one item's full command
    python scripts/paper.py --run "Table V" --quick   # its smoke version (minutes or less)
    python scripts/paper.py --check              # run every smoke version, report ok / failed

Commands run from the repository root with this interpreter (``python`` below is replaced by
``sys.executable``; ``gscodec-shac`` by ``python -m gscodec_shac``). Full commands read data from
``../shared`` and write under ``../outputs``; smoke versions write under a temporary folder.
Items produced by other parts of the project name their document only.
"""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import sys
import tempfile
import time

S = "../shared/data/scenes"
O = "../outputs/paper"

#: (item, document, full command or None, smoke command or None); {tmp} = a temporary folder;
#: " && " separates commands run in order.
ITEMS: list[tuple[str, str, str | None, str | None]] = [
    ("Table I", "docs/analysis.md",
     f"gscodec-shac analyze {S}/kacy_sh3_9k/point_cloud.ply {S}/bonsai_cpu_sh3/point_cloud.ply --er 0.95 --k 24 "
     f"--out {O}/analysis",
     "gscodec-shac analyze --synthetic 5000 --seeds 0 --er 0.95 --k 24 --out {tmp}/analysis"),
    ("Fig. 1", "docs/analysis.md",
     f"gscodec-shac analyze {S}/bonsai_cpu_sh3/point_cloud.ply --out {O}/analysis_fig1",
     "gscodec-shac analyze --synthetic 5000 --seeds 0 --out {tmp}/analysis_fig1"),
    ("Fig. 2", "docs/paper.md", "python scripts/fig2_sh_basis.py --out docs/figures/fig2_sh_basis.png",
     "python scripts/fig2_sh_basis.py --quick --out {tmp}/fig2.png"),
    ("Fig. 3", "docs/paper.md", "python scripts/fig3_lst_structure.py --out docs/figures/fig3_lst_structure.png",
     "python scripts/fig3_lst_structure.py --out {tmp}/fig3.png"),
    ("Table II", "docs/training.md",
     f"python scripts/table_train.py {S}/snowmiku_capture --runs ../outputs/train --prefix snowmiku --images images_8 "
     f"--json {O}/snowmiku_table.json",
     None),
    ("Table III", "docs/rate_control.md", "gscodec-shac rate-points paper_table3", "gscodec-shac rate-points paper_table3"),
    ("Fig. 4", "docs/gsplat_pca.md", None, None),
    ("Fig. 5", "docs/rd.md", f"gscodec-shac rd sweeps/bonsai.yaml {O}/rd_bonsai --workers 1", None),
    ("Fig. 6", "docs/paper.md",
     f"python scripts/table_lst_ablations.py ../outputs/paper-doc/lst_ablations --capture {S}/snowmiku_capture "
     "--iterations 800 --max-gaussians 20000 --only paper && "
     "python scripts/fig6_side_by_side.py --preset bonsai --preset snowmiku --out docs/figures/fig6_side_by_side.png "
     f"--json {O}/fig6.json",
     "python scripts/fig6_side_by_side.py --quick --out {tmp}/fig6.png"),
    ("Fig. 7", "docs/rate_control.md", f"gscodec-shac rd sweeps/rate_control.yaml {O}/rd_rate_control --workers 1", None),
    ("Fig. 8", "docs/rd.md", f"gscodec-shac rd sweeps/chair.yaml {O}/rd_chair --workers 1", None),
    ("Fig. 9", "docs/rd.md", f"gscodec-shac rd sweeps/playbot.yaml {O}/rd_playbot --workers 1", None),
    ("Table IV", "docs/dynamic.md", None, None),
    ("Table V", "docs/paper.md",
     f"python scripts/table5_training_overhead.py --capture {S}/snowmiku_capture --sizes 10000 40000 --rounds 3 "
     f"--block 6 --json {O}/table5.json --md {O}/table5.md",
     "python scripts/table5_training_overhead.py --quick"),
    ("Table VI", "docs/paper.md",
     f"python scripts/table6_sh_codec_time.py --scene bonsai_cpu_sh3={S}/bonsai_cpu_sh3/point_cloud.ply --repeats 3 "
     f"--json {O}/table6_bonsai.json && python scripts/table6_sh_codec_time.py --synthetic 200000 --sort morton "
     f"--repeats 1 --json {O}/table6_synthetic200k.json",
     "python scripts/table6_sh_codec_time.py --quick"),
    ("Fig. 10", "docs/ablations.md", None, None),
    ("Fig. 11", "docs/ablations.md", None, None),
    ("Table VII", "docs/paper.md",
     f"python scripts/table_lst_ablations.py {O}/lst_ablations_400 --capture {S}/snowmiku_capture --iterations 400 "
     "--max-gaussians 10000 --seeds 0 1 2 3 --rd",
     "python scripts/table_lst_ablations.py {tmp}/lst_ablations --quick --rd --capture " + f"{S}/snowmiku_capture"),
    ("Fig. 12", "docs/paper.md", "(Table VII's command: variants paper and l2, --rd)", None),
    ("Fig. 13", "docs/paper.md", "(Table VII's command: variants paper and lambda0, --rd)", None),
    ("Table VIII", "docs/paper.md", "(Table VII's command: variants vector, linear, mlp, paper)", None),
    ("Table IX", "docs/paper.md", "(Table VII's command: variants dense, separate, identity, paper)", None),
]


def argv_of(command: str, tmp: str) -> list[str]:
    words = shlex.split(command.format(tmp=tmp))
    if words[0] == "gscodec-shac":
        return [sys.executable, "-m", "gscodec_shac", *words[1:]]
    if words[0] == "python":
        return [sys.executable, *words[1:]]
    return words


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", metavar="ITEM", help='one item, e.g. "Table V" or "Fig. 6"')
    parser.add_argument("--quick", action="store_true", help="with --run: the smoke version")
    parser.add_argument("--check", action="store_true", help="run every smoke version")
    args = parser.parse_args(argv)
    env = dict(os.environ)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    if args.check:
        failed = 0
        with tempfile.TemporaryDirectory() as tmp:
            for item, _, _, quick in ITEMS:
                if quick is None:
                    continue
                t0 = time.perf_counter()
                done = subprocess.run(argv_of(quick, tmp), cwd=root, env=env, capture_output=True, text=True)
                status = "ok" if done.returncode == 0 else f"FAILED ({done.returncode})"
                failed += done.returncode != 0
                print(f"{item:10s} {status:12s} {time.perf_counter() - t0:6.1f} s  {quick.format(tmp='TMP')}", flush=True)
                if done.returncode:
                    print(done.stderr[-2000:])
        return 1 if failed else 0
    if args.run:
        match = [entry for entry in ITEMS if entry[0].lower() == args.run.lower()]
        if not match:
            parser.error(f"unknown item {args.run!r}; items: {', '.join(e[0] for e in ITEMS)}")
        item, doc, full, quick = match[0]
        command = quick if args.quick else full
        if command is None or command.startswith("("):
            print(f"{item}: no command of its own here; see {doc}" + (f" {command}" if command else ""))
            return 0
        if not args.quick:
            os.makedirs(os.path.join(root, O), exist_ok=True)  # the full commands write their JSON there
        with tempfile.TemporaryDirectory() as tmp:
            for part in command.split(" && "):  # several commands run in order, stopping at a failure
                code = subprocess.run(argv_of(part, tmp), cwd=root, env=env).returncode
                if code:
                    return code
            return 0
    for item, doc, full, quick in ITEMS:
        print(f"{item:10s} {doc:22s} {full or '(see the document)'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
