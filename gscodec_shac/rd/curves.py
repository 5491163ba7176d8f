"""RD curves: the ok rows of one (scene, method) of a sweep's results, sorted by size."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable


@dataclass
class Curve:
    """The ok rows of one (scene, method), sorted by bytes."""

    scene: str
    method: str
    rows: list[dict[str, Any]]

    def values(self, column: str) -> list[float]:
        return [num(r.get(column)) for r in self.rows]

    def has(self, column: str) -> bool:
        return any(math.isfinite(v) for v in self.values(column))


def num(value: Any) -> float:
    """A result cell as a float (NaN when empty or not a number)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def short_rate_point(ref: str) -> str:
    """``paper_table3:rp1`` -> ``rp1``; a path-qualified reference keeps only the point name."""
    return ref.rsplit(":", 1)[-1] if ":" in ref else Path(ref).stem


def ordered(values: Iterable[str]) -> list[str]:
    seen: list[str] = []
    for value in values:
        if value not in seen:
            seen.append(value)
    return seen


def curves(rows: list[dict[str, Any]]) -> dict[tuple[str, str], Curve]:
    """Curves of every (scene, method) with at least one ok row, in first-seen order."""
    out: dict[tuple[str, str], Curve] = {}
    for row in rows:
        if row.get("status") != "ok" or not num(row.get("bytes")) > 0:
            continue
        key = (row["scene"], row["method"])
        out.setdefault(key, Curve(*key, []))
        out[key].rows.append(row)
    for curve in out.values():
        curve.rows.sort(key=lambda r: num(r.get("bytes")))
    return out


def bd_label(entry: dict[str, Any]) -> str:
    """A BD row's method: ``shac-auto``, or ``shac-auto vs shac-auto-nosh`` when measured against its own anchor."""
    return f"{entry['method']} vs {entry['anchor']}" if entry.get("compared") else entry["method"]
