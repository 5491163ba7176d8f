"""``gscodec-shac rd SWEEP.yaml OUT_DIR``: run (or resume) a rate-distortion sweep."""

from __future__ import annotations

import argparse

from gscodec_shac.commands._options import add_command, add_output, add_quiet, add_threads


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "rd",
        help="run a rate-distortion sweep (scenes x methods x rate points); resumable",
        description="Encode, decode, render and score every scene x method x rate point of a sweep YAML. "
        "Rows go to OUT_DIR/results.csv and OUT_DIR/results.json as runs finish; finished runs are "
        "skipped when the command is repeated. Ends with the report of `gscodec-shac rd-report OUT_DIR`.",
        examples=["gscodec-shac rd sweeps/bonsai.yaml runs/bonsai --workers 2",
                  "gscodec-shac rd sweeps/bonsai.yaml runs/bonsai --dry-run"],
    )
    parser.add_argument("sweep", metavar="SWEEP.yaml", help="sweep YAML (see gscodec_shac/rd/spec.py or docs/rd.md)")
    add_output(parser, "OUT_DIR", "output folder (created; reused to resume)")
    parser.add_argument("--workers", type=int, default=1, metavar="N", help="runs executing at once (default 1)")
    parser.add_argument("--executor", choices=("local", "serial", "ray"), default="local",
                        help="local processes (default), this process, or Ray tasks")
    parser.add_argument("--address", default=None, metavar="HOST:PORT",
                        help="Ray cluster address ('auto' or HOST:PORT); default: start a local Ray instance")
    parser.add_argument("--num-cpus", type=float, default=None, metavar="N",
                        help="CPUs Ray reserves per run (default: --threads)")
    add_threads(parser, "threads per run", default="all cores, divided among the --workers runs")
    parser.add_argument("--force", action="store_true", help="run finished rows again; use a folder that holds "
                        "other files")
    parser.add_argument("--no-report", action="store_true", help="do not write OUT_DIR/report at the end")
    parser.add_argument("--dry-run", action="store_true", help="validate the sweep and list its runs, run nothing")
    add_quiet(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscodec_shac.errors import GscodecError
    from gscodec_shac.rd.methods import points_for
    from gscodec_shac.rd.report import write_report
    from gscodec_shac.rd.spec import load_sweep
    from gscodec_shac.rd.sweep import run_sweep

    from gscodec_shac.atomic import protect_inputs
    from gscodec_shac.commands._options import check_results_folder

    protect_inputs(args.sweep)
    check_results_folder(args.out, args.force)
    spec = load_sweep(args.sweep)
    protect_inputs(*(scene.ply for scene in spec.scenes if getattr(scene, "ply", None)))
    if args.workers < 1:
        raise GscodecError(f"--workers must be at least 1, got {args.workers}")
    if args.threads is not None and args.threads < 1:
        raise GscodecError(f"--threads must be at least 1, got {args.threads}")
    if args.address and args.executor != "ray":
        raise GscodecError("--address is only used with --executor ray")
    if args.dry_run:
        count = 0
        for scene in spec.scenes:
            for method in spec.methods:
                for point in points_for(method, spec.rate_points):
                    print(f"{scene.name}\t{method.name}\t{point}")
                    count += 1
        print(f"{count} runs ({len(spec.scenes)} scenes x {len(spec.methods)} methods)")
        return 0
    outcome = run_sweep(spec, args.out, executor=args.executor, workers=args.workers, threads=args.threads,
                        address=args.address, num_cpus=args.num_cpus, force=args.force, progress=not args.quiet)
    for scene, error in outcome.scene_errors.items():
        print(f"scene {scene}: not prepared: {error}")
    print(f"{outcome.planned} runs: {outcome.executed} executed, {outcome.reused} reused, "
          f"{outcome.failed} failed; {outcome.seconds:.0f} s on {outcome.executor}")
    print(f"results: {outcome.out_dir / 'results.csv'}")
    if not args.no_report:
        paths = write_report(outcome.out_dir)
        print(f"report: {paths['markdown']}")
    return 1 if outcome.failed else 0
