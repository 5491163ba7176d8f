"""Atomic file output: the new content appears under its name whole, or not at all.

Every writer of user-facing outputs (PLY, ``.gsc``, cameras, PNGs, checkpoints, sweep
results, reports) goes through :func:`atomic_output`, which guarantees, in one place:

* **all or nothing**: a reader sees the old file or the whole new one. The data goes to
  an unnamed file in the target folder (Linux ``O_TMPFILE``) that is linked under the
  target name when the block ends, so an exception, Ctrl-C, SIGTERM or even SIGKILL
  while writing leaves no temporary file. Replacing an existing file links the data
  under a hidden ``.NAME.*.tmp`` name and renames it over the target, two system calls
  apart. Where ``O_TMPFILE`` is missing, a named temporary file is written and removed
  on any error.
* **the umask**: new files get mode ``0666 & ~umask`` (0644 with the usual umask 022).
* **inputs stay intact**: a file registered with :func:`protect_inputs` is never written
  over, whatever the path that names it (links included), ``--force`` or not.
* **clear errors**: an output path that is a directory, or in a missing folder, raises
  the caller's error type naming it.

Commands call :func:`check_output` before the work starts, so an existing output is
refused (unless ``--force``) before minutes of encoding rather than after.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import secrets
import stat
import threading
from pathlib import Path
from typing import Any, BinaryIO, Iterable, Iterator

import numpy as np

from gscodec_shac.errors import GscodecError, OutputError

#: Files this process reads and must never write over (see :func:`protect_inputs`).
_PROTECTED: dict[tuple[int, int], str] = {}
#: The most files of one input folder registered (a model folder holds a handful).
_MAX_MEMBERS = 10_000
_UMASK_LOCK = threading.Lock()
#: OS errors of writing a file that are the environment's, not a bug: reported as one line.
_WRITE_ERRORS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO}


def protect_inputs(*paths: str | os.PathLike | None) -> None:
    """Register input files: no atomic output of this process may replace them.

    A multi-file input is every file it reads: a folder registers the files inside it (a SOG
    folder's images, a dynamic model's members), a JSON file the files beside it that it names
    (a SOG ``meta.json``'s images).
    """
    for path in paths:
        if path is None:
            continue
        try:
            info = os.stat(path)
        except OSError:
            continue
        _PROTECTED[(info.st_dev, info.st_ino)] = str(path)
        for member in _members(Path(path), info):
            try:
                member_info = os.stat(member)
            except OSError:
                continue
            _PROTECTED.setdefault((member_info.st_dev, member_info.st_ino), str(member))


def _members(path: Path, info: os.stat_result) -> list[Path]:
    """The files a folder input holds, or that a JSON input (a SOG ``meta.json``) names beside it."""
    if stat.S_ISDIR(info.st_mode):
        try:
            return [entry for entry in path.iterdir() if entry.is_file()][:_MAX_MEMBERS]
        except OSError:
            return []
    if path.suffix.lower() == ".json" and stat.S_ISREG(info.st_mode):
        from gscodec_shac.io.bounded import MAX_MODEL_JSON_BYTES, load_json, member_path, read_file

        try:
            document = load_json(read_file(path, MAX_MODEL_JSON_BYTES, "JSON"), str(path))
        except GscodecError:
            return []
        out = []
        for name in _strings(document):
            try:
                out.append(member_path(path.parent, name, str(path)))
            except GscodecError:
                continue
        return out[:_MAX_MEMBERS]
    return []


def _strings(value: Any) -> Iterator[str]:
    """Every string leaf of a parsed JSON document."""
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, str):
            yield item
        elif isinstance(item, dict):
            stack.extend(item.values())
        elif isinstance(item, list):
            stack.extend(item)


@contextlib.contextmanager
def inputs_protected(*paths: str | os.PathLike | None) -> Iterator[None]:
    """:func:`protect_inputs` for the duration of a block (library calls such as ``encode_file``)."""
    before = dict(_PROTECTED)
    protect_inputs(*paths)
    try:
        yield
    finally:
        _PROTECTED.clear()
        _PROTECTED.update(before)


def release_inputs() -> None:
    """Forget every registered input (the CLI does this after each command)."""
    _PROTECTED.clear()


def check_output(path: str | os.PathLike, *, force: bool = False, inputs: Iterable[str | os.PathLike | None] = (),
                 what: str = "output") -> Path:
    """Refuse an output path before the work: a directory, an input (even with ``force``),
    or an existing file unless ``force``. Registers ``inputs`` with :func:`protect_inputs`."""
    path = Path(path)
    protect_inputs(*inputs)
    if path.is_dir():
        raise OutputError(f"{path}: the {what} path is a directory; give a file name")
    _refuse_input(path, OutputError)
    if _occupied(path) and not force:
        raise OutputError(f"{path}: the {what} exists; pass --force to replace it")
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise OutputError(f"{path}: output directory {directory} does not exist")
    return path


def check_outputs(paths: Iterable[str | os.PathLike], *, force: bool = False, what: str = "output") -> None:
    """:func:`check_output` for several files a command writes into one folder (created later)."""
    for path in paths:
        path = Path(path)
        if path.is_dir():
            raise OutputError(f"{path}: the {what} path is a directory")
        _refuse_input(path, OutputError)
        if _occupied(path) and not force:
            raise OutputError(f"{path}: the {what} exists; pass --force to replace it")


@contextlib.contextmanager
def atomic_output(
    path: str | os.PathLike, *, error: type[Exception] = GscodecError, make_dirs: bool = False, fsync: bool = False
) -> Iterator[BinaryIO]:
    """A binary handle whose content replaces ``path`` when the block ends without error.

    A missing output folder raises ``error`` naming it, unless ``make_dirs`` creates it;
    ``fsync`` flushes the data to disk before the rename (for caches shared by processes).
    """
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    if make_dirs:
        directory.mkdir(parents=True, exist_ok=True)
    elif not directory.is_dir():
        raise error(f"{path}: output directory {directory} does not exist")
    if path.is_dir():
        raise error(f"{path}: is a directory, cannot write a file there")
    _refuse_input(path, error)
    try:
        fd = _unnamed_file(directory)
        if fd is None:
            with _named_output(path, directory, fsync) as handle:
                yield handle
            return
        with os.fdopen(fd, "wb") as handle:
            yield handle
            handle.flush()
            if fsync:
                os.fsync(handle.fileno())
            _refuse_input(path, error)
            _link_into_place(handle.fileno(), path, directory)
    except OSError as exc:
        if exc.errno in _WRITE_ERRORS:
            raise error(f"{path}: cannot write the file ({exc.strerror})") from None
        raise


def write_atomic(path: str | os.PathLike, data: bytes | str, **options: Any) -> Path:
    """Write ``data`` (text as UTF-8) to ``path`` atomically; ``options`` as for :func:`atomic_output`."""
    with atomic_output(path, **options) as handle:
        handle.write(data.encode("utf-8") if isinstance(data, str) else data)
    return Path(path)


def write_json(path: str | os.PathLike, value: Any, **options: Any) -> Path:
    """``value`` as indented JSON (numpy scalars and arrays, paths allowed), written atomically."""
    return write_atomic(path, json.dumps(value, indent=1, default=_json_default) + "\n", **options)


def write_npz(path: str | os.PathLike, arrays: dict[str, np.ndarray], **options: Any) -> Path:
    """``np.savez`` of ``arrays``, written atomically."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return write_atomic(path, buffer.getvalue(), **options)


def umask() -> int:
    """The process umask, read without changing it where the system allows."""
    try:
        with open("/proc/self/status") as handle:
            for line in handle:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _UMASK_LOCK:  # os.umask can only be read by setting it
        value = os.umask(0o022)
        os.umask(value)
    return value


# ------------------------------------------------------------------ internals
def _occupied(path: Path) -> bool:
    """Whether something is at ``path``: a file, or a symlink (even one whose target is missing)."""
    return path.exists() or path.is_symlink()


def _refuse_input(path: Path, error: type[Exception]) -> None:
    try:
        info = os.stat(path)
    except OSError:
        return
    source = _PROTECTED.get((info.st_dev, info.st_ino))
    if source is not None:
        raise error(f"{path}: is the input {source}; refusing to write over an input (even with --force)")


def _unnamed_file(directory: Path) -> int | None:
    """An ``O_TMPFILE`` descriptor in ``directory`` (mode 0666 minus the umask), or None where unsupported."""
    flag = getattr(os, "O_TMPFILE", None)
    if flag is None or not os.path.isdir("/proc/self/fd"):
        return None
    try:
        return os.open(directory, flag | os.O_WRONLY | getattr(os, "O_CLOEXEC", 0), 0o666)
    except OSError as exc:
        if exc.errno in (errno.EOPNOTSUPP, errno.EISDIR, errno.EINVAL, errno.ENOENT):
            return None
        raise


def _link_into_place(fd: int, path: Path, directory: Path) -> None:
    """Give the unnamed file ``fd`` the name ``path`` (replacing what is there)."""
    proc = os.open("/proc/self/fd", os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        # linkat(AT_SYMLINK_FOLLOW) through /proc names an O_TMPFILE file (a dir fd makes
        # os.link use linkat rather than link, which would not follow the magic link).
        try:
            os.link(str(fd), path, src_dir_fd=proc, follow_symlinks=True)  # nothing there: one atomic step
            return
        except FileExistsError:
            pass
        tmp = directory / f".{path.name}.{secrets.token_hex(4)}.tmp"
        try:
            os.link(str(fd), tmp, src_dir_fd=proc, follow_symlinks=True)
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise
    finally:
        os.close(proc)


@contextlib.contextmanager
def _named_output(path: Path, directory: Path, fsync: bool) -> Iterator[BinaryIO]:
    """The portable fallback: a named temporary file, removed on any error."""
    import tempfile

    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        os.fchmod(fd, 0o666 & ~umask())
        with os.fdopen(fd, "wb") as handle:
            yield handle
            if fsync:
                handle.flush()
                os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")
