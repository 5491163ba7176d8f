"""The default ``encode`` against the input file and SPZ (splat-transform) from the same model.

For each scene: the input is read (the "uncompressed model" is what it decodes to), encoded
with each candidate setting, and written as SPZ by splat-transform from a PLY of the same
model; every file is decoded and rendered on the scene's cameras (``--cameras``) or on
orbit views, and its PSNR against the uncompressed model's renders is printed with its size.

    python scripts/measure_default_encode.py OUT_DIR NAME=MODEL[@CAMERAS] ... \
        --candidate shac_ladder:rp5,pca,0.99
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np


def _psnr_views(reference: list[np.ndarray], images: list[np.ndarray]) -> float:
    """PSNR of the mean MSE over the views, images clipped to [0, 1] as they are displayed."""
    from gscodec_shac.metrics import mse as image_mse

    mse = float(np.mean([image_mse(b, a) for a, b in zip(reference, images)]))
    return 10.0 * math.log10(1.0 / max(mse, 1e-20))


def _views(cloud, cameras: str | None, width: int, count: int) -> list:
    from gscodec_shac.camera import orbit_views, spread_views
    from gscodec_shac.io.cameras import load_cameras

    if cameras:
        return spread_views(load_cameras(cameras), count, width)
    return orbit_views(cloud.means, count, width, elevations=(20.0,))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path)
    parser.add_argument("scenes", nargs="+", help="NAME=MODEL[@CAMERAS]")
    parser.add_argument("--candidate", action="append", default=[],
                        help="RATE_POINT[,STAGE[,ER]] (default: the encode default)")
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--width", type=int, default=320)
    args = parser.parse_args(argv)

    from gscodec_shac.codec import encode_file
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.decoder import Decoder
    from gscodec_shac.io.models import model_bytes, read_model
    from gscodec_shac.io.ply import write_ply
    from gscodec_shac.rd.external import encode_spz
    from gscodec_shac.render.renderer import render_views

    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for spec in args.scenes:
        name, _, rest = spec.partition("=")
        model, _, cameras = rest.partition("@")
        cloud, _ = read_model(model)
        n = cloud.num_gaussians
        views = _views(cloud, cameras or None, args.width, args.views)
        reference = render_views(cloud, views, progress=False)
        ply = args.out / f"{name}.ply"
        write_ply(ply, cloud)
        results = [{"file": "input", "path": model, "bytes": model_bytes(model), "psnr": float("inf")}]
        spz = args.out / f"{name}.spz"
        encode_spz(ply, spz)
        spz_cloud, _ = read_model(spz)
        results.append({"file": "spz (splat-transform)", "path": str(spz), "bytes": spz.stat().st_size,
                        "psnr": _psnr_views(reference, render_views(spz_cloud, views, progress=False))})
        for candidate in args.candidate or ["default"]:
            parts = candidate.split(",")
            out = args.out / f"{name}.{parts[0].replace(':', '_')}{'_' + '_'.join(parts[1:]) if parts[1:] else ''}.gsc"
            tic = time.process_time()
            if candidate == "default":
                from gscodec_shac.codec.defaults import DEFAULT_RATE_POINT, choose_default_sh

                summary = encode_file(model, out, DEFAULT_RATE_POINT, choose_sh=choose_default_sh)
            else:
                params = {"energy_retention": float(parts[2])} if len(parts) > 2 else {}
                summary = encode_file(model, out, parts[0], sh=parts[1] if len(parts) > 1 else None, **params)
            cpu = time.process_time() - tic
            decoded = Decoder().decode(Bitstream.read(out).to_bytes())
            results.append({"file": f"gsc {candidate}", "sh_stage": summary["sh_stage"], "path": str(out),
                            "bytes": summary["bytes"],
                            "decoded_gaussians": decoded.num_gaussians, "encode_cpu_s": cpu,
                            "psnr": _psnr_views(reference, render_views(decoded, views, progress=False))})
        for r in results:
            r.update(scene=name, input_gaussians=n, bits_per_input_gaussian=8.0 * r["bytes"] / n)
            print(json.dumps(r), flush=True)
        rows += results
    (args.out / "results.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
