"""``gscodec-shac info FILE``: what a 3DGS PLY or a .gsc file holds and where its bytes go."""

from __future__ import annotations

import argparse
import json
from typing import Any

from gscodec_shac.commands._options import add_command, add_json


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "info",
        help="describe a 3DGS PLY or a .gsc file (count, SH degree, where the bytes go)",
        description="Describe a 3DGS model (Gaussian count, SH degree, per-attribute ranges, bytes per "
        "Gaussian, SH share) or a .gsc file (header summary, bytes and bits per Gaussian per attribute and "
        "chunk, QPs and codecs).",
        examples=["gscodec-shac info scene.gsc", "gscodec-shac info scene.ply --json"],
    )
    parser.add_argument("file", metavar="FILE", help="a .gsc file or a model: Inria .ply, .compressed.ply, .spz, "
                        ".splat, .sog, SOG meta.json (or its folder), gsplat checkpoint .pt, a dynamic model "
                        "directory (deformation.json)")
    add_json(parser, "the description")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscodec_shac.codec.container import is_gsc

    if is_gsc(args.file):
        from gscodec_shac.codec.container import Bitstream

        summary = describe_gsc(Bitstream.read(args.file), args.file)
        print(json.dumps(summary, indent=2) if args.json else format_gsc_summary(summary))
        return 0

    from gscodec_shac.io.models import read_model, report_notes
    from gscodec_shac.codec.summary import describe_cloud, format_cloud_summary
    from gscodec_shac.deform_arch import is_dynamic_model

    if is_dynamic_model(args.file):
        from gscodec_shac.deform import load_dynamic_model

        model = load_dynamic_model(args.file)
        summary = describe_cloud(model.cloud, args.file)
        summary["deformation"] = {"arch": model.arch.to_dict(), "weights": model.net.n_params,
                                  "float32_bytes": 4 * model.net.n_params}
        text = format_cloud_summary(summary) + "\n" + _deformation_line(summary["deformation"])
        print(json.dumps(summary, indent=2) if args.json else text)
        return 0
    cloud, notes = read_model(args.file)
    report_notes(notes)
    summary = describe_cloud(cloud, args.file)
    print(json.dumps(summary, indent=2) if args.json else format_cloud_summary(summary))
    return 0


def _deformation_line(info: dict[str, Any]) -> str:
    arch = info["arch"]
    dtype = info.get("dtype", "float16")
    form = f"{info['bits']}-bit per-row quantised" if dtype == "uint8" else dtype
    stored = f"{info['bytes']:,} bytes ({form})" if "bytes" in info else \
        f"{info['float32_bytes']:,} bytes as float32"
    return (f"deformation       MLP {arch['depth']}x{arch['width']}"
            f"{' + time net' if arch['time_net'] else ''}, {info['weights']:,} weights, {stored}")


def describe_gsc(stream: Any, path: str) -> dict[str, Any]:
    """A JSON-serialisable summary of a parsed .gsc :class:`~gscodec_shac.codec.container.Bitstream`,
    from its checked header (:func:`~gscodec_shac.codec.header.read_header`)."""
    from gscodec_shac.codec.header import describe, read_header
    from gscodec_shac.errors import BitstreamError

    try:
        view = read_header(stream)
    except BitstreamError as exc:
        raise BitstreamError(f"{path}: {exc}") from None
    return {"file": str(path), **describe(view)}


def format_gsc_summary(summary: dict[str, Any]) -> str:
    """Human-readable lines for :func:`describe_gsc`."""
    lines = [
        f"file              {summary['file']} ({summary['bytes']:,} bytes, .gsc format {summary['format_version']}, "
        f"{summary['producer']})",
        f"Gaussians         {summary['num_gaussians']:,} (input {summary['input_gaussians']:,}; "
        f"pruned {summary['pruned']:,}, dropped {summary['dropped']:,})",
        f"SH                degree {summary['sh_degree']}, stage {summary['sh_stage']}"
        + (f" ({summary['sh_features']} features)" if summary["sh_features"] else ""),
        f"grid              {summary['grid']}, sort {summary['sort']}, padding {summary['padding']}, colour {summary['color']}",
        f"rate point        {summary['rate_point']}" + _target(summary.get("target")),
        f"bits per Gaussian {summary['bits_per_gaussian']:.3f}",
        "attribute                 bytes   share  bits/Gaussian",
    ]
    for name, info in summary["attributes"].items():
        share = 100.0 * info["bytes"] / summary["bytes"]
        lines.append(f"  {name:<16} {info['bytes']:>12,} {share:>6.1f}% {info['bits_per_gaussian']:>13.3f}")
    if summary.get("deformation"):
        lines.append(_deformation_line(summary["deformation"]))
    lines.append("chunk                     bytes  bits  QP    codec")
    for chunk in summary["chunks"]:
        qp = "-" if chunk["qp"] is None else str(chunk["qp"])
        bits = "-" if chunk["bits"] is None else str(chunk["bits"])
        lines.append(f"  {chunk['name']:<16} {chunk['bytes']:>12,} {bits:>5} {qp:>3}   {chunk['codec'] or '-'}")
    return "\n".join(lines)


def _target(target: dict | None) -> str:
    """`` (rate control: at most 1,234 bytes)`` for a stream made by the rate controller."""
    if not target:
        return ""
    value = target.get("value")
    if target.get("kind") == "bytes" and isinstance(value, (int, float)):
        return f" (rate control: at most {value:,.0f} bytes)"
    if target.get("kind") == "psnr" and isinstance(value, (int, float)):
        return f" (rate control: at least {value:.2f} dB against the uncompressed model)"
    return ""
