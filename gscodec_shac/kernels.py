"""The numba kernels' on-disk cache: where it lives, whether a run will compile, and a warm-up.

Every kernel is ``@numba.njit(cache=True)``, so numba compiles it once per machine and
Python/numba version and stores it beside its source (``<package>/__pycache__``) or, when
that folder is not writable (a system-wide install), in the user cache
(``~/.cache/numba``); ``$NUMBA_CACHE_DIR`` overrides both. Every later run loads it.

:func:`announce` prints one line ("compiling kernels once (about a minute)") when a command
actually starts compiling (numba's ``numba:compile`` event, which a cache hit does not fire).
``python -m gscodec_shac.kernels`` prints the cache state (a module counts as compiled when
its cache folder holds an index file ``<module>.*.nbi`` at least as new as its source), and with
``--compile`` compiles the renderer's kernels and the codec's (a small encode and decode),
e.g. right after installing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Iterable, TextIO

PACKAGE = Path(__file__).resolve().parent
#: Modules with ``cache=True`` kernels, by the part of the program that uses them.
GROUPS: dict[str, tuple[str, ...]] = {
    "codec": ("codec/gap_packing.py",),
    "render": ("render/projection.py", "render/binning.py", "render/key_sort.py", "render/shading.py",
               "render/raster.py", "render/moved.py"),
    "train": ("render/backward.py", "train/model.py", "train/fastloss.py", "train/colour_path.py"),
}
#: Kernel groups each command compiles on first use (commands not listed compile none; ``decode``
#: runs no kernel, and registering the notice would import numba, ~0.14 s of its start-up).
COMMANDS: dict[str, tuple[str, ...]] = {
    "encode": ("codec", "render"), "render": ("render",), "demo": ("codec", "render"),
    "rd": ("codec", "render"), "rate-points": ("codec", "render"), "train": ("render", "train"),
    "train-dynamic": ("render", "train"), "lst-finetune": ("render", "train"),
    "tune-network": ("render", "train"),
}
NOTICE = "compiling kernels once (about a minute); later runs load them from numba's cache"


def _probe() -> None:
    """A stand-in function: numba's cache locators want one to name a cache folder."""


def cache_dir(source: Path) -> Path | None:
    """The folder numba caches ``source``'s kernels in (numba's own locator order), or None."""
    try:
        from numba.core.caching import CacheImpl
    except ImportError:  # numba missing or reorganised: no notice rather than a failure
        return None
    for locator in CacheImpl._locator_classes:
        try:
            found = locator.from_function(_probe, str(source))
        except Exception:  # noqa: BLE001 - a locator that does not apply
            continue
        if found is not None:
            return Path(found.get_cache_path())
    return None


def is_cached(module: str) -> bool:
    """True when ``module`` (a path under the package) has a kernel index newer than its source."""
    source = PACKAGE / module
    folder = cache_dir(source)
    if folder is None or not source.is_file():
        return False
    newest = source.stat().st_mtime
    return any(index.stat().st_mtime >= newest for index in folder.glob(f"{source.stem}.*.nbi"))


def uncached(groups: Iterable[str]) -> list[str]:
    """The modules of ``groups`` whose kernels a run would compile."""
    return [module for group in groups for module in GROUPS[group] if not is_cached(module)]


_announced: list[TextIO] = []  # the stream a notice listener prints to, once per process


def announce(command: str | None, stream: TextIO | None = None) -> bool:
    """Arrange for :data:`NOTICE` to print once, when ``command`` actually starts compiling a kernel.

    A listener on numba's ``numba:compile`` event, which fires only on a cache miss (loading a
    cached kernel does not compile), so the line appears exactly when a compile happens and
    never for a run that fails before reaching a kernel. Returns whether a listener was registered.
    """
    if command not in COMMANDS or _announced:
        return False
    try:
        from numba.core import event
    except ImportError:
        return False
    _announced.append(stream or sys.stderr)

    class _FirstCompile(event.Listener):
        def on_start(self, _event: object) -> None:
            if _announced and _announced[0] is not None:
                print(NOTICE, file=_announced[0], flush=True)
                _announced[0] = None  # type: ignore[call-overload]

        def on_end(self, _event: object) -> None:
            pass

    event.register("numba:compile", _FirstCompile())
    return True


def compile_all(progress: bool = True) -> None:
    """Compile (or load) the renderer's and the codec's kernels: a warm-up render, a small encode and decode."""
    from gscodec_shac.codec import Decoder, Encoder
    from gscodec_shac.render.kernel_warmup import warmup
    from gscodec_shac.synthetic import make_synthetic_scene

    warmup()
    cloud = make_synthetic_scene(1_000, seed=0, n_cameras=1, width=16, height=16, progress=False).cloud
    stream = Encoder("shac_ladder:rp1", sh_stage="pca", progress=progress).encode(cloud)
    Decoder().decode(stream)


def _compile_with_notice() -> None:
    if uncached(("codec", "render")):
        print(NOTICE, file=sys.stderr, flush=True)
    compile_all(progress=sys.stderr.isatty())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m gscodec_shac.kernels", description=__doc__.split("\n")[0])
    parser.add_argument("--compile", action="store_true", help="compile the codec's and the renderer's kernels now")
    args = parser.parse_args(argv)
    if args.compile:
        from gscodec_shac.progress import plain_progress_lines

        with plain_progress_lines():
            _compile_with_notice()
    for group, modules in GROUPS.items():
        for module in modules:
            state = "cached" if is_cached(module) else "not compiled yet"
            print(f"{group:<7}{module:<24}{state:<18}{cache_dir(PACKAGE / module)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
