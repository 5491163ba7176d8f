"""Small helpers shared by the camera-file readers of :mod:`gscodec_shac.io`.

File and key checks, JSON loading, finding an image on disk, reading an image's
size and atomic writes; every failure is a :class:`CameraFormatError` naming the file.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from gscodec_shac.camera import IMAGE_EXTENSIONS
from gscodec_shac.errors import CameraFormatError
from gscodec_shac.limits import MAX_JSON_BYTES, MAX_NESTING, check_image_file, image_file_size, json_nesting


def require_file(path: Path, what: str) -> None:
    """Raise unless ``path`` is an existing file (``what`` names the expected format)."""
    if not path.exists():
        raise CameraFormatError(f"{path}: no such {what} file")
    if not path.is_file():
        raise CameraFormatError(f"{path}: is a directory, expected a {what} file")


def load_json(path: Path, what: str) -> Any:
    """The parsed JSON of ``path``; a missing, unreadable, malformed, too large
    (:data:`~gscodec_shac.limits.MAX_JSON_BYTES`) or too deeply nested file raises."""
    require_file(path, what)
    try:
        if path.stat().st_size > MAX_JSON_BYTES:
            raise CameraFormatError(f"{path}: {path.stat().st_size:,} bytes, more than a {what} file may hold "
                                    f"({MAX_JSON_BYTES:,})")
        raw = path.read_bytes()
        depth = json_nesting(raw)
        if depth > MAX_NESTING:
            raise CameraFormatError(f"{path}: JSON nested {depth} levels deep (at most {MAX_NESTING})")
        return json.loads(raw.decode("utf-8"))
    except json.JSONDecodeError as exc:
        raise CameraFormatError(f"{path}: invalid JSON at line {exc.lineno} column {exc.colno} ({exc.msg})") from None
    except UnicodeDecodeError:
        raise CameraFormatError(f"{path}: not a text (UTF-8 JSON) file") from None
    except ValueError as exc:  # e.g. an integer of thousands of digits
        raise CameraFormatError(f"{path}: a JSON value cannot be read ({str(exc).splitlines()[0]})") from None
    except OSError as exc:
        raise CameraFormatError(f"{path}: cannot be read ({exc.strerror or exc})") from None


def require_key(entry: dict, key: str, path: Path, where: str) -> Any:
    """``entry[key]``, or an error saying that ``where`` in ``path`` lacks it."""
    if key not in entry:
        raise CameraFormatError(f"{path}: {where} has no {key!r} key")
    return entry[key]


def find_image(directory: Path | None, name: str) -> Path | None:
    """``directory / name`` if it is a file, else with the first extension found on disk."""
    if directory is None or not name:
        return None
    exact = directory / name
    if exact.suffix and exact.is_file():
        return exact
    for ext in IMAGE_EXTENSIONS:
        candidate = directory / (name + ext)
        if candidate.is_file():
            return candidate
    return None


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, from its header (decoded with OpenCV when Pillow cannot read it)."""
    import cv2

    check_image_file(path, CameraFormatError)
    size = image_file_size(path)
    if size is not None:
        return size
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise CameraFormatError(f"{path}: cannot be decoded as an image")
    return int(image.shape[1]), int(image.shape[0])
