"""Subcommands of the ``gscodec-shac`` CLI, one module each (see :mod:`gscodec_shac.cli`).

A module defines ``register(subparsers)`` which adds its parser and sets
``func=run``; ``run(args) -> int`` does the work and imports heavy modules lazily.
"""
