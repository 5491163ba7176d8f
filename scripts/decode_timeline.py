"""Where a decode's wall time goes: each task of ``Decoder().decode`` with its start, end and thread.

Wraps the decoder's pieces (the set-coded positions, each chunk's decode, the SH stage's inverse) with
timers and decodes the file ``--repeat`` times in this process (after one warm-up decode), printing one
timeline per decode and writing them as JSON/CSV: which thread held the critical path, and what was
left after the last picture (docs/benchmarks.md, "Issue 25 at a glance").

    python scripts/decode_timeline.py ../out/bench/1M/s1M.gsc --repeat 3 --out decode_timeline_1M
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Sequence

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from bench_speed import write_results  # noqa: E402

FIELDS = ["decode", "task", "chunk", "start_s", "end_s", "seconds", "thread"]


def timed(events: list[dict[str, Any]], task: str, function: Callable, name_of: Callable[..., str] | None = None
          ) -> Callable:
    """``function`` recording each call's task, start, end (``time.perf_counter``) and thread in ``events``."""
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            events.append({"task": task, "chunk": name_of(*args) if name_of else "", "start": start,
                           "end": time.perf_counter(), "thread": threading.get_ident()})
    return wrapper


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stream", type=Path, help="a .gsc file")
    parser.add_argument("--repeat", type=int, default=3, help="decodes timed after the warm-up (default 3)")
    parser.add_argument("--out", type=Path, help="results stem: OUT.json and OUT.csv")
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")

    from gscodec_shac.codec import decoder

    events: list[dict[str, Any]] = []
    patched = [(decoder._ChunkTask, "decode", "chunk", lambda task: task.plan.name),
               (decoder, "_position_set", "position set", lambda chunk, *_: chunk.name),
               (decoder._FeatureCodes, "inverse", "SH inverse", None)]
    originals = [getattr(owner, name) for owner, name, _, _ in patched]
    for (owner, name, task, name_of), original in zip(patched, originals):
        setattr(owner, name, timed(events, task, original, name_of))
    try:
        data = args.stream.read_bytes()
        decoder.Decoder().decode(data)  # imports, first touches
        timelines = []
        for _ in range(args.repeat):
            events.clear()
            tic = time.perf_counter()
            decoder.Decoder().decode(data)
            timelines.append((tic, time.perf_counter() - tic, list(events)))
    finally:  # the decoder as it was (a caller in the same process decodes untimed)
        for (owner, name, _, _), original in zip(patched, originals):
            setattr(owner, name, original)
    rows = []
    for run, (tic, total, events) in enumerate(timelines):
        threads = {thread: i for i, thread in enumerate(dict.fromkeys(e["thread"] for e in sorted(
            events, key=lambda e: e["start"])))}
        print(f"decode {run + 1}: {total:.3f} s")
        for event in sorted(events, key=lambda e: e["start"]):
            row = {"decode": run + 1, "task": event["task"], "chunk": event["chunk"],
                   "start_s": event["start"] - tic, "end_s": event["end"] - tic,
                   "seconds": event["end"] - event["start"], "thread": threads[event["thread"]]}
            rows.append(row)
            print(f"  {row['task']:12s} {row['chunk']:14s} {row['start_s']:6.3f} -> {row['end_s']:6.3f} s "
                  f"({row['seconds']:.3f}) thread {row['thread']}")
        rows.append({"decode": run + 1, "task": "whole decode", "chunk": "", "start_s": 0.0, "end_s": total,
                     "seconds": total, "thread": ""})
    if args.out:
        write_results(args.out, {"stream": str(args.stream), "rows": rows}, rows, FIELDS)
    return rows


if __name__ == "__main__":
    main()
