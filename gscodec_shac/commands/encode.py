"""``gscodec-shac encode IN.ply OUT.gsc``: compress a 3DGS PLY at a rate point."""

from __future__ import annotations

import argparse
import sys

#: CLI option -> (SH stage parameter, stages it applies to).
STAGE_OPTIONS = {
    "er": ("energy_retention", ("pca",)),
    "components": ("n_components", ("pca",)),
    "degree": ("degree", ("trunc",)),
    "clusters": ("n_clusters", ("vq",)),
    "centroid_bits": ("centroid_bits", ("vq",)),
}


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "encode",
        help="compress a 3DGS PLY into one .gsc file",
        description="Compress an Inria 3DGS PLY into a self-describing .gsc file at a rate point "
        "(a shipped one such as paper_table3:rp2, or FILE.yaml[:POINT]), optionally with an SH stage.",
    )
    parser.add_argument("input", help="input .ply")
    parser.add_argument("output", help="output .gsc (written atomically)")
    parser.add_argument("--rate-point", "-r", default="paper_table3:rp2",
                        help="FILE:POINT, e.g. paper_table3:rp2, mpeg_ctc_video:rp01, gsplat_png (default: %(default)s)")
    parser.add_argument("--sh", choices=("none", "trunc", "pca", "lst", "vq"),
                        help="SH stage (default: the rate point's)")
    parser.add_argument("--er", type=float, help="pca: energy retention, e.g. 0.99")
    parser.add_argument("--components", type=int, help="pca: number of components M")
    parser.add_argument("--degree", type=int, help="trunc: SH degree L' kept")
    parser.add_argument("--clusters", type=int, help="vq: codebook size (default 65536)")
    parser.add_argument("--centroid-bits", type=int, help="vq: bits per codebook component (default 6)")
    parser.add_argument("--sort", choices=("plas", "morton", "random", "none"), help="grid sorting (default: the rate point's)")
    parser.add_argument("--preset", help="speed preset of the lossy codec (x265: ultrafast ... slow ... placebo)")
    parser.add_argument("--seed", type=int, help="seed of the sorting and of the vq k-means (default: the rate point's)")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress bars")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json

    from gscodec_shac.errors import GscodecError
    from gscodec_shac.codec import encode_file
    from gscodec_shac.codec.rate_points import load_rate_point

    point = load_rate_point(args.rate_point)
    stage = args.sh or point.sh_stage
    params = {}
    for option, (param, stages) in STAGE_OPTIONS.items():
        value = getattr(args, option)
        if value is None:
            continue
        if stage not in stages:
            flag = "--" + option.replace("_", "-")
            raise GscodecError(f"{flag} applies to --sh {' or '.join(stages)}, not to the {stage!r} stage")
        params[param] = value
    if args.seed is not None and stage == "vq":
        params["seed"] = args.seed  # --seed seeds the k-means as well as the sorting
    summary = encode_file(
        args.input, args.output, point, sh=args.sh, sort=args.sort, seed=args.seed, preset=args.preset,
        progress=not args.quiet and sys.stderr.isatty(), **params,
    )
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(
            f"wrote {summary['output']}: {summary['bytes']:,} bytes, {summary['bits_per_gaussian']:.2f} bits/Gaussian "
            f"({summary['num_gaussians']:,} Gaussians, {summary['rate_point']}, SH stage {summary['sh_stage']}) "
            f"in {summary['seconds']:.1f} s"
        )
    return 0
