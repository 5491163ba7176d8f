"""One fuzz case through the command line: ``gscodec-shac ARGS`` in a child process, classified.

Exit status 0 is ``valid``; 2, 3 or 5 with exactly one ``error:`` line and no traceback is a
clean ``error``; any other status (70: "this is a bug") is ``internal``; a signal is a
``crash``; no exit within the time limit a ``hang`` (the child is killed). The child's peak
resident set comes from ``wait4``; ``$GSCODEC_MAX_MEMORY`` sets its memory budget.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from tests.fuzzlib.models import Outcome

REPO = Path(__file__).resolve().parents[2]
CLEAN_STATUSES = (2, 3, 5)


def run(args: list[str], cwd: Path, *, timeout: float = 20.0, memory: str = "2G") -> Outcome:
    """Run ``python -m gscodec_shac ARGS`` in ``cwd`` and classify its outcome."""
    env = dict(os.environ, GSCODEC_MAX_MEMORY=memory, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    tic = time.perf_counter()
    with open(cwd / ".stderr", "w+b") as err:
        child = subprocess.Popen([sys.executable, "-m", "gscodec_shac", *args], cwd=cwd, env=env,
                                 stdout=subprocess.DEVNULL, stderr=err, stdin=subprocess.DEVNULL)
        status, usage = _wait(child, timeout)
        err.seek(0)
        text = err.read().decode("utf-8", "replace")
    seconds = time.perf_counter() - tic
    peak = usage.ru_maxrss * 1024 if usage else 0
    lines = [line for line in text.splitlines() if line.startswith("error:")]
    if status is None:
        return Outcome("hang", f"no exit within {timeout:g} s", seconds, peak)
    if status < 0:
        return Outcome("crash", f"signal {-status}: {text.strip()[-200:]}", seconds, peak)
    if status == 0:
        return Outcome("valid", "", seconds, peak)
    if status in CLEAN_STATUSES and len(lines) == 1 and "Traceback" not in text:
        return Outcome("error", f"exit {status}: {lines[0][:300]}", seconds, peak)
    return Outcome("internal", f"exit {status}: {text.strip()[-300:]}", seconds, peak)


def _wait(child: subprocess.Popen, timeout: float) -> tuple[int | None, Any]:
    """The child's exit status (negative: a signal; None: killed after ``timeout``) and rusage."""
    deadline = time.monotonic() + timeout
    while True:
        pid, status, usage = os.wait4(child.pid, os.WNOHANG)
        if pid:
            child.returncode = os.waitstatus_to_exitcode(status)
            return child.returncode, usage
        if time.monotonic() > deadline:
            child.kill()
            _, _, usage = os.wait4(child.pid, 0)
            child.returncode = -9
            return None, usage
        time.sleep(0.005)
