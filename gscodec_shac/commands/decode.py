"""``gscodec-shac decode IN.gsc OUT.ply|.spz|.splat|.sog|.pt``: decompress a .gsc file; the extension picks the format."""

from __future__ import annotations

import argparse
import sys

from gscodec_shac.commands._options import add_command, add_force, add_quiet


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "decode",
        help="decompress a .gsc file into a 3DGS PLY any viewer opens",
        description="Decode a .gsc file into a 3DGS model, written atomically; the output's extension picks "
        "the format: .ply (Inria 3DGS, any viewer opens it), .spz, .splat, .sog or .pt (a gsplat checkpoint).",
        examples=["gscodec-shac decode scene.gsc decoded.ply", "gscodec-shac decode scene.gsc decoded.spz"],
    )
    parser.add_argument("input", metavar="IN.gsc", help="input .gsc")
    parser.add_argument("output", metavar="OUT", help="output model: .ply (Inria 3DGS), .spz, .splat, .sog or .pt "
                        "(gsplat checkpoint)")
    add_quiet(parser)
    add_force(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscodec_shac.atomic import check_output
    from gscodec_shac.codec import decode_file
    from gscodec_shac.io.models import report_notes

    check_output(args.output, force=args.force, inputs=[args.input])
    summary = decode_file(args.input, args.output, progress=not args.quiet and sys.stderr.isatty())
    report_notes(summary["notes"])
    print(
        f"wrote {summary['output']}: {summary['num_gaussians']:,} Gaussians, SH degree {summary['sh_degree']}, "
        f"from {summary['bytes']:,} bytes in {summary['seconds']:.2f} s"
    )
    return 0
