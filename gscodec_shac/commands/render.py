"""``gscodec-shac render SCENE.ply OUT_DIR``: render views of a 3DGS PLY to 8-bit PNGs on the CPU.

Cameras come from ``--cameras`` (any file or capture folder :func:`load_cameras` reads) or,
without it, from an orbit around the scene (centre = median of the means, radius 2.5x the
median distance of the means from it, ``--up`` as the world up axis). When the cameras have
ground-truth images (``--images`` or the capture's ``images`` folder), PSNR and SSIM
against them (resized to the render size with INTER_AREA, RGBA composited over the
background) are printed and written to ``metrics.json``; LPIPS too when weights are supplied.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from gscodec_shac.commands._options import (
    add_alias,
    add_command,
    add_force,
    add_output,
    add_quiet,
    add_up,
    comma_floats,
    resize_cameras,
)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "render",
        help="render views of a 3DGS PLY to PNGs on the CPU (reference 3DGS rasteriser math)",
        description="Render a 3DGS model from its cameras (or an orbit) with the CPU tile rasteriser "
        "and write 8-bit PNGs (clipped to [0, 1]) into OUT_DIR; with ground-truth images, PSNR/SSIM "
        "(and LPIPS with weights) go to OUT_DIR/metrics.json.",
        examples=["gscodec-shac render scene.ply renders/ --cameras cameras.json --images images/ --split test",
                  "gscodec-shac render scene.ply orbit/ --orbit-views 24 --up 0,-1,0",
                  "gscodec-shac render jumpingjacks_model/ frames/ --cameras dnerf/jumpingjacks/transforms_test.json"],
    )
    parser.add_argument("scene", metavar="SCENE", help="a model: Inria .ply, .compressed.ply, .spz, .splat, .sog, "
                        "SOG meta.json, gsplat .pt, a .gsc (decoded), or a dynamic model directory (see --time)")
    add_output(parser, "OUT_DIR", "output directory for the PNGs and metrics.json (created)")
    parser.add_argument("--cameras", help="cameras.json, transforms*.json, poses_bounds.npy, a COLMAP model "
                        "or a capture folder; default: an orbit around the scene")
    images = parser.add_argument("--images", dest="images_dir", metavar="DIR",
                                 help="ground-truth images for the cameras (enables PSNR/SSIM; default: the "
                                 "capture's images folder, if any)")
    add_alias(parser, "--images-dir", images)
    select = parser.add_mutually_exclusive_group()
    select.add_argument("--every", type=int, metavar="N", help="render every N-th camera (name order)")
    select.add_argument("--split", choices=("test", "train", "all"), default="all",
                        help="the 3DGS evaluation split: test = every 8th camera in name order (default: all)")
    size = parser.add_mutually_exclusive_group()
    scale = size.add_argument("--resolution-scale", dest="scale", type=float, metavar="F",
                              help="scale every camera's resolution by F, e.g. 0.5")
    add_alias(size, "--scale", scale)
    size.add_argument("--width", type=int, metavar="W", help="resize every camera to width W (aspect kept)")
    parser.add_argument("--background", default="0,0,0", metavar="R,G,B",
                        help="background colour R,G,B in [0, 1] (default 0,0,0)")
    parser.add_argument("--orbit-views", type=int, default=24, metavar="N",
                        help="number of orbit views without --cameras (default 24)")
    add_up(parser, "the orbit without --cameras")
    parser.add_argument("--time", type=float, metavar="T", help="dynamic model: render every view at time T "
                        "(default: each frame's own 'time' from a D-NeRF transforms file)")
    parser.add_argument("--lpips-weights", metavar="FILE", help="LPIPS-VGG weights file (else $GSCODEC_LPIPS_WEIGHTS; "
                        "without either LPIPS is reported as unavailable)")
    add_quiet(parser)
    add_force(parser)
    parser.set_defaults(func=run)


def _orbit(cloud, views: int, up: list[float], width: int | None, scale: float | None) -> list:
    """One ring of ``views`` cameras 20 degrees up, around the median of the means."""
    from gscodec_shac.camera import orbit_views
    from gscodec_shac.errors import GscodecError

    if views < 1:
        raise GscodecError(f"--orbit-views must be at least 1, got {views}")
    w = max(1, width if width is not None else round(800 * (scale or 1.0)))
    return orbit_views(cloud.means, views, w, up=up, elevations=(20.0,))


def _select(cameras: list, args: argparse.Namespace) -> list:
    from gscodec_shac.errors import GscodecError
    from gscodec_shac.camera import test_split

    if args.every is not None:
        if args.every < 1:
            raise GscodecError(f"--every must be at least 1, got {args.every}")
        return sorted(cameras, key=lambda c: c.name)[:: args.every]
    if args.split == "all":
        return cameras
    train, test = test_split(cameras)
    return test if args.split == "test" else train


def _frame_times(cameras: list, args: argparse.Namespace) -> list[float]:
    """The instant each camera of a dynamic model is rendered at: ``--time``, else its frame's ``time``."""
    import math

    from gscodec_shac.errors import GscodecError

    if args.time is not None:
        if not math.isfinite(args.time):
            raise GscodecError(f"--time must be a finite number, got {args.time}")
        return [float(args.time)] * len(cameras)
    if not args.cameras or not str(args.cameras).endswith(".json"):
        raise GscodecError("a dynamic model needs --time, or --cameras transforms_*.json whose frames have a 'time'")
    from gscodec_shac.io.dnerf import read_dnerf_cameras

    by_name: dict[str, float] = {}
    for frame in read_dnerf_cameras(args.cameras):
        by_name.setdefault(frame.camera.name, frame.time)
    missing = [c.name for c in cameras if c.name not in by_name]
    if missing:
        raise GscodecError(f"{args.cameras}: no 'time' for camera {missing[0]!r}; pass --time")
    return [by_name[c.name] for c in cameras]


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from tqdm import tqdm

    from gscodec_shac.atomic import check_outputs, protect_inputs, write_atomic
    from gscodec_shac.errors import GscodecError, OutputError
    from gscodec_shac.io.cameras import load_cameras
    from gscodec_shac.io.models import read_model, report_notes
    from gscodec_shac.metrics import image_metrics, load_image, load_lpips
    from gscodec_shac.render import Renderer
    from gscodec_shac.render.output import png_names, save_png

    background = comma_floats(args.background, "--background")
    if not all(0.0 <= v <= 1.0 for v in background):
        raise GscodecError(f"--background values must lie in [0, 1], got {args.background!r}")
    protect_inputs(args.scene, args.cameras)
    from gscodec_shac.deform_arch import is_dynamic_model

    dynamic = None
    if is_dynamic_model(args.scene):
        from gscodec_shac.deform import load_dynamic_model

        dynamic = load_dynamic_model(args.scene)
        cloud, notes = dynamic.cloud, []
    elif args.time is not None:
        raise GscodecError("--time applies to a dynamic model (a directory with deformation.json)")
    else:
        cloud, notes = read_model(args.scene)
    report_notes(notes)
    if args.cameras:
        cameras = resize_cameras(_select(load_cameras(args.cameras, args.images_dir), args), args.scale, args.width)
    else:
        if args.images_dir:
            raise GscodecError("--images needs --cameras (orbit views have no ground truth)")
        if dynamic is not None and args.time is None:
            raise GscodecError("a dynamic model needs --time, or --cameras transforms_*.json whose frames have a "
                               "'time'")
        around = dynamic.at(args.time) if dynamic is not None else cloud  # the orbit of what is shown
        cameras = _select(_orbit(around, args.orbit_views, comma_floats(args.up, "--up"), args.width, args.scale),
                          args)
    if not cameras:
        raise GscodecError("no cameras left to render after the selection")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: OUT_DIR must be a directory, this is a file")
    with_truth = any(c.image_path is not None for c in cameras)
    protect_inputs(*(c.image_path for c in cameras))
    names = png_names([camera.name for camera in cameras])
    check_outputs([out / name for name in names] + ([out / "metrics.json"] if with_truth else []), force=args.force)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise GscodecError(f"{out}: cannot create the output directory ({exc.strerror or exc})") from None

    times = _frame_times(cameras, args) if dynamic is not None else [None] * len(cameras)
    lpips_model, lpips_reason = load_lpips(args.lpips_weights) if with_truth else (None, None)
    renderers: dict = {}
    rows = []
    for index, camera in enumerate(tqdm(cameras, desc="render", unit="view", disable=args.quiet)):
        t = times[index]
        if t not in renderers:  # one renderer per instant (a static model: one)
            renderers.clear()
            renderers[t] = Renderer(cloud if t is None else dynamic.at(t))
        image = renderers[t].render(camera, background=background).image
        path = save_png(out / names[index], image)
        row = {"name": camera.name, "png": path.name, "width": camera.width, "height": camera.height}
        if t is not None:
            row["time"] = t
        if camera.image_path is not None:
            truth = load_image(camera.image_path, background=background, size=(camera.width, camera.height))
            row.update(image_metrics(image, truth, lpips_model=lpips_model, lpips_reason=lpips_reason))
        rows.append(row)
    print(f"wrote {len(rows)} PNG(s) to {out}")
    measured = [r for r in rows if "psnr" in r]
    if measured:
        summary = {
            "views": len(measured),
            "psnr": float(np.mean([r["psnr"] for r in measured])),
            "ssim": float(np.mean([r["ssim"] for r in measured])),
            "lpips": float(np.mean([r["lpips"] for r in measured])) if lpips_model is not None else None,
            "lpips_note": lpips_reason,
        }
        write_atomic(out / "metrics.json", json.dumps({"mean": summary, "views": measured}, indent=2) + "\n")
        lpips_text = f"LPIPS {summary['lpips']:.4f}" if summary["lpips"] is not None else "LPIPS unavailable"
        print(f"{len(measured)} view(s) with ground truth: PSNR {summary['psnr']:.3f} dB, "
              f"SSIM {summary['ssim']:.4f}, {lpips_text} (metrics.json)")
    return 0
