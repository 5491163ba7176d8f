"""``gscodec-shac synthetic OUT.ply``: write a generated SH-3 scene and its orbit cameras."""

from __future__ import annotations

import argparse
from pathlib import Path

from gscodec_shac.commands._options import add_command, add_force, add_quiet


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "synthetic",
        help="generate a synthetic SH scene (PLY + cameras.json), no input files needed",
        description="Generate a seeded synthetic 3DGS scene with physically motivated view-dependent "
        "colour (see gscodec_shac.synthetic) and write it as an Inria PLY plus cameras.json (orbit views "
        "around the scene, world up +Z).",
        examples=["gscodec-shac synthetic scene.ply -n 100000 --views 32"],
    )
    parser.add_argument("out", metavar="OUT.ply", help="output .ply path; cameras.json is written beside it")
    parser.add_argument("-n", "--num-gaussians", type=int, default=20_000, metavar="N",
                        help="number of Gaussians, 1 to 20,000,000 (default 20000)")
    parser.add_argument("--sh-degree", type=int, default=3, choices=range(5), help="SH degree 0-4 (default 3)")
    parser.add_argument("--seed", type=int, default=0, help="random seed: the same seed gives the same scene "
                        "(default 0)")
    parser.add_argument("--views", type=int, default=24, metavar="N", help="number of orbit cameras (default 24)")
    parser.add_argument("--width", type=int, default=320, metavar="W", help="camera image width (default 320)")
    parser.add_argument("--height", type=int, default=240, metavar="H", help="camera image height (default 240)")
    add_quiet(parser)
    add_force(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscodec_shac.atomic import check_output
    from gscodec_shac.errors import GscodecError
    from gscodec_shac.io.inria_cameras import write_inria_cameras
    from gscodec_shac.io.ply import write_ply
    from gscodec_shac.synthetic import make_synthetic_scene

    if not 1 <= args.num_gaussians <= 20_000_000:
        raise GscodecError(f"--num-gaussians must be between 1 and 20,000,000, got {args.num_gaussians}")
    out = Path(args.out)
    check_output(out, force=args.force)
    check_output(out.with_name("cameras.json"), force=args.force, what="cameras file")
    scene = make_synthetic_scene(
        args.num_gaussians, sh_degree=args.sh_degree, seed=args.seed,
        n_cameras=args.views, width=args.width, height=args.height, progress=not args.quiet,
    )
    write_ply(out, scene.cloud)
    cameras_path = out.with_name("cameras.json")
    write_inria_cameras(cameras_path, scene.cameras)
    print(f"wrote {out} ({scene.cloud.num_gaussians:,} Gaussians, SH degree {args.sh_degree}) and {cameras_path}")
    return 0
