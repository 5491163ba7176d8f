"""What the rate controller's probe cache saves (issue 25): one size target, the cache on and off in turn.

The controller codes its probe (20,000 Gaussians and the extreme rows) 8-10 times in a size-target
run: at the four probe QPs, for the DC-only bar and at up to three plans. Those encodes share one
chunk cache (``RateController._probe_encoder``). This script runs ``fit()`` and ``encode(target)``
in one process with the cache (``cached``) and with every probe encode fresh (``fresh``, the code
before it), alternating which goes first, ``--repeat`` rounds. Per run: wall seconds, the
controller's own phases (``probe``, ``calibrate``, ``plan_probe``, ``encode``) and the file's sha256
(the same file both ways); medians per kind are printed and every row goes to
``OUT/bench_probe_cache.json`` and ``.csv``.

    python scripts/bench_probe_cache.py ../out/bench/250k/s250k.ply --bpg 100 --repeat 3 --out ../out/probe_cache
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from bench_speed import write_results  # noqa: E402

from gscodec_shac.codec.encoder import Encoder  # noqa: E402
from gscodec_shac.codec.rate_control import RateController, make_target  # noqa: E402
from gscodec_shac.codec.rate_points import RatePoint  # noqa: E402

PHASES = ("probe", "calibrate", "plan_probe", "encode")
COLUMNS = ("kind", "round", "wall_s", *PHASES, "bytes", "sha256")


class FreshProbes(RateController):
    """The controller with every probe encode fresh, as before the cache."""

    def _probe_encoder(self, point: RatePoint, *, cached: bool = True) -> Encoder:
        return super()._probe_encoder(point, cached=False)


def one_run(cloud, bpg: float, kind: str) -> dict:
    """Fit and one size target, timed; the controller's phases from its ``seconds``."""
    controller_class = RateController if kind == "cached" else FreshProbes
    tic = time.perf_counter()
    outcome = controller_class(cloud).fit().encode(make_target(cloud.num_gaussians, bpg=bpg))
    data = outcome.stream.to_bytes()
    return {"kind": kind, "wall_s": round(time.perf_counter() - tic, 3),
            **{phase: round(outcome.seconds.get(phase, 0.0), 3) for phase in PHASES},
            "bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("model", type=Path, help="a PLY (e.g. bench_speed.py's synthetic s250k.ply)")
    parser.add_argument("--bpg", type=float, default=100.0, help="the size target in bits per Gaussian")
    parser.add_argument("--repeat", type=int, default=3, help="rounds, each running both kinds")
    parser.add_argument("--out", type=Path, required=True, help="where the JSON and CSV go")
    args = parser.parse_args(argv)
    from gscodec_shac.io.models import read_model

    cloud, _ = read_model(args.model)
    rows = []
    for round_ in range(max(1, args.repeat)):
        for kind in (("cached", "fresh") if round_ % 2 == 0 else ("fresh", "cached")):
            rows.append({**one_run(cloud, args.bpg, kind), "round": round_ + 1})
            print(" ".join(f"{key}={rows[-1][key]}" for key in COLUMNS if key != "sha256"), flush=True)
    for kind in ("cached", "fresh"):
        mine = [row for row in rows if row["kind"] == kind]
        medians = {key: statistics.median(row[key] for row in mine) for key in ("wall_s", *PHASES)}
        print(f"{kind}: medians " + ", ".join(f"{key} {value:.2f}" for key, value in medians.items()))
    same = len({row["sha256"] for row in rows}) == 1
    print("the same file from every run" if same else "the files differ between runs")
    args.out.mkdir(parents=True, exist_ok=True)
    write_results(args.out / "bench_probe_cache", {"model": str(args.model), "bpg": args.bpg, "rows": rows},
                  rows, list(COLUMNS))
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
