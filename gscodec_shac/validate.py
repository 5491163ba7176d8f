"""One way to check parsed documents (YAML, JSON headers, parameters): :class:`Where`.

A :class:`Where` knows what is being read (a file, a rate point in it, a container
header) and which error type to raise. Its checks take a value and the key it came
from and either return the value in its proper type or raise one error whose message
names the source, the key and the problem::

    where = Where("sweeps/bonsai.yaml", SweepSpecError)
    n = where.integer(raw.get("n", 16), "scenes[0].orbit.n", 1, 4096)
    where.only(raw, {"n", "width"}, "scenes[0].orbit")
    # -> "sweeps/bonsai.yaml: key 'scenes[0].orbit.n': must be an integer in 1..4096, got 'x'"

Rate points, sweep specifications, RD method parameters, SH stage parameters and the
``.gsc`` header reader all use it, so the same mistake reads the same everywhere.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Sequence

from gscodec_shac.errors import GscodecError

#: The largest finite float64, as an exact integer (huge JSON integers are compared with it).
_FLOAT64_MAX = int(sys.float_info.max)
#: The longest problem text of an error (values quoted from the document are cut in the middle).
_MAX_PROBLEM = 300


@dataclass(frozen=True)
class Where:
    """The source of a document (``source``, optionally ``context``) and its error type."""

    source: str
    error_type: type[GscodecError] = GscodecError
    context: str = ""

    def at(self, context: str) -> "Where":
        """The same source, narrowed to a part (e.g. ``"point 'rp1'"``)."""
        return Where(self.source, self.error_type, context)

    # -------------------------------------------------------------- errors
    def error(self, key: str, problem: str) -> GscodecError:
        """The error to raise: ``source: context: key 'k': problem`` (a problem quoting a long
        hostile value is shortened in the middle)."""
        if len(problem) > _MAX_PROBLEM:
            problem = f"{problem[:_MAX_PROBLEM - 60]} ... {problem[-50:]}"
        parts = [p for p in (self.source, self.context) if p]
        if key:
            parts.append(f"key {key!r}")
        return self.error_type(": ".join(parts + [problem]))

    def only(self, mapping: Mapping, allowed: Iterable[str], prefix: str = "") -> None:
        """Refuse keys of ``mapping`` that are not in ``allowed``."""
        allowed = set(allowed)
        extra = sorted(str(k) for k in set(mapping) - allowed)
        if extra:
            key = f"{prefix}.{extra[0]}" if prefix else extra[0]
            raise self.error(key, f"unknown key (allowed: {', '.join(sorted(allowed)) or 'none'})")

    # -------------------------------------------------------------- checks
    def integer(self, value: Any, key: str, lo: int, hi: int | None = None) -> int:
        """An integer (not a bool) in ``lo..hi`` (no upper bound when ``hi`` is None)."""
        if isinstance(value, bool) or not isinstance(value, int) or value < lo or (hi is not None and value > hi):
            bound = f"in {lo}..{hi}" if hi is not None else f">= {lo}"
            raise self.error(key, f"must be an integer {bound}, got {shown(value)}")
        return value

    def number(self, value: Any, key: str, lo: float = -math.inf, hi: float = math.inf, *, open_lo: bool = False) -> float:
        """A finite number in ``[lo, hi]`` (``(lo, hi]`` with ``open_lo``); an integer of any size
        is compared exactly and must also fit a float64."""
        ok = (
            not isinstance(value, bool) and isinstance(value, (int, float)) and _fits_float(value)
            and (lo < value if open_lo else lo <= value) and value <= hi
        )
        if not ok:
            raise self.error(key, f"must be a number in {'(' if open_lo else '['}{lo:g}, {hi:g}], got {shown(value)}")
        return float(value)

    def boolean(self, value: Any, key: str) -> bool:
        if not isinstance(value, bool):
            raise self.error(key, f"must be true or false, got {value!r}")
        return value

    def string(self, value: Any, key: str) -> str:
        """A non-empty string."""
        if not isinstance(value, str) or not value:
            raise self.error(key, f"must be a non-empty string, got {value!r}")
        return value

    def choice(self, value: Any, choices: Sequence[Any], key: str) -> Any:
        if isinstance(value, bool) or value not in choices:
            raise self.error(key, f"must be one of {', '.join(map(str, choices))}, got {value!r}")
        return value

    def mapping(self, value: Any, key: str, *, optional: bool = True) -> dict:
        """A mapping (``None`` is an empty one when ``optional``)."""
        if value is None and optional:
            return {}
        if not isinstance(value, dict):
            raise self.error(key, f"must be a mapping, got {type(value).__name__}")
        return dict(value)

    def sequence(self, value: Any, key: str, *, min_length: int = 1) -> list:
        """A list with at least ``min_length`` items."""
        if not isinstance(value, list) or len(value) < min_length:
            wanted = "a non-empty list" if min_length == 1 else f"a list of at least {min_length} items"
            raise self.error(key, f"must be {wanted}, got {value!r}")
        return value

    def vector3(self, value: Any, key: str, lo: float = -math.inf, hi: float = math.inf) -> tuple[float, float, float]:
        """Three finite numbers in ``[lo, hi]``."""
        if (
            not isinstance(value, (list, tuple)) or len(value) != 3
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not _fits_float(v) or not lo <= v <= hi
                   for v in value)
        ):
            bounds = f" in [{lo:g}, {hi:g}]" if math.isfinite(lo) else ""
            raise self.error(key, f"must be a list of 3 numbers{bounds}, got {value!r}")
        return (float(value[0]), float(value[1]), float(value[2]))


def _fits_float(value: int | float) -> bool:
    """Whether a number is finite as a float64 (a huge integer is not; no OverflowError)."""
    if isinstance(value, int):
        return -_FLOAT64_MAX <= value <= _FLOAT64_MAX
    return math.isfinite(value)


def shown(value: Any, limit: int = 60) -> str:
    """``repr(value)`` for a message, shortened (a 400-digit integer becomes ``1234...(400 digits)``)."""
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 10**limit:
        digits = len(str(abs(value))) if abs(value).bit_length() < 14_000 else None
        return f"an integer of {digits:,} digits" if digits else "an integer of more than 4,000 digits"
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit - 3]}..."
