"""Speed and memory of the codec at real-scene sizes, beside PlayCanvas splat-transform (issue 25).

For each size N (synthetic SH-3 scenes, ``gscodec-shac synthetic -n N``) this runs, each
in its own process, and records wall time, CPU time (user + system of the process and
its children, from ``os.wait4``) and peak RSS:

* ``encode``: ``gscodec-shac encode -r RATE_POINT --sh pca --er 0.97``;
* ``decode``: the stream back to a PLY; ``decode_arrays``: the stream to arrays only
  (the :class:`~gscodec_shac.codec.Decoder` in a fresh interpreter, no file written);
* ``target_bpg``: ``encode --target-bpg B`` (the controller picks the SH settings; skipped
  with ``--no-target``); ``chosen_fixed``: a fixed encode (``-r chosen.yaml:chosen``) of the
  settings that run chose (its stream's QPs, position bits and pruning on the SHAC-auto
  template; the chunks that differ from the target file's are printed);
* ``spz_write`` / ``spz_read``: ``splat-transform`` PLY -> SPZ and SPZ -> PLY of the same
  file (skipped, with a line saying why, when node or the tool is absent);

plus ``startup``: ``gscodec-shac decode`` of a 300-Gaussian fixture stream (start-up cost).
``--ladder`` also encodes every point of the rate-point file of ``--rate-point`` (``encode_rpK``,
the bar "any ``shac_ladder`` point"), and ``--target-psnr P`` a PSNR target (``target_psnr``,
with the fixed encode of its chosen settings, ``chosen_fixed_psnr``, and their ratio; ``--repeat R``
runs that pair R times, each target run followed by its fixed encode, and prints the ratio of the
medians too). Without ``--baseline``, ``--repeat R`` runs the ``--target-bpg`` pair (``target_bpg``,
``chosen_fixed``) R times in the same way. ``--target-cameras N`` runs that pair on the same scene
with N orbit cameras ``--camera-width`` wide given to both encodes (``target_bpg_cameras``,
``chosen_fixed_cameras``): what a capture's cameras cost a target (importance on every camera).
``--baseline ../main`` runs the encode, every decode step and the target encode under that
checkout too, right before ours (the baseline's stream is overwritten by ours, except the target
stream, ``_target_baseline.gsc``; the two fixed encodes' sha256 are compared and printed), and
prints the baseline's ratios beside ours. ``--repeat R`` runs each paired encode R times, the
baseline first in odd rounds and ours first in even ones (the load of a shared machine drifts),
and each decode step R times (the median is printed; a fresh process's first touch of its pages
varies with the kernel's memory state).
Ratios (target / encode, target / the fixed encode of its own chosen settings, decode /
spz_read, encode / spz_write) are printed; all rows go
to ``OUT/bench_speed.json`` and ``.csv`` with the load average at each step.

    python scripts/bench_speed.py --sizes 250k,1M --out ../out/speed
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gscodec_shac.rd.external import find_splat_transform, unavailable_reason  # noqa: E402

TINY = ROOT / "tests" / "fixtures" / "streams" / "v2.0" / "ladder_rp6_pca.gsc"
DECODE_ARRAYS = (
    "import sys, time; t = time.perf_counter()\n"
    "from gscodec_shac.codec import Bitstream, Decoder\n"
    "data = Bitstream.read(sys.argv[1]); t1 = time.perf_counter()\n"
    "cloud = Decoder().decode(data)\n"
    "t2 = time.perf_counter(); print(f'{t2 - t:.3f} s with imports, decode {t2 - t1:.3f} s')\n"
)


def parse_size(text: str) -> int:
    """``250k`` / ``1M`` / ``4000000`` -> an integer."""
    text = text.strip().lower()
    scale = {"k": 1_000, "m": 1_000_000}.get(text[-1:], 1)
    return int(float(text[:-1] if scale > 1 else text) * scale)


def label(n: int) -> str:
    return f"{n // 1_000_000}M" if n % 1_000_000 == 0 else f"{n // 1000}k"


def _tree_memory(pid: int) -> tuple[int, int]:
    """(RSS, PSS) bytes of process ``pid`` and all its descendants (x265 worker processes), from
    /proc: RSS counts shared library pages once per process, PSS shares them out."""
    rss = pss = 0
    stack = [pid]
    while stack:
        current = stack.pop()
        try:
            with open(f"/proc/{current}/smaps_rollup") as rollup:
                for line in rollup:
                    if line.startswith(("Rss:", "Pss:")):
                        value = int(line.split()[1]) * 1024
                        rss, pss = (rss + value, pss) if line.startswith("Rss:") else (rss, pss + value)
            for task in os.listdir(f"/proc/{current}/task"):
                with open(f"/proc/{current}/task/{task}/children") as children:
                    stack += [int(child) for child in children.read().split()]
        except (OSError, ValueError):
            continue
    return rss, pss


def _sample_tree_peak(pid: int, done: threading.Event, peak: list[int]) -> None:
    while not done.wait(0.05):
        rss, pss = _tree_memory(pid)
        peak[0], peak[1] = max(peak[0], rss), max(peak[1], pss)


def measured(command: list[str], nice: int, root: Path = ROOT, *, keep_output: bool = False) -> dict:
    """Run ``command`` with the checkout ``root`` first on the path: wall seconds, CPU seconds (with
    its reaped children) and peak memory (GB): RSS of that process alone (``os.wait4``), and RSS
    and PSS of it with its worker processes, summed (``/proc`` sampled every 50 ms); the end of its
    last line of output, and with ``keep_output`` its whole standard output (``stdout``)."""
    env = {**os.environ, "PYTHONPATH": str(root) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    load = os.getloadavg()[0]
    tic = time.perf_counter()
    # cwd = the checkout: ``python -m`` / ``-c`` put the working directory first on sys.path
    errors = tempfile.TemporaryFile() if keep_output else None  # the progress bars and messages, apart
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=errors or subprocess.STDOUT, env=env,
                               cwd=root, preexec_fn=(lambda: os.nice(nice)) if nice else None)
    done, tree_peak = threading.Event(), [0, 0]
    sampler = threading.Thread(target=_sample_tree_peak, args=(process.pid, done, tree_peak), daemon=True)
    sampler.start()
    output = process.stdout.read()  # type: ignore[union-attr]
    done.set()
    sampler.join()
    _, status, usage = os.wait4(process.pid, 0)
    wall = time.perf_counter() - tic
    process.returncode = os.waitstatus_to_exitcode(status)
    if errors is not None:
        errors.seek(0)
        messages = errors.read()
        errors.close()
        if process.returncode != 0:
            output = messages
    if process.returncode != 0:
        raise SystemExit(f"error: {shlex.join(command)} failed ({process.returncode}): {output.decode()[-400:]}")
    row = {"wall_s": round(wall, 3), "cpu_s": round(usage.ru_utime + usage.ru_stime, 3),
           "peak_rss_gb": round(usage.ru_maxrss / 1024**2, 3),
           "peak_tree_rss_gb": round(max(tree_peak[0], usage.ru_maxrss * 1024) / 1024**3, 3),
           "peak_tree_pss_gb": round(tree_peak[1] / 1024**3, 3), "load": round(load, 2),
           "output": output.decode().strip().splitlines()[-1][-200:] if output.strip() else ""}
    return row | {"stdout": output.decode()} if keep_output else row


def target_ratios(size: str, ply: Path, args: argparse.Namespace, cli: list[str], record: Any, kind: str,
                  cameras: Path | None = None) -> None:
    """A target encode (``kind`` ``"bpg"``: ``--target-bpg``, ``"psnr"``: ``--target-psnr``), then a fixed
    encode of the settings it chose, ``--repeat`` times in turn (rows ``target_bpg`` / ``chosen_fixed``,
    ``target_psnr`` / ``chosen_fixed_psnr``; with ``cameras``, both encodes are given them and the rows
    end in ``_cameras``: the SH stage is then fitted in their view metric, which the chosen rate point
    does not record); prints whether each fixed encode coded the target file's chunks (not the SH's
    when the target pruned: the controller fits the SH stage on the whole cloud, a fixed encode on the
    Gaussians it keeps), each pair's ratio and the ratio of the medians."""
    value = args.target_bpg if kind == "bpg" else args.target_psnr
    with_cameras = "_cameras" if cameras is not None else ""
    tag = ("" if kind == "bpg" else "_psnr") + with_cameras
    seen_by = ["--cameras", str(cameras)] if cameras is not None else []
    aimed = ply.with_name(f"s{size}_target{tag}.gsc")
    pairs = []
    for _ in range(max(1, args.repeat)):
        target = record(size, f"target_{kind}{with_cameras}", measured(
            [*cli, "encode", str(ply), str(aimed), f"--target-{kind}", str(value), *seen_by, "--force"], args.nice))
        chosen = chosen_rate_point(aimed, ply.with_name(f"chosen{tag}.yaml"))
        if chosen is None:
            print(f"{size:>5} chosen settings of the {kind} target: not a rate point (skipped)")
            return
        fixed = aimed.with_name(aimed.stem + "_chosen_fixed.gsc")
        pairs.append((target, record(size, f"chosen_fixed{tag}", measured(
            [*cli, "encode", str(ply), str(fixed), "-r", f"{chosen}:chosen", *seen_by, "--force"], args.nice))))
        differ = differing_chunks(aimed, fixed)  # the SH's when the target pruned (the stage's fit differs)
        pairs[-1][1]["same_bytes"] = not differ
        print(f"{size:>5} chosen_fixed{tag}: " + (f"{len(differ)} chunks unlike the target file's ({differ[0]}, ...)"
                                                   if differ else "the same chunks as the target file"), flush=True)
    what = ("size" if kind == "bpg" else "PSNR") + (f" target with {cameras.parent.name}" if cameras else " target")
    for key, unit in (("wall_s", "wall"), ("cpu_s", "cpu")):
        each = ", ".join(f"{target[key] / own[key]:.2f}" for target, own in pairs)
        targets, owns = (statistics.median(row[key] for row in rows) for rows in zip(*pairs))
        print(f"{size:>5} ratio {what} / fixed encode of its own chosen settings ({unit}): {each}; "
              f"of the medians {targets / owns:.2f}", flush=True)


def camera_scene(size: str, n: int, args: argparse.Namespace, cli: list[str]) -> Path:
    """The synthetic scene of ``n`` Gaussians again (the same PLY: the same seed) with ``--target-cameras``
    orbit cameras ``--camera-width`` wide, in ``OUT/SIZE/camsN/``; its ``cameras.json``."""
    folder = args.out / size / f"cams{args.target_cameras}"
    if not (folder / "cameras.json").exists():
        folder.mkdir(parents=True, exist_ok=True)
        width = args.camera_width
        measured([*cli, "synthetic", str(folder / f"s{size}.ply"), "-n", str(n), "--views", str(args.target_cameras),
                  "--width", str(width), "--height", str(width * 3 // 4), "-q", "--force"], args.nice)
    return folder / "cameras.json"


def write_results(stem: Path, document: Any, rows: list[dict], fields: list[str]) -> None:
    """``document`` as ``STEM.json`` and ``rows`` (their ``fields``; a dict or list value as JSON) as
    ``STEM.csv``; says so."""
    stem.with_suffix(".json").write_text(json.dumps(document, indent=1) + "\n")
    with open(stem.with_suffix(".csv"), "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        writer.writerows({key: json.dumps(value) if isinstance(value, (dict, list)) else value
                          for key, value in row.items()} for row in rows)
    print(f"wrote {stem.with_suffix('.json')} and .csv")


def chosen_rate_point(stream: Path, out: Path) -> Path | None:
    """The settings a ``--target-bpg`` encode chose (its stream's rate point: QPs, position bits,
    pruning, the SH stage with its DC-only bar, the importance tiers) written as the point ``chosen`` of a rate-point file ``out`` on the SHAC-auto template,
    so a fixed encode codes the same configuration; None when the stream's rate point is not a
    SHAC-auto choice."""
    import yaml

    from gscodec_shac.codec import Bitstream

    point = Bitstream.read(stream).header.get("rate_point") or {}
    if not str(point.get("name", "")).endswith("+auto"):
        return None
    document = yaml.safe_load((ROOT / "rate_points" / "shac_auto.yaml").read_text())
    settings = document["points"]["template"]
    attributes = point["attributes"]
    settings["qp"].update({name: attributes[name]["qp"] for name in ("opacity", "rotation", "scale", "sh_dc",
                                                                     "sh_features")})
    settings["attributes"] = {"positions": {"bits": attributes["positions"]["bits"]}}
    settings["prune"] = dict(point.get("prune") or {})
    settings["sh"] = dict(point["sh"])  # the stage as coded, with a DC-only bar the controller chose
    settings.pop("tiers", None)  # importance tiers as coded: the controller codes them from 30,000 Gaussians on
    if point.get("tiers"):
        settings["tiers"] = point["tiers"]
    document["points"] = {"chosen": settings}
    out.write_text(yaml.safe_dump(document, sort_keys=False))
    return out


def differing_chunks(a: Path, b: Path) -> list[str]:
    """The chunks two streams do not share byte for byte (their headers aside), with both sizes."""
    from gscodec_shac.codec import Bitstream

    first, second = ({chunk.name: chunk.data for chunk in Bitstream.read(path).chunks} for path in (a, b))
    return [f"{name} ({len(first.get(name, b''))} / {len(second.get(name, b''))} bytes)"
            for name in sorted(set(first) | set(second)) if first.get(name) != second.get(name)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="250k,1M,4M", help="comma-separated Gaussian counts (250k,1M,4M)")
    parser.add_argument("--out", type=Path, default=ROOT.parent / "out" / "bench_speed", help="work and result folder")
    parser.add_argument("--rate-point", default="shac_ladder:rp4")
    parser.add_argument("--target-bpg", type=float, default=100.0)
    parser.add_argument("--no-target", action="store_true", help="skip the --target-bpg encodes")
    parser.add_argument("--ladder", action="store_true",
                        help="also encode every point of --rate-point's file (e.g. shac_ladder:rp1..rp9)")
    parser.add_argument("--target-psnr", type=float, metavar="DB",
                        help="also encode to this PSNR target (dB against the uncompressed model's orbit renders)")
    parser.add_argument("--target-cameras", type=int, default=0, metavar="N",
                        help="also run the --target-bpg pair with N orbit cameras (a capture's case: importance "
                             "ranked on every camera, SHAC-PCA in their view metric)")
    parser.add_argument("--camera-width", type=int, default=1024, help="the width of those cameras (3:4)")
    parser.add_argument("--no-peer", action="store_true", help="skip splat-transform")
    parser.add_argument("--nice", type=int, default=5, help="niceness of the measured processes")
    parser.add_argument("--baseline", type=Path,
                        help="another checkout: its encodes and decodes run right before ours (paired)")
    parser.add_argument("--repeat", type=int, default=1,
                        help="paired encodes per size (with --baseline: alternating which runs first)")
    args = parser.parse_args(argv)
    args.out = args.out.resolve()
    args.out.mkdir(parents=True, exist_ok=True)
    cli = [sys.executable, "-m", "gscodec_shac"]
    peer = None if args.no_peer else find_splat_transform()
    if peer is None:
        print(f"splat-transform: skipped ({'--no-peer' if args.no_peer else unavailable_reason()})")
    rows: list[dict] = []
    suffixes = ("@baseline",) * (args.baseline is not None) + ("",)  # the steps' names: the baseline's, ours

    def record(size: str, step: str, result: dict) -> dict:
        row = {"size": size, "step": step, **result}
        rows.append(row)
        print(f"{size:>5} {step:<23} wall {row['wall_s']:8.2f} s  cpu {row.get('cpu_s', float('nan')):8.2f} s  "
              f"peak {row.get('peak_rss_gb', float('nan')):6.2f} GB (with workers: RSS {row.get('peak_tree_rss_gb', float('nan')):.2f}, PSS {row.get('peak_tree_pss_gb', float('nan')):.2f})  load {row['load']:.1f}", flush=True)
        return row

    def paired_step(size: str, step: str, command: list[str]) -> dict:
        if args.baseline is not None:
            record(size, step + "@baseline", measured(command, args.nice, args.baseline.resolve()))
        return record(size, step, measured(command, args.nice))

    def paired_encode(size: str, command: list[str], gsc: Path, ours_first: bool) -> dict:
        """An encode under the baseline and ours (in either order); the streams' sha256 compared."""
        if args.baseline is None:
            return record(size, "encode", measured(command, args.nice))
        digests, rows_ = {}, {}
        for who in (("ours", "baseline") if ours_first else ("baseline", "ours")):
            root = ROOT if who == "ours" else args.baseline.resolve()
            rows_[who] = record(size, "encode" if who == "ours" else "encode@baseline", measured(command, args.nice, root))
            digests[who] = hashlib.sha256(gsc.read_bytes()).hexdigest()
        same = digests["ours"] == digests["baseline"]
        rows_["ours"]["same_bytes"] = same
        print(f"{size:>5} encode bytes {'the same' if same else 'DIFFERENT'} (sha256 {digests['ours'][:16]}"
              f"{'' if same else ' vs baseline ' + digests['baseline'][:16]})", flush=True)
        return rows_["ours"]

    paired_step("300", "startup", [*cli, "decode", str(TINY), str(args.out / "tiny.ply"), "--force"])
    for n in (parse_size(s) for s in args.sizes.split(",")):
        size = label(n)
        ply, gsc, dec = (args.out / size / f"s{size}{ext}" for ext in (".ply", ".gsc", "_dec.ply"))
        if not ply.exists():  # one folder per size: synthetic writes cameras.json beside the PLY
            ply.parent.mkdir(exist_ok=True)
            measured([*cli, "synthetic", str(ply), "-n", str(n), "--views", "4", "-q", "--force"], args.nice)
        point = ["-r", args.rate_point, "--sh", "pca", "--er", "0.97", "--force"]
        for round_ in range(max(1, args.repeat)):
            enc = paired_encode(size, [*cli, "encode", str(ply), str(gsc), *point], gsc, ours_first=round_ % 2 == 1)
        if args.ladder:
            from gscodec_shac.codec.rate_points import _split_reference, load_rate_point_file

            stem = args.rate_point.rsplit(":", 1)[0]
            for name in load_rate_point_file(_split_reference(args.rate_point)[0]):
                out = args.out / size / f"s{size}_{name}.gsc"
                record(size, f"encode_{name}", measured([*cli, "encode", str(ply), str(out), "-r", f"{stem}:{name}",
                                                         "--sh", "pca", "--er", "0.97", "--force"], args.nice))
                rows[-1]["bytes"] = out.stat().st_size
        if args.target_psnr is not None:
            target_ratios(size, ply, args, cli, record, "psnr")
        if args.target_cameras:
            cameras = camera_scene(size, n, args, cli)
            target_ratios(size, cameras.with_name(ply.name), args, cli, record, "bpg", cameras)
        median: dict[str, dict] = {}  # per decode step, the run of median wall time
        for step, command in (("decode_arrays", [sys.executable, "-c", DECODE_ARRAYS, str(gsc)]),
                              ("decode", [*cli, "decode", str(gsc), str(dec), "--force"])):
            runs = sorted((paired_step(size, step, command) for _ in range(max(1, args.repeat))),
                          key=lambda row: row["wall_s"])
            median[step] = runs[len(runs) // 2]
            if len(runs) > 1:
                for suffix in suffixes:
                    walls = sorted(row["wall_s"] for row in rows if row["size"] == size and row["step"] == step + suffix)
                    print(f"{size:>5} {step + suffix} median wall {walls[len(walls) // 2]:.2f} s of {len(walls)} runs",
                          flush=True)
        # the Decoder call alone, without the interpreter's start and imports (DECODE_ARRAYS prints both)
        for suffix in suffixes:
            calls = sorted(float(row["output"].rsplit("decode ", 1)[1].split()[0])
                           for row in rows if row["size"] == size and row["step"] == "decode_arrays" + suffix)
            print(f"{size:>5} decode_arrays{suffix}: the decode call {calls[len(calls) // 2]:.2f} s "
                  f"(median of {len(calls)})", flush=True)
        decode = median["decode"]  # for the ratio to splat-transform's read
        if not args.no_target and args.repeat > 1 and args.baseline is None:
            target_ratios(size, ply, args, cli, record, "bpg")
        elif not args.no_target:
            checkouts = ([("@baseline", args.baseline.resolve())] if args.baseline is not None else []) + [("", ROOT)]
            aimed = {suffix: args.out / size / f"s{size}_target{suffix.replace('@', '_')}.gsc"
                     for suffix, _ in checkouts}
            for suffix, root in checkouts:
                record(size, "target_bpg" + suffix, measured(
                    [*cli, "encode", str(ply), str(aimed[suffix]), "--target-bpg", str(args.target_bpg), "--force"],
                    args.nice, root))
            for suffix, root in checkouts:  # the controller's choice encoded at a fixed rate point
                chosen = chosen_rate_point(aimed[suffix], args.out / size / f"chosen{suffix.replace('@', '_')}.yaml")
                if chosen is None:
                    print(f"{size:>5} chosen settings{suffix}: not a rate point (skipped)")
                    continue
                chosen_gsc = aimed[suffix].with_name(aimed[suffix].stem + "_chosen_fixed.gsc")
                record(size, "chosen_fixed" + suffix, measured(
                    [*cli, "encode", str(ply), str(chosen_gsc), "-r", f"{chosen}:chosen", "--force"], args.nice, root))
                differ = differing_chunks(aimed[suffix], chosen_gsc)
                rows[-1]["same_bytes"] = not differ
                chunks = "chunks unlike the target file: " + ", ".join(differ) if differ else \
                    "the same chunks as the target file"
                print(f"{size:>5} chosen_fixed{suffix}: {chosen_gsc.stat().st_size:,} bytes, {chunks} (the headers "
                      "differ in the rate point's name and the target)", flush=True)
            for suffix, _ in checkouts:
                fixed, target = (next(r for r in reversed(rows) if r["size"] == size and r["step"] == step + suffix)
                                 for step in ("encode", "target_bpg"))
                print(f"{size:>5} ratio target / encode{suffix}: {target['wall_s'] / fixed['wall_s']:.2f} (wall), "
                      f"{target['cpu_s'] / fixed['cpu_s']:.2f} (cpu)")
                own = next((r for r in reversed(rows) if r["size"] == size and r["step"] == "chosen_fixed" + suffix),
                           None)
                if own is not None:
                    print(f"{size:>5} ratio target / fixed encode of its own chosen settings{suffix}: "
                          f"{target['wall_s'] / own['wall_s']:.2f} (wall), {target['cpu_s'] / own['cpu_s']:.2f} (cpu)")
        if peer is not None:
            spz = args.out / size / f"s{size}.spz"
            write = record(size, "spz_write", measured([str(peer), "-w", "-q", str(ply), str(spz)], args.nice))
            back = args.out / size / f"s{size}_spz.ply"
            read = record(size, "spz_read", measured([str(peer), "-w", "-q", str(spz), str(back)], args.nice))
            print(f"{size:>5} ratio decode / spz_read: {decode['wall_s'] / read['wall_s']:.2f} (wall), "
                  f"{decode['cpu_s'] / read['cpu_s']:.2f} (cpu); encode / spz_write: "
                  f"{enc['wall_s'] / write['wall_s']:.2f} (wall)")
    write_results(args.out / "bench_speed", rows, rows, ["size", "step", "wall_s", "cpu_s", "peak_rss_gb",
                  "peak_tree_rss_gb", "peak_tree_pss_gb", "load", "same_bytes", "output"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
