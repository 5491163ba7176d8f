"""``gscodec-shac info FILE``: what a 3DGS PLY holds and where its bytes go."""

from __future__ import annotations

import argparse
import json


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "info",
        help="describe a 3DGS PLY (count, SH degree, ranges, SH share of the size)",
        description="Describe a 3DGS PLY: Gaussian count, SH degree, per-attribute ranges, "
        "bytes per Gaussian and the SH share of them.",
    )
    parser.add_argument("file", help="an Inria 3DGS .ply")
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.summary import describe_cloud, format_cloud_summary

    cloud = read_ply(args.file)
    summary = describe_cloud(cloud, args.file)
    print(json.dumps(summary, indent=2) if args.json else format_cloud_summary(summary))
    return 0
