"""The results of a sweep on disk: an append-only log plus CSV/JSON tables.

``OUT/runs.jsonl`` gets one JSON line per finished run, appended and fsync'd by the
driver as each row arrives; a run repeated later appends a newer line for the same key
and the newest wins. A line cut short by a crash is ignored on reading, so an interrupted
sweep never leaves a corrupt log. ``OUT/results.csv`` and ``OUT/results.json`` are
regenerated from the log (written to a temporary file and renamed into place).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from pathlib import Path
from typing import Any, Iterable

from gscodec_shac.errors import GscodecError
from gscodec_shac.atomic import write_atomic, write_json
from gscodec_shac.rd.cache import DURABLE
from gscodec_shac.rd.runner import ROW_FIELDS

LOG_NAME = "runs.jsonl"
CSV_NAME = "results.csv"
JSON_NAME = "results.json"
#: Statuses a resumed sweep does not run again.
FINISHED = ("ok", "skipped")


class ResultsError(GscodecError):
    """A results folder is missing or unreadable."""


def clean(value: Any) -> Any:
    """JSON-safe copy: non-finite floats become None."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [clean(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        try:
            return clean(value.item())
        except (TypeError, ValueError):
            return str(value)
    return value


class ResultStore:
    """Append-only run log of one output folder (written by the driver only)."""

    def __init__(self, out_dir: str | os.PathLike) -> None:
        self.out_dir = Path(out_dir)
        self.log_path = self.out_dir / LOG_NAME

    def append(self, row: dict[str, Any]) -> None:
        """Add one row durably (one line, flushed and fsync'd)."""
        self.out_dir.mkdir(parents=True, exist_ok=True)
        line = json.dumps(clean(row), separators=(",", ":"), allow_nan=False)
        with open(self.log_path, "a", encoding="utf-8") as handle:
            if handle.tell() > 0 and not self._ends_with_newline():
                handle.write("\n")  # a torn last line stays isolated (and ignored)
            handle.write(line + "\n")
            handle.flush()
            os.fsync(handle.fileno())

    def _ends_with_newline(self) -> bool:
        with open(self.log_path, "rb") as handle:
            handle.seek(-1, os.SEEK_END)
            return handle.read(1) == b"\n"

    def latest(self) -> dict[str, dict[str, Any]]:
        """The newest row per key (torn or foreign lines are skipped)."""
        rows: dict[str, dict[str, Any]] = {}
        if not self.log_path.is_file():
            return rows
        with open(self.log_path, encoding="utf-8", errors="replace") as handle:
            for line in handle:
                line = line.strip()
                if not line:
                    continue
                try:
                    row = json.loads(line)
                except ValueError:
                    continue
                if isinstance(row, dict) and isinstance(row.get("key"), str):
                    rows[row["key"]] = row
        return rows

    def finished_keys(self) -> set[str]:
        return {k for k, row in self.latest().items() if row.get("status") in FINISHED}

    def export(self, keys: Iterable[str] | None = None) -> list[dict[str, Any]]:
        """Write ``results.csv`` and ``results.json`` (the newest row of each key, in ``keys`` order)."""
        latest = self.latest()
        order = list(keys) if keys is not None else list(latest)
        rows = [latest[k] for k in order if k in latest]
        write_json(self.out_dir / JSON_NAME, rows, **DURABLE)
        write_atomic(self.out_dir / CSV_NAME, rows_to_csv(rows), **DURABLE)
        return rows


def size_columns(rows: list[dict[str, Any]]) -> list[str]:
    """The ``bytes_<attribute>`` columns of a set of rows, in a stable order."""
    names: list[str] = []
    for row in rows:
        for name in (row.get("sizes") or {}):
            if name not in names:
                names.append(name)
    return [f"bytes_{n}" for n in names]


def rows_to_csv(rows: list[dict[str, Any]]) -> str:
    """One CSV line per row: :data:`ROW_FIELDS` with the per-attribute bytes after ``bytes``."""
    sizes = size_columns(rows)
    fields = list(ROW_FIELDS)
    at = fields.index("bytes") + 1
    fields[at:at] = sizes
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=fields, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        flat = {k: _cell(row.get(k)) for k in ROW_FIELDS}
        for column in sizes:
            flat[column] = (row.get("sizes") or {}).get(column[len("bytes_"):], "")
        writer.writerow(flat)
    return buffer.getvalue()


def _cell(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}" if math.isfinite(value) else ""
    if isinstance(value, (dict, list)):
        return json.dumps(value, sort_keys=True, separators=(",", ":"))
    return value


def load_results(path: str | os.PathLike) -> list[dict[str, Any]]:
    """Rows of a results folder (``results.json``, else the run log) or of a results JSON file."""
    path = Path(path)
    if path.is_dir():
        if (path / JSON_NAME).is_file():
            path = path / JSON_NAME
        elif (path / LOG_NAME).is_file():
            return list(ResultStore(path).latest().values())
        else:
            raise ResultsError(f"{path}: no {JSON_NAME} or {LOG_NAME} here; run 'gscodec-shac rd' first")
    if not path.is_file():
        raise ResultsError(f"{path}: no such results file or folder")
    try:
        rows = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ResultsError(f"{path}: unreadable results JSON ({exc})") from None
    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        raise ResultsError(f"{path}: not a list of result rows")
    return rows
