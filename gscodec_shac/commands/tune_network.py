"""``gscodec-shac tune-network MODEL SCENE_DIR OUT_DIR --network-bits B``: fit a trained dynamic
model's deformation network to the B-bit grid ``encode`` codes it on, the Gaussians frozen
(:mod:`gscodec_shac.train.network_tune`). OUT_DIR is a dynamic model directory with the same
canonical Gaussians and the tuned network, plus ``metrics.json`` (test PSNR/SSIM of the input
model and of the tuned one, the tuning log)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from gscodec_shac.commands._options import add_command, add_force, add_threads, set_numba_threads


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "tune-network",
        help="fit a trained dynamic model's deformation network to the grid `encode --network-bits B` codes "
        "(Gaussians frozen)",
        description="Quantisation-aware tuning after training: the canonical Gaussians stay as they are; the "
        "deformation network trains on the training views, first in float, then through the per-row B-bit grid "
        "that `encode --network-bits B` codes it on, and is saved on that grid. `encode` then recognises the grid and "
        "codes the tuned network as it is. MODEL is a dynamic model directory or a Deformable-3DGS output folder; "
        "SCENE_DIR is the D-NeRF scene it was trained on. metrics.json gives the test PSNR/SSIM of the input "
        "model (float network) and of the tuned one (the network on its grid).",
        examples=["gscodec-shac tune-network jj/ dnerf/jumpingjacks jj_t4/ --network-bits 4 && "
                  "gscodec-shac encode jj_t4/ jj4.gsc --sh pca --er 0.96"],
    )
    parser.add_argument("model", metavar="MODEL", help="dynamic model directory or Deformable-3DGS output folder")
    parser.add_argument("scene", metavar="SCENE_DIR", help="the D-NeRF scene the model was trained on")
    parser.add_argument("out_dir", metavar="OUT_DIR", help="output folder (created): the tuned model")
    parser.add_argument("--network-bits", type=int, default=4, metavar="B",
                        help="the grid to tune for: `encode --network-bits B` (2-7, default 4); 16: the float network "
                        "trained the same way, without a grid (a control)")
    parser.add_argument("--float-iterations", type=int, default=600, metavar="N",
                        help="training views seen in float first (default 600)")
    parser.add_argument("--float-lr", type=float, default=1e-4, metavar="LR",
                        help="learning rate of the float phase's first step (default 1e-4; decays log-linearly to "
                        "--float-lr-final)")
    parser.add_argument("--float-lr-final", type=float, default=1e-5, metavar="LR",
                        help="learning rate of the float phase's last step (default 1e-5)")
    parser.add_argument("--iterations", type=int, default=300, metavar="N",
                        help="training views seen through the grid (default 300)")
    parser.add_argument("--lr", type=float, default=3e-5, metavar="LR", help="learning rate of the grid phase's "
                        "first step (default 3e-5; decays log-linearly to --lr-final)")
    parser.add_argument("--lr-final", type=float, default=1e-5, metavar="LR",
                        help="learning rate of the grid phase's last step (default 1e-5)")
    parser.add_argument("--resolution-scale", type=float, default=0.5, metavar="F",
                        help="scale the training images by F (default 0.5 = 400x400, as train-dynamic)")
    parser.add_argument("--background", choices=("black", "white"), default="black",
                        help="composite RGBA over black (default) or white: as the model was trained")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the view order (default 0)")
    add_threads(parser, "numba threads of the rasteriser")
    parser.add_argument("--no-eval", action="store_true", help="skip the test-frame evaluation")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_force(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import json
    import time

    from tqdm import tqdm

    from gscodec_shac.atomic import check_outputs, protect_inputs, write_atomic
    from gscodec_shac.deform import load_dynamic_model, save_dynamic_model
    from gscodec_shac.errors import GscodecError, OutputError
    from gscodec_shac.train.dynamic import evaluate_dynamic, load_dnerf_capture
    from gscodec_shac.train.network_tune import NetworkTuneConfig, tune_network

    started = time.perf_counter()
    out = Path(args.out_dir)
    set_numba_threads(args.threads)
    config = NetworkTuneConfig(bits=args.network_bits, float_iterations=args.float_iterations, float_lr=args.float_lr,
                               float_lr_final=args.float_lr_final, iterations=args.iterations, lr=args.lr,
                               lr_final=args.lr_final, seed=args.seed)
    config.validate()
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: OUT_DIR must be a folder, this is a file")
    if out.resolve() == Path(args.model).resolve():
        raise OutputError(f"{out}: OUT_DIR must not be the input model's folder")
    check_outputs([out / n for n in ("point_cloud.ply", "deformation.npz", "deformation.json", "metrics.json")],
                  force=args.force)
    model = load_dynamic_model(args.model)
    scene = Path(args.scene)
    protect_inputs(*(sorted(scene.iterdir()) if scene.is_dir() else [scene]))
    background = (1.0, 1.0, 1.0) if args.background == "white" else (0.0, 0.0, 0.0)
    capture = load_dnerf_capture(scene, resolution_scale=args.resolution_scale, background=background,
                                 progress=not args.quiet)
    log: list[dict] = []
    total = config.float_iterations + (config.iterations if config.bits != 16 else 0)
    bar = tqdm(total=total, desc="tune-network", unit="view", disable=args.quiet, dynamic_ncols=True, mininterval=2.0)
    recent: list = []

    def record(step) -> None:
        recent.append(step)
        bar.update(1)
        last = config.float_iterations if step.phase == "float" else config.iterations
        if step.iteration % 50 == 0 or step.iteration == last:
            log.append({"phase": step.phase, "it": step.iteration, "loss": sum(s.loss for s in recent) / len(recent),
                        "psnr": sum(s.psnr for s in recent) / len(recent),
                        "s_per_it": sorted(s.seconds for s in recent)[len(recent) // 2]})
            bar.set_postfix(loss=f"{log[-1]['loss']:.4f}", psnr=f"{log[-1]['psnr']:.2f}")
            recent.clear()

    tic = time.perf_counter()
    try:
        tuned = tune_network(model, capture, config, callback=record)
    finally:
        bar.close()
    tune_seconds = time.perf_counter() - tic
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise GscodecError(f"{out}: cannot create the output folder ({exc.strerror or exc})") from None
    metrics: dict = {"source_model": str(Path(args.model).resolve()), "scene": capture.name,
                     "config": config.to_dict(), "tune_seconds": tune_seconds, "log": log}
    if not args.no_eval:
        metrics["input_test"] = evaluate_dynamic(model, capture, progress=not args.quiet)
        metrics["tuned_test"] = evaluate_dynamic(tuned, capture, progress=not args.quiet)
    save_dynamic_model(out, tuned, {"source": "gscodec-shac tune-network", "network_bits": config.bits,
                                    "iterations": config.iterations})
    metrics["wall_seconds"] = time.perf_counter() - started
    write_atomic(out / "metrics.json", json.dumps(metrics, indent=1))
    quality = ""
    if not args.no_eval:
        before, after = metrics["input_test"]["mean_psnr"], metrics["tuned_test"]["mean_psnr"]
        grid = "in float" if config.bits == 16 else f"on its {config.bits}-bit grid"
        quality = f"; test PSNR {before:.3f} dB (input network) -> {after:.3f} dB ({grid})"
    print(f"tuned the network ({config.bits} bits) in {tune_seconds:.0f} s{quality}; wrote {out}")
    return 0
