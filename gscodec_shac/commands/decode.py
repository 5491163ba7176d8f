"""``gscodec-shac decode IN.gsc OUT.ply|.spz|.splat|.sog|meta.json|.pt``: decompress a .gsc file; the extension picks the format."""

from __future__ import annotations

import argparse
import sys

from gscodec_shac.commands._options import add_command, add_force, add_quiet


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "decode",
        help="decompress a .gsc file into a 3DGS PLY any viewer opens",
        description="Decode a .gsc file into a 3DGS model, written atomically; the output's extension picks "
        "the format: .ply (Inria 3DGS, any viewer opens it), .compressed.ply (PlayCanvas's chunked format), .spz, "
        ".splat, .sog or .pt (a gsplat checkpoint); DIR/meta.json writes an unbundled SOG (meta.json and its WebP "
        "images in DIR). "
        "A dynamic model (a stream with a deformation network) decodes to a model directory: point_cloud.ply "
        "(canonical Gaussians), deformation.npz and deformation.json.",
        examples=["gscodec-shac decode scene.gsc decoded.ply", "gscodec-shac decode scene.gsc decoded.spz"],
    )
    parser.add_argument("input", metavar="IN.gsc", help="input .gsc")
    parser.add_argument("output", metavar="OUT", help="output model: .ply (Inria 3DGS), .compressed.ply, .spz, .splat, "
                        ".sog, DIR/meta.json (unbundled SOG) or .pt (gsplat checkpoint); a directory for a dynamic model")
    add_quiet(parser)
    add_force(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscodec_shac.atomic import check_output
    from gscodec_shac.codec import decode_file
    from gscodec_shac.io.models import report_notes

    from pathlib import Path

    from gscodec_shac.codec.files import is_dynamic_stream
    from gscodec_shac.errors import OutputError

    if Path(args.input).is_file() and is_dynamic_stream(args.input):  # a dynamic model: OUT is a directory
        from gscodec_shac.atomic import check_outputs, protect_inputs
        from gscodec_shac.deform_arch import ARCH_FILE, MODEL_PLY, WEIGHTS_FILE

        protect_inputs(args.input)
        out = Path(args.output)
        if out.exists() and not out.is_dir():
            raise OutputError(f"{out}: {args.input} holds a dynamic model; OUT must be a directory")
        check_outputs([out / n for n in (MODEL_PLY, WEIGHTS_FILE, ARCH_FILE)], force=args.force)
    else:
        from gscodec_shac.atomic import check_outputs
        from gscodec_shac.io.models import output_files

        check_output(args.output, force=args.force, inputs=[args.input])
        check_outputs(output_files(args.output), force=args.force)  # an unbundled SOG's images too
    summary = decode_file(args.input, args.output, progress=not args.quiet and sys.stderr.isatty())
    report_notes(summary["notes"])
    print(
        f"wrote {summary['output']}: {summary['num_gaussians']:,} Gaussians, SH degree {summary['sh_degree']}, "
        f"from {summary['bytes']:,} bytes in {summary['seconds']:.2f} s"
    )
    return 0
