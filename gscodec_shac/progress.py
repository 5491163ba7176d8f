"""Progress bars in logs: plain periodic lines when stderr is not a terminal.

tqdm redraws its bar in place with carriage returns, many times a second. In a log file
that is one endless line (or nothing readable until the end). :func:`plain_progress_lines`
puts a filter in front of ``sys.stderr`` while a command runs, when stderr is not a
terminal: a bar running longer than ``$GSCODEC_PROGRESS_INTERVAL`` seconds (default 30)
writes its latest state as an ordinary line every interval, and then its final state when
it closes; shorter bars write nothing (the log looks as it did), and every other output
passes through unchanged. The filter
answers ``isatty()`` with True, so commands that show progress only on a terminal (see
:func:`gscodec_shac.commands._options.resolve_args`) show it in logs too; no tqdm call site
needs to change. ``-q`` still silences a command; ``GSCODEC_PROGRESS_INTERVAL=off`` keeps
the old behaviour (no progress when stderr is not a terminal). Only the process's own stderr
is filtered, never a stream a caller (or pytest) put in its place.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import time
from typing import Any, Callable, Iterable, Iterator, TextIO

INTERVAL_ENV = "GSCODEC_PROGRESS_INTERVAL"
#: Commands that write their own log lines when stderr is not a terminal (JSON every 100 steps).
OWN_LOG_LINES = frozenset({"train", "train-dynamic"})
DEFAULT_INTERVAL = 30.0


class PlainProgressStream:
    """A text stream that turns carriage-return redraws into throttled plain lines."""

    def __init__(self, stream: TextIO, interval: float = DEFAULT_INTERVAL,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._stream = stream
        self._interval = interval
        self._clock = clock
        self._since = math.nan  # when the current bar's first state (or its last line) came
        self._pending: str | None = None  # the newest status not yet written
        self._shown: str | None = None  # the status just written, awaiting tqdm's closing newline
        self._printed = False  # the current bar has written a line (so its final state follows)

    def write(self, text: str) -> int:
        head, *statuses = text.split("\r")
        self._plain(head)
        for status in statuses:
            self._status(status)
        return len(text)

    def _plain(self, text: str) -> None:
        if not text:
            return
        if text.startswith("\n") and (self._pending is not None or self._shown is not None):
            if self._pending is not None and self._printed:  # a long bar closing (leave=True): final state
                self._stream.write(self._pending + "\n")
            text = text[1:]  # the newline ending the status line
        self._reset()
        self._stream.write(text)

    def _reset(self) -> None:
        self._pending = self._shown = None
        self._printed = False
        self._since = math.nan

    def _status(self, status: str) -> None:
        line = status.rstrip(" ")
        if "\n" in line:  # not a redraw: ordinary text after a carriage return
            self._reset()
            self._stream.write(line)
            return
        if not line:  # a bar erased (leave=False)
            self._reset()
            return
        now = self._clock()
        if math.isnan(self._since):
            self._since = now
        if now - self._since >= self._interval:
            self._stream.write(line + "\n")
            self._since, self._pending, self._shown, self._printed = now, None, line, True
        else:
            self._pending = line

    def flush(self) -> None:
        self._stream.flush()

    def isatty(self) -> bool:
        """True: progress shown here is log-friendly (see the module docstring)."""
        return True

    def __getattr__(self, name: str):  # encoding, fileno, errors, ... of the real stream
        return getattr(self._stream, name)


def interval_from_env() -> float | None:
    """Seconds between progress lines: ``$GSCODEC_PROGRESS_INTERVAL`` (default 30; ``off``: None)."""
    text = os.environ.get(INTERVAL_ENV, "").strip().lower()
    if text in ("off", "none", "no"):
        return None
    try:
        return max(0.0, float(text)) if text else DEFAULT_INTERVAL
    except ValueError:
        return DEFAULT_INTERVAL


def _is_terminal(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


@contextlib.contextmanager
def plain_progress_lines(command: str | None = None) -> Iterator[None]:
    """While active, progress bars on a non-terminal stderr become periodic plain lines
    (not for the commands in :data:`OWN_LOG_LINES`, which log in their own way)."""
    original = sys.stderr
    interval = interval_from_env()
    if (original is None or original is not sys.__stderr__ or interval is None or _is_terminal(original)
            or command in OWN_LOG_LINES):
        yield
        return
    sys.stderr = PlainProgressStream(original, interval)  # type: ignore[assignment]
    try:
        yield
    finally:
        if sys.stderr is not original:
            sys.stderr = original


def optional_bar(items: Iterable, show: bool, **options: Any) -> Iterable:
    """``items`` behind a tqdm bar (``options``: tqdm's) when ``show``, else as they are; tqdm is
    imported only when a bar is shown, so a quiet encode or decode does not import it."""
    if not show:
        return items
    from tqdm.auto import tqdm

    return tqdm(items, **options)
