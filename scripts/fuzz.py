"""The long fuzz run of every reader: ``.gsc`` streams and every model format, in-process and
through the command line, each case in a child process with a time and a memory limit.

    python scripts/fuzz.py --cases 100000 --out docs/fuzz

``.gsc`` (:mod:`tests.fuzzlib.gsc`): one small stream per SH stage of a synthetic scene and
every legacy stream under ``tests/fixtures/streams``; ``--cases`` mutated streams shared out
over the families ``bytes``, ``resigned``, ``header``, ``state``, ``resize`` and the seeds,
plus every truncation offset of every seed; each through ``decode`` and ``info`` in-process,
and ``--cli-cases`` of them through ``gscodec-shac decode`` in a child process.

Models (:mod:`tests.fuzzlib.models`): one seed per format (dynamic directory, SPZ v1-v4,
.splat, SOG bundle and folder, compressed.ply, gsplat .pt); every truncation (every offset
of members up to 4 KiB), ``--model-cases`` byte edits and ``--hostile`` structured hostile
values per format, read in-process as ``gscodec-shac info`` does, and ``--cli-cases`` per
format and family through ``gscodec-shac info`` in a child process.

Workers are child processes (``--workers``); each limits its address space to its size after
start-up plus ``--memory`` MiB and stops a case after ``--timeout`` seconds; a worker that stops
answering is killed (a hang), one that dies is restarted (a crash). Outcome classes: ``valid``,
``error`` (one clean ``GscodecError``; through the CLI exit 2, 3 or 5 with one ``error:`` line),
and the failures ``internal`` (any other exception; exit 70), ``memory`` (``MemoryError``, or a
case whose peak memory growth exceeds ``--memory-floor`` MiB + ``--memory-factor`` x its input
bytes), ``hang`` and ``crash``. Writes ``OUT/fuzz.json`` (counts and every failure with the case
that rebuilds it) and ``OUT/fuzz.md`` (the table of docs/reliability.md); exits 1 on any failure.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import signal
import sys
import tempfile
import time
import zlib
from collections import Counter, defaultdict
from multiprocessing.connection import wait
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

GSC_FAMILIES = ("bytes", "resigned", "header", "state", "resize")
FAILURES = ("internal", "memory", "hang", "crash")


class CaseTimeout(BaseException):
    """A case ran past its CPU-time limit (raised by SIGPROF inside the worker)."""


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


class Cases:
    """Builds and runs the cases of a worker (seeds given by the parent)."""

    def __init__(self, gsc_seeds: list[tuple[str, bytes]], model_seeds: dict, timeout: float) -> None:
        self.gsc_seeds, self.model_seeds, self.timeout = gsc_seeds, model_seeds, timeout

    def build(self, job: tuple) -> tuple[Any, int]:
        """The case of ``job`` and its input bytes."""
        from tests.fuzzlib import gsc, models

        domain, family, key, index, _ = job
        if domain == "gsc":
            data = gsc.make_case(family, self.gsc_seeds[key][1], key, index)
            return data, len(data)
        files, links = models.make_case(self.model_seeds[key], family, index)
        return (files, links), sum(len(v) for v in files.values())

    def run(self, job: tuple, case: Any, target: str):
        from tests.fuzzlib import cli, gsc, models

        domain, _, key, _, _ = job
        if domain == "gsc" and target != "cli":
            outcome = gsc.run_case(target, case)
            kind = outcome.kind
            if kind == "crash":
                kind = "memory" if outcome.detail.startswith("MemoryError") else "internal"
            return models.Outcome(kind, outcome.detail, outcome.seconds)
        if domain == "gsc":
            with tempfile.TemporaryDirectory(prefix="gscodec-fuzz-") as tmp:
                (Path(tmp) / "case.gsc").write_bytes(case)
                return cli.run(["decode", "case.gsc", "out.ply"], Path(tmp), timeout=self.timeout)
        seed = self.model_seeds[key]
        if target == "cli":
            return models.run_cli(seed, *case, timeout=self.timeout)
        return models.run_case(seed, *case)


def worker_main(conn, gsc_seeds, model_seeds, timeout: float, memory: int, floor: int, factor: float,
                cli: bool) -> None:
    """Run the cases the parent sends, one at a time, and answer with one result per target."""
    import resource

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C

    def alarm(signum, frame):
        raise CaseTimeout()

    signal.signal(signal.SIGPROF, alarm)  # CPU time: a loaded machine does not make hangs
    cases = Cases(gsc_seeds, model_seeds, timeout)
    # load the codec libraries and the readers before the limit is set; the CLI's own size
    cases.run(("gsc", "bytes", 0, 0, ()), gsc_seeds[0][1], "decode")
    for key, seed in model_seeds.items():
        cases.run(("model", "bytes", key, 0, ()), (dict(seed.files), {}), "read")
    # the CLI's own peak on each clean seed: what start-up and a clean read of that format need
    cli_base = {key: cases.run(("model", "bytes", key, 0, ()), (dict(seed.files), {}), "cli").peak_bytes
                for key, seed in model_seeds.items()} if cli else {}
    if cli:
        cli_base["gsc"] = cases.run(("gsc", "bytes", 0, 0, ()), gsc_seeds[0][1], "cli").peak_bytes
    limit = _status("VmSize") + memory
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    while True:
        job = conn.recv()
        if job is None:
            return
        case, size = cases.build(job)
        results = []
        for target in job[4]:
            conn.send(("start", target))
            base = _status("VmRSS")
            peak_ok = _reset_peak()
            signal.setitimer(signal.ITIMER_PROF, timeout if target != "cli" else 7 * timeout)
            try:
                outcome = cases.run(job, case, target)
                kind, detail, seconds = outcome.kind, outcome.detail, outcome.seconds
                if target == "cli":
                    peak = max(0, outcome.peak_bytes - cli_base["gsc" if job[0] == "gsc" else job[2]])
                else:
                    peak = max(0, _status("VmHWM") - base) if peak_ok else 0
            except CaseTimeout:
                kind, detail, seconds, peak = "hang", f"over {timeout:g} s of CPU time (in Python)", timeout, 0
            except MemoryError:
                kind, detail, seconds, peak = "memory", "MemoryError", 0.0, 0
            finally:
                signal.setitimer(signal.ITIMER_PROF, 0)
            if kind in ("valid", "error") and peak > floor + factor * size:
                kind, detail = "memory", f"peak {peak / 2**20:.0f} MiB for {size:,} input bytes ({detail or kind})"
            results.append((target, kind, detail, seconds, peak, size))
        conn.send(("done", results))


# ------------------------------------------------------------------ parent
class Pool:
    """``workers`` child processes, each running one case at a time, restarted when they die or hang."""

    def __init__(self, workers: int, args: tuple, timeout: float) -> None:
        self.args = args
        self.deadline = 8 * timeout + 30.0
        self.context = mp.get_context("spawn")
        self.slots = [self._start() for _ in range(workers)]

    def _start(self) -> dict:
        parent, child = self.context.Pipe()
        process = self.context.Process(target=worker_main, args=(child, *self.args), daemon=True)
        process.start()
        child.close()
        return {"process": process, "conn": parent, "job": None, "target": None, "since": time.monotonic()}

    def run(self, jobs, record) -> None:
        """Run every job; ``record(job, target, kind, detail, seconds, peak, size)`` gets each outcome."""
        pending = iter(jobs)
        busy = sum(self._give(slot, pending) for slot in self.slots)
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
                        self._lost(slot, record, "crash", self._exit_detail(slot))
                        busy += self._give(slot, pending) - 1
                        continue
                    slot["since"] = now
                    if message[0] == "start":
                        slot["target"] = message[1]
                        continue
                    for result in message[1]:
                        record(slot["job"], *result)
                    slot["job"] = None
                    busy += self._give(slot, pending) - 1
                elif now - slot["since"] > self.deadline:
                    slot["process"].kill()
                    slot["process"].join()
                    self._lost(slot, record, "hang", f"no answer for {self.deadline:g} s (killed)")
                    busy += self._give(slot, pending) - 1

    def _give(self, slot: dict, pending) -> int:
        job = next(pending, None)
        if job is None:
            return 0
        slot["job"], slot["target"], slot["since"] = job, None, time.monotonic()
        slot["conn"].send(job)
        return 1

    def _lost(self, slot: dict, record, kind: str, detail: str) -> None:
        """The worker of ``slot`` hung or died: record the case, start a new worker."""
        record(slot["job"], slot["target"] or slot["job"][4][0], kind, detail, 0.0, 0, 0)
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
    """Counts per (reader, family, target) and the failing cases."""

    def __init__(self, gsc_names: list[str]) -> None:
        self.gsc_names = gsc_names
        self.rows: dict[tuple[str, str, str], Counter] = defaultdict(Counter)
        self.slowest: dict[tuple[str, str, str], float] = defaultdict(float)
        self.peak: dict[tuple[str, str, str], int] = defaultdict(int)
        self.ratio: dict[tuple[str, str, str], float] = defaultdict(float)
        self.failures: list[dict[str, Any]] = []

    def record(self, job, target: str, kind: str, detail: str, seconds: float, peak: int, size: int) -> None:
        domain, family, key, index, _ = job
        reader = ".gsc" if domain == "gsc" else key
        row_key = (reader, family, target)
        row = self.rows[row_key]
        row["cases"] += 1
        row[kind] += 1
        self.slowest[row_key] = max(self.slowest[row_key], seconds)
        self.peak[row_key] = max(self.peak[row_key], peak)
        if size:
            self.ratio[row_key] = max(self.ratio[row_key], peak / size)
        if kind in FAILURES:
            seed = self.gsc_names[key] if domain == "gsc" else key
            self.failures.append({"domain": domain, "family": family, "seed": seed, "seed_index": key, "index": index,
                                  "target": target, "kind": kind, "detail": detail})

    def table(self) -> list[dict[str, Any]]:
        out = []
        for key in sorted(self.rows, key=lambda k: (k[0] != ".gsc", k[0], k[1], k[2])):
            row = self.rows[key]
            out.append({
                "reader": key[0], "family": key[1], "target": key[2], "cases": row["cases"], "valid": row["valid"],
                "clean_errors": row["error"], **{kind: row[kind] for kind in FAILURES},
                "max_seconds": round(self.slowest[key], 3), "max_peak_mib": round(self.peak[key] / 2**20, 1),
            })
        return out


def markdown(table: list[dict[str, Any]], config: dict[str, Any]) -> str:
    """One row per reader and family: in-process outcomes (both targets of a .gsc case count)
    and CLI runs, the outcome classes over both, the slowest case and the largest peak growth."""
    rows: dict[tuple[str, str], Counter] = defaultdict(Counter)
    slowest: dict[tuple[str, str], list[float]] = defaultdict(lambda: [0.0, 0.0])
    peak: dict[tuple[str, str], float] = defaultdict(float)
    for row in table:
        key, cli = (row["reader"], row["family"]), row["target"] == "cli"
        rows[key]["cli" if cli else "inproc"] += row["cases"]
        rows[key].update({c: row[c] for c in ("valid", "clean_errors") + FAILURES})
        slowest[key][int(cli)] = max(slowest[key][int(cli)], row["max_seconds"])
        if not cli:
            peak[key] = max(peak[key], row["max_peak_mib"])
    cols = ("inproc", "cli", "valid", "clean_errors") + FAILURES
    lines = ["| reader | family | in-process | CLI | valid | clean errors | internal | memory | hangs | crashes "
             "| max s (in-process / CLI) | max peak MiB |", "|---|---|" + "---:|" * 10]
    totals: Counter = Counter()
    for key in sorted(rows, key=lambda k: (k[0] != ".gsc", k[0], k[1])):
        row = rows[key]
        lines.append(f"| {key[0]} | {key[1]} | " + " | ".join(f"{row[c]:,}" for c in cols)
                     + f" | {slowest[key][0]:.2f} / {slowest[key][1]:.2f} | {peak[key]:.0f} |")
        totals.update({c: row[c] for c in cols})
    lines.append("| **all** | | " + " | ".join(f"**{totals[c]:,}**" for c in cols) + " | | |")
    lines.append("")
    lines.append(f"{config['gsc_mutated']:,} mutated .gsc streams and {config['gsc_truncations']:,} truncations "
                 f"({len(config['gsc_seeds'])} seeds), each through decode and info in-process, {config['gsc_cli']:,} "
                 f"of them through `gscodec-shac decode`; {config['model_cases']:,} model cases in-process and "
                 f"{config['model_cli']:,} through `gscodec-shac info`; {config['seconds']:.0f} s with "
                 f"{config['workers']} workers; limits {config['timeout']:g} s and {config['memory_mib']:,} MiB of "
                 f"address space per case; a case counts as memory when its resident set grows past "
                 f"{config['memory_floor_mib']} MiB + {config['memory_factor']:g} x its input bytes.")
    return "\n".join(lines) + "\n"


def _jobs(args, gsc_seeds, model_seeds) -> tuple[list[tuple], dict[str, int]]:
    from tests.fuzzlib import models

    jobs: list[tuple] = []
    counts = Counter()
    if args.only in ("all", "gsc"):
        if not args.no_truncations:
            for s, (_, data) in enumerate(gsc_seeds):
                jobs += [("gsc", "truncate", s, offset, ("decode", "info")) for offset in range(len(data))]
                counts["gsc_truncations"] += len(data)
        for k in range(args.cases):
            family = GSC_FAMILIES[k % len(GSC_FAMILIES)]
            seed = (k // len(GSC_FAMILIES)) % len(gsc_seeds)
            index = k // (len(GSC_FAMILIES) * len(gsc_seeds))
            jobs.append(("gsc", family, seed, index, ("decode", "info")))
            if k < args.cli_cases * len(GSC_FAMILIES):
                jobs.append(("gsc", family, seed, index, ("cli",)))
                counts["gsc_cli"] += 1
        counts["gsc_mutated"] = args.cases
    if args.only in ("all", "models"):
        for key, seed in model_seeds.items():
            sizes = {"truncate": len(models.truncation_cases(seed)) if not args.no_truncations else 0,
                     "bytes": args.model_cases, "hostile": args.hostile}
            for family, count in sizes.items():
                jobs += [("model", family, key, index, ("read",)) for index in range(count)]
                counts["model_cases"] += count
                step = max(1, count // max(1, args.cli_cases))
                cli = [("model", family, key, index, ("cli",)) for index in range(0, count, step)][: args.cli_cases]
                jobs += cli
                counts["model_cli"] += len(cli)
    if args.cli_only:
        jobs = [job for job in jobs if job[4] == ("cli",)]
        counts["gsc_mutated"] = counts["gsc_truncations"] = counts["model_cases"] = 0
    # interleave so that the slow CLI and bomb cases spread over the run
    jobs.sort(key=lambda job: zlib.crc32(repr(job).encode()))
    return jobs, counts


def _merge(records: list[dict[str, Any]]) -> dict[str, Any]:
    """One record of several runs: rows by (reader, family, target), the later run's kept."""
    rows: dict[tuple, dict] = {}
    failures: list[dict] = []
    config = dict(records[0]["config"])
    for record in records:
        kept = {(r["reader"], r["family"], r["target"]) for r in record["table"]}
        failures = [f for f in failures if ((".gsc" if f["domain"] == "gsc" else f["seed"]), f["family"], f["target"])
                    not in kept] + record["failures"]
        rows.update({(r["reader"], r["family"], r["target"]): r for r in record["table"]})
        for key in ("gsc_mutated", "gsc_truncations", "gsc_cli", "model_cases", "model_cli"):
            if record["config"][key]:
                config[key] = record["config"][key]
    config["seconds"] = sum(record["config"]["seconds"] for record in records)
    config["command"] = " && ".join(record["config"]["command"] for record in records)
    return {"config": config, "table": list(rows.values()), "failures": failures}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=10_000, help="mutated .gsc streams (default 10000)")
    parser.add_argument("--model-cases", type=int, default=2000, help="byte-edit cases per model format (default 2000)")
    parser.add_argument("--hostile", type=int, default=500, help="hostile-value cases per model format (default 500)")
    parser.add_argument("--cli-cases", type=int, default=40,
                        help="cases through the CLI per model format and family, and per .gsc family (default 40)")
    parser.add_argument("--only", choices=("all", "gsc", "models"), default="all", help="which readers (default all)")
    parser.add_argument("--out", default="fuzz-output", help="folder for fuzz.json and fuzz.md")
    parser.add_argument("--fixtures", default=str(REPO / "tests" / "fixtures" / "streams"),
                        help="folder of legacy .gsc seeds ('' for none)")
    parser.add_argument("--seed-gaussians", type=int, default=300, help="Gaussians of the synthetic .gsc seeds")
    parser.add_argument("--workers", type=int, default=max(1, min(4, os.cpu_count() or 1)))
    parser.add_argument("--timeout", type=float, default=10.0, help="seconds per case and target (default 10)")
    parser.add_argument("--memory", type=int, default=2048, help="MiB of address space per case (default 2048)")
    parser.add_argument("--memory-floor", type=int, default=64, help="MiB any case may grow by (default 64)")
    parser.add_argument("--memory-factor", type=float, default=64.0,
                        help="and this many times its input bytes on top (default 64)")
    parser.add_argument("--no-truncations", action="store_true", help="skip the truncations")
    parser.add_argument("--cli-only", action="store_true", help="only the cases through the CLI")
    parser.add_argument("--from-json", metavar="FUZZ_JSON", nargs="+",
                        help="only rewrite the table of earlier runs' fuzz.json (several: merged into --out, a later "
                             "run's rows replacing an earlier one's of the same reader, family and target)")
    args = parser.parse_args(argv)
    from gscodec_shac.atomic import write_atomic, write_json

    if args.from_json:
        record = _merge([json.loads(Path(path).read_text()) for path in args.from_json])
        if len(args.from_json) > 1:
            write_json(Path(args.out) / "fuzz.json", record)
        text = markdown(record["table"], record["config"])
        write_atomic((Path(args.out) if len(args.from_json) > 1 else Path(args.from_json[0]).parent) / "fuzz.md", text)
        print(text)
        return 0
    os.environ.setdefault("MALLOC_ARENA_MAX", "2")  # glibc arenas reserve 64 MiB of address space per thread
    from tests.fuzzlib import gsc, models

    tic = time.monotonic()
    gsc_seeds = list(gsc.seed_streams(args.seed_gaussians, fixtures=args.fixtures or None).items())
    model_seeds = models.make_seeds()
    jobs, counts = _jobs(args, gsc_seeds, model_seeds)
    outcomes = sum(len(job[4]) for job in jobs)
    tally = Tally([name for name, _ in gsc_seeds])
    pool = Pool(args.workers, (gsc_seeds, model_seeds, args.timeout, args.memory << 20, args.memory_floor << 20,
                               args.memory_factor, args.cli_cases > 0), args.timeout)
    done = [0]

    def record(*item) -> None:
        tally.record(*item)
        done[0] += 1
        if done[0] % 20_000 == 0:
            print(f"{done[0]:,} of {outcomes:,} outcomes, {time.monotonic() - tic:.0f} s", flush=True)

    try:
        pool.run(jobs, record)
    finally:
        pool.close()
    table = tally.table()
    config = {
        "command": "python scripts/fuzz.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "gsc_mutated": counts["gsc_mutated"], "gsc_truncations": counts["gsc_truncations"],
        "gsc_cli": counts["gsc_cli"], "model_cases": counts["model_cases"], "model_cli": counts["model_cli"],
        "gsc_seeds": {n: len(d) for n, d in gsc_seeds},
        "model_seeds": {k: sum(len(v) for v in s.files.values()) for k, s in model_seeds.items()},
        "workers": args.workers, "timeout": args.timeout, "memory_mib": args.memory,
        "memory_floor_mib": args.memory_floor, "memory_factor": args.memory_factor,
        "seconds": time.monotonic() - tic,
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "fuzz.json", {"config": config, "table": table, "failures": tally.failures})
    write_atomic(out / "fuzz.md", markdown(table, config))
    print(markdown(table, config))
    for failure in tally.failures[:20]:
        print(f"{failure['kind']}: {failure['target']} of {failure['domain']} {failure['seed']} {failure['family']} "
              f"case {failure['index']}: {failure['detail']}")
    return 1 if tally.failures else 0


if __name__ == "__main__":
    sys.exit(main())
