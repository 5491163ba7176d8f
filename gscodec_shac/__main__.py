"""``python -m gscodec_shac`` runs the CLI."""

from gscodec_shac.cli import run

run()
