"""Reading a user's YAML file with one clear error per problem (missing, unreadable, bad YAML).

Untrusted YAML is bounded before it can exhaust the stack or memory: at most
:data:`~gscodec_shac.limits.MAX_YAML_BYTES` long, nested at most
:data:`~gscodec_shac.limits.MAX_NESTING` levels (checked while composing, before the
recursive constructor runs) and with at most :data:`~gscodec_shac.limits.MAX_YAML_ALIASES`
aliases; values that do not fit (an integer of thousands of digits) are refused.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from gscodec_shac.errors import GscodecError
from gscodec_shac.limits import MAX_NESTING, MAX_YAML_ALIASES, MAX_YAML_BYTES


class _LimitExceeded(Exception):
    """A bound of :class:`BoundedLoader` was crossed."""


class BoundedLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses deep nesting and alias bombs while composing."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._aliases = 0

    def compose_node(self, parent, index):  # noqa: ANN001 - PyYAML's signature
        if self.check_event(yaml.AliasEvent):
            self._aliases += 1
            if self._aliases > MAX_YAML_ALIASES:
                raise _LimitExceeded(f"more than {MAX_YAML_ALIASES} aliases")
        self._depth += 1
        if self._depth > MAX_NESTING:
            raise _LimitExceeded(f"nested more than {MAX_NESTING} levels deep")
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def parse_yaml(text: str, source: str, error: type[GscodecError] = GscodecError) -> Any:
    """The parsed content of YAML ``text`` read from ``source`` (named in messages)."""
    if len(text) > MAX_YAML_BYTES:
        raise error(f"{source}: {len(text):,} characters of YAML (at most {MAX_YAML_BYTES:,})")
    loader = BoundedLoader(text)
    try:
        return loader.get_single_data()
    except _LimitExceeded as exc:
        raise error(f"{source}: YAML {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise error(f"{source}: not valid YAML{where}: {getattr(exc, 'problem', exc)}") from None
    except (ValueError, OverflowError) as exc:  # e.g. an integer of more digits than Python converts
        raise error(f"{source}: a YAML value cannot be read ({str(exc).splitlines()[0]})") from None
    finally:
        loader.dispose()


def read_yaml_file(path: str | os.PathLike, what: str, error: type[GscodecError] = GscodecError) -> Any:
    """The parsed content of ``path``; ``what`` names the file kind in messages (e.g. "sweep file")."""
    path = Path(path)
    if path.is_dir():
        raise error(f"{path}: is a directory, expected a {what}")
    try:
        size = path.stat().st_size
        if size > MAX_YAML_BYTES:
            raise error(f"{path}: {what} of {size:,} bytes (at most {MAX_YAML_BYTES:,})")
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{path}: cannot read {what} ({exc})") from None
    return parse_yaml(text, str(path), error)
