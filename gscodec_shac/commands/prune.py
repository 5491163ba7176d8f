"""``gscodec-shac prune IN OUT --keep 0.45``: keep the most important Gaussians, then recover them.

Importance is each Gaussian's share of the rendered views (:mod:`gscodec_shac.codec.importance`);
the recovery fine-tunes what is kept towards the input's own renders from the same views
(:mod:`gscodec_shac.train.recover`), so no photos are needed. OUT is then encoded as any model.
"""

from __future__ import annotations

import argparse

from gscodec_shac.commands._options import (
    add_command,
    add_force,
    add_json,
    add_quiet,
    comma_floats,
    require_input,
    show_progress,
)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "prune",
        help="keep the most important Gaussians of a model and fine-tune them to its renders",
        description="Rank every Gaussian by what it adds to the rendered views (its summed blending weight; the "
        "scene's cameras, else 24 orbit views), keep the most important share, then fine-tune the kept ones "
        "for --recover steps towards the input model's own renders from the same views (no photos needed; "
        "0: prune only). Writes OUT in the format its extension names, atomically. Encode OUT as usual; "
        "docs/rate_control.md, 'Pruning with recovery'.",
        examples=["gscodec-shac prune scene.ply pruned.ply --keep 0.45 --cameras cameras.json --split train",
                  "gscodec-shac prune lego.ply pruned.ply --keep 0.6 --cameras cameras.json --background 1,1,1"],
    )
    parser.add_argument("input", metavar="IN", help="input model (any readable format, or a .gsc)")
    parser.add_argument("output", metavar="OUT", help="output model: .ply, .compressed.ply, .spz, .splat, .sog or .pt")
    parser.add_argument("--keep", type=float, required=True, metavar="SHARE",
                        help="share of the Gaussians kept, in (0, 1], e.g. 0.45")
    parser.add_argument("--recover", type=int, metavar="STEPS",
                        help="fine-tuning steps after pruning (default 400, gscodec_shac.train.recover; 0: prune only)")
    parser.add_argument("--cameras", help="the scene's cameras (cameras.json, transforms*.json, a COLMAP model or "
                        "a capture folder); default: orbit views around the model")
    parser.add_argument("--split", choices=("all", "train"), default="all",
                        help="cameras used: all, or train = all but every 8th in name order (the 3DGS held-out "
                        "views, left for evaluation); default all")
    parser.add_argument("--background", default="0,0,0", metavar="R,G,B",
                        help="render background R,G,B in [0, 1] (default 0,0,0; NeRF-synthetic scenes: 1,1,1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the fine-tune's view order (default 0)")
    add_json(parser)
    add_quiet(parser)
    add_force(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from gscodec_shac.atomic import check_output, check_outputs, inputs_protected
    from gscodec_shac.camera import test_split
    from gscodec_shac.errors import GscodecError, OutputError
    from gscodec_shac.io.cameras import load_cameras
    from gscodec_shac.io.models import check_model_extension, output_files, read_model, report_notes, write_model
    from gscodec_shac.train.recover import DEFAULT_ITERATIONS, check_settings, prune_and_recover

    require_input(args.input)
    steps = DEFAULT_ITERATIONS if args.recover is None else args.recover
    if Path(args.output).suffix.lower() == ".gsc":
        raise OutputError(f"{args.output}: prune writes a model; encode it with 'gscodec-shac encode' afterwards")
    check_settings(args.keep, steps)
    background = comma_floats(args.background, "--background")
    if not all(0.0 <= v <= 1.0 for v in background):
        raise GscodecError(f"--background values must lie in [0, 1], got {args.background!r}")
    if args.split == "train" and not args.cameras:
        raise GscodecError("--split train needs --cameras")
    check_model_extension(args.output)
    check_output(args.output, force=args.force, inputs=[args.input] + ([args.cameras] if args.cameras else []))
    check_outputs(output_files(args.output), force=args.force)
    cloud, notes = read_model(args.input)
    cameras = None
    if args.cameras:
        cameras = load_cameras(args.cameras)
        if args.split == "train":
            cameras = test_split(cameras)[0]
        if not cameras:
            raise GscodecError(f"{args.cameras}: no cameras left for --split {args.split}")
    result = prune_and_recover(cloud, cameras, keep_share=args.keep, iterations=steps, background=background,
                               seed=args.seed, measure=steps > 0, progress=show_progress(args))
    with inputs_protected(args.input):
        notes += write_model(args.output, result.cloud, progress=show_progress(args))
    report_notes(notes)
    summary = {"output": str(args.output), "input_gaussians": cloud.num_gaussians, **result.summary()}
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    recovered = (f"; recovered in {result.iterations} steps on {result.views} views: "
                 f"{result.psnr_pruned:.2f} -> {result.psnr_recovered:.2f} dB against the input's renders"
                 if result.iterations else " (no recovery)")
    print(f"wrote {args.output}: kept {result.kept:,} of {cloud.num_gaussians:,} Gaussians{recovered} "
          f"({result.seconds:.1f} s)")
    return 0
