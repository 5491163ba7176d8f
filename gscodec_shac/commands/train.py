"""``gscodec-shac train CAPTURE_DIR OUT_DIR``: train a 3DGS model on the CPU (full SH or SHAC-LST).

Reads a capture (COLMAP, Inria ``cameras.json`` or NeRF-synthetic transforms, see
:mod:`gscodec_shac.train.data`), trains with the reference 3DGS recipe
(:mod:`gscodec_shac.train.trainer`) and writes to OUT_DIR: ``point_cloud.ply`` (full SH, any
viewer), ``point_cloud.lst.npz`` (SHAC-LST only: S, DC, geometry and T), ``cameras.json``,
``metrics.json`` (test-view PSNR/SSIM, sizes, timings) and ``checkpoint.npz`` (resume with
``--resume``; a run stopped by ``--time-budget`` continues where it stopped).
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

from gscodec_shac.commands._options import (
    add_command, add_lst_variant_options, add_training_run_options, set_numba_threads,
)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "train",
        help="train a 3DGS model on the CPU from a capture (full SH or SHAC-LST)",
        description="Train 3D Gaussian Splatting on the CPU with the reference 3DGS recipe, full SH or "
        "SHAC-LST (S T, paper Sec. V-B). Every 8th view (name order) is held out for testing. OUT_DIR gets "
        "point_cloud.ply, cameras.json, metrics.json, run.json and checkpoint.npz (--resume continues it).",
        examples=["gscodec-shac train capture/ out/ --sh lst --iterations 3000 --max-gaussians 50000",
                  "gscodec-shac train capture/ out_mlp/ --sh lst --lst-operator mlp --iterations 600",
                  "gscodec-shac train mipnerf360_bonsai/ bonsai/ --images images --resolution-scale 0.25"],
    )
    parser.add_argument("capture", metavar="CAPTURE_DIR", help="capture folder: COLMAP (sparse/0 + images), Inria "
                        "cameras.json + images, or NeRF-synthetic (transforms_train.json)")
    parser.add_argument("out_dir", metavar="OUT_DIR", help="output folder (created)")
    parser.add_argument("--sh", choices=("full", "lst"), default="full", help="SH parameterisation (default full)")
    parser.add_argument("--sh-degree", type=int, default=3, help="SH degree 0-3 (default 3; 2 = Train-L2-D24)")
    lst = parser.add_argument_group("SHAC-LST variant (--sh lst; defaults = the paper's model; ablations of "
                                    "Sec. VII-E, Tables VII-IX, Fig. 13)")
    add_lst_variant_options(lst)
    parser.add_argument("--iterations", type=int, default=30_000, help="training iterations (default 30000); "
                        "the reference schedule's intervals are scaled by iterations/30000")
    parser.add_argument("--strategy", choices=("default", "mcmc"), default=None,
                        help="density control: 'default' (clone/split/prune) or 'mcmc' (fixed budget); "
                        "default: mcmc when --max-gaussians is given, else default")
    parser.add_argument("--max-gaussians", type=int, help="number of Gaussians (mcmc: exact budget; default "
                        "strategy: cap)")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--resolution-scale", type=float, metavar="F", help="scale the images by F (INTER_AREA), e.g. 0.25")
    size.add_argument("--width", type=int, metavar="W", help="resize the images to width W (aspect kept)")
    parser.add_argument("--images", metavar="DIR", help="image folder: a folder name inside the capture (e.g. "
                        "images_8) or an absolute path (default: the capture's images folder)")
    parser.add_argument("--init", choices=("sfm", "random"), default="sfm",
                        help="initial points: the capture's SfM points or random ones (default sfm)")
    parser.add_argument("--random-points", type=int, default=0, metavar="N",
                        help="add N random background points to the initial points (e.g. bonsai)")
    parser.add_argument("--background", metavar="R,G,B", help="background R,G,B in [0, 1] (default: white for "
                        "NeRF-synthetic, else black)")
    parser.add_argument("--opacity-lr", type=float, default=0.05, help="opacity learning rate (default 0.05 as "
                        "the original 3DGS; newer releases use 0.025)")
    add_training_run_options(parser, on_stop="checkpoint written", evaluated="test-view")
    parser.set_defaults(func=run)


def _background(text: str | None) -> tuple[float, float, float] | None:
    from gscodec_shac.errors import GscodecError

    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in values):
        raise GscodecError(f"--background must be three comma-separated numbers in [0, 1], got {text!r}")
    return values  # type: ignore[return-value]


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch or numba start OpenMP
    import json
    import time

    from gscodec_shac.atomic import check_outputs, protect_inputs, write_atomic
    from gscodec_shac.errors import GscodecError, OutputError
    from gscodec_shac.train.data import load_capture
    from gscodec_shac.train.trainer import CHECKPOINT_NAME, TrainConfig, Trainer, write_outputs

    started = time.perf_counter()
    out = Path(args.out_dir)
    checkpoint = out / CHECKPOINT_NAME
    set_numba_threads(args.threads)
    if args.time_budget is not None and not args.time_budget > 0:
        raise GscodecError(f"--time-budget must be a positive number of seconds, got {args.time_budget}")
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: OUT_DIR must be a folder, this is a file")
    if checkpoint.exists() and not args.resume and not args.force:
        raise GscodecError(f"{out} already holds a training checkpoint; pass --resume to continue it, --force to "
                           "start over, or choose another OUT_DIR")
    if not args.resume:
        check_outputs([out / name for name in ("point_cloud.ply", "metrics.json", "run.json")], force=args.force)
    capture_dir = Path(args.capture)
    protect_inputs(*(sorted(capture_dir.iterdir()) if capture_dir.is_dir() else [capture_dir]))
    if args.resume and not checkpoint.exists():
        raise GscodecError(f"--resume: {checkpoint} does not exist")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise GscodecError(f"{out}: cannot create the output folder ({exc.strerror or exc})") from None

    capture = load_capture(
        args.capture, images=args.images, resolution_scale=args.resolution_scale, width=args.width,
        background=_background(args.background), init=args.init, random_points=args.random_points,
        seed=args.seed, progress=not args.quiet,
    )
    loaded = time.perf_counter()
    if args.resume:
        trainer = Trainer.from_checkpoint(capture, checkpoint)
        print(f"resuming {capture.name} at iteration {trainer.iteration} of {trainer.config.iterations} "
              f"({trainer.model.num_gaussians:,} Gaussians); the checkpoint's settings apply")
    else:
        strategy = args.strategy or ("mcmc" if args.max_gaussians else "default")
        config = TrainConfig(
            iterations=args.iterations, sh=args.sh, sh_degree=args.sh_degree, strategy=strategy,
            max_gaussians=args.max_gaussians, seed=args.seed, lr_opacity=args.opacity_lr,
            checkpoint_every=args.checkpoint_every, lambda_t=args.lambda_t, lst_subset=args.lst_subset,
            lst_operator=args.lst_operator, lst_structure=args.lst_structure, lst_rgb=args.lst_rgb,
            lst_init=args.lst_init,
        )
        trainer = Trainer(capture, config)
        write_atomic(out / "run.json", json.dumps({
            "capture": str(Path(args.capture).resolve()), "config": config.to_dict(), "schedule": trainer.schedule,
            "train_views": len(capture.train_cameras), "test_views": len(capture.test_cameras),
            "size": [capture.train_cameras[0].width, capture.train_cameras[0].height], "init": capture.info,
            "initial_gaussians": trainer.model.num_gaussians, "extent": capture.extent,
        }, indent=1))
        print(f"training {capture.name}: {len(capture.train_cameras)} train / {len(capture.test_cameras)} test views "
              f"at {capture.train_cameras[0].width}x{capture.train_cameras[0].height}, "
              f"{trainer.model.num_gaussians:,} initial Gaussians, {config.iterations} iterations, "
              f"{config.sh} SH degree {config.sh_degree}, {strategy} strategy")
    complete = trainer.train(time_budget=args.time_budget, out_dir=out, progress=not args.quiet)
    trained = time.perf_counter()
    metrics = write_outputs(
        trainer, out, evaluate=not args.no_eval, progress=not args.quiet,
        extra={"load_seconds": loaded - started, "wall_seconds_this_run": trained - started},
    )
    state = "done" if complete else f"stopped by --time-budget at iteration {trainer.iteration} (use --resume)"
    test = metrics.get("test") or {}
    quality = (f", test PSNR {test['mean_psnr']:.2f} dB, SSIM {test['mean_ssim']:.4f}"
               if test.get("mean_psnr") is not None else "")
    print(f"{state}: {trainer.model.num_gaussians:,} Gaussians, {trainer.elapsed:.0f} s training{quality}; "
          f"wrote {out}")
    return 0
