"""``python -m gscodec_shac`` runs the CLI."""

import sys

from gscodec_shac.cli import main

sys.exit(main())
