"""Reading a user's YAML file with one clear error per problem (missing, unreadable, bad YAML)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from gscodec_shac.errors import GscodecError


def read_yaml_file(path: str | os.PathLike, what: str, error: type[GscodecError] = GscodecError) -> Any:
    """The parsed content of ``path``; ``what`` names the file kind in messages (e.g. "sweep file")."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{path}: cannot read {what} ({exc})") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise error(f"{path}: not valid YAML{where}: {getattr(exc, 'problem', exc)}") from None
