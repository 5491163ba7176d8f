"""Read and write PlayCanvas SOG (version 2): ``meta.json`` + lossless WebP images, or zipped as ``.sog``.

Each image holds one texel per Gaussian in row-major order (RGBA, 8 bits a channel;
texels past ``count`` are padding). ``meta.json``::

    {"version": 2, "count": N,
     "means":  {"mins": [3], "maxs": [3], "files": ["means_l.webp", "means_u.webp"]},
     "scales": {"codebook": [256], "files": ["scales.webp"]},
     "quats":  {"files": ["quats.webp"]},
     "sh0":    {"codebook": [256], "files": ["sh0.webp"]},
     "shN":    {"count": P, "bands": 1-3, "codebook": [256], "files": ["shN_centroids.webp", "shN_labels.webp"]}}

* means: 16 bits per axis (low byte in ``means_l``, high in ``means_u``) spanning
  [mins, maxs] of ``sign(x) * log(|x| + 1)``; the reader inverts that transform.
* quats: the three smaller components of the unit wxyz quaternion (sign chosen so that
  the largest is positive) as ``(c * sqrt(2) * 0.5 + 0.5) * 255``; alpha = 252 + index
  of the largest component.
* scales (log-scales) and sh0 (f_dc) R, G, B: indices into a 256-entry codebook;
  sh0's alpha is sigmoid(opacity) * 255.
* shN: labels (R + 256 G) pick a palette entry; palette entry ``p`` occupies texels
  ``(p % 64) * K + j`` of row ``p // 64`` of the centroids image (``K`` coefficients per
  channel), whose R, G, B index the shN codebook.

Axes are those of the PLY (no conversion). What SOG loses: positions to 16 bits over
the log-compressed extent, rotations to 8 bits per component, log-scales and DC colour
to a 256-entry codebook each, opacity to 8 bits, and the SH to a palette of at most 64k
entries (k-means) whose values come from a 256-entry codebook; extra properties are
dropped. Alpha 0 or 255 reads as an infinite logit, clamped with a note.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path
from typing import Any, Callable

import numpy as np

from gscodec_shac import sh_index
from gscodec_shac.atomic import write_atomic
from gscodec_shac.errors import GscodecError, ModelFormatError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.bounded import (
    MAX_MODEL_JSON_BYTES, READ_COPIES, BoundedZip, check_memory, cloud_bytes, decode_rgba, load_json, member_path,
    read_file,
)
from gscodec_shac.limits import MAX_GAUSSIANS
from gscodec_shac.io.model_common import (
    check_rows, logits_from_alpha, note, sigmoid, to_uint8, unit_quats, zero_sh_rest,
)

SQRT2 = np.sqrt(2.0)
#: Which wxyz slots the three stored components fill, by index of the dropped largest one.
_QUAT_SLOTS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
_SH_COEFFS = {1: 3, 2: 8, 3: 15}
_PALETTE_COLUMNS = 64
#: The images an unbundled SOG writes beside its ``meta.json``.
SOG_IMAGES = ("means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp", "shN_centroids.webp",
              "shN_labels.webp")
#: The largest SH palette (labels are 16 bits) and the most members a ``.sog`` zip may hold.
_MAX_PALETTE = 1 << 16
_MAX_MEMBERS = 64
#: Texels an image may have beyond twice the Gaussian count (small scenes, padding).
_SLACK_TEXELS = 1 << 16


def is_sog_meta(data: Any) -> bool:
    """Whether a parsed JSON document looks like a SOG ``meta.json`` (of any version)."""
    return isinstance(data, dict) and all(key in data for key in ("means", "scales", "quats", "sh0"))


def find_sog_meta(path: str | os.PathLike) -> Path | None:
    """The SOG ``meta.json`` that ``path`` (the file, or a folder holding it) names, else None."""
    path = Path(path)
    candidate = path / "meta.json" if path.is_dir() else path
    if candidate.suffix.lower() != ".json" or not candidate.is_file():
        return None
    try:
        return candidate if is_sog_meta(load_json(read_file(candidate, MAX_MODEL_JSON_BYTES, "JSON"), str(candidate))) \
            else None
    except GscodecError:
        return None


def sog_files(meta_path: str | os.PathLike) -> list[Path]:
    """The files a SOG ``meta.json`` names beside it (the images an unbundled SOG reads), checked
    to stay inside its folder; [] when the document is unreadable."""
    meta_path = Path(meta_path)
    try:
        meta = load_json(read_file(meta_path, MAX_MODEL_JSON_BYTES, "JSON"), str(meta_path))
    except GscodecError:
        return []
    names = [name for section in (meta.values() if isinstance(meta, dict) else ())
             if isinstance(section, dict) and isinstance(section.get("files"), list)
             for name in section["files"] if isinstance(name, str)]
    out = []
    for name in names:
        try:
            out.append(member_path(meta_path.parent, name, str(meta_path)))
        except GscodecError:
            continue
    return out


def read_sog(path: str | os.PathLike) -> GaussianCloud:
    """Read a SOG scene: a ``.sog`` zip, a ``meta.json`` or the folder holding it."""
    path = Path(path)
    if not path.exists():
        raise ModelFormatError(f"{path}: no such SOG file or folder")
    if path.is_file() and zipfile.is_zipfile(path):
        with BoundedZip(path, max_members=_MAX_MEMBERS) as bundle:
            names: dict[str, str] = {}
            for name in bundle.names():
                if Path(name).name in names:
                    raise ModelFormatError(f"{path}: the SOG bundle holds two members named {Path(name).name}")
                names[Path(name).name] = name
            if "meta.json" not in names:
                raise ModelFormatError(f"{path}: a zip without meta.json is not a SOG bundle")
            where = f"{path}: member 'meta.json'"
            meta = _parse_meta(where, bundle.read(names["meta.json"], MAX_MODEL_JSON_BYTES, "SOG meta.json"))

            def load(name: str, limit: int) -> bytes:
                if name not in names:
                    raise ModelFormatError(f"{path}: the SOG bundle lacks {name}")
                return bundle.read(names[name], limit, "SOG image")

            return _decode(path, meta, load)
    meta_path = path / "meta.json" if path.is_dir() else path
    if not meta_path.is_file():
        raise ModelFormatError(f"{path}: no meta.json in this folder, so it is not a SOG scene")
    meta = _parse_meta(str(meta_path), read_file(meta_path, MAX_MODEL_JSON_BYTES, "SOG meta.json"))

    def load_file(name: str, limit: int) -> bytes:
        file = member_path(meta_path.parent, name, str(meta_path))
        if not os.path.lexists(file):
            raise ModelFormatError(f"{meta_path}: names {name}, which does not exist beside it")
        return read_file(file, limit, "SOG image")

    return _decode(meta_path, meta, load_file)


# ------------------------------------------------------------------ decoding
def _decode(path: Path, meta: dict[str, Any], load: Callable[[str, int], bytes]) -> GaussianCloud:
    n = meta["count"]
    texels = _max_texels(n)

    def image(section: str, index: int) -> np.ndarray:
        name = _files(path, meta, section)[index]
        return _texels(path, name, load(name, _image_bytes(texels)), n, texels)

    lo, hi = image("means", 0), image("means", 1)
    mins, maxs = (np.asarray(_numbers(path, meta["means"], key, 3), dtype=np.float64) for key in ("mins", "maxs"))
    steps = (lo[:, :3].astype(np.float64) + 256.0 * hi[:, :3]) / 65535.0
    span = np.where(maxs - mins == 0, 1.0, maxs - mins)
    logged = mins + span * steps
    means = np.sign(logged) * np.expm1(np.abs(logged))

    quats = _decode_quats(path, image("quats", 0))
    scale_book = np.asarray(_numbers(path, meta["scales"], "codebook", 256), dtype=np.float32)
    scales = scale_book[image("scales", 0)[:, :3]]
    color_book = np.asarray(_numbers(path, meta["sh0"], "codebook", 256), dtype=np.float32)
    sh0 = image("sh0", 0)
    sh_rest = _decode_sh_rest(path, meta, load, n)
    return GaussianCloud(
        means=means, scales=scales, quats=quats,
        opacities=logits_from_alpha(sh0[:, 3].astype(np.float64) / 255.0, path),
        sh_dc=color_book[sh0[:, :3]], sh_rest=sh_rest,
    )


def _decode_quats(path: Path, texels: np.ndarray) -> np.ndarray:
    tag = texels[:, 3].astype(np.int64)
    valid = (tag >= 252) & (tag <= 255)
    if not valid.all():
        note(f"{path}: {int((~valid).sum()):,} rotation texel(s) without a valid tag read as the identity")
    largest = np.where(valid, tag - 252, 0)
    stored = (texels[:, :3].astype(np.float64) / 255.0 * 2.0 - 1.0) / SQRT2
    n = texels.shape[0]
    quats = np.zeros((n, 4))
    rows = np.arange(n)[:, None]
    quats[rows, _QUAT_SLOTS[largest]] = stored
    quats[np.arange(n), largest] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(stored * stored, axis=1)))
    quats[~valid] = (1.0, 0.0, 0.0, 0.0)
    return quats


def _decode_sh_rest(path: Path, meta: dict[str, Any], load: Callable[[str, int], bytes], n: int) -> np.ndarray:
    section = meta.get("shN")
    if section is None:
        return zero_sh_rest(n)
    if not isinstance(section, dict):
        raise ModelFormatError(f"{path}: key 'shN' must be an object")
    bands = section.get("bands")
    if not isinstance(bands, int) or isinstance(bands, bool) or bands not in _SH_COEFFS:
        raise ModelFormatError(f"{path}: key 'shN.bands' must be 1, 2 or 3, got {bands!r}")
    k = _SH_COEFFS[bands]
    book = np.asarray(_numbers(path, section, "codebook", 256), dtype=np.float32)
    palette_size = section.get("count")
    if not isinstance(palette_size, int) or palette_size < 1:
        raise ModelFormatError(f"{path}: key 'shN.count' must be a positive integer, got {palette_size!r}")
    names = _files(path, meta, "shN", 2)
    palette_pixels = _PALETTE_COLUMNS * k * (-(-min(palette_size, _MAX_PALETTE) // _PALETTE_COLUMNS) + 1)
    centroids = decode_rgba(load(names[0], _image_bytes(palette_pixels)), f"{path}: {names[0]}", palette_pixels)
    texels = _max_texels(n)
    labels_img = _texels(path, names[1], load(names[1], _image_bytes(texels)), n, texels)
    if centroids.shape[1] != _PALETTE_COLUMNS * k:
        raise ModelFormatError(
            f"{path}: {names[0]} is {centroids.shape[1]} texels wide; {bands} SH band(s) need {_PALETTE_COLUMNS * k}"
        )
    labels = labels_img[:, 0].astype(np.int64) + 256 * labels_img[:, 1].astype(np.int64)
    usable = min(palette_size, centroids.shape[0] * _PALETTE_COLUMNS)
    bad = labels >= usable
    if bad.any():
        note(f"{path}: {int(bad.sum()):,} SH palette label(s) beyond the palette read as zero SH")
    palette = centroids[:, :, :3].reshape(-1, k, 3)  # entry p: row p // 64, texels (p % 64) * k + j
    values = book[palette[np.where(bad, 0, labels)]]  # (N, k, 3): coefficient-major, R, G, B
    values[bad] = 0.0
    sh_index.degree_from_rest_count(k)
    return values


# ------------------------------------------------------------------ parsing
def _parse_meta(where: str, raw: bytes) -> dict[str, Any]:
    meta = load_json(raw, where)
    if not is_sog_meta(meta):
        raise ModelFormatError(f"{where}: not a SOG meta.json (needs means, scales, quats and sh0)")
    version = meta.get("version")
    if version is None:
        raise ModelFormatError(f"{where}: SOG version 1 (no 'version' key) is not supported; re-save it as version 2")
    if version != 2 or isinstance(version, bool):
        raise ModelFormatError(f"{where}: SOG version {version!r} is not supported (2 is)")
    count = meta.get("count")
    if not isinstance(count, int) or isinstance(count, bool):
        raise ModelFormatError(f"{where}: key 'count' must be an integer, got {count!r}")
    check_rows(where, count, "SOG scene")
    if count > MAX_GAUSSIANS:
        raise ModelFormatError(f"{where}: key 'count': {count:,} Gaussians (at most {MAX_GAUSSIANS:,})")
    for section in ("means", "scales", "quats", "sh0"):
        if not isinstance(meta[section], dict):
            raise ModelFormatError(f"{where}: key {section!r} must be an object")
    shn = meta.get("shN")
    bands = shn.get("bands") if isinstance(shn, dict) else None
    degree = bands if isinstance(bands, int) and not isinstance(bands, bool) and bands in _SH_COEFFS else 0
    check_memory(where, READ_COPIES * cloud_bytes(count, degree) + 6 * 8 * _max_texels(count),
                 f"reading {count:,} Gaussians")
    return meta


def _max_texels(n: int) -> int:
    """The most texels an image of ``n`` Gaussians may have (the writer's layout needs n + O(sqrt n))."""
    return 2 * n + _SLACK_TEXELS


def _image_bytes(pixels: int) -> int:
    """The most bytes a PNG or WebP of ``pixels`` RGBA texels needs, stored without compression."""
    return 5 * pixels + (1 << 20)


def _files(path: Path, meta: dict[str, Any], section: str, count: int | None = None) -> list[str]:
    files = meta[section].get("files")
    need = count if count is not None else (2 if section == "means" else 1)
    if not isinstance(files, list) or len(files) < need or not all(isinstance(f, str) for f in files[:need]):
        raise ModelFormatError(f"{path}: key '{section}.files' must list {need} image name(s)")
    if any(Path(f).is_absolute() or ".." in Path(f).parts for f in files[:need]):
        raise ModelFormatError(f"{path}: key '{section}.files' must name files beside meta.json")
    return files


def _numbers(path: Path, section: dict[str, Any], key: str, count: int) -> list[float]:
    values = section.get(key)
    if (not isinstance(values, list) or len(values) != count
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)):
        raise ModelFormatError(f"{path}: key {key!r} must be a list of {count} numbers")
    return values


def _texels(path: Path, name: str, data: bytes, n: int, max_texels: int) -> np.ndarray:
    """The first ``n`` texels (row-major) of an image, (n, 4) RGBA."""
    image = decode_rgba(data, f"{path}: {name}", max_texels)
    if image.shape[0] * image.shape[1] < n:
        raise ModelFormatError(f"{path}: {name} has {image.shape[0] * image.shape[1]:,} texels, fewer than count {n:,}")
    return image.reshape(-1, 4)[:n]


# ------------------------------------------------------------------ writing
def write_sog(
    path: str | os.PathLike,
    cloud: GaussianCloud,
    *,
    order: str = "morton",
    iterations: int = 10,
    palette_size: int | None = None,
    seed: int = 0,
    progress: bool = False,
) -> None:
    """Write ``cloud`` as SOG version 2: a zipped ``.sog``, or ``meta.json`` + images beside it.

    ``order``: ``"morton"`` places the Gaussians along a Morton curve (smaller images, as
    splat-transform does; the file then holds them in that order) or ``"keep"``.
    ``iterations``: k-means iterations of the SH palette (``palette_size`` entries;
    default as splat-transform: 1k-64k by scene size). Images are lossless WebP (Pillow,
    exact RGB under transparent texels). ``progress``: a progress bar over the palette's k-means
    (about a minute for 1M Gaussians).
    """
    path = Path(path)
    bundle = path.suffix.lower() == ".sog"
    if not bundle and path.name != "meta.json":
        raise ModelFormatError(f"{path}: a SOG output is a .sog file or a meta.json")
    if order not in ("morton", "keep"):
        raise ModelFormatError(f"{path}: SOG order must be 'morton' or 'keep', got {order!r}")
    if not path.parent.is_dir():
        raise ModelFormatError(f"{path}: output directory {path.parent} does not exist")
    n = cloud.num_gaussians
    width = int(np.ceil(np.sqrt(n) / 4.0)) * 4
    height = int(np.ceil(n / width / 4.0)) * 4
    if width > 16383 or height > 16383:
        raise ModelFormatError(f"{path}: {n:,} Gaussians exceed SOG's 16383 x 16383 texels")
    if cloud.sh_degree > 3:
        note(f"{path}: SOG holds SH bands 1-3; band 4 is dropped")
        cloud = cloud.truncate_sh(3)
    if cloud.extra:
        note(f"{path}: SOG has no place for extra properties; dropped {', '.join(cloud.extra)}")
    if order == "morton":
        cloud = cloud.select(_morton_order(cloud.means))

    def texels(channels: list[np.ndarray], alpha: np.ndarray | int = 255) -> np.ndarray:
        image = np.zeros((width * height, 4), dtype=np.uint8)
        for c, values in enumerate(channels):
            image[:n, c] = values
        image[:n, 3] = alpha
        return image.reshape(height, width, 4)

    files: dict[str, bytes] = {}
    logged = np.sign(cloud.means.astype(np.float64)) * np.log1p(np.abs(cloud.means.astype(np.float64)))
    mins, maxs = logged.min(axis=0), logged.max(axis=0)
    steps = np.rint(65535.0 * (logged - mins) / np.where(maxs > mins, maxs - mins, 1.0)).astype(np.int64)
    files["means_l.webp"] = _webp(texels([steps[:, i] & 0xFF for i in range(3)]))
    files["means_u.webp"] = _webp(texels([steps[:, i] >> 8 for i in range(3)]))

    q = unit_quats(cloud.quats)
    largest = np.argmax(np.abs(q), axis=1)
    q = q * np.where(q[np.arange(n), largest] < 0, -SQRT2, SQRT2)[:, None]
    stored = q[np.arange(n)[:, None], _QUAT_SLOTS[largest]]
    files["quats.webp"] = _webp(texels([to_uint8(255.0 * (stored[:, i] * 0.5 + 0.5)) for i in range(3)], 252 + largest))

    scale_book, scale_labels = _codebook_1d(cloud.scales, iterations)
    files["scales.webp"] = _webp(texels([scale_labels[:, i] for i in range(3)]))
    color_book, color_labels = _codebook_1d(cloud.sh_dc, iterations)
    alpha = to_uint8(sigmoid(cloud.opacities) * 255.0)
    files["sh0.webp"] = _webp(texels([color_labels[:, i] for i in range(3)], alpha))
    meta: dict[str, Any] = {
        "version": 2, "asset": {"generator": "gscodec-shac"}, "count": n,
        "means": {"mins": mins.tolist(), "maxs": maxs.tolist(), "files": ["means_l.webp", "means_u.webp"]},
        "scales": {"codebook": scale_book.tolist(), "files": ["scales.webp"]},
        "quats": {"files": ["quats.webp"]},
        "sh0": {"codebook": color_book.tolist(), "files": ["sh0.webp"]},
    }
    if cloud.sh_degree:
        meta["shN"] = _write_palette(cloud, files, texels, iterations, palette_size, seed, progress)
    meta_bytes = json.dumps(meta).encode("utf-8")
    if bundle:
        buffer = io.BytesIO()
        with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as archive:
            archive.writestr("meta.json", meta_bytes)
            for name, data in files.items():
                archive.writestr(name, data)
        write_atomic(path, buffer.getvalue(), error=ModelFormatError)
    else:  # images first, meta.json last: a reader never finds a meta.json without its images
        for name, data in files.items():
            write_atomic(path.parent / name, data, error=ModelFormatError)
        write_atomic(path, meta_bytes, error=ModelFormatError)


def _write_palette(cloud: GaussianCloud, files: dict[str, bytes], texels, iterations: int,
                   palette_size: int | None, seed: int, progress: bool = False) -> dict[str, Any]:
    """k-means palette of the SH AC vectors (the project's ``vq`` stage), its images and meta entry."""
    from gscodec_shac.shac.vq import VectorQuantizer

    n, k = cloud.num_gaussians, cloud.sh_rest.shape[1]
    if palette_size is None:
        palette_size = int(min(64, 2.0 ** np.floor(np.log2(n / 1024))) * 1024)
    palette_size = max(1, min(int(palette_size), 65536, n))
    vq = VectorQuantizer(n_clusters=palette_size, centroid_bits=16, n_iter=iterations, seed=seed)
    vq.progress = progress
    vq.fit(cloud.ac_matrix())
    centres = vq.codebook_.reshape(-1, k, 3)
    labels = vq.labels_
    book, codes = _codebook_1d(centres.reshape(-1, 3), iterations)
    codes = codes.reshape(-1, k, 3)
    rows = -(-centres.shape[0] // _PALETTE_COLUMNS)
    image = np.zeros((rows * _PALETTE_COLUMNS, k, 4), dtype=np.uint8)
    image[: centres.shape[0], :, :3] = codes
    image[:, :, 3] = 255
    files["shN_centroids.webp"] = _webp(image.reshape(rows, _PALETTE_COLUMNS * k, 4))
    files["shN_labels.webp"] = _webp(texels([labels & 0xFF, labels >> 8]))
    bands = {3: 1, 8: 2, 15: 3}[k]
    return {"count": int(centres.shape[0]), "bands": bands, "codebook": book.tolist(),
            "files": ["shN_centroids.webp", "shN_labels.webp"]}


def _codebook_1d(values: np.ndarray, iterations: int, size: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """A 1-D k-means codebook (``size`` entries, ascending) of all ``values`` and each value's index."""
    flat = np.asarray(values, dtype=np.float64).ravel()
    unique = np.unique(flat)
    if unique.size <= size:
        book = np.concatenate([unique, np.full(size - unique.size, unique[-1])])
    else:
        book = np.quantile(flat, (np.arange(size) + 0.5) / size)
        for _ in range(max(1, iterations)):
            labels = np.searchsorted((book[1:] + book[:-1]) / 2.0, flat)
            sums = np.bincount(labels, weights=flat, minlength=size)
            counts = np.bincount(labels, minlength=size)
            book = np.where(counts > 0, sums / np.maximum(counts, 1), book)
            book = np.sort(book)
    book = book.astype(np.float32)
    labels = np.searchsorted((book[1:].astype(np.float64) + book[:-1]) / 2.0, flat)
    return book, labels.astype(np.uint8).reshape(np.shape(values))


def _morton_order(means: np.ndarray) -> np.ndarray:
    """Indices sorting the positions along a 3-D Morton (Z-order) curve, 10 bits per axis."""
    p = means.astype(np.float64)
    low, span = p.min(axis=0), np.ptp(p, axis=0)
    cells = np.minimum((p - low) / np.where(span > 0, span, 1.0) * 1024.0, 1023).astype(np.uint64)
    code = np.zeros(p.shape[0], dtype=np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((cells[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + (2 - axis))
    return np.argsort(code, kind="stable")


def _webp(rgba: np.ndarray) -> bytes:
    """Lossless WebP bytes of an RGBA image (RGB kept exactly under alpha 0)."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgba), "RGBA").save(buffer, "WEBP", lossless=True, exact=True, quality=100, method=4)
    return buffer.getvalue()
