"""How far the rate controller's models are from a real encode, attribute by attribute.

For a PSNR or size target the controller fits its models (``RateController.fit``), takes its
first plan and encodes it. Then, for each attribute, the whole cloud is rendered with only that
attribute as the encode decoded it, and its rendered MSE (against the uncompressed cloud, on
the controller's calibration views) is set beside the MSE the model predicted for it; and the
attribute's bytes in the file beside the bytes the model predicted (after pruning and the DC-only
bar, as the plan counts them). A ratio above 1: the model overstates that attribute's error, or
its bytes (docs/benchmarks.md, "Every ladder point and a PSNR target at 1M" and "Re-measure on
this session's machine").

    python scripts/psnr_model_check.py ../out/bench/250k/s250k.ply --psnr 52 [--cameras cameras.json] [--background 1,1,1]
    python scripts/psnr_model_check.py ../out/bench/1M/s1M.ply --bpg 100
"""

from __future__ import annotations

import argparse
import json

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", help="a static model file (PLY, or any format the codec reads)")
    goal = parser.add_mutually_exclusive_group(required=True)
    goal.add_argument("--psnr", type=float, help="a PSNR target (dB against the uncompressed model)")
    goal.add_argument("--bpg", type=float, help="a size target in bits per Gaussian")
    parser.add_argument("--cameras", help="a camera file (default: the controller's orbit views)")
    parser.add_argument("--background", default="0,0,0", help="r,g,b in [0, 1] (1,1,1 for NeRF-synthetic)")
    parser.add_argument("--json", help="write the rows here too")
    args = parser.parse_args()

    from gscodec_shac.io.cameras import load_cameras
    from gscodec_shac.codec import rate_control as rc
    from gscodec_shac.codec.encoder import Encoder
    from gscodec_shac.io.models import read_model

    cloud, _ = read_model(args.model)
    views = load_cameras(args.cameras) if args.cameras else None
    background = tuple(float(v) for v in args.background.split(","))
    controller = rc.RateController(cloud, views=views, background=background).fit()
    target = rc.Target("psnr", args.psnr) if args.psnr is not None else rc.make_target(cloud.num_gaussians, bpg=args.bpg)
    plan = controller._first_plan(target)
    # the encode the controller's _encode makes, kept here for its placement: the source row of every decoded row
    encoder = Encoder(plan.rate_point, sh_stage=controller.stage_, fit_stage=False, chunk_cache=controller._cache,
                      importance=controller.importance_)
    stream = encoder.encode(cloud)
    measured = controller.measured_psnr(stream)
    decoded = rc._decoded(stream, None)
    coded = rc._model_sizes(stream)
    rows = []
    for name, model in controller.models_.items():
        predicted = float(model.mse[np.searchsorted(model.choices, plan.settings[name])])
        row = {"attribute": name, "setting": plan.settings[name], "model_mse": predicted}
        model_bytes = controller._attribute_bytes(plan.settings, name)
        row.update(model_bytes=model_bytes, bytes=coded.get(name, 0), bytes_ratio=model_bytes / max(coded.get(name, 0), 1))
        if name != "positions":  # positions: the model is the quantisation step's, not a render
            rendered = controller._rendered_with_decoded(name, encoder.order_, decoded)
            row.update(rendered_mse=rendered, ratio=predicted / max(rendered, 1e-30))
        rows.append(row)
    print(f"first plan {plan.settings}: predicted {plan.predicted_psnr:.2f} dB, {plan.predicted_bytes:,.0f} bytes; "
          f"measured {measured:.2f} dB, {stream.total_bytes():,} bytes")
    for row in rows:
        extra = f"  rendered {row['rendered_mse']:.3e}  model / rendered {row['ratio']:.2f}" if "ratio" in row else ""
        print(f"{row['attribute']:10s} {row['setting']:>4}  model {row['model_mse']:.3e}{extra}  "
              f"bytes: model {row['model_bytes']:,.0f} coded {row['bytes']:,} model / coded {row['bytes_ratio']:.2f}")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump({"predicted_psnr": plan.predicted_psnr, "measured_psnr": measured,
                       "predicted_bytes": plan.predicted_bytes, "bytes": stream.total_bytes(), "rows": rows}, handle,
                      indent=1)


if __name__ == "__main__":
    main()
