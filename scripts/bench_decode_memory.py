"""Decode peak memory against decoded size, and against the decoder's own estimate.

Encodes a scene with one rate point per SH stage (Morton sort and x265 ``ultrafast`` to keep
it quick; the decoder's memory does not depend on either), then decodes each stream in a
fresh child process: the extra peak resident memory of the decode (``VmHWM`` reset just
before it, minus the resident set at that moment) is compared with the decoded cloud's
float32 arrays and with :meth:`gscodec_shac.codec.header.StreamHeader.peak_memory`, the
estimate the decoder checks against the memory budget before allocating.

    python scripts/bench_decode_memory.py --scene ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply
    python scripts/bench_decode_memory.py --synthetic 600000

Streams go to ``--work`` (default a temporary folder), never into the repository.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
#: (SH stage, rate point, stage parameters) per stream.
STREAMS = [
    ("none", "paper_table3:rp2", None),
    ("trunc", "mpeg_ctc_video:rp01", {"degree": 1}),
    ("pca", "paper_table3:rp2", {"energy_retention": 0.99}),
    ("lst", "shac_recommended:rp3", None),
    ("vq", "gsplat_png", {"n_clusters": 4096}),
]


def _status(key: str) -> int:
    with open("/proc/self/status") as handle:
        for line in handle:
            if line.startswith(key):
                return int(line.split()[1]) * 1024
    return 0


def child(path: str, workers: int) -> dict:
    """Decode one stream in this (fresh) process and measure it."""
    from gscodec_shac.codec import Decoder
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.header import read_header

    data = Path(path).read_bytes()
    stream = Bitstream.from_bytes(data)
    view = read_header(stream)
    decoder = Decoder(workers=workers)
    with open("/proc/self/clear_refs", "w") as handle:
        handle.write("5")  # reset VmHWM
    base = _status("VmRSS")
    cloud = decoder.decode(stream)
    extra = _status("VmHWM") - base
    decoded = sum(a.nbytes for a in (cloud.means, cloud.scales, cloud.quats, cloud.opacities, cloud.sh_dc,
                                     cloud.sh_rest))
    return {"stream": Path(path).stem, "gaussians": cloud.num_gaussians, "file_bytes": len(data),
            "decoded_bytes": decoded, "extra_peak_bytes": extra, "estimate_bytes": view.peak_memory(decoder.workers),
            "workers": decoder.workers}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--scene", help="an Inria PLY")
    source.add_argument("--synthetic", type=int, metavar="N", help="a synthetic SH-3 scene of N Gaussians")
    parser.add_argument("--work", help="folder for the streams (default: a temporary one)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="decoder threads to measure")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--child-workers", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.child_workers)))
        return 0
    if not (args.scene or args.synthetic):
        parser.error("give --scene PLY or --synthetic N")

    from gscodec_shac.codec import Encoder
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.synthetic import make_synthetic_scene

    cloud = (read_ply(args.scene) if args.scene
             else make_synthetic_scene(args.synthetic, seed=0, n_cameras=1, width=32, height=24).cloud)
    work = Path(args.work or tempfile.mkdtemp(prefix="decode-memory-"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for stage, point, params in STREAMS:
        path = work / f"{stage}.gsc"
        Encoder(point, sh_stage=stage, sh_params=params, sort="morton",
                codec_options={"preset": "ultrafast"} if "png" not in point else None).encode(cloud).write(path)
        for workers in args.workers:
            result = subprocess.run([sys.executable, __file__, "--child", str(path),
                                     "--child-workers", str(workers)], capture_output=True, text=True, check=True)
            rows.append(json.loads(result.stdout))
    print("| stream | workers | Gaussians | file MB | decoded MB | extra peak MB | peak / decoded | estimate / peak |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        print(f"| {row['stream']} | {row['workers']} | {row['gaussians']:,} | {row['file_bytes'] / 1e6:.2f} | "
              f"{row['decoded_bytes'] / 1e6:.1f} | {row['extra_peak_bytes'] / 1e6:.1f} | "
              f"{row['extra_peak_bytes'] / row['decoded_bytes']:.2f} | "
              f"{row['estimate_bytes'] / row['extra_peak_bytes']:.2f} |")
    worst = max(row["extra_peak_bytes"] / row["decoded_bytes"] for row in rows)
    under = min(row["estimate_bytes"] / row["extra_peak_bytes"] for row in rows)
    print(f"\nworst peak / decoded: {worst:.2f}; the estimate is at least {under:.2f}x the measured peak")
    return 0


if __name__ == "__main__":
    sys.exit(main())
