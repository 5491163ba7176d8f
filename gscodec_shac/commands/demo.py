"""``gscodec-shac demo``: the main job on a scene the project makes itself."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="run the end-to-end demo on the built-in synthetic scene",
        description="Generate the built-in synthetic SH-3 scene, write it and describe it.",
    )
    parser.add_argument("--out", default="demo-output", help="output directory (created)")
    parser.add_argument("-n", "--num-gaussians", type=int, default=20_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscodec_shac.io.cameras import write_inria_cameras
    from gscodec_shac.io.ply import write_ply
    from gscodec_shac.summary import describe_cloud, format_cloud_summary
    from gscodec_shac.synthetic import make_synthetic_scene

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = make_synthetic_scene(args.num_gaussians, seed=args.seed)
    ply = out / "synthetic.ply"
    write_ply(ply, scene.cloud)
    write_inria_cameras(out / "cameras.json", scene.cameras)
    print(format_cloud_summary(describe_cloud(scene.cloud, ply)))
    return 0
