"""Progress bars in logs (plain periodic lines) and the kernel-cache notice."""

import io
import os
import subprocess
import sys

from tqdm import tqdm

from gscodec_shac import kernels
from gscodec_shac.progress import PlainProgressStream
from tests.conftest import REPO_ROOT


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_redraws_become_throttled_lines_and_the_final_state_is_kept():
    out, clock = io.StringIO(), Clock()
    stream = PlainProgressStream(out, interval=30.0, clock=clock)
    bar = tqdm(total=100, desc="encode", file=stream, mininterval=0, miniters=1, ncols=60)
    for step in range(100):
        clock.now = step  # one second per step: lines at 30, 60 and 90 s and the final state
        bar.update(1)
    bar.close()
    print("encoded", file=stream)
    lines = out.getvalue().split("\n")
    assert "\r" not in out.getvalue()
    progress = [line for line in lines if line.startswith("encode:")]
    assert [line.split("|")[0].split(":")[1].strip() for line in progress] == ["31%", "61%", "91%", "100%"]
    assert lines[-2:] == ["encoded", ""]  # ordinary output unchanged, no blank line after the final state


def test_short_bars_leave_nothing_and_plain_text_passes_through():
    out = io.StringIO()
    stream = PlainProgressStream(out, interval=30.0, clock=Clock())
    stream.write("warning: one\n")
    for leave in (True, False):  # shorter than the interval: no line, kept or erased
        bar = tqdm(total=3, desc="render", file=stream, leave=leave, mininterval=0, miniters=1)
        bar.update(3)
        bar.close()
    bar = tqdm(total=3, desc="sorting", file=stream, mininterval=0, miniters=1)
    bar.update(1)
    stream.write("error: stopped half way\n")  # an error during a bar: the bar's state is dropped
    assert out.getvalue().splitlines() == ["warning: one", "error: stopped half way"]


def test_cli_writes_plain_progress_lines_to_a_log(tmp_path):
    """A real command with stderr redirected to a file: no carriage returns, one line per state."""
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "GSCODEC_PROGRESS_INTERVAL": "0"}
    with open(tmp_path / "log", "w") as log:
        subprocess.run([sys.executable, "-m", "gscodec_shac", "synthetic", str(tmp_path / "s.ply"), "-n", "2000",
                        "--views", "2"], stderr=log, stdout=subprocess.DEVNULL, env=env, check=True, timeout=300)
    text = (tmp_path / "log").read_text()
    assert "\r" not in text
    assert any(line.startswith("synthetic scene:") for line in text.splitlines()), text


def test_kernel_cache_state_follows_numba_index_files(tmp_path, monkeypatch):
    source = tmp_path / "codec" / "quantize.py"
    source.parent.mkdir()
    source.write_text("# kernels\n")
    monkeypatch.setattr(kernels, "PACKAGE", tmp_path)
    monkeypatch.setitem(kernels.GROUPS, "codec", ("codec/quantize.py",))
    folder = kernels.cache_dir(source)
    assert folder is not None and folder.is_dir()
    assert kernels.uncached(["codec"]) == ["codec/quantize.py"]
    index = folder / "quantize.kernel-12.py312.nbi"
    index.write_bytes(b"")
    os.utime(index, (source.stat().st_mtime + 1,) * 2)
    assert kernels.uncached(["codec"]) == []
    os.utime(source, (index.stat().st_mtime + 1,) * 2)  # source edited after the cache: numba recompiles
    assert kernels.uncached(["codec"]) == ["codec/quantize.py"]


def test_the_notice_prints_once_when_a_kernel_compiles(monkeypatch):
    import numba

    monkeypatch.setattr(kernels, "_announced", [])
    out = io.StringIO()
    assert kernels.announce("info", out) is False  # a command without kernels: no listener
    assert kernels.announce("encode", out) is True
    assert out.getvalue() == ""  # nothing compiled yet

    @numba.njit  # not cached: this call compiles
    def twice(x):
        return 2 * x

    @numba.njit
    def thrice(x):
        return 3 * x

    assert twice(2) == 4 and thrice(2) == 6 and twice(3) == 6
    assert out.getvalue() == kernels.NOTICE + "\n"
