"""Command-line entry point ``gscodec-shac``.

Each subcommand lives in its own module under :mod:`gscodec_shac.commands` and
exposes ``register(subparsers)``; modules are discovered at start-up, so adding a
command touches no shared file. Modules import heavy dependencies inside their
``run`` function to keep ``--help`` fast.

A :class:`~gscodec_shac.errors.GscodecError` (a user mistake or a missing tool)
is printed as one line, ``error: ...``, with exit status 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from typing import Sequence

from gscodec_shac import __version__, commands
from gscodec_shac.errors import GscodecError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="gscodec-shac",
        description="Low-rank SH compression (SHAC) for 2D-mapped 3D Gaussian Splatting codecs.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        module.register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    try:
        result = args.func(args)
    except GscodecError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return int(result or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
