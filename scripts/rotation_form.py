"""The rotation coded as a quaternion or as a rotation vector, at one plan of the rate controller.

Fits the rate controller (SHAC-auto) on the model, takes its plan at ``--bpg`` and, with every other
setting of the plan fixed, codes the rotation at each QP of ``--qps`` in both forms (rate point
``attributes.rotation.form``: ``quaternion``, x, y, z at the QP and w ``--w-offset`` QPs above it, as
the template of controller versions 7-18 did; ``vector``, angle * axis, at the QP). PSNR
against the uncompressed model on the held-out cameras (every ``--test-every``-th); prints the
BD-rate of the vector form against the quaternion of the whole file and of the rotation bytes, and
writes one CSV row per encode (docs/rate_control.md, "Controller version 19").

    python scripts/rotation_form.py ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply \\
        --cameras ../shared/data/scenes/bonsai_cpu_sh3/cameras.json --test-every 8 --csv bonsai_rotation.csv
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from tqdm import tqdm

from gscodec_shac.codec import rate_control as rc_module
from gscodec_shac.codec.attributes import ROTATION_FORMS
from gscodec_shac.codec.decoder import Decoder
from gscodec_shac.codec.encoder import Encoder
from gscodec_shac.codec.rate_points import RatePoint
from gscodec_shac.errors import GscodecError
from gscodec_shac.rd.bd import bd_rate
from held_out_scene import HeldOutScene, add_scene_arguments, write_rows


def with_rotation(point: RatePoint, form: str, qp: int, w_offset: int) -> RatePoint:
    """``point`` with its rotation coded in ``form`` at ``qp`` (a quaternion's w ``w_offset`` QPs above)."""
    qps = (qp, min(51, qp + w_offset)) if form == "quaternion" and w_offset else qp
    attributes = dict(point.attributes)
    attributes["rotation"] = dataclasses.replace(attributes["rotation"], form=form, qp=qps)
    return dataclasses.replace(point, attributes=attributes)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, bpg=55.0)
    parser.add_argument("--qps", type=int, nargs="+", default=[2, 6, 10, 14, 18, 22])
    parser.add_argument("--w-offset", type=int, default=12,
                        help="a quaternion's w this many QPs above x, y, z (the template of versions 7-18: 12)")
    args = parser.parse_args()
    try:
        scene = HeldOutScene.from_arguments(args)
        cloud = scene.cloud
        controller = rc_module.RateController(cloud, views=scene.train, background=scene.background,
                                              workers=2).fit()
    except (GscodecError, OSError, ValueError) as exc:
        sys.exit(f"error: {exc}")
    settings = controller.encode(rc_module.Target("bytes", args.bpg * cloud.num_gaussians / 8)).plan.settings
    print("plan", settings)
    stage = rc_module.fitted_stage(controller.template, cloud, controller._sh_metric())
    references = scene.references()
    rows = []
    with tqdm(total=len(ROTATION_FORMS) * len(args.qps), desc="rotation forms", unit="encode") as bar:
        for form in ROTATION_FORMS:
            for qp in args.qps:
                point = with_rotation(controller._rate_point(settings), form, qp, args.w_offset)
                stream = Encoder(point, sh_stage=stage, fit_stage=False, workers=2,
                                 importance=controller.importance_).encode(cloud)
                data = stream.to_bytes()
                quality = scene.mean_psnr(Decoder().decode(data), references)
                rows.append({"form": form, "qp": qp, "bytes": len(data),
                             "rotation_bytes": stream.attribute_sizes()["rotation"], "psnr_held_out": quality})
                bar.update(1)
    write_rows(args.csv, rows)
    quaternion, vector = ([r for r in rows if r["form"] == form] for form in ("quaternion", "vector"))
    for rate in ("bytes", "rotation_bytes"):
        value = bd_rate([r[rate] for r in quaternion], [r["psnr_held_out"] for r in quaternion],
                        [r[rate] for r in vector], [r["psnr_held_out"] for r in vector]).value
        print(f"vector vs quaternion, {rate}: BD-rate {value:+.2f}%")


if __name__ == "__main__":
    main()
