"""Is a run-to-run byte difference in x265's input (ours) or in x265? (docs/reliability.md)

Sub-commands over directories written with ``GSCODEC_X265_DUMP=DIR``
(:mod:`gscodec_shac.codec.grid.x265_dump`):

``compare DIR...``  one directory per run of the same encode: for every input (frames'
    sha256) the distinct outputs x265 wrote across the runs, and whether every run fed
    x265 the same multiset of inputs. Same input, two outputs: x265. Inputs that differ:
    an earlier stage of ours.

``shuffle DIR --rounds N [--extra :wpp=0]``  code every kept piece N times, in a new random order each round and
    two at once, so every worker codes each piece after a different history; count the outputs
    that differ from the recorded ones.

``repeat DIR --times N [--extra :wpp=0] [--bytes MIN:MAX]``  feed every kept piece (``frames-*.npz`` and its
    options) to x265 N times through the worker processes, optionally with x265 parameters
    appended, and count the distinct outputs per piece; prints CPU time per setting.

``options DIR --extra :me=dia --extra :me=hex ...``  code every kept piece once with its recorded options
    and once per ``--extra`` (appended; ``:me=star`` restores the preset's search where the recorded
    options set another), decode it, and print per setting the bytes, the PSNR of the decoded samples
    against x265's input (the sample range of its bit depth) and the CPU seconds, in total and per piece.

``curve DIR --piece K --offsets=-2,0,2 --extra :rect=0 [--preset medium] ...``  the K-th largest kept piece
    coded at its recorded QP plus each offset, under the recorded options and under each ``--extra`` (a
    ``--preset`` per ``--extra``, optional, replaces the recorded preset); per setting the BD-rate of its
    (bytes, sample PSNR) curve against the recorded options' curve and the CPU seconds relative to theirs
    (docs/benchmarks.md, "A narrower x265 analysis for the long SH streams").

Every ``--extra`` is NAME=VALUE pairs separated by ':'; the leading ':' is optional (it is added).

Example (a stress loop under load):
    for i in 1 2 3; do GSCODEC_X265_DUMP=out/d$i gscodec-shac encode scene.ply out/r$i.gsc \\
        -r shac_ladder:rp4 --sh pca --er 0.97 -q; done
    python scripts/x265_repeat.py compare out/d1 out/d2 out/d3
    python scripts/x265_repeat.py repeat out/d1 --times 20 --extra :wpp=0
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import os
import re
import resource
import time
from typing import Any, Callable

from gscodec_shac.codec.grid import x265_dump, x265_processes


def _records(folder: str) -> list[dict]:
    rows = []
    for path in sorted(glob.glob(os.path.join(folder, "x265-*.jsonl"))):
        with open(path, encoding="utf-8") as lines:
            rows += [json.loads(line) for line in lines if line.strip()]
    return rows


def _settings(row: dict) -> str:
    return json.dumps([row["pix_fmt"], row["options"]], sort_keys=True)


def _workers_cpu(work: Callable[[], Any]) -> tuple[Any, float]:
    """``work()``'s result and the CPU seconds of the x265 worker processes it used (they are
    shut down after it: a child's CPU time is counted once it has ended)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    result = work()
    x265_processes.shutdown()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return result, after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime


def compare(folders: list[str]) -> int:
    """Print per-input output counts across runs; the number of inputs with several outputs."""
    outputs: dict[tuple[str, str], collections.Counter] = collections.defaultdict(collections.Counter)
    sizes: dict[str, int] = {}
    inputs_per_run = []
    for folder in folders:
        rows = _records(folder)
        inputs_per_run.append(collections.Counter((r["input"], _settings(r)) for r in rows))
        for row in rows:
            outputs[(row["input"], _settings(row))][row["output"]] += 1
            sizes[row["output"]] = row["bytes"]
    same_inputs = all(run == inputs_per_run[0] for run in inputs_per_run)
    differing = {key: seen for key, seen in outputs.items() if len(seen) > 1}
    print(f"runs {len(folders)}, pieces per run {sorted({sum(r.values()) for r in inputs_per_run})}, "
          f"distinct (input, settings) {len(outputs)}, every run fed x265 the same inputs: {same_inputs}")
    for (source, settings), seen in differing.items():
        shown = ", ".join(f"{sizes[o]} B x{n}" for o, n in seen.most_common())
        print(f"  same input {source[:16]} {settings[:90]}: {len(seen)} outputs ({shown})")
    if not same_inputs:
        everywhere = set.intersection(*(set(r) for r in inputs_per_run))
        for index, run in enumerate(inputs_per_run):
            extra = [k[0][:16] for k in run if k not in everywhere]
            if extra:
                print(f"  run {folders[index]}: inputs not in every run: {extra}")
    print(f"inputs with more than one output: {len(differing)}")
    return len(differing)


def repeat(folder: str, times: int, extra: str, sizes: tuple[int, int] = (0, 2**62)) -> int:
    """Code every kept piece (of ``sizes`` bytes) ``times`` times; print distinct outputs per piece and CPU seconds."""
    pieces = {}
    for row in _records(folder):
        if sizes[0] <= row["bytes"] <= sizes[1]:
            pieces.setdefault((row["input"], _settings(row)), row)
    changed, total_bytes, total_cpu = 0, 0, 0.0
    for (source, _), row in sorted(pieces.items(), key=lambda kv: -kv[1]["bytes"]):
        frames = x265_dump.load_frames(os.path.join(folder, f"frames-{source[:16]}.npz"))
        options = dict(row["options"])
        options["x265-params"] += extra
        seen: collections.Counter = collections.Counter()
        wall = time.monotonic()
        _, cpu = _workers_cpu(lambda: seen.update(x265_processes.encode(frames, row["pix_fmt"], options)
                                                  for _ in range(times)))
        cpu /= times
        sizes = ", ".join(f"{len(s)} B x{n}" for s, n in seen.most_common())
        changed += len(seen) > 1
        total_bytes, total_cpu = total_bytes + len(seen.most_common(1)[0][0]), total_cpu + cpu
        print(f"{source[:16]} {len(frames)}x{list(frames[0].shape)} {options['x265-params'][:40]}... "
              f"{len(seen)} outputs ({sizes}); {cpu:.2f} CPU s, {(time.monotonic() - wall) / times:.2f} s wall per encode")
    print(f"pieces {len(pieces)}, times {times}, extra {extra!r}: pieces with more than one output: {changed}; "
          f"{total_bytes} bytes, {total_cpu:.2f} CPU s per round (most common outputs); load {os.getloadavg()[0]:.2f}")
    return changed


def _pieces(folder: str) -> dict:
    """The recorded pieces, one per (input, settings), or one clear error for a folder without records."""
    pieces = {}
    for row in _records(folder):
        pieces.setdefault((row["input"], _settings(row)), row)
    if not pieces:
        raise SystemExit(f"{folder}: no x265 records (write them with GSCODEC_X265_DUMP={folder} during an encode)")
    return pieces


def _code_and_measure(folder: str, source: str, row: dict, settings: dict) -> tuple[int, float, int, float]:
    """A recorded piece coded under ``settings``: (stream bytes, squared error of its decoded samples
    against x265's input, samples, CPU seconds of the x265 worker)."""
    import numpy as np

    from gscodec_shac.codec.grid.hevc import _decoded_frames, _planes_from_frame

    frames = x265_dump.load_frames(os.path.join(folder, f"frames-{source[:16]}.npz"))
    stream, cpu = _workers_cpu(lambda: x265_processes.encode(frames, row["pix_fmt"], settings))
    chroma = 3 if frames[0].ndim == 3 else 0
    height, width = frames[0].shape[-2:]
    decoded = [_planes_from_frame(f, 0, height, width, chroma).astype(np.float64) for f in _decoded_frames(stream, 0)]
    error = sum(float(((d - f.reshape(d.shape)) ** 2).sum()) for d, f in zip(decoded, frames))
    return len(stream), error, sum(f.size for f in frames), cpu


def _psnr(squared: float, samples: int, pix_fmt: str) -> float:
    """PSNR of a squared error over ``samples`` samples, peak the sample range of ``pix_fmt``'s bit depth."""
    import numpy as np

    from gscodec_shac.codec.grid.hevc import _GRAY_FMT, _YUV444_FMT

    depths = {fmt: depth for table in (_GRAY_FMT, _YUV444_FMT) for depth, fmt in table.items()}
    peak = float((1 << depths[pix_fmt]) - 1)
    return float(10 * np.log10(peak**2 / max(squared / samples, 1e-12)))


def options(folder: str, extras: list[str]) -> None:
    """Per x265 parameter set: total bytes, PSNR of the decoded samples, CPU seconds (docs/benchmarks.md,
    "Diamond motion search for the frames layout")."""
    pieces = _pieces(folder)
    for extra in ["", *extras]:
        total_bytes, total_cpu, squared, samples, per_piece = 0, 0.0, 0.0, 0, []
        for (source, _), row in sorted(pieces.items(), key=lambda kv: -kv[1]["bytes"]):
            settings = dict(row["options"], **{"x265-params": row["options"]["x265-params"] + extra})
            size, error, count, cpu = _code_and_measure(folder, source, row, settings)
            per_piece.append(f"{len(row['shape'])}x {size} B "
                             f"{_psnr(error, count, row['pix_fmt']):.2f} dB {cpu:.2f} s")
            total_bytes, total_cpu, squared, samples = total_bytes + size, total_cpu + cpu, squared + error, samples + count
        print(f"{extra or '(recorded)':32s} {total_bytes:>11,} B  {_psnr(squared, samples, 'gray10le'):.3f} dB "
              f"(10-bit peak)  {total_cpu:6.2f} CPU s | " + "; ".join(per_piece), flush=True)
    print(f"pieces {len(pieces)}; load {os.getloadavg()[0]:.2f}")


#: ``qp=Q`` in an x265 parameter string (group 2: Q).
_QP = re.compile(r"(^|:)qp=(\d+)")


def x265_params(text: str) -> str:
    """An ``--extra`` value as the suffix appended to the recorded ``x265-params``: ``rd=2:ctu=32`` or
    ``:rd=2:ctu=32`` -> ``:rd=2:ctu=32``. Without the leading colon the first parameter used to run into
    the recorded last one (``frame-threads=1rd=2``), which x265 reads as ``frame-threads=1`` and says
    nothing: the setting was silently not applied."""
    items = [item.strip() for item in text.strip().strip(":").split(":")] if text.strip(": ") else []
    bad = [item for item in items if not re.fullmatch(r"[A-Za-z][A-Za-z0-9-]*=\S+", item)]
    if bad:
        raise argparse.ArgumentTypeError(f"x265 parameters are NAME=VALUE separated by ':', got {bad[0]!r} in {text!r}")
    return "".join(f":{item}" for item in items)


def curve(folder: str, piece: int, offsets: list[int], extras: list[str], presets: list[str] | None = None) -> dict:
    """The ``piece``-th largest recorded piece at its QP plus ``offsets``, under the recorded options and each
    of ``extras`` (with ``presets[i]`` replacing the preset when given): per setting its BD-rate over the
    sample PSNR against the recorded options, and its CPU relative to theirs. Returns {setting: (BD-rate %, CPU ratio)}."""
    from gscodec_shac.rd.bd import bd_rate

    ranked = sorted(_pieces(folder).items(), key=lambda kv: -kv[1]["bytes"])
    if not 0 <= piece < len(ranked):
        raise SystemExit(f"{folder}: --piece must be 0-{len(ranked) - 1}, got {piece}")
    (source, _), row = ranked[piece]
    recorded = row["options"]["x265-params"]
    match = _QP.search(recorded)
    if match is None:
        raise SystemExit(f"{folder}: piece {piece} is lossless (no qp= in its options): it has no curve")
    qp = int(match.group(2))
    qps = [qp + offset for offset in offsets]
    if min(qps) < 0 or max(qps) > 51:
        raise SystemExit(f"QPs {qps} leave x265's range 0-51 (the recorded QP is {qp})")
    print(f"piece {piece}: {len(row['shape'])} frame(s) {row['shape'][0]} {row['pix_fmt']}, recorded {recorded}")
    presets = list(presets or [])
    settings_tried = [("", ""), *zip(extras, presets + [""] * (len(extras) - len(presets)))]  # ("": the recorded)
    points: dict[str, list[tuple[int, float, float]]] = {}
    for extra, preset in settings_tried:
        label = (f"preset {preset} " if preset else "") + (extra or "(recorded)")
        for value in qps:
            params = _QP.sub(f"\\g<1>qp={value}", recorded) + extra
            settings = dict(row["options"], **{"x265-params": params}, **({"preset": preset} if preset else {}))
            size, error, count, cpu = _code_and_measure(folder, source, row, settings)
            points.setdefault(label, []).append((size, _psnr(error, count, row["pix_fmt"]), cpu))
            print(f"  {label:40s} qp {value:2d} {size:>11,} B {points[label][-1][1]:.3f} dB {cpu:.2f} s", flush=True)
    reference = points["(recorded)"]
    result = {}
    for label, curve_points in points.items():
        bd = bd_rate([p[0] for p in reference], [p[1] for p in reference],
                     [p[0] for p in curve_points], [p[1] for p in curve_points])
        cpu = sum(p[2] for p in curve_points) / max(sum(p[2] for p in reference), 1e-9)
        value = bd.value if bd.value is not None else float("nan")
        result[label] = (value, cpu)
        print(f"{label:40s} BD-rate {value:+.3f}%  CPU {sum(p[2] for p in curve_points):.2f} s ({cpu:.3f}x)", flush=True)
    return result


def shuffle(folder: str, rounds: int, seed: int = 0, extra: str = "") -> int:
    """Code every kept piece ``rounds`` times in a new random order each round, two at once through
    the workers (as the encode scheduler does), so each worker codes them after a different history;
    count the pieces with more than one output (without ``extra``, the recorded output counts too)."""
    import hashlib
    import random
    from concurrent.futures import ThreadPoolExecutor

    pieces = {}
    for row in _records(folder):
        pieces.setdefault((row["input"], _settings(row)), row)
    frames = {key: x265_dump.load_frames(os.path.join(folder, f"frames-{key[0][:16]}.npz")) for key in pieces}
    seen: dict = {key: collections.Counter() if extra else collections.Counter({(row["output"], row["bytes"]): 0})
                  for key, row in pieces.items()}

    def code(key: tuple[str, str]) -> tuple[str, int]:
        row = pieces[key]
        options = dict(row["options"], **{"x265-params": row["options"]["x265-params"] + extra})
        stream = x265_processes.encode(frames[key], row["pix_fmt"], options)
        return hashlib.sha256(stream).hexdigest(), len(stream)

    order, shuffler = list(pieces), random.Random(seed)
    with ThreadPoolExecutor(2) as pool:
        for index in range(rounds):
            shuffler.shuffle(order)
            for key, output in zip(order, pool.map(code, order)):
                if output not in seen[key] and seen[key]:
                    print(f"  {key[0][:16]}: a new output of {output[1]} B (seen: "
                          f"{', '.join(f'{size} B x{n}' for (_, size), n in seen[key].items())})", flush=True)
                seen[key][output] += 1
            varying = sum(len(c) > 1 for c in seen.values())
            print(f"round {index + 1}: pieces with more than one output so far {varying}; "
                  f"load {os.getloadavg()[0]:.2f}", flush=True)
    varying = {key[0][:16]: [f"{size} B x{n}" for (_, size), n in c.most_common()] for key, c in seen.items() if len(c) > 1}
    print(f"pieces {len(pieces)}, rounds {rounds}, extra {extra!r}: {len(pieces) * rounds} encodes; "
          f"pieces with more than one output: {len(varying)} {varying}")
    return len(varying)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    cmp_parser = commands.add_parser("compare")
    cmp_parser.add_argument("folders", nargs="+")
    rep_parser = commands.add_parser("repeat")
    rep_parser.add_argument("folder")
    rep_parser.add_argument("--times", type=int, default=10)
    rep_parser.add_argument("--extra", type=x265_params, default="", help="x265 parameters appended, e.g. :wpp=0")
    rep_parser.add_argument("--bytes", default="0:4611686018427387904", metavar="MIN:MAX",
                            help="only the pieces whose recorded stream has MIN-MAX bytes")
    mix_parser = commands.add_parser("shuffle")
    mix_parser.add_argument("folder")
    mix_parser.add_argument("--rounds", type=int, default=5)
    mix_parser.add_argument("--seed", type=int, default=0)
    mix_parser.add_argument("--extra", type=x265_params, default="", help="x265 parameters appended, e.g. :wpp=0")
    opt_parser = commands.add_parser("options")
    opt_parser.add_argument("folder")
    opt_parser.add_argument("--extra", type=x265_params, action="append", default=[], help="x265 parameters appended (repeatable)")
    curve_parser = commands.add_parser("curve")
    curve_parser.add_argument("folder")
    curve_parser.add_argument("--piece", type=int, default=0, help="the K-th largest recorded piece (0: the largest)")
    curve_parser.add_argument("--offsets", default="-2,0,2", help="QP offsets from the recorded QP")
    curve_parser.add_argument("--extra", type=x265_params, action="append", default=[], help="x265 parameters appended (repeatable)")
    curve_parser.add_argument("--preset", action="append", default=[],
                              help="x265 preset for the --extra of the same position ('' keeps the recorded one)")
    args = parser.parse_args()
    if args.command == "curve":
        curve(args.folder, args.piece, [int(v) for v in args.offsets.split(",")], args.extra, args.preset)
    elif args.command == "options":
        options(args.folder, args.extra)
    elif args.command == "compare":
        compare(args.folders)
    elif args.command == "shuffle":
        shuffle(args.folder, args.rounds, args.seed, args.extra)
    else:
        low, high = (int(v) for v in args.bytes.split(":"))
        repeat(args.folder, args.times, args.extra, (low, high))


if __name__ == "__main__":
    main()
