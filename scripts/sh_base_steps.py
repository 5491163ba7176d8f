"""Bytes and rendered PSNR of one rate-controller plan as only the SH features' base QP moves.

Fits the rate controller (``shac_auto:template``) on a scene, then encodes the plan given by
``--settings`` (the other QPs, position bits, pruning and DC-only choices, as an encode's
``rate_control.settings`` records them) at each base QP of ``--bases`` (whole or in quarter
steps, controller version 17) and measures each file's PSNR against the uncompressed model on
the controller's views (docs/rate_control.md, "Controller version 17"). Results are printed and
written as CSV.

    python scripts/sh_base_steps.py ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply \\
        --cameras ../shared/data/scenes/bonsai_cpu_sh3/cameras.json --test-every 8 \\
        --settings '{"opacity": 7, "rotation": 8, "scale": 5, "sh_dc": 11, "positions": 13, "prune": 5, "dc_only": 1}' \\
        --bases 19 19.5 20 20.25 20.5 20.75 21 21.5 22 --csv ../out/sh_base_steps.csv
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

from gscodec_shac.codec import Encoder
from gscodec_shac.codec.rate_control import RateController, _setting
from gscodec_shac.errors import GscodecError
from gscodec_shac.io.cameras import load_cameras
from gscodec_shac.io.models import read_model
from gscodec_shac.rd.scenes import test_split


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", help="a model file")
    parser.add_argument("--cameras", help="the scene's cameras (default: orbit views)")
    parser.add_argument("--test-every", type=int, default=8, help="every k-th camera is held out, as the RD runner does")
    parser.add_argument("--background", type=float, nargs=3, default=(0.0, 0.0, 0.0))
    parser.add_argument("--settings", required=True, help="the plan's other settings, a JSON object")
    parser.add_argument("--bases", type=float, nargs="+", required=True, help="SH features' base QPs (multiples of 0.25)")
    parser.add_argument("--csv", type=Path, help="also write the rows here")
    args = parser.parse_args()
    try:
        settings = json.loads(args.settings)
        cloud, _ = read_model(args.model)
        views = None
        if args.cameras:
            train, test = test_split(load_cameras(args.cameras), args.test_every)
            views = train or test
        controller = RateController(cloud, views=views, background=tuple(args.background)).fit()
        rows = []
        for base in args.bases:
            point = controller._rate_point({**settings, "sh": _setting(base)})
            stream = Encoder(point, sh_stage=controller.stage_, fit_stage=False, chunk_cache=controller._cache,
                             importance=controller.importance_).encode(cloud)
            row = {"base_qp": base, "bytes": stream.total_bytes(), "sh_bytes": stream.attribute_sizes().get("sh", 0),
                   "psnr": round(controller.measured_psnr(stream), 3)}
            rows.append(row)
            print(", ".join(f"{k} {v}" for k, v in row.items()), flush=True)
        if args.csv:
            with open(args.csv, "w", newline="") as handle:
                writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
                writer.writeheader()
                writer.writerows(rows)
    except (GscodecError, json.JSONDecodeError, KeyError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
