"""``gscodec-shac decode IN.gsc OUT.ply|.spz|.splat|.sog|.pt``: decompress a .gsc file; the extension picks the format."""

from __future__ import annotations

import argparse
import sys

from gscodec_shac.commands._options import add_force


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "decode",
        help="decompress a .gsc file into a 3DGS PLY any viewer opens",
        description="Decode a .gsc file into an Inria 3DGS PLY (written atomically).",
    )
    parser.add_argument("input", help="input .gsc")
    parser.add_argument("output", help="output model: .ply (Inria 3DGS), .spz, .splat, .sog or .pt (gsplat checkpoint)")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress bars")
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
