"""``gscodec-shac lst-finetune IN.ply OUT.ply``: fine-tune SHAC-LST (S, T, DC) with the render loss.

Geometry stays fixed; every view is rendered through the sparse colour path
(:mod:`gscodec_shac.train.colour_path`). Cameras come from ``--cameras`` (any file or capture
folder :func:`load_cameras` reads; the 3DGS test split, every 8th view in name order, is held
out unless ``--all-views``) or from ``--orbit N`` views around the scene. Targets are the
ground-truth images when every camera has one (``--images DIR`` or the capture's ``images``
folder), else the original model's renders; ``--targets`` forces either.

Writes (each atomically): ``OUT.ply`` (full SH ``[DC | S T]``, a standard 3DGS PLY),
``OUT.lst.npz`` (the compact S + T form, see :mod:`gscodec_shac.train.finetune`),
``OUT.ckpt.pt`` (checkpoint; ``--resume`` continues from it), ``OUT.log.csv`` (loss per
step) and ``OUT.finetune.json`` (settings, timings, summary).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from gscodec_shac.commands._options import (
    add_alias,
    add_command,
    add_force,
    add_lst_variant_options,
    add_quiet,
    add_threads,
    add_up,
    all_cores,
    check_threads,
    comma_floats,
    resize_cameras,
)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "lst-finetune",
        help="fine-tune SHAC-LST (S, T, DC) of a 3DGS PLY with the 3DGS render loss, geometry fixed",
        description="Start from the post-hoc SHAC-LST fit of IN.ply and optimise the subset S, the "
        "transform T and the DC colours with 0.8 L1 + 0.2 D-SSIM + lambda_t L_T (paper eq. 37) on "
        "one random training view per step. Writes OUT.ply (full SH) and OUT.lst.npz (compact S + T).",
        examples=["gscodec-shac lst-finetune scene.ply scene_lst.ply --cameras capture/ --images capture/images",
                  "gscodec-shac lst-finetune scene.ply scene_lst.ply --orbit 64 --up 0,-1,0 --width 200"],
    )
    parser.add_argument("scene", metavar="IN.ply", help="an Inria 3DGS .ply with SH degree 2-4")
    parser.add_argument("out", metavar="OUT.ply", help="output PLY path (OUT.lst.npz, OUT.ckpt.pt, OUT.log.csv, OUT.finetune.json beside it)")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--cameras", help="cameras.json, transforms*.json, poses_bounds.npy, a COLMAP model or a capture folder")
    source.add_argument("--orbit", type=int, metavar="N", help="train on N orbit views around the scene (targets: original renders)")
    parser.add_argument("--images", metavar="DIR",
                        help="folder of ground-truth images for the cameras (default: the capture's images folder, if any)")
    parser.add_argument("--targets", choices=("auto", "images", "original"), default="auto",
                        help="what the renders are compared with: ground-truth images, the original model's renders, "
                        "or auto = images when every camera has one (default)")
    parser.add_argument("--all-views", action="store_true", help="train on every camera (default: hold out every 8th, the 3DGS test split)")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--width", type=int, metavar="W", help="resize every camera to width W (aspect kept)")
    scale = size.add_argument("--resolution-scale", dest="scale", type=float, metavar="F",
                              help="scale every camera's resolution by F, e.g. 0.5")
    add_alias(size, "--scale", scale)
    add_up(parser, "the --orbit views")
    parser.add_argument("--steps", type=int, default=3000, help="optimisation steps (default 3000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the view order (default 0)")
    parser.add_argument("--refit-subset", type=int, default=0, metavar="R",
                        help="start from the post-hoc fit with R rounds of least-squares S re-fitting (default 0)")
    parser.add_argument("--ridge", type=float, default=1e-6,
                        help="scale penalty of the post-hoc starting fit (eq. 36 units; default 1e-6, "
                        "5e-3 recommended with --refit-subset)")
    parser.add_argument("--lambda-t", type=float, default=5e-3, help="weight of the eq. 36 scale term (default 5e-3)")
    variant = parser.add_argument_group("SHAC-LST variant (defaults = the paper's model; ablations of Sec. VII-E)")
    add_lst_variant_options(variant, lambda_t=False)
    variant.add_argument("--start", choices=("posthoc", "module"), default="posthoc",
                         help="starting point: the post-hoc ridge fit of T and S (default; matrix operator, joint "
                         "RGB) or the module's own initialisation (--lst-init) with S = the subset columns")
    parser.add_argument("--freeze-dc", action="store_true", help="keep the DC colours fixed (default: trained at 2.5e-3)")
    parser.add_argument("--background", default="0,0,0", metavar="R,G,B",
                        help="background colour R,G,B in [0, 1] (default 0,0,0)")
    parser.add_argument("--checkpoint-every", type=int, default=500, metavar="N",
                        help="steps between checkpoints (default 500)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT.ckpt.pt when it exists")
    parser.add_argument("--cache-gb", type=float, default=4.0, metavar="GIB",
                        help="memory budget of the per-view weight cache in GiB (default 4)")
    add_threads(parser, "torch threads", default="all cores; on a busy machine 1 can be many times faster, docs/lst.md")
    add_quiet(parser)
    add_force(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscodec_shac.errors import GscodecError

    out = Path(args.out)
    if out.suffix.lower() != ".ply":
        raise GscodecError(f"the output must be a .ply path, got {args.out!r}")
    if not out.parent.is_dir() and str(out.parent):
        raise GscodecError(f"{out}: output directory {out.parent} does not exist")
    if args.cameras is None and args.orbit is None:
        raise GscodecError("no cameras: give --cameras FILE (or a capture folder) or --orbit N")
    if args.orbit is not None and args.orbit < 2:
        raise GscodecError(f"--orbit needs at least 2 views, got {args.orbit}")
    if args.images and not args.cameras:
        raise GscodecError("--images needs --cameras (orbit views have no ground truth)")
    if args.steps < 1:
        raise GscodecError(f"--steps must be at least 1, got {args.steps}")
    if args.checkpoint_every < 1:
        raise GscodecError(f"--checkpoint-every must be at least 1, got {args.checkpoint_every}")
    if not (math.isfinite(args.lambda_t) and args.lambda_t >= 0):
        raise GscodecError(f"--lambda-t must be a number >= 0, got {args.lambda_t}")
    if not (math.isfinite(args.ridge) and args.ridge >= 0):
        raise GscodecError(f"--ridge must be a number >= 0, got {args.ridge}")
    if args.refit_subset < 0:
        raise GscodecError(f"--refit-subset must be >= 0, got {args.refit_subset}")
    if not (math.isfinite(args.cache_gb) and args.cache_gb > 0):
        raise GscodecError(f"--cache-gb must be a positive number, got {args.cache_gb}")
    threads = check_threads(args.threads) or all_cores()
    background = comma_floats(args.background, "--background")
    if not all(0.0 <= v <= 1.0 for v in background):
        raise GscodecError(f"--background values must lie in [0, 1], got {args.background!r}")
    if args.images and not Path(args.images).is_dir():
        raise GscodecError(f"{args.images}: no such image folder")
    from gscodec_shac.atomic import check_output, check_outputs
    from gscodec_shac.train.finetune import checkpoint_path_for, compact_path_for, log_path_for, summary_path_for

    check_output(out, force=args.force or args.resume, inputs=[args.scene, args.cameras])
    check_outputs([compact_path_for(out), log_path_for(out), summary_path_for(out)]
                  + ([] if args.resume else [checkpoint_path_for(out)]), force=args.force or args.resume)

    from gscodec_shac.atomic import write_atomic
    from gscodec_shac.camera import orbit_views, test_split
    from gscodec_shac.io.cameras import load_cameras
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.shac.lst_torch import LSTConfig
    from gscodec_shac.train.finetune import (
        FinetuneConfig,
        FinetuneError,
        LstFinetuner,
        checkpoint_path_for,
        log_path_for,
        summary_path_for,
    )

    cloud = read_ply(args.scene)
    if args.cameras:
        cameras = resize_cameras(load_cameras(args.cameras, args.images), args.scale, args.width)
        lacking = [c.name for c in cameras if c.image_path is None]
        if lacking and (args.images or args.targets == "images"):
            where = args.images or "the capture"
            raise GscodecError(f"{where}: no image for camera {lacking[0]!r} ({len(lacking)} of {len(cameras)} missing)")
        targets = "images" if args.targets == "images" or (args.targets == "auto" and not lacking) else "original"
    else:
        if args.targets == "images":
            raise GscodecError("--targets images needs --cameras with ground-truth images (orbit views have none)")
        width = args.width or round(320 * (args.scale or 1.0))
        cameras = orbit_views(cloud.means, args.orbit, max(1, width), up=comma_floats(args.up, "--up"))
        targets = "original"
    train, held_out = (cameras, []) if args.all_views else test_split(cameras)
    if not train:
        raise GscodecError("no training views left after holding out the test split; use --all-views")

    if cloud.sh_degree < 2:
        raise GscodecError(f"{args.scene}: SHAC-LST fine-tuning needs SH degree 2-4, the model has degree {cloud.sh_degree}")
    if args.start == "posthoc" and (args.lst_operator != "matrix" or args.lst_rgb != "joint" or args.lst_init != "zero"):
        raise GscodecError("--start posthoc needs the matrix operator with joint RGB (its T is the post-hoc fit, so "
                           "--lst-init does not apply); use --start module for this variant")
    lst_config = LSTConfig(degree=cloud.sh_degree, lambda_t=args.lambda_t, subset=args.lst_subset,
                           operator=args.lst_operator, structure=args.lst_structure, rgb=args.lst_rgb,
                           init=args.lst_init)
    config = FinetuneConfig(
        steps=args.steps, seed=args.seed, lst=lst_config, init=args.start,
        refit_subset=args.refit_subset, ridge=args.ridge, train_dc=not args.freeze_dc, background=tuple(background),
        cache_bytes=int(args.cache_gb * (1 << 30)), threads=threads,
    )
    if lst_config.operator in ("linear", "mlp"):
        import torch

        torch.manual_seed(args.seed)  # torch's default initialisation of the linear / hidden MLP layers
    tuner = LstFinetuner(cloud, train, targets=targets, config=config)
    checkpoint = checkpoint_path_for(out)
    result = tuner.run(progress=not args.quiet, checkpoint=checkpoint, checkpoint_every=args.checkpoint_every,
                       resume=args.resume, log_path=log_path_for(out))
    ply_path, compact = tuner.save_outputs(out, meta={"source": str(args.scene)})
    if lst_config.operator == "matrix":
        stage = tuner.to_stage()
        n_features, side_bytes = stage.n_features, stage.state().nbytes()
    else:  # ablation operators: no compact stage; count their float32 weights
        n_features, side_bytes = tuner.module.d, 4 * tuner.module.n_params
    summary = {
        "scene": str(args.scene),
        "out": str(ply_path),
        "compact": str(compact) if compact else None,
        "n_gaussians": cloud.num_gaussians,
        "train_views": len(train),
        "held_out_views": [c.name for c in held_out],
        "targets": targets,
        "resolution": [train[0].width, train[0].height],
        "config": tuner.fingerprint()["config"],
        "threads": threads,
        "sh_floats_per_gaussian": 3 + n_features,
        "side_bytes": side_bytes,
        **result.summary(),
    }
    summary_path = summary_path_for(out)
    write_atomic(summary_path, json.dumps(summary, indent=2) + "\n", error=FinetuneError)
    per_step = result.step_seconds_median
    timing = f"{per_step:.3f} s/step median" if per_step is not None else "nothing left to do"
    start = "resumed at step " + str(result.start_step) + ", " if result.resumed else ""
    loss_first, loss_last = summary["loss_first"], summary["loss_last_10pct_mean"]
    print(
        f"lst-finetune: {start}{result.steps} steps on {len(train)} views ({timing}, {result.wall_seconds:.0f} s), "
        f"loss {loss_first:.4f} -> {loss_last:.4f}; wrote {ply_path}" + (f" and {compact}" if compact else "")
        + f" ({3 + n_features} SH floats/Gaussian + {side_bytes} B of T)"
    )
    return 0
