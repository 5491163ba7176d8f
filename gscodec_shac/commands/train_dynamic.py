"""``gscodec-shac train-dynamic SCENE_DIR OUT_DIR``: train deformable 3DGS on a D-NeRF scene on the CPU.

Reads a D-NeRF scene (:mod:`gscodec_shac.io.dnerf`), trains canonical Gaussians + a
deformation network (:mod:`gscodec_shac.train.dynamic`) and writes a dynamic model directory
to OUT_DIR: ``point_cloud.ply`` (canonical Gaussians), ``deformation.npz`` +
``deformation.json`` (the network), ``metrics.json`` (per-test-frame PSNR/SSIM at each
frame's time, sizes, timings), ``run.json`` and the checkpoint (``--resume`` continues it).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from gscodec_shac.commands._options import add_command, add_training_run_options, set_numba_threads


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "train-dynamic",
        help="train deformable 3DGS (canonical Gaussians + deformation MLP) on a D-NeRF scene on the CPU",
        description="Train Deformable 3D Gaussians on the CPU: canonical SH-3 Gaussians and a deformation MLP "
        "(positional encoding of the canonical centre and the frame time; offsets to position, rotation and "
        "scale), static warm-up then joint training, the reference's density control. Test PSNR/SSIM are the "
        "means over the test frames, each rendered at its own time. OUT_DIR becomes a dynamic model directory "
        "(point_cloud.ply + deformation.npz + deformation.json) that encode, decode, info and render accept.",
        examples=["gscodec-shac train-dynamic dnerf/jumpingjacks jj/ --iterations 3000 --net-depth 4 "
                  "--net-width 128 --max-gaussians 30000 --time-budget 1500"],
    )
    parser.add_argument("scene", metavar="SCENE_DIR", help="D-NeRF scene folder (transforms_{train,test}.json "
                        "with a 'time' per frame)")
    parser.add_argument("out_dir", metavar="OUT_DIR", help="output folder (created): the dynamic model")
    parser.add_argument("--iterations", type=int, default=40_000, help="training iterations (default 40000, the "
                        "reference); the schedule's intervals are scaled by iterations/40000")
    parser.add_argument("--resolution-scale", type=float, metavar="F",
                        help="scale the 800x800 images by F (default 0.5 = 400x400; --resume: the run's)")
    parser.add_argument("--background", choices=("black", "white"),
                        help="composite RGBA over black (default, the reference's D-NeRF command) or white "
                        "(--resume: the run's)")
    parser.add_argument("--sh", choices=("full", "lst"), default="full", help="SH parameterisation (default full; "
                        "lst = training-integrated SHAC-LST)")
    parser.add_argument("--net-depth", type=int, default=8, help="deformation MLP depth (default 8, the reference)")
    parser.add_argument("--net-width", type=int, default=256, help="deformation MLP width (default 256, the "
                        "reference; 128 with depth 4 is about 4x faster on the CPU)")
    parser.add_argument("--max-gaussians", type=int, help="cap on the number of Gaussians (densification stops "
                        "growing at the cap)")
    parser.add_argument("--init-points", type=int, default=100_000, help="random initial points in [-1.3, 1.3]^3 "
                        "(default 100000, the reference)")
    parser.add_argument("--deform-lr-final", type=float, default=1.6e-6, metavar="LR",
                        help="the deformation network's learning rate at the last iteration (it decays log-linearly "
                        "from 8e-4; default 1.6e-6, the reference's over 40000 iterations; a short run learns the "
                        "motion better with a higher floor: docs/dynamic.md)")
    parser.add_argument("--network-bits", type=int, metavar="B",
                        help="quantisation-aware training: the last 10%% of the iterations train the network through "
                        "the B-bit grid (2-8) that `encode --network-bits B` codes, and the saved network is on that "
                        "grid, so coding it at B bits changes nothing (default: off, float weights)")
    for name, text in (("warm-up", "static warm-up iterations (reference 3000 of 40000)"),
                       ("densify-from", "first densification iteration (reference 500)"),
                       ("densify-until", "last densification iteration (reference 15000)"),
                       ("densify-interval", "iterations between densifications (reference 100)"),
                       ("opacity-reset-interval", "iterations between opacity resets (reference 3000)"),
                       ("sh-interval", "iterations between SH degree increases (reference 1000)")):
        parser.add_argument(f"--{name}", type=int, metavar="N", help=f"{text}; default: scaled")
    add_training_run_options(parser, on_stop="the model is written from the state reached", evaluated="test-frame")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import json
    import time

    from gscodec_shac.atomic import check_outputs, protect_inputs, write_atomic
    from gscodec_shac.errors import GscodecError, OutputError
    from gscodec_shac.train.dynamic import (
        CHECKPOINT_NAME, DynamicConfig, DynamicTrainer, load_dnerf_capture, write_dynamic_outputs,
    )

    started = time.perf_counter()
    out = Path(args.out_dir)
    set_numba_threads(args.threads)
    if args.time_budget is not None and not args.time_budget > 0:
        raise GscodecError(f"--time-budget must be a positive number of seconds, got {args.time_budget}")
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: OUT_DIR must be a folder, this is a file")
    checkpoint = out / CHECKPOINT_NAME
    if checkpoint.exists() and not args.resume and not args.force:
        raise GscodecError(f"{out} already holds a training checkpoint; pass --resume to continue it, --force to "
                           "start over, or choose another OUT_DIR")
    if args.resume and not checkpoint.exists():
        raise GscodecError(f"--resume: {checkpoint} does not exist")
    if not args.resume:
        check_outputs([out / n for n in ("point_cloud.ply", "deformation.npz", "deformation.json", "metrics.json",
                                         "run.json")], force=args.force)
    config = None
    if not args.resume:  # a bad setting is refused before the scene is read or OUT_DIR is made
        config = DynamicConfig(
            iterations=args.iterations, sh=args.sh, max_gaussians=args.max_gaussians, init_points=args.init_points,
            seed=args.seed, depth=args.net_depth, width=args.net_width, warm_up=args.warm_up,
            densify_from=args.densify_from, densify_until=args.densify_until,
            densify_interval=args.densify_interval, opacity_reset_interval=args.opacity_reset_interval,
            sh_interval=args.sh_interval, checkpoint_every=args.checkpoint_every, lr_deform_final=args.deform_lr_final,
            network_bits=args.network_bits,
        )
        config.validate()
    scene = Path(args.scene)
    protect_inputs(*(sorted(scene.iterdir()) if scene.is_dir() else [scene]))
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise GscodecError(f"{out}: cannot create the output folder ({exc.strerror or exc})") from None
    if args.resume:  # the images the run was trained on
        try:
            previous = json.loads((out / "run.json").read_text())
        except (OSError, ValueError):
            previous = {}
        for key in ("resolution_scale", "background"):
            given, stored = getattr(args, key), previous.get(key)
            if given is not None and stored is not None and given != stored:
                raise GscodecError(f"--resume: the run was trained with --{key.replace('_', '-')} {stored}, "
                                   f"not {given}")
            setattr(args, key, given if given is not None else stored)
    args.resolution_scale = 0.5 if args.resolution_scale is None else args.resolution_scale
    args.background = args.background or "black"
    background = (1.0, 1.0, 1.0) if args.background == "white" else (0.0, 0.0, 0.0)
    capture = load_dnerf_capture(scene, resolution_scale=args.resolution_scale, background=background,
                                 progress=not args.quiet)
    loaded = time.perf_counter()
    if args.resume:
        trainer = DynamicTrainer.from_checkpoint(capture, out)
        print(f"resuming {capture.name} at iteration {trainer.iteration} of {trainer.config.iterations}")
    else:
        trainer = DynamicTrainer(capture, config)
        size = [capture.train_cameras[0].width, capture.train_cameras[0].height]
        write_atomic(out / "run.json", json.dumps({
            "scene": str(scene.resolve()), "config": config.to_dict(), "schedule": trainer.schedule,
            "train_frames": len(capture.train_cameras), "test_frames": len(capture.test_cameras), "size": size,
            "background": args.background, "resolution_scale": args.resolution_scale, "initial_gaussians": trainer.model.num_gaussians,
            "network_params": trainer.net.n_params, "extent": capture.extent,
        }, indent=1))
        print(f"training {capture.name}: {len(capture.train_cameras)} train / {len(capture.test_cameras)} test "
              f"frames at {size[0]}x{size[1]} on {args.background}, {trainer.model.num_gaussians:,} initial "
              f"Gaussians, network {config.depth}x{config.width} ({trainer.net.n_params:,} weights), "
              f"{config.iterations} iterations, schedule {trainer.schedule}", flush=True)
    complete = trainer.train(time_budget=args.time_budget, out_dir=out, progress=not args.quiet)
    trained = time.perf_counter()
    metrics = write_dynamic_outputs(trainer, out, evaluate=not args.no_eval, progress=not args.quiet,
                                    extra={"load_seconds": loaded - started,
                                           "wall_seconds_this_run": trained - started})
    state = "done" if complete else f"stopped by --time-budget at iteration {trainer.iteration} (use --resume)"
    test = metrics.get("test") or {}
    quality = (f", test PSNR {test['mean_psnr']:.2f} dB, SSIM {test['mean_ssim']:.4f}"
               if test.get("mean_psnr") is not None else "")
    print(f"{state}: {trainer.model.num_gaussians:,} Gaussians, {trainer.elapsed:.0f} s training{quality}; "
          f"wrote {out}")
    return 0
