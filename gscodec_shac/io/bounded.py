"""Bounded reading of the containers untrusted model files come in: zip/npz, JSON, images, deflate.

Every reader of a model format opens its input through these helpers, so that the same
hostile input meets the same checks everywhere (docs/reliability.md, "Model files"):

* :func:`read_file` reads a regular file of at most a given size, and :func:`member_path`
  names a file inside an input folder (no absolute path, no ``..``, no symlink leading out);
* :func:`load_json` parses JSON of bounded size and nesting (counted before parsing, so no
  ``RecursionError``) and refuses integers beyond 2^63 and numbers beyond float64 by name;
* :class:`BoundedZip` opens a zip (``.sog``, ``.npz``) after checking its member count,
  member names (no ``..``, no absolute path, no repeats), compression methods (stored or
  deflated), encryption and the declared sizes against a cap; a member is read through a
  stream that never yields more than its declared size and whose CRC is checked;
* :func:`read_npz` reads ``.npy`` members whose dtype and shape are checked against the
  member's size before anything is allocated;
* :func:`image_size` takes the dimensions from a PNG or WebP header, so that
  :func:`decode_rgba` refuses an image larger than its caller allows before decoding;
* :class:`Inflater` inflates a zlib/gzip stream in pieces of known size and refuses at
  the first byte past what the header said.

Each failure is one :class:`~gscodec_shac.errors.ModelFormatError` (or a
:class:`~gscodec_shac.errors.MemoryLimitError`) naming the file, the member and the field.
"""

from __future__ import annotations

import io
import json
import math
import os
import stat
import struct
import tokenize
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from gscodec_shac.errors import GscodecError, MemoryLimitError, ModelFormatError
from gscodec_shac.limits import MAX_NESTING, MEMORY_ENV, format_bytes, json_nesting, memory_budget

#: The largest JSON document of a model (a SOG ``meta.json`` is ~20 KiB, ``deformation.json`` < 1 KiB).
MAX_MODEL_JSON_BYTES = 1 << 20
#: The most members a model zip may hold (a SOG bundle: 7; a weights ``.npz``: 2 per layer).
MAX_ZIP_MEMBERS = 256
#: Zip compression methods a reader accepts: stored and deflated (what every writer uses).
ZIP_METHODS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflated"}
#: Deflate expands at most 1032:1 (zlib, gzip and zip framing included).
DEFLATE_MAX_RATIO = 1032
#: The largest integer a model document may hold (int64).
MAX_JSON_INT = 1 << 63
#: dtype kinds an ``.npy`` member may hold: bool, signed/unsigned integers, floats.
NPY_KINDS = "biuf"
#: A model read holds at most this many float32 copies of the decoded cloud at its peak.
READ_COPIES = 6
_READ_BLOCK = 1 << 20


# ------------------------------------------------------------------ files
def member_path(folder: str | os.PathLike, name: str, where: str, error: type[GscodecError] = ModelFormatError) -> Path:
    """``folder / name`` for a file an input folder names; refused when ``name`` is absolute,
    climbs out with ``..``, or resolves (through a symlink) outside ``folder``."""
    folder = Path(folder)
    parts = Path(name.replace("\\", "/")).parts
    if not name or Path(name).is_absolute() or ".." in parts:
        raise error(f"{where}: names {name!r}, which is not a file inside {folder}")
    path = folder / name
    try:
        inside = path.resolve().is_relative_to(folder.resolve())
    except (OSError, RuntimeError):  # a symlink loop
        inside = False
    if not inside:
        raise error(f"{where}: {name} is a symlink that leaves {folder}; refusing to follow it")
    return path


def read_file(path: str | os.PathLike, limit: int, what: str, error: type[GscodecError] = ModelFormatError) -> bytes:
    """The bytes of the regular file ``path``, at most ``limit`` of them."""
    path = Path(path)
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise error(f"{path}: no such {what} file") from None
    except OSError as exc:
        raise error(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if not stat.S_ISREG(info.st_mode):
        raise error(f"{path}: is not a regular file, expected a {what} file")
    if info.st_size > limit:
        raise error(f"{path}: the {what} file is larger than {format_bytes(limit)}, the most this reader accepts")
    try:
        with open(path, "rb") as handle:
            data = handle.read(info.st_size + 1)  # a file that grew meanwhile shows as one byte too many
    except OSError as exc:
        raise error(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if len(data) > limit:
        raise error(f"{path}: the {what} file is larger than {format_bytes(limit)}, the most this reader accepts")
    return data


def check_memory(where: str, need: int, what: str) -> None:
    """Refuse, before allocating, a read that needs more than :func:`memory_budget`."""
    budget = memory_budget()
    if need > budget:
        raise MemoryLimitError(f"{where}: {what} needs about {format_bytes(need)}, more than the "
                               f"{format_bytes(budget)} this process may use (${MEMORY_ENV} and system limits)")


def cloud_bytes(n: int, sh_degree: int) -> int:
    """Bytes of a decoded cloud's float32 arrays: 14 values and 3 per AC coefficient per Gaussian."""
    return 4 * n * (14 + 3 * ((sh_degree + 1) ** 2 - 1))


# ------------------------------------------------------------------ JSON
class _JsonNumberError(ValueError):
    """A JSON number a model document may not hold."""


def _parse_int(text: str) -> int:
    if len(text.lstrip("-")) > 19 or abs(int(text)) >= MAX_JSON_INT:
        raise _JsonNumberError(f"the integer {_clip(text)} is beyond 2^63")
    return int(text)


def _parse_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise _JsonNumberError(f"the number {_clip(text)} is beyond float64")
    return value


def _parse_constant(name: str) -> Any:
    raise _JsonNumberError(f"{name} is not a number a model file may hold")


def _clip(text: str) -> str:
    return text if len(text) <= 24 else f"{text[:12]}...{text[-6:]} ({len(text)} characters)"


def load_json(raw: bytes, where: str, *, limit: int = MAX_MODEL_JSON_BYTES,
              error: type[GscodecError] = ModelFormatError) -> Any:
    """Parse a JSON document of at most ``limit`` bytes and :data:`MAX_NESTING` levels."""
    if len(raw) > limit:
        raise error(f"{where}: the JSON document is {format_bytes(len(raw))}, more than {format_bytes(limit)}")
    depth = json_nesting(raw)
    if depth > MAX_NESTING:
        raise error(f"{where}: the JSON document nests {depth} levels deep (at most {MAX_NESTING})")
    try:
        return json.loads(raw.decode("utf-8"), parse_int=_parse_int, parse_float=_parse_float,
                          parse_constant=_parse_constant)
    except _JsonNumberError as exc:
        raise error(f"{where}: {exc}") from None
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise error(f"{where}: invalid JSON ({str(exc)[:200]})") from None


# ------------------------------------------------------------------ zip
class BoundedZip:
    """A zip file whose directory was checked (see the module docstring); use as a context manager.

    ``max_total``: the most bytes all members may inflate to (default: what deflate can make of
    the file, and the memory budget).
    """

    def __init__(self, path: str | os.PathLike, *, max_members: int = MAX_ZIP_MEMBERS, max_total: int | None = None,
                 error: type[GscodecError] = ModelFormatError) -> None:
        self.path, self.error = Path(path), error
        try:
            size = self.path.stat().st_size
            self._zip = zipfile.ZipFile(self.path)
            infos = self._zip.infolist()
        except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError, NotImplementedError) as exc:
            raise error(f"{self.path}: corrupt zip file ({str(exc)[:200]})") from None
        try:
            self.members = self._check(infos, size, max_members, max_total)
        except BaseException:
            self._zip.close()
            raise

    def _check(self, infos: list[zipfile.ZipInfo], size: int, max_members: int,
               max_total: int | None) -> dict[str, zipfile.ZipInfo]:
        if len(infos) > max_members:
            raise self.error(f"{self.path}: the zip holds {len(infos):,} members (at most {max_members})")
        members: dict[str, zipfile.ZipInfo] = {}
        for info in infos:
            name = info.filename
            where = f"{self.path}: member {name!r}"
            parts = name.replace("\\", "/").split("/")
            if not name or name.startswith(("/", "\\")) or ".." in parts or (len(name) > 1 and name[1] == ":"):
                raise self.error(f"{where}: a member name must be a relative path without '..'")
            if name in members:
                raise self.error(f"{where}: appears twice in the zip")
            if info.flag_bits & 0x1:
                raise self.error(f"{where}: is encrypted")
            if info.compress_type not in ZIP_METHODS:
                raise self.error(f"{where}: compression method {info.compress_type} is not supported "
                                 f"({', '.join(ZIP_METHODS.values())} are)")
            stored = info.compress_type == zipfile.ZIP_STORED
            if (stored and info.file_size != info.compress_size) or info.file_size > DEFLATE_MAX_RATIO * max(
                    info.compress_size, 1):
                raise self.error(f"{where}: declares {info.file_size:,} bytes from {info.compress_size:,} "
                                 f"{ZIP_METHODS[info.compress_type]} bytes, which no zip writer makes")
            members[name] = info
        total = sum(info.file_size for info in members.values())
        cap = DEFLATE_MAX_RATIO * max(size, 1) if max_total is None else max_total
        if total > cap:
            raise self.error(f"{self.path}: the members declare {format_bytes(total)} in all, more than the "
                             f"{format_bytes(cap)} this file may hold")
        check_memory(str(self.path), total, "inflating the zip members")
        return members

    def __enter__(self) -> "BoundedZip":
        return self

    def __exit__(self, *exc: Any) -> None:
        self._zip.close()

    def names(self) -> list[str]:
        return list(self.members)

    def info(self, name: str) -> zipfile.ZipInfo:
        if name not in self.members:
            raise self.error(f"{self.path}: the zip has no member {name!r}")
        return self.members[name]

    def read(self, name: str, limit: int, what: str = "member") -> bytes:
        """The bytes of member ``name``: its declared size must be at most ``limit``; the stream
        stops at the declared size and the CRC is checked at its end."""
        info = self.info(name)
        where = f"{self.path}: member {name!r}"
        if info.file_size > limit:
            raise self.error(f"{where}: declares {format_bytes(info.file_size)}, more than the "
                             f"{format_bytes(limit)} a {what} may hold")
        try:
            with self._zip.open(info) as stream:
                data = self._drain(stream, info.file_size)
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, NotImplementedError) as exc:
            raise self.error(f"{where}: corrupt ({str(exc)[:200] or type(exc).__name__})") from None
        if len(data) != info.file_size:
            raise self.error(f"{where}: holds {len(data):,} bytes, the zip directory says {info.file_size:,}")
        return data

    @staticmethod
    def _drain(stream: Any, size: int) -> bytes:
        out = bytearray()
        while len(out) <= size:
            block = stream.read(min(_READ_BLOCK, size + 1 - len(out)))
            if not block:
                break
            out += block
        return bytes(out)


def read_npz(path: str | os.PathLike, *, max_total: int | None = None,
             error: type[GscodecError] = ModelFormatError) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` file (numeric dtypes only, no pickles): each member's ``.npy``
    header is parsed and its shape and dtype checked against the member's size before reading it."""
    arrays: dict[str, np.ndarray] = {}
    with BoundedZip(path, max_total=max_total, error=error) as bundle:
        for name in bundle.names():
            key = name[:-4] if name.endswith(".npy") else name
            arrays[key] = _read_npy(bundle, name, error)
    return arrays


def _read_npy(bundle: BoundedZip, name: str, error: type[GscodecError]) -> np.ndarray:
    from numpy.lib import format as npy

    info = bundle.info(name)
    where = f"{bundle.path}: member {name!r}"
    raw = bundle.read(name, info.file_size)
    handle = io.BytesIO(raw)
    try:
        version = npy.read_magic(handle)
        if version not in ((1, 0), (2, 0), (3, 0)):
            raise ValueError(f"unknown .npy version {version}")
        reader = npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
        shape, fortran, dtype = reader(handle, max_header_size=1 << 16)
    except (ValueError, SyntaxError, TypeError, EOFError, struct.error, tokenize.TokenError) as exc:
        raise error(f"{where}: not a readable .npy array ({str(exc)[:200]})") from None
    if dtype.hasobject or dtype.fields is not None or dtype.kind not in NPY_KINDS or dtype.subdtype is not None:
        raise error(f"{where}: dtype {dtype} is not allowed (booleans, integers and floats are)")
    if len(shape) > 32 or any(not isinstance(s, int) or s < 0 for s in shape):
        raise error(f"{where}: bad shape {shape}")
    count = math.prod(shape)
    body = len(raw) - handle.tell()
    if count * dtype.itemsize != body:
        raise error(f"{where}: shape {shape} of {dtype} needs {count * dtype.itemsize:,} bytes, the member holds {body:,}")
    array = np.frombuffer(raw, dtype=dtype, count=count, offset=handle.tell())
    return array.reshape(shape, order="F" if fortran else "C").copy()


# ------------------------------------------------------------------ images
def image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) declared by a PNG or WebP header; None for anything else."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24 and data[12:16] == b"IHDR":
        return struct.unpack(">II", data[16:24])
    if len(data) < 30 or data[:4] != b"RIFF" or data[8:12] != b"WEBP":
        return None
    kind, body = data[12:16], data[20:]
    if kind == b"VP8X":
        return 1 + int.from_bytes(body[4:7], "little"), 1 + int.from_bytes(body[7:10], "little")
    if kind == b"VP8L" and body[0] == 0x2F:
        bits = int.from_bytes(body[1:5], "little")
        return 1 + (bits & 0x3FFF), 1 + ((bits >> 14) & 0x3FFF)
    if kind == b"VP8 " and body[3:6] == b"\x9d\x01\x2a":
        return int.from_bytes(body[6:8], "little") & 0x3FFF, int.from_bytes(body[8:10], "little") & 0x3FFF
    return None


def decode_rgba(data: bytes, where: str, max_pixels: int, error: type[GscodecError] = ModelFormatError) -> np.ndarray:
    """A PNG or WebP as (H, W, 4) RGBA uint8; its header's dimensions are checked against
    ``max_pixels`` before decoding, and the decoded image against the header."""
    import cv2

    if not data:
        raise error(f"{where}: the image is empty")
    size = image_size(data)
    if size is None:
        raise error(f"{where}: not a PNG or WebP image")
    width, height = size
    if width < 1 or height < 1 or width * height > max_pixels:
        raise error(f"{where}: a {width}x{height} image, more than the {max_pixels:,} pixels it may have here")
    logging = cv2.utils.logging
    level = logging.getLogLevel()
    logging.setLogLevel(logging.LOG_LEVEL_SILENT)  # our one error line says what OpenCV would log
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise error(f"{where}: cannot be decoded ({str(exc).strip().splitlines()[-1][:200]})") from None
    finally:
        logging.setLogLevel(level)
    if image is None or image.dtype != np.uint8 or image.ndim not in (2, 3) or image.shape[:2] != (height, width):
        raise error(f"{where}: cannot be decoded as an 8-bit {width}x{height} image")
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGBA)
    if image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGBA)
    if image.shape[2] != 4:
        raise error(f"{where}: an image with {image.shape[2]} channels")
    return cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)


# ------------------------------------------------------------------ deflate
class Inflater:
    """Inflate ``data`` (zlib, or gzip with ``wbits=31``) piece by piece: :meth:`read` gives exactly
    ``n`` more bytes or raises; :meth:`finish` refuses any byte past the end the header implies."""

    def __init__(self, data: bytes, where: str, *, wbits: int = zlib.MAX_WBITS,
                 error: type[GscodecError] = ModelFormatError) -> None:
        self._inflater = zlib.decompressobj(wbits)
        self._pending = data
        self.where, self.error = where, error

    def read(self, n: int) -> bytes:
        out = bytearray()
        while len(out) < n:
            try:
                block = self._inflater.decompress(self._pending, min(n - len(out), 1 << 24))
            except zlib.error as exc:
                raise self.error(f"{self.where}: corrupt deflate data ({exc})") from None
            progressed = block or len(self._inflater.unconsumed_tail) != len(self._pending)
            self._pending = self._inflater.unconsumed_tail
            out += block
            if self._inflater.eof or not progressed:
                break
        if len(out) < n:
            raise self.error(f"{self.where}: truncated ({self._offset(out, n)})")
        return bytes(out)

    def _offset(self, out: bytearray, n: int) -> str:
        return f"{len(out):,} of {n:,} bytes inflated"

    def finish(self) -> None:
        """Refuse data past the expected end; the stream must end here (its checksum is checked)."""
        try:
            extra = self._inflater.decompress(self._pending, 1)
        except zlib.error as exc:
            raise self.error(f"{self.where}: corrupt deflate data ({exc})") from None
        if extra:
            raise self.error(f"{self.where}: the data goes on past the end its header implies")
        if not self._inflater.eof:
            raise self.error(f"{self.where}: truncated (the compressed stream does not end)")
        if self._inflater.unused_data.strip(b"\0"):
            raise self.error(f"{self.where}: {len(self._inflater.unused_data):,} bytes follow the compressed stream")

