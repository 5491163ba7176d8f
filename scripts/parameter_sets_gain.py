"""What storing the HEVC parameter sets once per file saves (format 2.4, codec/parameter_sets.py).

Encodes the model at each rate point twice in one process, with the parameter-set table and with
each stream keeping its own (the encoder's ``parameter_sets.share`` replaced by a no-op), checks that
both decode to the same arrays and prints the bytes (docs/codec.md, "HEVC parameter sets once per file").
With ``--decode-times FILE.gsc`` it instead writes a copy of that file with every stream's parameter sets
put back (no table) and times the decode call of both in fresh processes, alternately (medians).

    python scripts/parameter_sets_gain.py ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply \\
        shac_auto:template shac_ladder:rp1 shac_ladder:rp4
    python scripts/parameter_sets_gain.py --decode-times s1M.gsc --repeat 5
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import zlib
from pathlib import Path
from unittest import mock

from gscodec_shac.codec import parameter_sets
from gscodec_shac.codec.container import Bitstream
from gscodec_shac.codec.decoder import Decoder
from gscodec_shac.codec.encoder import Encoder
from gscodec_shac.errors import GscodecError
from gscodec_shac.io.models import read_model

ARRAYS = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")
#: A fresh process timing the decode call of one file (seconds).
_TIME_DECODE = ("import sys, time; from gscodec_shac.codec.decoder import Decoder; "
                "data = open(sys.argv[1], 'rb').read(); "
                "tic = time.perf_counter(); Decoder().decode(data); print(time.perf_counter() - tic)")


def without_table(data: bytes) -> bytes:
    """``data`` with each HEVC stream's parameter sets put back and the table dropped (what the
    encoder wrote before format 2.4)."""
    stream = Bitstream.from_bytes(data)
    chunk = stream.chunk(parameter_sets.CHUNK)
    table = parameter_sets.read_table(zlib.decompress(chunk.data), chunk.meta["sets"])
    for each in stream.chunks:
        if parameter_sets.META_KEY in each.meta:
            each.data = parameter_sets.restore(each.data, tuple(each.meta.pop(parameter_sets.META_KEY)), table)
    stream.chunks.remove(chunk)
    stream.features.discard(parameter_sets.FEATURE)
    return stream.to_bytes()


def decode_times(path: Path, repeat: int) -> None:
    """Median decode-call seconds of ``path`` and of its copy without the table, alternately."""
    copy = path.with_name(path.stem + "_without_table.gsc")
    copy.write_bytes(without_table(path.read_bytes()))
    times: dict[Path, list[float]] = {path: [], copy: []}
    for _ in range(repeat):
        for each in times:
            out = subprocess.run([sys.executable, "-c", _TIME_DECODE, str(each)], check=True, capture_output=True,
                                 text=True).stdout
            times[each].append(float(out))
    for each, seconds in times.items():
        print(f"{each.name}: {each.stat().st_size:,} bytes, decode call median {statistics.median(seconds):.3f} s "
              f"of {repeat} ({min(seconds):.3f}-{max(seconds):.3f})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", nargs="?", help="a 3DGS model (PLY)")
    parser.add_argument("rate_points", nargs="*", help="rate points, e.g. shac_auto:template")
    parser.add_argument("--decode-times", type=Path, metavar="GSC",
                        help="time decoding this file with and without its table")
    parser.add_argument("--repeat", type=int, default=5, help="decodes of each file (--decode-times)")
    args = parser.parse_args()
    if args.decode_times:
        decode_times(args.decode_times, args.repeat)
        return
    if not args.model or not args.rate_points:
        parser.error("give a model and rate points (or --decode-times)")
    try:
        cloud, _ = read_model(args.model)
        for point in args.rate_points:
            shared = Encoder(point, workers=2).encode(cloud).to_bytes()
            with mock.patch.object(parameter_sets, "share", lambda stream, codecs: None):
                whole = Encoder(point, workers=2).encode(cloud).to_bytes()
            a, b = Decoder().decode(shared), Decoder().decode(whole)
            same = all(getattr(a, k).tobytes() == getattr(b, k).tobytes() for k in ARRAYS)
            chunks = sum(1 for c in Bitstream.from_bytes(whole).chunks if "codec" in c.meta)
            print(f"{point}: {len(whole):,} -> {len(shared):,} bytes ({len(shared) / len(whole) - 1:+.3%}; "
                  f"{chunks} grid-coded chunks; the same decoded arrays: {same})")
    except (GscodecError, OSError) as exc:
        sys.exit(f"error: {exc}")


if __name__ == "__main__":
    main()
