"""The long fuzz run of the ``.gsc`` readers: N mutated streams plus every truncation, for
``decode`` and ``info``, each case in a child process with a time and a memory limit.

    python scripts/fuzz.py --cases 100000 --out docs/fuzz

Seeds: one small stream per SH stage (none, trunc, pca, lst, vq) of a synthetic scene and
every legacy stream under ``tests/fixtures/streams``. The ``--cases`` mutated streams are
shared out over the mutation families (``bytes``, ``resigned``, ``header``, ``state``,
``resize``; see :mod:`gscodec_shac.fuzz`) and the seeds; every truncation offset of every
seed is run on top. Each case goes through both targets.

Workers are child processes (``--workers``); each sets ``RLIMIT_AS`` to its size after
start-up plus ``--memory`` and raises a timeout in a case after ``--timeout`` seconds; a
worker that stops answering is killed (a hang), one that dies is restarted (the case is
counted as died). The per-case peak memory is the growth of the worker's resident set
(``VmHWM``, reset before every target). Writes ``OUT/fuzz.json`` (every count, the failures
with the case that reproduces each) and ``OUT/fuzz.md`` (the table in docs/reliability.md);
the exit status is 1 when any case crashed, hung or died.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import signal
import sys
import time
from collections import Counter, defaultdict
from multiprocessing.connection import wait
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

MUTATION_FAMILIES = ("bytes", "resigned", "header", "state", "resize")


class CaseTimeout(BaseException):
    """A case ran past its time limit (raised by SIGALRM inside the worker)."""


# ------------------------------------------------------------------ worker
def _status(key: str) -> int:
    with open("/proc/self/status") as handle:
        for line in handle:
            if line.startswith(key):
                return int(line.split()[1]) * 1024
    return 0


def _reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as handle:
            handle.write("5")
        return True
    except OSError:
        return False


def worker_main(conn, seeds: list[tuple[str, bytes]], targets: tuple[str, ...], timeout: float, memory: int) -> None:
    """Run the cases the parent sends, one at a time, and answer with one result per target."""
    import resource

    from gscodec_shac import fuzz

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C

    def alarm(signum, frame):
        raise CaseTimeout()

    signal.signal(signal.SIGALRM, alarm)
    for _, data in seeds[:3]:  # load the codec libraries before the limit is set
        for target in targets:
            fuzz.run_case(target, data)
    limit = _status("VmSize") + memory
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    while True:
        job = conn.recv()
        if job is None:
            return
        family, seed_index, index = job
        data = fuzz.make_case(family, seeds[seed_index][1], seed_index, index)
        results = []
        for target in targets:
            conn.send(("start", target))
            base = _status("VmRSS")
            peak_ok = _reset_peak()
            signal.setitimer(signal.ITIMER_REAL, timeout)
            try:
                outcome = fuzz.run_case(target, data)
                kind, detail, seconds = outcome.kind, outcome.detail, outcome.seconds
            except CaseTimeout:
                kind, detail, seconds = "hang", f"over {timeout:g} s (in Python)", timeout
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            peak = max(0, _status("VmHWM") - base) if peak_ok else 0
            results.append((target, kind, detail, seconds, peak))
        conn.send(("done", results))


# ------------------------------------------------------------------ parent
class Pool:
    """``workers`` child processes, each running one case at a time, restarted when they die or hang."""

    def __init__(self, workers: int, seeds, targets, timeout: float, memory: int) -> None:
        self.args = (seeds, targets, timeout, memory)
        self.deadline = 2 * timeout * len(targets) + 30.0
        self.context = mp.get_context("spawn")
        self.slots = [self._start() for _ in range(workers)]

    def _start(self) -> dict:
        parent, child = self.context.Pipe()
        process = self.context.Process(target=worker_main, args=(child, *self.args), daemon=True)
        process.start()
        child.close()
        return {"process": process, "conn": parent, "job": None, "target": None, "since": time.monotonic()}

    def run(self, jobs, record) -> None:
        """Run every job; ``record(job, target, kind, detail, seconds, peak)`` gets each outcome."""
        pending = iter(jobs)
        busy = 0
        for slot in self.slots:
            busy += self._give(slot, pending)
        while busy:
            ready = wait([s["conn"] for s in self.slots if s["job"] is not None], timeout=1.0)
            now = time.monotonic()
            for slot in self.slots:
                if slot["job"] is None:
                    continue
                if slot["conn"] in ready:
                    try:
                        message = slot["conn"].recv()
                    except (EOFError, OSError):
                        self._lost(slot, record, "died", self._exit_detail(slot))
                        busy -= 1
                        busy += self._give(slot, pending)
                        continue
                    slot["since"] = now
                    if message[0] == "start":
                        slot["target"] = message[1]
                        continue
                    for target, kind, detail, seconds, peak in message[1]:
                        record(slot["job"], target, kind, detail, seconds, peak)
                    slot["job"] = None
                    busy -= 1
                    busy += self._give(slot, pending)
                elif now - slot["since"] > self.deadline:
                    slot["process"].kill()
                    slot["process"].join()
                    self._lost(slot, record, "hang", f"no answer for {self.deadline:g} s (killed)")
                    busy -= 1
                    busy += self._give(slot, pending)

    def _give(self, slot: dict, pending) -> int:
        job = next(pending, None)
        if job is None:
            return 0
        slot["job"], slot["target"], slot["since"] = job, None, time.monotonic()
        slot["conn"].send(job)
        return 1

    def _lost(self, slot: dict, record, kind: str, detail: str) -> None:
        """The worker of ``slot`` hung or died: record the case, start a new worker."""
        record(slot["job"], slot["target"] or "decode", kind, detail, 0.0, 0)
        slot["process"].join(timeout=5)
        slot.update(self._start())
        slot["job"] = None

    @staticmethod
    def _exit_detail(slot: dict) -> str:
        slot["process"].join(timeout=5)
        code = slot["process"].exitcode
        return f"worker exited with {code}" + (f" ({signal.Signals(-code).name})" if code and code < 0 else "")

    def close(self) -> None:
        for slot in self.slots:
            try:
                slot["conn"].send(None)
            except OSError:
                pass
        for slot in self.slots:
            slot["process"].join(timeout=10)
            if slot["process"].is_alive():
                slot["process"].kill()


# ------------------------------------------------------------------ summary
class Tally:
    """Counts per (family, target) and the failing cases."""

    def __init__(self, seed_names: list[str]) -> None:
        self.seed_names = seed_names
        self.rows: dict[tuple[str, str], Counter] = defaultdict(Counter)
        self.errors: dict[tuple[str, str], Counter] = defaultdict(Counter)
        self.slowest: dict[tuple[str, str], float] = defaultdict(float)
        self.peak: dict[tuple[str, str], int] = defaultdict(int)
        self.failures: list[dict[str, Any]] = []

    def record(self, job, target: str, kind: str, detail: str, seconds: float, peak: int) -> None:
        family, seed_index, index = job
        key = (family, target)
        row = self.rows[key]
        row["cases"] += 1
        if kind == "crash" and detail.startswith(("MemoryError", "RecursionError")):
            kind = detail.split(":")[0]
        row[kind] += 1
        if kind == "error":
            self.errors[key][detail.split(":")[0]] += 1
        self.slowest[key] = max(self.slowest[key], seconds)
        self.peak[key] = max(self.peak[key], peak)
        if kind not in ("valid", "error"):
            self.failures.append({"family": family, "seed": self.seed_names[seed_index], "seed_index": seed_index,
                                  "index": index, "target": target, "kind": kind, "detail": detail})

    def table(self) -> list[dict[str, Any]]:
        out = []
        for (family, target), row in sorted(self.rows.items(), key=lambda item: (_order(item[0][0]), item[0][1])):
            out.append({
                "family": family, "target": target, "cases": row["cases"], "valid": row["valid"],
                "clean_errors": row["error"], "tracebacks": row["crash"], "MemoryError": row["MemoryError"],
                "RecursionError": row["RecursionError"], "hangs": row["hang"], "died": row["died"],
                "max_seconds": round(self.slowest[(family, target)], 3),
                "max_peak_mib": round(self.peak[(family, target)] / 2**20, 1),
                "errors_by_type": dict(self.errors[(family, target)].most_common()),
            })
        return out


def _order(family: str) -> int:
    return (("truncate",) + MUTATION_FAMILIES).index(family)


def markdown(table: list[dict[str, Any]], config: dict[str, Any]) -> str:
    cols = ("cases", "valid", "clean_errors", "tracebacks", "MemoryError", "RecursionError", "hangs", "died")
    lines = [
        "| family | target | cases | valid | clean errors | tracebacks | MemoryError | RecursionError | "
        "hangs | died | max s | max peak MiB |",
        "|---|---|" + "---:|" * 10,
    ]
    totals: Counter = Counter()
    for row in table:
        lines.append(f"| {row['family']} | {row['target']} | " + " | ".join(f"{row[c]:,}" for c in cols)
                     + f" | {row['max_seconds']:.2f} | {row['max_peak_mib']:.0f} |")
        totals.update({c: row[c] for c in cols})
    lines.append("| **all** | both | " + " | ".join(f"**{totals[c]:,}**" for c in cols) + " | | |")
    lines.append("")
    lines.append(f"{config['mutated_streams']:,} mutated streams and {config['truncations']:,} truncations "
                 f"({len(config['seeds'])} seeds), each through {' and '.join(config['targets'])}; "
                 f"{config['seconds']:.0f} s with {config['workers']} workers, limits {config['timeout']:g} s and "
                 f"{config['memory_mib']:,} MiB per case.")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=10_000, help="mutated streams (default 10000)")
    parser.add_argument("--out", default="fuzz-output", help="folder for fuzz.json and fuzz.md")
    parser.add_argument("--fixtures", default=str(REPO / "tests" / "fixtures" / "streams"),
                        help="folder of legacy .gsc seeds ('' for none)")
    parser.add_argument("--seed-gaussians", type=int, default=300, help="Gaussians of the synthetic seeds")
    parser.add_argument("--workers", type=int, default=max(1, min(4, os.cpu_count() or 1)))
    parser.add_argument("--timeout", type=float, default=20.0, help="seconds per case and target (default 20)")
    parser.add_argument("--memory", type=int, default=2048, help="MiB of address space per case (default 2048)")
    parser.add_argument("--no-truncations", action="store_true", help="skip the every-offset truncations")
    parser.add_argument("--targets", nargs="+", default=["decode", "info"], choices=("decode", "info"))
    parser.add_argument("--from-json", metavar="FUZZ_JSON", help="only rewrite the table of an earlier run's fuzz.json")
    args = parser.parse_args(argv)
    if args.from_json:
        record = json.loads(Path(args.from_json).read_text())
        text = markdown(record["table"], record["config"])
        from gscodec_shac.atomic import write_atomic

        write_atomic(Path(args.from_json).with_name("fuzz.md"), text)
        print(text)
        return 0
    os.environ.setdefault("MALLOC_ARENA_MAX", "2")  # glibc arenas reserve 64 MiB of address space per thread

    from gscodec_shac import fuzz

    tic = time.monotonic()
    seeds = list(fuzz.seed_streams(args.seed_gaussians, fixtures=args.fixtures or None).items())
    jobs: list[tuple[str, int, int]] = []
    if not args.no_truncations:
        jobs += [("truncate", s, offset) for s, (_, data) in enumerate(seeds) for offset in range(len(data))]
    truncations = len(jobs)
    for k in range(args.cases):
        family = MUTATION_FAMILIES[k % len(MUTATION_FAMILIES)]
        seed = (k // len(MUTATION_FAMILIES)) % len(seeds)
        jobs.append((family, seed, k // (len(MUTATION_FAMILIES) * len(seeds))))
    tally = Tally([name for name, _ in seeds])
    pool = Pool(args.workers, seeds, tuple(args.targets), args.timeout, args.memory << 20)
    done = [0]

    def record(*item) -> None:
        tally.record(*item)
        done[0] += 1
        if done[0] % 20_000 == 0:
            print(f"{done[0]:,} of {len(jobs) * len(args.targets):,} outcomes, {time.monotonic() - tic:.0f} s",
                  flush=True)

    try:
        pool.run(jobs, record)
    finally:
        pool.close()
    table = tally.table()
    config = {
        "command": "python scripts/fuzz.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "mutated_streams": args.cases, "truncations": truncations, "seeds": {n: len(d) for n, d in seeds},
        "targets": args.targets, "workers": args.workers, "timeout": args.timeout, "memory_mib": args.memory,
        "seconds": time.monotonic() - tic,
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from gscodec_shac.atomic import write_atomic, write_json

    write_json(out / "fuzz.json", {"config": config, "table": table, "failures": tally.failures})
    write_atomic(out / "fuzz.md", markdown(table, config))
    print(markdown(table, config))
    bad = [f for f in tally.failures]
    for failure in bad[:20]:
        print(f"{failure['kind']}: {failure['target']} of {failure['family']} case {failure['index']} of seed "
              f"{failure['seed']}: {failure['detail']}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
