"""``gscodec-shac convert IN OUT``: any model format we read -> any we write, by OUT's extension."""

from __future__ import annotations

import argparse

from gscodec_shac.commands._options import add_command, add_force, add_quiet, require_input, show_progress


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "convert",
        help="convert a 3DGS model between formats (PLY, SPZ, .splat, SOG, compressed.ply, gsplat .pt)",
        description="Read a 3DGS model in any format gscodec-shac reads (Inria .ply, .compressed.ply, .spz, "
        ".splat, SOG .sog / meta.json / its folder, gsplat checkpoint .pt, or a .gsc, decoded) and write it in "
        "the format OUT's extension names: .ply (Inria), .compressed.ply (PlayCanvas), .spz, .splat, .sog or "
        ".pt, atomically. What a format cannot hold is dropped with a note (docs/formats.md). To compress, use "
        "'gscodec-shac encode'.",
        examples=["gscodec-shac convert scene.spz scene.compressed.ply",
                  "gscodec-shac convert scene.gsc scene.splat"],
    )
    parser.add_argument("input", metavar="IN", help="input model (any readable format, or a .gsc)")
    parser.add_argument("output", metavar="OUT", help="output model: .ply, .compressed.ply, .spz, .splat, .sog or "
                        ".pt (a .gsc is written by 'encode')")
    parser.add_argument("--spz-version", type=int, choices=(2, 3, 4), default=3,
                        help="SPZ version of an .spz output (default 3, gzip; 4 is zstd, splat-transform's default)")
    add_quiet(parser)
    add_force(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from gscodec_shac.atomic import check_output, check_outputs, inputs_protected
    from gscodec_shac.errors import OutputError
    from gscodec_shac.io.models import check_model_extension, detect_format, output_files, output_format, read_model
    from gscodec_shac.io.models import report_notes, write_model

    require_input(args.input)
    if Path(args.output).suffix.lower() == ".gsc":
        raise OutputError(f"{args.output}: a .gsc is written by 'gscodec-shac encode IN OUT.gsc', not by convert")
    check_model_extension(args.output)
    check_output(args.output, force=args.force, inputs=[args.input])
    check_outputs(output_files(args.output), force=args.force)  # an unbundled SOG's images too
    source = detect_format(args.input)
    cloud, notes = read_model(args.input)
    with inputs_protected(args.input):
        options = {"version": args.spz_version} if output_format(args.output) == "spz" else {}
        notes += write_model(args.output, cloud, progress=show_progress(args), **options)
    report_notes(notes)
    print(f"wrote {args.output}: {cloud.num_gaussians:,} Gaussians, SH degree {cloud.sh_degree} "
          f"({source} -> {output_format(args.output)}, {Path(args.output).stat().st_size:,} bytes)")
    return 0
