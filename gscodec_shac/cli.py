"""Command-line entry point ``gscodec-shac``.

Each subcommand lives in its own module under :mod:`gscodec_shac.commands` and
exposes ``register(subparsers)``; modules are discovered at start-up, so adding a
command touches no shared file. Modules import heavy dependencies inside their
``run`` function to keep ``--help`` fast.

Failures end in one line on stderr and a documented exit status (:data:`EXIT_CODES`,
docs/reliability.md), never a traceback unless ``--debug`` (or ``GSCODEC_DEBUG=1``):
a :class:`~gscodec_shac.errors.GscodecError` prints ``error: ...`` with its class's
status, Ctrl-C and SIGTERM stop quietly (outputs are atomic, no temporary file is
left), a closed output pipe (``| head``) is a quiet exit, and warnings of any library
become one ``warning: ...`` line.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import pkgutil
import signal
import sys
import warnings
from typing import Iterator, NoReturn, Sequence

from gscodec_shac import __version__, commands
from gscodec_shac import errors, kernels
from gscodec_shac.commands._options import resolve_args
from gscodec_shac.errors import GscodecError
from gscodec_shac.heap import returns_freed_memory, trim_freed_memory
from gscodec_shac.progress import plain_progress_lines

#: Exit statuses, as ``--help`` lists them.
EXIT_CODES = (
    (errors.EXIT_OK, "success"),
    (errors.EXIT_FAILED_RUNS, "finished, but some runs of a sweep failed (rd, demo)"),
    (errors.EXIT_USAGE, "bad option or input file (PLY, YAML, cameras), or an output that exists or is an input"),
    (errors.EXIT_CORRUPT_STREAM, "corrupt, truncated, foreign or unsupported .gsc file"),
    (errors.EXIT_MISSING_TOOL, "a codec library or external tool is not installed"),
    (errors.EXIT_LIMIT, "the input needs more memory than this process may use ($GSCODEC_MAX_MEMORY)"),
    (errors.EXIT_INTERNAL, "internal error (a bug: rerun with --debug and report the traceback)"),
    (errors.EXIT_INTERRUPTED, "interrupted (Ctrl-C)"),
    (errors.EXIT_BROKEN_PIPE, "the output pipe was closed (e.g. `| head`)"),
    (errors.EXIT_TERMINATED, "terminated (SIGTERM)"),
)
DEBUG_ENV = "GSCODEC_DEBUG"


#: Signals our handler turned into exceptions during this command (see :func:`_fail_for_signal`).
_SIGNALS_RECEIVED: list[int] = []


class Terminated(BaseException):
    """SIGTERM arrived (a BaseException, like KeyboardInterrupt, so no ``except Exception`` swallows it)."""


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT). A subclass: code catching KeyboardInterrupt still does, and CPython, which
    notes a plain KeyboardInterrupt passing through some C paths and then kills itself with SIGINT
    at exit even when it was handled, exits with our status 130."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse's parser, except that a bad command line is one line ``error: ...`` (status 2)
    pointing at ``--help``, like every other user mistake (subcommand parsers share the class)."""

    def error(self, message: str) -> NoReturn:
        self.exit(errors.EXIT_USAGE, f"error: {self.prog}: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    epilog = "exit status:\n" + "\n".join(f"  {code:>3}  {what}" for code, what in EXIT_CODES)
    epilog += ("\n\nCommands that write files refuse an existing output unless --force and never write over "
               "an input.\nSee docs/reliability.md for the limits on untrusted input.")
    parser = ArgumentParser(
        prog="gscodec-shac",
        description="Low-rank SH compression (SHAC) for 2D-mapped 3D Gaussian Splatting codecs.\n\n"
        "Example:\n  gscodec-shac encode scene.ply scene.gsc --rate-point paper_table3:rp2 --sh pca --er 0.99\n\n"
        "Every command: gscodec-shac COMMAND --help (all of them in docs/cli.md).",
        epilog=epilog,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("--debug", action="store_true", help=f"show tracebacks (also ${DEBUG_ENV}=1)")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        module.register(subparsers)
    for sub in subparsers.choices.values():  # --debug after the command works too
        sub.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = _parse_args(parser, argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    debug = bool(args.debug or os.environ.get(DEBUG_ENV, "") not in ("", "0"))
    if returns_freed_memory(args):
        trim_freed_memory()  # peak memory of large encodes and decodes (gscodec_shac/heap.py)
    try:
        with _signals_as_exceptions(), _warnings_as_lines(debug), plain_progress_lines(args.command):
            args = resolve_args(args)
            if not getattr(args, "quiet", True):
                kernels.announce(args.command)
            result = int(args.func(args) or 0)
            sys.stdout.flush()
        return result
    except GscodecError as exc:
        if _SIGNALS_RECEIVED:
            return _fail_for_signal()
        if debug:
            raise
        return _fail(f"error: {exc}", exc.exit_code)
    except KeyboardInterrupt:
        return _fail("interrupted", errors.EXIT_INTERRUPTED)
    except Terminated:
        return _fail("terminated", errors.EXIT_TERMINATED)
    except BrokenPipeError:
        _silence_stdout()
        return errors.EXIT_BROKEN_PIPE
    except MemoryError:
        if debug:
            raise
        return _fail("error: out of memory (set $GSCODEC_MAX_MEMORY below the free memory to be refused earlier)",
                     errors.EXIT_LIMIT)
    except Exception as exc:  # noqa: BLE001 - the one place a bug becomes one line
        if _SIGNALS_RECEIVED:
            return _fail_for_signal()
        if debug:
            raise
        return _fail(f"error: internal error ({type(exc).__name__}: {_first_line(exc)}); this is a bug, "
                     "rerun with --debug and report the traceback", errors.EXIT_INTERNAL)
    finally:
        from gscodec_shac.atomic import release_inputs

        release_inputs()


def _parse_args(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> argparse.Namespace:
    """``parser.parse_args``, except that a positional output left over after options
    (``rd-report RESULTS --x-axis bpg OUT``: argparse gives an optional positional nothing once
    the positionals before it are taken) still becomes the output."""
    args, extras = parser.parse_known_args(argv)
    if (len(extras) == 1 and not extras[0].startswith("-") and getattr(args, "output_spec", None) is not None
            and args.out is None):
        args.out = extras[0]
    elif extras:
        commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
        commands.get(getattr(args, "command", None), parser).error(f"unrecognized arguments: {' '.join(extras)}")
    return args


def _fail(message: str, code: int) -> int:
    with contextlib.suppress(OSError, ValueError):
        sys.stdout.flush()
    try:
        print(message, file=sys.stderr)
    except (OSError, ValueError):
        pass
    return code


def _fail_for_signal() -> int:
    """The exit for a signal whose exception a C callback swallowed (numba's compiler does),
    after which the code it interrupted failed with an error of its own."""
    if _SIGNALS_RECEIVED[0] == signal.SIGINT:
        return _fail("interrupted", errors.EXIT_INTERRUPTED)
    return _fail("terminated", errors.EXIT_TERMINATED)


def _silence_stdout() -> None:
    """After EPIPE: point stdout at /dev/null so the exit-time flush does not complain."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass


@contextlib.contextmanager
def _signals_as_exceptions() -> Iterator[None]:
    """SIGINT raises :class:`Interrupted`, SIGTERM :class:`Terminated` in this process, so cleanup
    runs; forked children (process pools) keep the default behaviour."""
    main_pid = os.getpid()

    def handler(signum: int, frame: object) -> None:
        if os.getpid() != main_pid:  # a forked worker
            if signum == signal.SIGINT:
                raise KeyboardInterrupt()
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        _SIGNALS_RECEIVED.append(signum)
        raise Interrupted() if signum == signal.SIGINT else Terminated()

    def unraisable(info: "sys.UnraisableHookArgs") -> None:
        if not isinstance(info.exc_value, (Interrupted, Terminated)):  # ours: main() reports it
            previous_hook(info)

    try:
        previous = {signum: signal.signal(signum, handler) for signum in (signal.SIGINT, signal.SIGTERM)}
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    previous_hook, sys.unraisablehook = sys.unraisablehook, unraisable
    _SIGNALS_RECEIVED.clear()
    try:
        yield
    finally:
        sys.unraisablehook = previous_hook
        for signum, old in previous.items():
            signal.signal(signum, old)


@contextlib.contextmanager
def _warnings_as_lines(debug: bool) -> Iterator[None]:
    """Warnings (ours and any library's) print as one ``warning: ...`` line, each once."""
    if debug:
        yield
        return

    def show(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
        try:
            print(f"warning: {_first_line(message)}", file=sys.stderr)
        except (OSError, ValueError):
            pass

    with warnings.catch_warnings():
        warnings.simplefilter("once")
        warnings.showwarning = show
        yield


def _first_line(value: object) -> str:
    lines = str(value).strip().splitlines()
    return lines[0] if lines else type(value).__name__


def run() -> NoReturn:
    """The process entry (``gscodec-shac``, ``python -m gscodec_shac``): :func:`main`, then exit with its
    status. After SIGINT or SIGTERM the process ends at once (``os._exit``, stdout and stderr flushed)
    instead of through the interpreter's shutdown: the interrupted work's threads (the encoder's
    scheduler, numba's and x265's) may still be running native code, and two fresh-clone CI runs saw
    an interrupted encode print its message and then die of SIGSEGV on the way out (docs/reliability.md,
    "A crash after an interrupted encode"). Every output is whole or absent by then (the atomic writes
    and the input release ran inside :func:`main`); x265's worker processes end when their pipes close."""
    code = main()
    if _SIGNALS_RECEIVED:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError):
                stream.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    run()
