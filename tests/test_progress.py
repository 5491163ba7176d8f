"""Progress bars in logs (plain periodic lines) and the kernel-cache notice."""

import io
import os
import re
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


def test_the_groups_list_exactly_the_modules_with_cached_kernels():
    """A module with ``cache=True`` kernels outside GROUPS is neither reported nor compiled up front; a
    listed module without any would always read "not compiled yet"."""
    listed = {module for modules in kernels.GROUPS.values() for module in modules}
    with_kernels = {path.relative_to(kernels.PACKAGE).as_posix() for path in kernels.PACKAGE.rglob("*.py")
                    if re.search(r"^@numba\.njit\(cache=True", path.read_text(encoding="utf-8"), re.MULTILINE)}
    assert with_kernels == listed


_CHECK_COMPILED = """
import importlib, sys
import numba
from gscodec_shac import kernels
kernels.compile_all(progress=False)
missing = []
for group in ("codec", "render"):
    for module in kernels.GROUPS[group]:
        loaded = importlib.import_module("gscodec_shac." + module[:-3].replace("/", "."))
        dispatchers = {name: value for name, value in vars(loaded).items()
                       if isinstance(value, numba.core.registry.CPUDispatcher)}
        # helpers called only from other kernels are compiled into them, not dispatched themselves
        helpers = {name for value in dispatchers.values() for name in value.py_func.__code__.co_names}
        missing += [module + ":" + name for name, value in dispatchers.items()
                    if name not in helpers and not value.signatures]
print(" ".join(missing))
"""


def test_the_warm_up_compiles_every_codec_and_render_kernel():
    """``python -m gscodec_shac.kernels --compile`` (run by the install) reaches every kernel of the
    commands that encode and render: none is left to compile during a user's first large encode."""
    done = subprocess.run([sys.executable, "-c", _CHECK_COMPILED], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == ""
