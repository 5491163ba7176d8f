"""One fuzz case through the command line: ``gscodec-shac ARGS`` in a child process, classified.

Exit status 0 is ``valid``; 2, 3 or 5 with exactly one ``error:`` line and no traceback is a
clean ``error``; any other status (70: "this is a bug") is ``internal``; a signal is a
``crash``; more than the time limit of CPU time (or six times it of wall time, when the child
is killed) a ``hang``, so that a loaded machine does not make hangs. The child's peak resident
set is its own ``VmHWM``, which it writes at exit (``wait4``'s ``ru_maxrss`` would include the
parent's at the fork); ``$GSCODEC_MAX_MEMORY`` sets its memory budget.
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
#: Runs the CLI as ``python -m gscodec_shac`` does and writes the process's VmHWM (KiB) at exit.
_BOOTSTRAP = """
import atexit, os, runpy, sys
def _peak():
    with open("/proc/self/status") as status:
        kib = [line.split()[1] for line in status if line.startswith("VmHWM")]
    with open(os.environ["GSCODEC_FUZZ_PEAK"], "w") as out:
        out.write(kib[0] if kib else "0")
atexit.register(_peak)
sys.argv[0] = "gscodec-shac"
runpy.run_module("gscodec_shac", run_name="__main__", alter_sys=True)
"""


def run(args: list[str], cwd: Path, *, timeout: float = 20.0, memory: str = "2G") -> Outcome:
    """Run ``python -m gscodec_shac ARGS`` in ``cwd`` and classify its outcome."""
    peak_file = cwd / ".peak"
    env = dict(os.environ, GSCODEC_MAX_MEMORY=memory, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1",
               GSCODEC_FUZZ_PEAK=str(peak_file))
    tic = time.perf_counter()
    with open(cwd / ".stderr", "w+b") as err:
        child = subprocess.Popen([sys.executable, "-c", _BOOTSTRAP, *args], cwd=cwd, env=env,
                                 stdout=subprocess.DEVNULL, stderr=err, stdin=subprocess.DEVNULL)
        status, usage = _wait(child, 6 * timeout)
        err.seek(0)
        text = err.read().decode("utf-8", "replace")
    seconds = time.perf_counter() - tic
    cpu = usage.ru_utime + usage.ru_stime if usage else 0.0
    try:
        peak = int(peak_file.read_text() or 0) * 1024
    except (OSError, ValueError):
        peak = 0
    lines = [line for line in text.splitlines() if line.startswith("error:")]
    if status is None or cpu > timeout:
        return Outcome("hang", f"{cpu:.1f} s of CPU, {seconds:.1f} s of wall time", seconds, peak)
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
