"""What storing the HEVC parameter sets once per file saves (format 2.4, codec/parameter_sets.py).

Encodes the model at each rate point twice in one process, with the parameter-set table and with
each stream keeping its own (the encoder's ``parameter_sets.share`` replaced by a no-op), checks that
both decode to the same arrays and prints the bytes (docs/codec.md, "HEVC parameter sets once per file").

    python scripts/parameter_sets_gain.py ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply \\
        shac_auto:template shac_ladder:rp1 shac_ladder:rp4
"""

from __future__ import annotations

import argparse
import sys
from unittest import mock

from gscodec_shac.codec import parameter_sets
from gscodec_shac.codec.container import Bitstream
from gscodec_shac.codec.decoder import Decoder
from gscodec_shac.codec.encoder import Encoder
from gscodec_shac.errors import GscodecError
from gscodec_shac.io.models import read_model

ARRAYS = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", help="a 3DGS model (PLY)")
    parser.add_argument("rate_points", nargs="+", help="rate points, e.g. shac_auto:template")
    args = parser.parse_args()
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
