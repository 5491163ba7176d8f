"""``gscodec-shac info FILE``: what a 3DGS PLY or a .gsc file holds and where its bytes go."""

from __future__ import annotations

import argparse
import json
from typing import Any

from gscodec_shac.commands._options import add_command, add_json, add_up


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "info",
        help="describe a 3DGS PLY or a .gsc file (count, SH degree, where the bytes go)",
        description="Describe a 3DGS model (Gaussian count, SH degree, per-attribute ranges, bytes per "
        "Gaussian, SH share) or a .gsc file (header summary, bytes and bits per Gaussian per attribute and "
        "chunk, QPs and codecs).",
        examples=["gscodec-shac info scene.gsc", "gscodec-shac info scene.ply --json",
                  "gscodec-shac info --compare scene.ply scene.gsc --cameras cameras.json"],
    )
    parser.add_argument("file", metavar="FILE", nargs="?", help="a .gsc file or a model: Inria .ply, .compressed.ply, .spz, "
                        ".splat, .sog, SOG meta.json (or its folder), gsplat checkpoint .pt, a dynamic model "
                        "directory (deformation.json)")
    compare = parser.add_argument_group("comparing two models (instead of FILE)")
    compare.add_argument("--compare", nargs=2, metavar=("A", "B"),
                         help="PSNR of model B rendered against model A (either may be a .gsc or any model "
                         "format), on --cameras or else orbit views")
    compare.add_argument("--cameras", help="views to compare from (any camera file or capture folder)")
    compare.add_argument("--views", type=int, default=8, metavar="N", help="orbit views without --cameras, and "
                         "at most this many of --cameras (default 8)")
    compare.add_argument("--width", type=int, default=320, help="render width (default 320)")
    add_up(compare, "the orbit views without --cameras")
    add_json(parser, "the description")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscodec_shac.codec.container import is_gsc
    from gscodec_shac.errors import GscodecError

    if args.compare:
        if args.file is not None:
            raise GscodecError("give either FILE or --compare A B, not both")
        return _compare(args)
    if args.file is None:
        raise GscodecError("info needs a FILE (or --compare A B)")

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
        from gscodec_shac.codec.deformation import trained_grid

        summary["deformation"] = {"arch": model.arch.to_dict(), "weights": model.net.n_params,
                                  "float32_bytes": 4 * model.net.n_params,
                                  "trained_grid": trained_grid(model.arch, model.net.weights())}
        text = format_cloud_summary(summary) + "\n" + _deformation_line(summary["deformation"])
        print(json.dumps(summary, indent=2) if args.json else text)
        return 0
    cloud, notes = read_model(args.file)
    report_notes(notes)
    summary = describe_cloud(cloud, args.file)
    print(json.dumps(summary, indent=2) if args.json else format_cloud_summary(summary))
    return 0


def _compare(args: argparse.Namespace) -> int:
    """``info --compare A B``: PSNR of B's renders against A's on the same views."""
    import math

    import numpy as np

    from gscodec_shac.commands._options import comma_floats, resize_cameras
    from gscodec_shac.errors import GscodecError
    from gscodec_shac.io.models import model_bytes, read_model, report_notes
    from gscodec_shac.render.renderer import render_views

    if args.views < 1 or args.width < 1:
        raise GscodecError(f"--views and --width must be positive, got {args.views} and {args.width}")
    first, notes = read_model(args.compare[0])
    second, more = read_model(args.compare[1])
    report_notes(notes + more)
    if args.cameras:
        from gscodec_shac.io.cameras import load_cameras

        from gscodec_shac.camera import spread_views

        views = spread_views(load_cameras(args.cameras), args.views)
        views = resize_cameras(views, None, min(args.width, min(v.width for v in views)))
        source = f"{len(views)} views of {args.cameras}"
    else:
        from gscodec_shac.camera import orbit_views

        views = orbit_views(first.means, args.views, args.width, up=comma_floats(args.up, "--up"), elevations=(20.0,))
        source = f"{len(views)} orbit views"
    reference = render_views(first, views, progress=False)
    images = render_views(second, views, progress=False)
    from gscodec_shac.metrics import mse as image_mse

    mse = float(np.mean([image_mse(b, a) for a, b in zip(reference, images)]))  # displayed images: clipped to [0, 1]
    psnr = 10.0 * math.log10(1.0 / mse) if mse > 0 else math.inf
    result = {"a": args.compare[0], "b": args.compare[1], "psnr": psnr, "views": len(views), "on": source,
              "a_gaussians": first.num_gaussians, "b_gaussians": second.num_gaussians,
              "a_bytes": model_bytes(args.compare[0]), "b_bytes": model_bytes(args.compare[1])}
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"PSNR of {result['b']} against {result['a']}: {psnr:.2f} dB on {source} "
              f"({result['a_gaussians']:,} / {result['b_gaussians']:,} Gaussians; "
              f"{result['a_bytes']:,} / {result['b_bytes']:,} bytes)")
    return 0


def _deformation_line(info: dict[str, Any]) -> str:
    arch = info["arch"]
    dtype = info.get("dtype", "float16")
    bits = info.get("bits")
    form = f"{bits}-bit per-row quantised" if dtype == "uint8" else dtype
    if isinstance(bits, (list, tuple)):  # one per matrix in state_dict order (format 2.2)
        form = f"per-row quantised, bits per matrix {','.join(map(str, bits))}"
    stored = f"{info['bytes']:,} bytes ({form})" if "bytes" in info else \
        f"{info['float32_bytes']:,} bytes as float32"
    if info.get("trained_grid"):  # a model directory whose network lies on a coded grid
        bits = ",".join(map(str, info["trained_grid"]))
        stored += f"; on a coded grid, bits per matrix {bits} (encode codes it at those bits)"
    return (f"deformation       MLP {arch['depth']}x{arch['width']}"
            f"{' + time net' if arch['time_net'] else ''}, {info['weights']:,} weights, {stored}")


def describe_gsc(stream: Any, path: str) -> dict[str, Any]:
    """A JSON-serialisable summary of a parsed .gsc :class:`~gscodec_shac.codec.container.Bitstream`,
    from its checked header (:func:`~gscodec_shac.codec.header.read_header`)."""
    from gscodec_shac.codec.header import describe, read_header
    from gscodec_shac.errors import BitstreamError

    from gscodec_shac.codec import tiers

    try:
        if tiers.is_tiered(stream):
            return {"file": str(path), **tiers.describe(stream)}
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
        f"SH                degree {summary['sh_degree']}, stage {summary['sh_stage'] or 'none'}"
        + (f" ({summary['sh_features']} features)" if summary["sh_features"] else "")
        + (f", {summary['sh_dc_only']:,} DC-only" if summary.get("sh_dc_only") is not None else ""),
        f"grid              {summary['grid']}, sort {summary['sort']}, padding {summary['padding']}, colour {summary['color']}",
        *([f"tiers             {len(summary['tiers'])} by importance: "
           + ", ".join(f"{t['num_gaussians']:,} Gaussians at QP offset {t['qp_offset']:+d}"
                       if isinstance(t["qp_offset"], int) else f"{t['num_gaussians']:,} Gaussians"
                       for t in summary["tiers"])] if summary.get("tiers") else []),
        f"rate point        {summary['rate_point']}" + _target(summary.get("target")),
        f"bits/Gaussian     {summary['bits_per_gaussian']:.3f} bits per {_per(summary)} Gaussian",
        f"attribute                 bytes   share  bits/{summary.get('bits_per_gaussian_of', 'input')} G",
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


def _per(summary: dict[str, Any]) -> str:
    """``input``, or for a stream without the input count ``decoded (no input count in this older stream)``."""
    if summary.get("bits_per_gaussian_of", "input") == "input":
        return "input"
    return "decoded (no input count in this older stream)"


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
