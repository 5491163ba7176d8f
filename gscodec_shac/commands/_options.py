"""Option parsing shared by several commands (not a command itself: the leading underscore
keeps it out of the CLI's command discovery).

One convention across commands: positional input and output where a command has one of
each, the same option for the same thing (``--images``, ``--resolution-scale``,
``--threads``, ``-q/--quiet``, ``--json``, ``--force``), an ``Example:`` in every
command's description. Earlier spellings (``--out``, ``--images-dir``, ``--scale``) keep
working as hidden aliases (:func:`add_alias`, :func:`add_output`).
"""

from __future__ import annotations

import argparse
import math
import sys
import textwrap
from dataclasses import dataclass
from typing import Sequence

from gscodec_shac.errors import GscodecError

#: Descriptions are filled to this width (they keep their lines, so the Example: block stays as written).
DESCRIPTION_WIDTH = 79


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions keep their lines; an output that may also come as the hidden ``--out`` is shown
    without brackets in the usage when it is required."""

    def _format_args(self, action: argparse.Action, default_metavar: str) -> str:
        if getattr(action, "shown_required", False):
            return "%s" % self._metavar_formatter(action, default_metavar)(1)
        return super()._format_args(action, default_metavar)


def add_command(
    subparsers: argparse._SubParsersAction, name: str, *, help: str, description: str, examples: Sequence[str]
) -> argparse.ArgumentParser:
    """A subcommand's parser: ``description`` (paragraphs filled) followed by an ``Example:`` block."""
    paragraphs = [textwrap.fill(" ".join(p.split()), DESCRIPTION_WIDTH) for p in description.split("\n\n")]
    label = "Example:" if len(examples) == 1 else "Examples:"
    text = "\n\n".join(paragraphs) + f"\n\n{label}\n" + "\n".join(f"  {example}" for example in examples)
    return subparsers.add_parser(name, help=help, description=text, formatter_class=HelpFormatter)


@dataclass(frozen=True)
class OutputSpec:
    """How a command's positional output is resolved (:func:`resolve_args`)."""

    command: str
    metavar: str
    default: str | None
    required: bool


def add_output(parser: argparse.ArgumentParser, metavar: str, help: str, *, default: str | None = None,
               required: bool = True) -> None:
    """The output as a positional ``args.out``; the earlier ``--out X`` spelling still works, hidden."""
    action = parser.add_argument("out", nargs="?", metavar=metavar, default=None, help=help)
    action.shown_required = required  # type: ignore[attr-defined]
    parser.add_argument("--out", dest="out_option", default=None, help=argparse.SUPPRESS)
    parser.set_defaults(output_spec=OutputSpec(parser.prog.split()[-1], metavar, default, required))


def add_alias(container: argparse._ActionsContainer, old: str, action: argparse.Action) -> None:
    """``old``: an earlier spelling of ``action``'s option, still accepted, not shown in the help
    (add it right after the group's other members: argparse lays out a group's usage in order)."""
    container.add_argument(old, dest=action.dest, type=action.type, choices=action.choices, metavar=action.metavar,
                           default=argparse.SUPPRESS, help=argparse.SUPPRESS)


#: What ``--up`` means, the same for every command that makes orbit views (docs/cli.md, "The up axis").
UP_HELP = ("x,y,z in the model's own coordinates (default 0,0,1: +Z up, as the synthetic scene and "
           "NeRF-synthetic/D-NeRF captures). 3DGS PLYs trained from COLMAP are mostly -Y up: pass 0,-1,0, the "
           "up that splat-transform and SuperSplat show for .ply/.spz/.splat/.sog files (they turn them 180 "
           "degrees about Z into their +Y-up world)")


def add_up(container: argparse._ActionsContainer, what: str) -> None:
    """``--up X,Y,Z``: the world up axis of ``what`` (see :data:`UP_HELP`)."""
    container.add_argument("--up", default="0,0,1", metavar="X,Y,Z", help=f"world up axis of {what}: {UP_HELP}")


def add_quiet(parser: argparse.ArgumentParser) -> None:
    """``-q/--quiet``: no progress bars (in a log, long ones write plain lines: gscodec_shac.progress)."""
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="no progress bars (in a log file, bars over 30 s write a plain line every 30 s)")


def add_json(parser: argparse.ArgumentParser, what: str = "the summary") -> None:
    """``--json``: print ``what`` as JSON instead of text."""
    parser.add_argument("--json", action="store_true", help=f"print {what} as JSON instead of text")


def add_threads(parser: argparse.ArgumentParser, what: str, default: str = "all cores") -> None:
    """``--threads N``, by default all cores (:func:`all_cores`); ``what`` says which threads."""
    parser.add_argument("--threads", type=int, metavar="N", help=f"{what} (default: {default})")


def set_numba_threads(threads: int | None) -> None:
    """Apply a trainer's ``--threads N`` to numba (at most the threads it started with); None: all."""
    if threads is None:
        return
    if threads < 1:
        raise GscodecError(f"--threads must be at least 1, got {threads}")
    import numba

    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


def add_training_run_options(parser: argparse.ArgumentParser, *, on_stop: str, evaluated: str) -> None:
    """The run options every trainer command shares: seed, checkpoints, resume, time budget,
    threads, evaluation switch, quiet and ``--force``. ``on_stop`` says what a budget stop
    writes; ``evaluated`` names the held-out images."""
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--checkpoint-every", type=int, default=500, metavar="N", help="checkpoint every N "
                        "iterations (default 500)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT_DIR's checkpoint (its settings "
                        "are used)")
    parser.add_argument("--time-budget", type=float, metavar="SECONDS", help="stop training after this many "
                        f"seconds of this run ({on_stop}; --resume continues)")
    add_threads(parser, "numba threads of the rasteriser")
    parser.add_argument("--no-eval", action="store_true", help=f"skip the {evaluated} evaluation")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars: a JSON log line every 100 "
                        "steps instead (also when stderr is not a terminal)")
    add_force(parser)


#: SHAC-LST variant choices (gscodec_shac.shac.lst_torch.LSTConfig validates them; kept here so that
#: building the parser does not import torch; tests/test_train.py checks they agree).
LST_SUBSETS = ("lowest", "highest")
LST_OPERATORS = ("matrix", "vector", "linear", "mlp")
LST_STRUCTURES = ("block", "dense")
LST_RGB = ("joint", "separate")
LST_INITS = ("zero", "identity")


def add_lst_variant_options(container: argparse._ActionsContainer, *, lambda_t: bool = True) -> None:
    """The SHAC-LST variant options (paper Sec. VII-E ablations; defaults = the paper's model):
    ``--lst-subset``, ``--lst-operator``, ``--lst-structure``, ``--lst-rgb``, ``--lst-init`` and,
    unless ``lambda_t=False``, ``--lambda-t`` (eq. 37)."""
    container.add_argument("--lst-subset", choices=LST_SUBSETS, default="lowest",
                           help="subset S: lowest degree l per order m (eq. 32, default) or highest (Table VII)")
    container.add_argument("--lst-operator", choices=LST_OPERATORS, default="matrix",
                           help="S -> A~ operator: matrix (T, default), vector, linear (with bias) or mlp "
                           "(two hidden layers, Table VIII)")
    container.add_argument("--lst-structure", choices=LST_STRUCTURES, default="block",
                           help="matrix operator: block-diagonal T (eq. 34, default) or one dense map (Table IX)")
    container.add_argument("--lst-rgb", choices=LST_RGB, default="joint",
                           help="matrix operator: RGB predicted jointly (default) or per channel (Table IX)")
    container.add_argument("--lst-init", choices=LST_INITS, default="zero",
                           help="initial T: zero (default) or identity on same-order entries (Table IX)")
    if lambda_t:
        container.add_argument("--lambda-t", type=float, default=5e-3,
                               help="weight of the eq. 36 scale regulariser on T (default 5e-3; 0 = off, Fig. 13)")


def add_force(parser: argparse.ArgumentParser) -> None:
    """``--force``: replace existing outputs (inputs are never written over, even with it)."""
    parser.add_argument("--force", action="store_true",
                        help="replace existing output files (an input is never overwritten, even with --force)")


def resolve_args(args: argparse.Namespace) -> argparse.Namespace:
    """After parsing: the hidden ``--out`` alias folded into the positional output (one clear error
    when both differ or neither is given), and ``args.quiet`` set when stderr is not a terminal."""
    spec = getattr(args, "output_spec", None)
    if spec is not None:
        alias = args.out_option
        if alias is not None and args.out is not None and alias != args.out:
            raise GscodecError(f"the output is given twice ({args.out} and --out {alias}); "
                               f"give it once as {spec.metavar}")
        args.out = args.out if args.out is not None else alias if alias is not None else spec.default
        if args.out is None and spec.required:
            raise GscodecError(f"{spec.command} needs an output {spec.metavar} "
                               f"(see gscodec-shac {spec.command} --help)")
    if hasattr(args, "quiet") and not args.quiet and not _is_terminal(sys.stderr):
        args.quiet = True
    return args


def _is_terminal(stream: object) -> bool:
    try:
        return bool(stream.isatty())  # type: ignore[attr-defined]
    except (AttributeError, ValueError):
        return False


def show_progress(args: argparse.Namespace) -> bool:
    """Progress bars for this command: not ``-q`` and stderr a terminal (see :func:`resolve_args`)."""
    return not getattr(args, "quiet", False) and _is_terminal(sys.stderr)


def all_cores() -> int:
    """The cores this process may run on (its CPU affinity), the default of every ``--threads``."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def check_threads(threads: int | None) -> int | None:
    """``--threads``: None (all cores) or a positive integer, else one clear error."""
    if threads is not None and threads < 1:
        raise GscodecError(f"--threads must be at least 1, got {threads}")
    return threads


def comma_floats(text: str, what: str, count: int = 3) -> list[float]:
    """``"a,b,c"`` -> ``[a, b, c]``: exactly ``count`` finite numbers, else one clear error."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise GscodecError(f"{what} must be {count} comma-separated numbers, got {text!r}")
    return values


def resize_cameras(cameras: list, scale: float | None, width: int | None) -> list:
    """Cameras scaled by ``--resolution-scale`` or resized to ``--width`` (aspect kept), else unchanged."""
    if scale is not None:
        if not (math.isfinite(scale) and scale > 0):
            raise GscodecError(f"--resolution-scale must be a positive number, got {scale}")
        return [c.scaled(scale) for c in cameras]
    if width is not None:
        if width < 1:
            raise GscodecError(f"--width must be a positive integer, got {width}")
        return [c.resized(width, max(1, round(width * c.height / c.width))) for c in cameras]
    return cameras


def require_input(path: str) -> None:
    """A missing input is the error to report first, before anything about the output."""
    from pathlib import Path

    if not Path(path).exists():
        raise GscodecError(f"{path}: no such file or folder")


def check_results_folder(out, force: bool) -> None:
    """A sweep's output folder: absent, empty, or one a sweep wrote (it resumes there); anything
    else (a file, a folder of other files) is refused unless ``--force``."""
    from pathlib import Path

    from gscodec_shac.errors import OutputError

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: the output folder is a file")
    if out.is_dir() and any(out.iterdir()) and not force and not (
        (out / "sweep.json").is_file() or (out / "runs.jsonl").is_file()
    ):
        raise OutputError(f"{out}: the folder holds files but no sweep results (sweep.json); choose another "
                          "output folder or pass --force")
