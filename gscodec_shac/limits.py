"""Limits that keep untrusted input (``.gsc`` files, PLYs, YAML, camera files) bounded.

Every reader checks its input against these before it allocates or recurses, and
refuses what exceeds them with one error naming the limit (docs/reliability.md lists
them all). Memory: :func:`memory_budget` is what one process may use; the decoder
compares its estimate of a stream's peak memory with it before the first allocation.
"""

from __future__ import annotations

import os
import re

#: The largest ``.gsc`` JSON header read (a real one is 4-20 KiB).
MAX_HEADER_BYTES = 1 << 20
#: The deepest nesting of lists/objects in a JSON header or a YAML file (real ones: 6).
MAX_NESTING = 64
#: The largest camera JSON file read (cameras.json, transforms*.json: KiB to a few MiB).
MAX_JSON_BYTES = 64 << 20
#: The largest YAML document read (rate points, sweeps: a few KiB).
MAX_YAML_BYTES = 4 << 20
#: YAML aliases (``*name``) per document: enough for shared defaults, not for an alias bomb.
MAX_YAML_ALIASES = 256
#: The most Gaussians a stream may declare (64 Mi; real scenes hold 0.1-10 M).
MAX_GAUSSIANS = 1 << 26
#: The largest image side and pixel count a camera may ask for (renders, fine-tuning targets).
MAX_IMAGE_SIDE = 16384
MAX_IMAGE_PIXELS = 1 << 26
#: Bytes the CPU renderer needs per pixel (float64 colour, transmittance, depth, the float32
#: image and alpha, tile tables); renders larger than the memory budget are refused.
RENDER_BYTES_PER_PIXEL = 128
#: Environment variable that caps the memory budget (bytes, or with a K/M/G/T suffix).
MEMORY_ENV = "GSCODEC_MAX_MEMORY"

_SIZE = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*([kmgt]?)(i?)(b|bytes?)?\s*$", re.IGNORECASE)


def json_nesting(data: bytes) -> int:
    """The deepest ``[``/``{`` nesting of JSON text, counted in linear time without parsing
    it (brackets inside strings are skipped), so deep input never reaches a recursive parser."""
    import numpy as np

    text = np.frombuffer(data, dtype=np.uint8)
    if text.size == 0:
        return 0
    index = np.arange(text.size)
    backslash = text == ord("\\")
    # A quote is escaped when an odd number of backslashes precede it.
    last_other = np.maximum.accumulate(np.where(backslash, -1, index))
    run_before = np.empty(text.size, dtype=np.int64)
    run_before[0] = 0
    run_before[1:] = index[:-1] - last_other[:-1]
    quote = (text == ord('"')) & (run_before % 2 == 0)
    outside = np.cumsum(quote) % 2 == 0  # a closing quote counts as outside, an opening one as inside
    steps = (np.isin(text, (ord("["), ord("{"))).astype(np.int32) - np.isin(text, (ord("]"), ord("}"))).astype(np.int32))
    return int(np.cumsum(np.where(outside & ~quote, steps, 0)).max(initial=0))


def parse_size(text: str) -> int:
    """A size in bytes: ``"1200000"``, ``"800kB"``, ``"2.5MB"`` (powers of 1000), ``"3MiB"`` or the
    memory-style ``"512M"``, ``"4G"`` (powers of 1024); ValueError for anything else or a size <= 0."""
    match = _SIZE.match(str(text))
    if not match:
        raise ValueError(f"{text!r} is not a size such as 2.5MB, 800kB, 3MiB, 512M or 4G")
    number, prefix, binary, unit = match.groups()
    power = " kmgt".index(prefix.lower() or " ")
    base = 1000 if unit and not binary and prefix else 1024
    value = int(float(number) * base**power)
    if value <= 0:
        raise ValueError(f"{text!r} is not a positive size")
    return value


def memory_budget() -> int:
    """Bytes this process may still allocate: the smallest of physical memory, the cgroup
    limit, the address-space rlimit (minus what is mapped already) and ``$GSCODEC_MAX_MEMORY``."""
    candidates = [_physical_memory()]
    candidates.append(_cgroup_limit())
    candidates.append(_address_space_left())
    override = os.environ.get(MEMORY_ENV)
    if override:
        try:
            candidates.append(parse_size(override))
        except ValueError as exc:
            from gscodec_shac.errors import GscodecError

            raise GscodecError(f"${MEMORY_ENV}: {exc}") from None
    return min(c for c in candidates if c is not None)


def format_bytes(count: float) -> str:
    """``1536`` -> ``"1.5 KiB"`` (for messages)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(count) < 1024 or unit == "TiB":
            return f"{count:.0f} {unit}" if unit == "B" else f"{count:.1f} {unit}"
        count /= 1024
    return f"{count:.1f} TiB"  # pragma: no cover


def _physical_memory() -> int:
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        return 1 << 40


def _cgroup_limit() -> int | None:
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(path) as handle:
                value = handle.read().strip()
        except OSError:
            continue
        if value.isdigit() and int(value) < 1 << 60:
            return int(value)
    return None


def _address_space_left() -> int | None:
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (ImportError, ValueError, OSError):  # pragma: no cover - not POSIX
        return None
    if soft == resource.RLIM_INFINITY:
        return None
    return max(0, soft - _mapped_bytes())


def _mapped_bytes() -> int:
    try:
        with open("/proc/self/statm") as handle:
            return int(handle.read().split()[0]) * int(os.sysconf("SC_PAGE_SIZE"))
    except (OSError, ValueError, IndexError):
        return 0


def check_render_memory(width: int, height: int, what: str) -> None:
    """Refuse a render whose per-pixel buffers would not fit in :func:`memory_budget`."""
    from gscodec_shac.errors import MemoryLimitError

    need, budget = RENDER_BYTES_PER_PIXEL * width * height, memory_budget()
    if need > budget:
        raise MemoryLimitError(f"{what}: a {width}x{height} render needs about {format_bytes(need)}, more than the "
                               f"{format_bytes(budget)} this process may use (${MEMORY_ENV} and system limits)")


def image_file_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """(width, height) from an image file's header, without decoding it; None if unreadable."""
    try:
        from PIL import Image

        with Image.open(path) as image:
            return int(image.size[0]), int(image.size[1])
    except Exception:  # noqa: BLE001 - Pillow raises many types for foreign files; the caller decodes
        return None


def check_image_file(path: str | os.PathLike, error: type[Exception]) -> None:
    """Refuse, before decoding, an image file larger than the image limits (a decompression bomb)."""
    size = image_file_size(path)
    if size is not None and (max(size) > MAX_IMAGE_SIDE or size[0] * size[1] > MAX_IMAGE_PIXELS):
        raise error(f"{path}: a {size[0]}x{size[1]} image exceeds the maximum ({MAX_IMAGE_SIDE:,} pixels a side, "
                    f"{MAX_IMAGE_PIXELS:,} pixels in all)")


def default_workers() -> int:
    """Grid-codec calls run in this many threads (x265, PNG and FFmpeg release the GIL)."""
    return max(1, min(8, os.cpu_count() or 1))
