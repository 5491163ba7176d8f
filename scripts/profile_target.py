"""Where a rate-controlled encode goes: ``encode --target-bpg`` under cProfile, in one process.

Prints wall and CPU seconds, the controller's own split (probe, calibrate, encode), the file's
sha256 (the same bytes as the CLI writes) and the top of the cumulative profile; the full
profile is kept beside the output as ``OUT.prof`` (docs/benchmarks.md, "Rate control cost").

    python scripts/profile_target.py ../out/bench/1M/s1M.ply ../out/prof_1M.gsc --bpg 100
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import json
import pstats
import time
from pathlib import Path

from gscodec_shac.codec.files import encode_file_to_target


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", help="a model file (e.g. `gscodec-shac synthetic -n 1000000` output)")
    parser.add_argument("out", type=Path, help="the .gsc to write")
    parser.add_argument("--bpg", type=float, default=100.0, help="bits per Gaussian target")
    parser.add_argument("--psnr", type=float, help="a PSNR target (dB) instead of --bpg")
    parser.add_argument("--cameras", help="a camera file (default: orbit views)")
    parser.add_argument("--top", type=int, default=60, help="profile rows shown")
    args = parser.parse_args()
    profile = cProfile.Profile()
    wall, cpu = time.perf_counter(), time.process_time()
    profile.enable()
    summary = encode_file_to_target(args.model, args.out, bpg=None if args.psnr else args.bpg, psnr=args.psnr,
                                    cameras=args.cameras)
    profile.disable()
    print(f"wall {time.perf_counter() - wall:.2f} s, cpu {time.process_time() - cpu:.2f} s (this process)")
    print(json.dumps(summary["rate_control"], indent=1))
    print("sha256", hashlib.sha256(args.out.read_bytes()).hexdigest(), args.out.stat().st_size)
    profile.dump_stats(f"{args.out}.prof")
    pstats.Stats(profile).sort_stats("cumulative").print_stats(args.top)


if __name__ == "__main__":
    main()
