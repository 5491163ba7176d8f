"""``gscodec-shac encode IN.ply OUT.gsc``: compress a 3DGS PLY at a rate point or to a target.

With ``--target-size``, ``--target-bpg`` or ``--target-psnr`` the rate controller
(:mod:`gscodec_shac.codec.rate_control`) picks the settings of the ``shac_auto`` template.
"""

from __future__ import annotations

import argparse
import sys

from gscodec_shac.codec.effort import ANALYSES, FULL_ANALYSIS_MAX_GAUSSIANS
from gscodec_shac.commands._options import add_command, add_force, add_json, add_quiet, add_up
from gscodec_shac.shac.base import STAGES, StageParam

_TYPES = {"int": int, "float": float}


def stage_options() -> dict[str, list[tuple[str, StageParam]]]:
    """CLI flag -> the (stage, parameter) pairs it sets, from the stages' declarations."""
    options: dict[str, list[tuple[str, StageParam]]] = {}
    for name, cls in STAGES.items():
        for param in cls.params:
            if param.flag:
                options.setdefault(param.flag, []).append((name, param))
    return options


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "encode",
        help="compress a 3DGS model into one .gsc file",
        description="Compress a 3DGS model (Inria PLY, SPZ, .splat, SOG, compressed.ply, gsplat checkpoint, or "
        "a .gsc to re-encode) into a self-describing .gsc file. By default SHAC-PCA (ER 0.99) on the rate point "
        "shac_ladder:rp5, chosen to be smaller than SPZ at a better PSNR on the shared scenes (docs/formats.md); "
        "or at a rate point (a shipped one such as paper_table3:rp2, see "
        "'gscodec-shac rate-points', or FILE.yaml[:POINT]), optionally with an SH stage; or to a target "
        "size or quality, with the settings chosen per scene by the rate controller.",
        examples=["gscodec-shac encode scene.ply scene.gsc",
                  "gscodec-shac encode scene.ply scene.gsc --rate-point paper_table3:rp2 --sh pca --er 0.99",
                  "gscodec-shac encode scene.ply scene.gsc --target-size 2.5MB"],
    )
    parser.add_argument("input", metavar="IN", help="input model: Inria .ply, .compressed.ply, .spz, .splat, .sog, "
                        "SOG meta.json (or its folder), gsplat checkpoint .pt, a .gsc (decoded and re-encoded), a dynamic "
                        "model directory or a Deformable-3DGS output folder (its canonical Gaussians are coded as any "
                        "model, the deformation network as one chunk, see --network-bits)")
    parser.add_argument("output", metavar="OUT.gsc", help="output .gsc (written atomically)")
    parser.add_argument("--rate-point", "-r", metavar="SET:POINT",
                        help="e.g. paper_table3:rp2 (the paper's), shac_ladder:rp3, my.yaml:fast (default: "
                        "shac_ladder:rp5 with --sh pca --er 0.99, about visually lossless and smaller than SPZ, "
                        "see docs/formats.md; with a target: the template shac_auto:template); list them with "
                        "'gscodec-shac rate-points'")
    target = parser.add_argument_group("rate control (one target; the settings are chosen per scene)")
    target.add_argument("--target-size", metavar="SIZE",
                        help="the largest file, e.g. 2.5MB, 800kB, 1200000 (B, kB, MB, GB, KiB, MiB, GiB)")
    target.add_argument("--target-bpg", type=float, metavar="BITS",
                        help="the largest size in bits per Gaussian, e.g. 100")
    target.add_argument("--target-psnr", type=float, metavar="DB",
                        help="the lowest PSNR (dB) against the uncompressed model on --cameras (else orbit views), "
                        "e.g. 40")
    target.add_argument("--cameras", help="views the quality is judged from (any camera file or capture folder, "
                        "e.g. cameras.json); SHAC-PCA (a target's, the default's, --sh pca) weighs the SH by the "
                        "directions they see the Gaussians from; with --prune-keep, the views importance is "
                        "measured from")
    target.add_argument("--background", default="0,0,0",
                        help="background colour R,G,B in [0, 1] the views are rendered over (default 0,0,0; "
                        "NeRF-synthetic scenes use 1,1,1)")
    add_up(target, "the orbit views without --cameras")
    target.add_argument("--recover", action="store_true",
                        help="also code the model pruned to its most important 45%% and fine-tuned to its "
                        "own renders (on the cameras the quality is not judged from), and keep the file that "
                        "measures best against the model: smaller files at equal quality up to about 55 bits/G, "
                        "2-6x the time of a plain target (docs/rate_control.md, 'Pruning with recovery')")
    target.add_argument("--recover-steps", type=int, metavar="STEPS",
                        help="with --recover: the fine-tuning steps of the recovery (default 400; fewer are faster "
                        "and restore less; 0: prune only)")
    parser.add_argument("--prune-keep", type=float, metavar="SHARE",
                        help="keep this share of the Gaussians, in (0, 1]: those that contribute most to renders "
                        "from --cameras (else orbit views), after the rate point's opacity threshold "
                        "(default: the rate point's prune.keep_share, 1; docs/rate_control.md)")
    parser.add_argument("--sh-dc-only", type=float, metavar="SHARE",
                        help="code this share of the Gaussians, in [0, 1), with their DC colour only: those whose "
                        "view-dependent colour (AC energy times opacity) is weakest; the SH stage sees the others "
                        "only (default: the rate point's sh.dc_only_share, 0; docs/rate_control.md)")
    parser.add_argument("--sh-dc-energy", type=float, metavar="BAR",
                        help="instead of --sh-dc-only: code DC-only as many Gaussians as drop at most this fraction "
                        "of the cloud's view-dependent energy, in [0, 1), e.g. 0.02 (rate point sh.dc_only_energy)")
    parser.add_argument("--sh-dc-weight", choices=("alpha", "render"),
                        help="what a Gaussian's view-dependent energy is weighted by: its opacity (alpha) or its "
                        "contribution to renders from --cameras, else orbit views (render) (default: the rate "
                        "point's sh.dc_only_weight, alpha)")
    parser.add_argument("--sh", choices=STAGES.names(),
                        help="SH stage (default: pca without --rate-point, else the rate point's): "
                        + "; ".join(f"{name}: {cls.summary}" for name, cls in STAGES.items()))
    for flag, users in stage_options().items():
        kind = users[0][1].kind
        parser.add_argument(
            "--" + flag.replace("_", "-"), dest=flag, type=_TYPES.get(kind),
            choices=users[0][1].choices or None,
            help="; ".join(f"{stage}: {p.help}" + (f" (default {p.default})" if p.default is not None else "")
                           for stage, p in users),
        )
    parser.add_argument("--sort", choices=("plas", "morton", "random", "none"), help="grid sorting (default: the rate point's)")
    parser.add_argument("--preset", help="speed preset of the lossy codec (x265: ultrafast ... slow ... placebo)")
    parser.add_argument("--analysis", choices=ANALYSES,
                        help="x265's analysis of the lossy streams: full (RD level 6: 2-4%% smaller, 1.3-3.5x x265's "
                             f"time) or the preset's (default: full for scenes up to {FULL_ANALYSIS_MAX_GAUSSIANS:,} "
                             "Gaussians)")
    parser.add_argument("--seed", type=int, help="seed of the sorting and of the vq k-means (default: the rate point's)")
    parser.add_argument("--network-bits", type=int, choices=(16, 8, 7, 6, 5, 4, 3, 2), metavar="BITS",
                        help="a dynamic model's deformation network: 16 stores float16 weights, 2-8 quantises each "
                        "weight matrix per row to that many bits (below 8: the output heads and the time net's first "
                        "layer at 8, the matrix after the skip at one bit more; default 8, or the grid a network "
                        "trained with `train-dynamic --network-bits` was trained on; docs/dynamic.md)")
    add_quiet(parser)
    add_json(parser)
    add_force(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json

    from gscodec_shac.codec import encode_file
    from gscodec_shac.codec.defaults import DEFAULT_RATE_POINT, DEFAULT_SH_STAGE, choose_default_sh, describe_default
    from gscodec_shac.codec.rate_points import load_rate_point
    from gscodec_shac.commands._options import comma_floats
    from gscodec_shac.errors import GscodecError
    from gscodec_shac.io.models import report_notes

    check_paths(args)
    if args.recover_steps is not None and not args.recover:
        raise GscodecError("--recover-steps sets the recovery of --recover: give --recover too")
    if args.recover_steps is not None and args.recover_steps < 0:
        raise GscodecError(f"--recover-steps must be 0 or more, got {args.recover_steps}")
    targets = (args.target_size, args.target_bpg, args.target_psnr)
    if any(t is not None for t in targets):
        return _run_to_target(args)
    if args.recover:
        raise GscodecError("--recover applies to a target (--target-size, --target-bpg or --target-psnr); at a fixed "
                           "rate point, prune and recover first: gscodec-shac prune IN PRUNED.ply --keep SHARE")
    if args.sh_dc_only is not None and args.sh_dc_energy is not None:
        raise GscodecError("--sh-dc-only and --sh-dc-energy both choose the DC-only Gaussians: give one of them")
    default = args.rate_point is None
    point = load_rate_point(args.rate_point or DEFAULT_RATE_POINT)
    automatic = default and args.sh is None  # the SH stage is chosen from the model (codec/defaults.py)
    stage = args.sh or (DEFAULT_SH_STAGE if default else point.sh_stage)
    if args.cameras is not None and args.prune_keep is None and args.sh_dc_weight != "render" and stage != "pca":
        raise GscodecError("--cameras applies to --target-psnr (the views the quality is judged from), to SHAC-PCA "
                           "(--sh pca: the SH weighed by the directions they see), to --prune-keep and to "
                           "--sh-dc-weight render (the views importance is measured from)")
    params = {}
    for flag, users in stage_options().items():
        value = getattr(args, flag)
        if value is None:
            continue
        param = next((p for name, p in users if name == stage), None)
        if param is None:
            stages = " or ".join(name for name, _ in users)
            raise GscodecError(f"--{flag.replace('_', '-')} applies to --sh {stages}, not to the {stage!r} stage")
        params[param.name] = value
    if args.seed is not None and any(p.name == "seed" for p in STAGES.get(stage).params):
        params["seed"] = args.seed  # --seed seeds the stage (e.g. vq's k-means) as well as the sorting
    if params:  # stage options without --sh: they set the default's PCA
        automatic = False
    summary = encode_file(
        args.input, args.output, point, sh=stage, sort=args.sort, seed=args.seed, preset=args.preset,
        analysis=args.analysis,
        progress=not args.quiet and sys.stderr.isatty(), choose_sh=choose_default_sh if automatic else None,
        network_bits=args.network_bits, keep_share=args.prune_keep, dc_only_share=args.sh_dc_only,
        dc_only_energy=args.sh_dc_energy, dc_only_weight=args.sh_dc_weight, cameras=args.cameras,
        up=tuple(comma_floats(args.up, "--up")), **params,
    )
    notes = list(summary["notes"])
    if summary.get("sh_degree") == 0 and args.sh not in (None, "none"):
        notes.append(f"{args.input}: SH degree 0 (no AC coefficients), so the SH stage {stage!r} has nothing "
                     "to do (a no-op)")
    report_notes(notes)
    summary["default"] = default
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        chosen = (describe_default(summary["sh_stage"]) if automatic else
                  f"{summary['rate_point']}, SH stage {summary['sh_stage'] or 'none'}")
        if summary.get("sh_view_metric_cameras"):
            chosen += f", the SH weighed by the views of {summary['sh_view_metric_cameras']} cameras"
        print(f"wrote {summary['output']}: {summary['bytes']:,} bytes, {size_phrase(summary)} "
              f"({'default: ' if default else ''}{chosen}) in {summary['seconds']:.1f} s")
    return 0


def size_phrase(summary: dict) -> str:
    """``154.41 bits per input Gaussian (75,000 in, 7,732 pruned)``: the one bits-per-Gaussian
    definition of every command (file bits / Gaussians given to the encoder)."""
    n_in, n_out = summary["input_gaussians"], summary["num_gaussians"]
    removed = n_in - n_out
    kept = f"{removed:,} pruned" if removed else "none pruned"
    return f"{summary['bits_per_gaussian']:.2f} bits per input Gaussian ({n_in:,} in, {kept})"


def check_paths(args: argparse.Namespace) -> None:
    """The input first (a missing input is the error to see), then the output's name and place."""
    from pathlib import Path

    from gscodec_shac.atomic import check_output
    from gscodec_shac.commands._options import require_input
    from gscodec_shac.errors import OutputError

    require_input(args.input)
    check_output(args.output, force=args.force,
                 inputs=[args.input, (args.rate_point or "").rsplit(":", 1)[0], args.cameras])
    if Path(args.output).suffix.lower() != ".gsc":
        raise OutputError(f"{args.output}: encode writes a .gsc file; name the output OUT.gsc (to write another "
                          "model format use 'gscodec-shac convert IN OUT')")


def _run_to_target(args: argparse.Namespace) -> int:
    import json

    from gscodec_shac.codec import encode_file_to_target
    from gscodec_shac.codec.rate_control import SIZE_TOLERANCE, TEMPLATE
    from gscodec_shac.commands._options import comma_floats
    from gscodec_shac.errors import GscodecError
    from gscodec_shac.io.models import report_notes

    fixed = [flag for flag, value in (("--sh", args.sh), ("--sort", args.sort), ("--seed", args.seed),
                                      ("--network-bits", args.network_bits), ("--prune-keep", args.prune_keep),
                                      ("--sh-dc-only", args.sh_dc_only), ("--sh-dc-energy", args.sh_dc_energy),
                                      ("--sh-dc-weight", args.sh_dc_weight))
             if value is not None]
    fixed += ["--" + f.replace("_", "-") for f in stage_options() if getattr(args, f) is not None]
    if fixed:
        raise GscodecError(f"{', '.join(fixed)} cannot be combined with a target: the rate controller chooses the "
                           "SH stage settings and the pruning, and the grid order follows from the positions")
    summary = encode_file_to_target(
        args.input, args.output, size=args.target_size, bpg=args.target_bpg, psnr=args.target_psnr,
        template=args.rate_point or TEMPLATE, cameras=args.cameras, up=tuple(comma_floats(args.up, "--up")),
        background=tuple(comma_floats(args.background, "--background")),
        preset=args.preset, analysis=args.analysis, progress=not args.quiet and sys.stderr.isatty(),
        recover=args.recover, recover_steps=args.recover_steps,
    )
    notes = list(summary["notes"])
    control = summary["rate_control"]
    target = control["target"]
    if target["kind"] == "bytes" and summary["bytes"] < (1 - 2 * SIZE_TOLERANCE) * target["value"]:
        what = (f"--target-size {args.target_size}" if args.target_size is not None
                else f"--target-bpg {args.target_bpg:g}")
        notes.append(f"{what} is above the largest file the rate controller makes for this scene: its best "
                     f"settings need only {summary['bytes']:,} bytes, which were written")
    report_notes(notes)
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    settings = ", ".join(f"{k} {v}" for k, v in control["settings"].items())
    quality = f", {control['measured_psnr']:.2f} dB against the uncompressed model" if "measured_psnr" in control else ""
    if "recovery" in control:
        keep = control["recovery"]["keep"]
        quality += (f", from the model pruned to {keep:.0%} and recovered" if keep < 1
                    else ", from the model itself (the recovered ones measured worse)")
    if "tiers" in control:  # codec/tiers.py
        settings += "; in importance tiers, QP " + " / ".join(f"{v:+d}" for v in control["tiers"]["qp_offsets"])
    print(f"wrote {summary['output']}: {summary['bytes']:,} bytes, {size_phrase(summary)}"
          f"{quality} (rate control, {summary['rate_point']}: {settings}; {control['encodes']} encode(s)) "
          f"in {summary['seconds']:.1f} s")
    return 0
