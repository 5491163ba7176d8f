"""Fuzzing the Gaussian model readers: seed files of every format, reproducible mutations, one case.

A seed is a small scene in one format (:data:`FORMATS`) as a set of files (``{relative
path: bytes}``) and the path a reader is handed (a file, or the folder of a SOG scene or a
dynamic model). A case is ``(format, family, index)``, always the same files:

=============== ========================================================================
``truncate``    one member cut at one offset (``index`` runs over every offset of every
                member; members larger than :data:`EVERY_OFFSET_BYTES` are cut at a
                stride so that each seed has at most that many cuts per member)
``bytes``       1-8 random byte edits of one member (flip, set, insert, delete, repeat); half
                of them inside the gzip stream or one zip member, re-compressed and re-signed
``hostile``     one structured hostile value (:data:`HOSTILE` per format): huge or
                negative counts and sizes, NaN/inf, zip bombs and gzip bombs, zip members
                named ``../x``, flipped compression methods, bad CRCs, size lies, deep or
                huge-number JSON, image headers declaring 16383x16383, pickles, symlinks
                that leave the folder
=============== ========================================================================

:func:`run_case` writes a case into a fresh folder and reads it the way ``gscodec-shac info``
does (in-process); :func:`run_cli` runs ``gscodec-shac info`` on it in a child process. Each
outcome is ``valid``, ``error`` (one clean :class:`~gscodec_shac.errors.GscodecError`; through
the CLI: exit status 2, 3 or 5 with one ``error:`` line) or a failure: ``internal`` (any other
exception; exit status 70), ``crash`` (a signal), ``hang``, ``memory``.
"""

from __future__ import annotations

import functools
import gzip
import io
import json
import os
import struct
import tempfile
import time
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from gscodec_shac.errors import GscodecError
from tests.fuzzlib import zipfile_raw as rawzip
from tests.fuzzlib.gsc import _dump, _edit_bytes, _edit_value

FORMATS = ("dynamic", "d3dgs", "spz1", "spz2", "spz3", "spz4", "splat", "sog", "sogdir", "cply", "pt")
FAMILIES = ("truncate", "bytes", "hostile")
#: Members up to this size are cut at every offset; larger ones at a stride giving this many cuts.
EVERY_OFFSET_BYTES = 4096
#: Gaussians of every seed scene (SH degree 3).
SEED_GAUSSIANS = 64


@dataclass(frozen=True)
class Seed:
    """A scene in one format: its files and the path (relative) a reader is handed."""

    fmt: str
    entry: str
    files: dict[str, bytes]


@dataclass(frozen=True)
class Outcome:
    """What reading a case gave: ``kind`` (valid, error, internal, crash, hang, memory) and detail."""

    kind: str
    detail: str
    seconds: float
    peak_bytes: int = 0


# ------------------------------------------------------------------ seeds
def make_seeds(n: int = SEED_GAUSSIANS, seed: int = 0) -> dict[str, Seed]:
    """One seed per format of an ``n``-Gaussian synthetic scene."""
    from gscodec_shac.io.gsplat_ckpt import write_gsplat_checkpoint
    from gscodec_shac.io.sog import write_sog
    from gscodec_shac.io.splat import write_splat
    from gscodec_shac.io.spz import write_spz
    from gscodec_shac.synthetic import make_synthetic_scene

    cloud = make_synthetic_scene(n, seed=seed, n_cameras=1, width=16, height=12).cloud
    seeds: dict[str, Seed] = {}
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the writers' notes (e.g. .splat drops the SH)
        root = Path(tmp)
        for version in (2, 3):
            write_spz(root / f"v{version}.spz", cloud, version=version)
            seeds[f"spz{version}"] = Seed(f"spz{version}", "scene.spz", {"scene.spz": (root / f"v{version}.spz").read_bytes()})
        body = gzip.decompress(seeds["spz3"].files["scene.spz"])
        seeds["spz1"] = Seed("spz1", "scene.spz", {"scene.spz": _spz_v1(body, cloud.means)})
        seeds["spz4"] = Seed("spz4", "scene.spz", {"scene.spz": _spz_v4(body)})
        write_splat(root / "a.splat", cloud)
        seeds["splat"] = Seed("splat", "scene.splat", {"scene.splat": (root / "a.splat").read_bytes()})
        write_sog(root / "a.sog", cloud, order="keep", palette_size=32, iterations=2)
        seeds["sog"] = Seed("sog", "scene.sog", {"scene.sog": (root / "a.sog").read_bytes()})
        (root / "dir").mkdir()
        write_sog(root / "dir" / "meta.json", cloud, order="keep", palette_size=32, iterations=2)
        seeds["sogdir"] = Seed("sogdir", "scene", {f"scene/{p.name}": p.read_bytes() for p in (root / "dir").iterdir()})
        seeds["cply"] = Seed("cply", "scene.compressed.ply", {"scene.compressed.ply": _compressed_ply(n, seed)})
        write_gsplat_checkpoint(root / "a.pt", cloud)
        seeds["pt"] = Seed("pt", "ckpt.pt", {"ckpt.pt": (root / "a.pt").read_bytes()})
        seeds["dynamic"] = _dynamic_seed(cloud, root)
        seeds["d3dgs"] = _deformable3dgs_seed(cloud, root)
    return seeds


def _spz_v1(body: bytes, means: np.ndarray) -> bytes:
    """Version 1: the version-3 body with float16 positions and 3-byte rotations."""
    n = struct.unpack_from("<I", body, 8)[0]
    header = bytearray(body[:16])
    struct.pack_into("<I", header, 4, 1)
    rest = body[16 + 9 * n:]
    alphas_colors_scales = rest[: 7 * n]
    rotations = np.frombuffer(rest[7 * n: 11 * n], dtype="<u4")
    xyz = np.stack([(rotations >> s) & 0xFF for s in (0, 8, 16)], axis=1).astype(np.uint8)
    positions = (means.astype(np.float32) * np.array([1, -1, -1], np.float32)).astype("<f2").tobytes()
    return gzip.compress(bytes(header) + positions + alphas_colors_scales + xyz.tobytes() + rest[11 * n:], mtime=0)


def _zstd_raw(data: bytes) -> bytes:
    """A zstd frame of raw (stored) blocks: magic, single-segment header with an 8-byte size, blocks."""
    out = bytearray(struct.pack("<IB", 0xFD2FB528, 0xE0) + struct.pack("<Q", len(data)))
    blocks = [data[i: i + (1 << 17)] for i in range(0, len(data), 1 << 17)] or [b""]
    for index, block in enumerate(blocks):
        last = index == len(blocks) - 1
        out += (int(last) | (len(block) << 3)).to_bytes(3, "little") + block
    return bytes(out)


def _spz_v4(body: bytes) -> bytes:
    """Version 4 (NGSP header, table of contents, zstd streams) holding the version-3 streams."""
    _, _, n, degree, bits, flags, _ = struct.unpack_from("<IIIBBBB", body)
    k = (degree + 1) ** 2 - 1
    sizes = [s for s in (9 * n, n, 3 * n, 3 * n, 4 * n, 3 * n * k) if s]
    streams, offset = [], 16
    for size in sizes:
        streams.append(body[offset: offset + size])
        offset += size
    packed = [_zstd_raw(s) for s in streams]
    header = struct.pack("<IIIBBBBI12x", 0x5053474E, 4, n, degree, bits, flags, len(sizes), 32)
    toc = b"".join(struct.pack("<QQ", len(p), len(s)) for p, s in zip(packed, streams))
    return header + toc + b"".join(packed)


def _compressed_ply(n: int, seed: int) -> bytes:
    """A PlayCanvas compressed PLY (chunk bounds, packed vertices, 8-bit SH-3) built from its layout."""
    import plyfile

    rng = np.random.default_rng(seed)
    chunks = -(-n // 256)
    names = [f"{e}_{a}" for e in ("min", "max") for a in "xyz"] + [f"{e}_scale_{a}" for e in ("min", "max") for a in "xyz"] \
        + [f"{e}_{c}" for e in ("min", "max") for c in "rgb"]
    chunk = np.zeros(chunks, dtype=[(c, "<f4") for c in names])
    for c in names:
        chunk[c] = -1.0 if c.startswith("min") else 1.0
    vertex = np.zeros(n, dtype=[(c, "<u4") for c in ("packed_position", "packed_rotation", "packed_scale", "packed_color")])
    for c in vertex.dtype.names:
        vertex[c] = rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32)
    sh = np.zeros(n, dtype=[(f"f_rest_{i}", "u1") for i in range(45)])
    for c in sh.dtype.names:
        sh[c] = rng.integers(0, 256, n)
    elements = [plyfile.PlyElement.describe(chunk, "chunk"), plyfile.PlyElement.describe(vertex, "vertex"),
                plyfile.PlyElement.describe(sh, "sh")]
    buffer = io.BytesIO()
    plyfile.PlyData(elements, byte_order="<").write(buffer)
    return buffer.getvalue()


def _dynamic_seed(cloud, root: Path) -> Seed:
    import torch

    from gscodec_shac.deform import DeformArch, DeformNetwork, DynamicModel, save_dynamic_model

    torch.manual_seed(0)
    arch = DeformArch(depth=2, width=8, xyz_freqs=2, t_freqs=1, time_net=False)
    save_dynamic_model(root / "dyn", DynamicModel(cloud, DeformNetwork(arch)))
    return Seed("dynamic", "model", {f"model/{p.name}": p.read_bytes() for p in (root / "dyn").iterdir()})


#: The iteration folder of the Deformable-3DGS seed.
D3DGS_ITERATION = "iteration_7000"


def _deformable3dgs_seed(cloud, root: Path) -> Seed:
    """A Deformable-3DGS output folder (:mod:`gscodec_shac.io.deformable3dgs`): the canonical PLY and a
    ``torch.save``d state dict under the reference's keys (D-NeRF variant, a small 4 x 8 network)."""
    import torch

    from gscodec_shac.io.ply import write_ply

    gen = torch.Generator().manual_seed(0)
    depth, width, x_ch, t_ch = 4, 8, 3 + 6 * 10, 30
    shapes = {"timenet.0": (256, 1 + 2 * 6), "timenet.2": (t_ch, 256)}
    for i in range(depth):
        shapes[f"linear.{i}"] = (width, x_ch + t_ch if i == 0 else width + (x_ch + t_ch if i == depth // 2 + 1 else 0))
    shapes |= {"gaussian_warp": (3, width), "gaussian_rotation": (4, width), "gaussian_scaling": (3, width)}
    state = {}
    for name, (out, fan_in) in shapes.items():
        state[f"{name}.weight"] = (torch.rand(out, fan_in, generator=gen) * 2 - 1) / fan_in ** 0.5
        state[f"{name}.bias"] = (torch.rand(out, generator=gen) * 2 - 1) / fan_in ** 0.5
    ply = root / "d3dgs" / "point_cloud" / D3DGS_ITERATION / "point_cloud.ply"
    pth = root / "d3dgs" / "deform" / D3DGS_ITERATION / "deform.pth"
    ply.parent.mkdir(parents=True)
    pth.parent.mkdir(parents=True)
    write_ply(ply, cloud)
    torch.save(state, pth)
    return Seed("d3dgs", "out", {f"out/{p.relative_to(root / 'd3dgs')}": p.read_bytes() for p in (ply, pth)})


# ------------------------------------------------------------------ cases
def truncation_cases(seed: Seed) -> list[tuple[str, int]]:
    """``(member, length)`` of every truncation of a seed (see the module table)."""
    out = []
    for name, data in sorted(seed.files.items()):
        step = max(1, -(-len(data) // EVERY_OFFSET_BYTES))
        out.extend((name, cut) for cut in range(0, len(data), step))
    return out


def make_case(seed: Seed, family: str, index: int) -> tuple[dict[str, bytes], dict[str, str]]:
    """The files of case ``index`` of ``family`` on ``seed``: ``(files, symlinks)``, symlinks
    being ``{relative path: target}`` (reproducible)."""
    files = dict(seed.files)
    if family == "truncate":
        cuts = truncation_cases(seed)
        name, cut = cuts[index % len(cuts)]
        files[name] = files[name][:cut]
        return files, {}
    rng = np.random.default_rng([FORMATS.index(seed.fmt), FAMILIES.index(family), index])
    if family == "bytes":
        name = sorted(files)[int(rng.integers(len(files)))]
        files[name] = _edit_inside(files[name], rng) if rng.random() < 0.5 else \
            _edit_bytes(bytearray(files[name]), rng, header_bias=True)
        return files, {}
    if family == "hostile":
        edits = HOSTILE[seed.fmt]
        return edits[index % len(edits)](seed, files, rng)
    raise ValueError(f"unknown family {family!r}; known: {', '.join(FAMILIES)}")


def _edit_inside(data: bytes, rng: np.random.Generator) -> bytes:
    """Byte edits inside a gzip stream or one zip member, re-compressed and re-signed (the CRCs
    match: what an attacker sends); other files are edited as they are."""
    if data[:2] == b"\x1f\x8b":
        return gzip.compress(_edit_bytes(bytearray(gzip.decompress(data)), rng, header_bias=True), mtime=0)
    if data[:4] == b"PK\x03\x04":
        members = rawzip.members_of(data)
        target = int(rng.integers(len(members)))
        members[target] = rawzip.Member(members[target].name,
                                        _edit_bytes(bytearray(members[target].stored), rng, header_bias=True))
        return rawzip.build(members)
    return _edit_bytes(bytearray(data), rng, header_bias=True)


def write_case(root: Path, seed: Seed, files: dict[str, bytes], links: dict[str, str]) -> Path:
    """Write a case's files (and symlinks) under ``root``; the path a reader is handed."""
    for name, data in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    for name, target in links.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.exists() or path.is_symlink():
            path.unlink()
        path.symlink_to(target)
    return root / seed.entry


# ------------------------------------------------------------------ hostile values
Edit = Callable[[Seed, dict, np.random.Generator], tuple[dict[str, bytes], dict[str, str]]]
_HUGE_COUNTS = (0, 1, 2**26, 2**26 + 1, 2**31 - 1, 2**32 - 1)


def _pick(rng: np.random.Generator, values: list | tuple) -> Any:
    """One of ``values``, as it is (``rng.choice`` would make numpy scalars of them)."""
    return values[int(rng.integers(len(values)))]


def _only(seed: Seed, suffix: str) -> str:
    return next(name for name in sorted(seed.files) if name.endswith(suffix))


@functools.lru_cache(maxsize=8)
def _gzip_bomb(size: int, prefix: bytes = b"") -> bytes:
    """gzip data inflating to ``prefix`` then zeros up to ``size`` bytes, made in 1 MiB steps."""
    packer = zlib.compressobj(9, zlib.DEFLATED, 31)
    parts = [packer.compress(prefix)]
    block = bytes(1 << 20)
    for _ in range(max(0, size - len(prefix)) >> 20):
        parts.append(packer.compress(block))
    return b"".join(parts) + packer.flush()


@functools.lru_cache(maxsize=2)
def _deflate_bomb(size: int) -> bytes:
    """Raw deflate data inflating to ``size`` zero bytes (a zip member's bomb)."""
    packer = zlib.compressobj(9, zlib.DEFLATED, -15)
    return b"".join(packer.compress(bytes(1 << 20)) for _ in range(size >> 20)) + packer.flush()


def _spz_header_edit(seed, files, rng):
    body = bytearray(gzip.decompress(files["scene.spz"]))
    field = int(rng.integers(5))
    if field == 0:
        struct.pack_into("<I", body, 8, int(_pick(rng, _HUGE_COUNTS)))
    elif field == 1:
        body[12] = int(_pick(rng, [4, 5, 255]))
    elif field == 2:
        body[13] = int(_pick(rng, [0, 24, 31, 255]))
    elif field == 3:
        body[14] = int(_pick(rng, [2, 0xFF]))
    else:
        struct.pack_into("<I", body, 4, int(_pick(rng, [0, 4, 2**32 - 1])))
    files["scene.spz"] = gzip.compress(bytes(body), mtime=0)
    return files, {}


def _spz_bomb(seed, files, rng):
    body = gzip.decompress(files["scene.spz"])
    choice = int(rng.integers(3))
    if choice == 0:  # a consistent count whose body is zeros: 3 GiB declared
        header = bytearray(body[:16])
        struct.pack_into("<I", header, 8, 2**26)
        files["scene.spz"] = _gzip_bomb(64 << 20, bytes(header))
    elif choice == 1:  # 256 MiB of trailing zeros after a valid body
        files["scene.spz"] = _gzip_bomb(len(body) + (256 << 20), body)
    else:  # trailing garbage after the gzip stream
        files["scene.spz"] = files["scene.spz"] + b"garbage" * int(rng.integers(1, 100))
    return files, {}


def _spz4_edit(seed, files, rng):
    data = bytearray(files["scene.spz"])
    choice = int(rng.integers(4))
    if choice == 0:
        struct.pack_into("<I", data, 8, int(_pick(rng, _HUGE_COUNTS)))
    elif choice == 1:  # a table entry's sizes
        entry = 32 + 16 * int(rng.integers(data[15]))
        struct.pack_into("<QQ", data, entry, int(_pick(rng, [0, 2**63, 2**64 - 1])), int(_pick(rng, [0, 2**40, 2**64 - 1])))
    elif choice == 2:
        struct.pack_into("<I", data, 16, int(_pick(rng, [0, 31, 2**32 - 1])))
    else:
        data[15] = int(_pick(rng, [0, 7, 255]))
    files["scene.spz"] = bytes(data)
    return files, {}


def _splat_values(seed, files, rng):
    data = bytearray(files["scene.splat"])
    floats = np.frombuffer(bytes(data), dtype="<f4").copy()
    records = len(data) // 32
    for _ in range(int(rng.integers(1, 5))):
        record, slot = int(rng.integers(records)), int(rng.integers(6))
        floats[record * 8 + slot] = _pick(rng, [np.nan, np.inf, -np.inf, -1.0, 0.0, 3.4e38, -3.4e38])
    out = bytearray(floats.tobytes())
    out[:] = out[: len(data)]
    if rng.random() < 0.3:
        out += bytes(int(rng.integers(1, 32)))
    files["scene.splat"] = bytes(out)
    return files, {}


def _sog_meta_edit(seed, files, rng):
    name = _only(seed, "meta.json") if seed.fmt == "sogdir" else None
    if name:
        files[name] = _dump(_edit_value(json.loads(files[name]), rng))
        return files, {}
    members = rawzip.members_of(files["scene.sog"])
    for i, member in enumerate(members):
        if member.name == "meta.json":
            members[i] = rawzip.Member("meta.json", _dump(_edit_value(json.loads(member.stored), rng)))
    files["scene.sog"] = rawzip.build(members)
    return files, {}


@functools.lru_cache(maxsize=4)
def _big_png(width: int, height: int, zeros: bool) -> bytes:
    """A PNG whose header declares ``width x height`` RGBA; its data are all zero rows (a bomb)
    when ``zeros``, else one short IDAT."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)
    if zeros:
        packer, row = zlib.compressobj(9), bytes(1 + 4 * width)
        rows_per_block = max(1, (1 << 20) // len(row))
        parts, left = [], height
        while left:
            take = min(rows_per_block, left)
            parts.append(packer.compress(row * take))
            left -= take
        idat = b"".join(parts) + packer.flush()
    else:
        idat = zlib.compress(bytes(64))
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def _webp_header(width: int, height: int) -> bytes:
    """A lossless WebP header declaring ``width x height``, with a few bytes of data after it."""
    bits = (width - 1) | ((height - 1) << 14) | (1 << 28)
    body = b"\x2f" + bits.to_bytes(4, "little") + bytes(16)
    return b"RIFF" + struct.pack("<I", 4 + 8 + len(body)) + b"WEBP" + b"VP8L" + struct.pack("<I", len(body)) + body


def _sog_image_edit(seed, files, rng):
    """Replace one image by an empty file, a 16383x16383 WebP header, a PNG bomb or garbage."""
    choice = int(rng.integers(5))
    image = [b"", _webp_header(16383, 16383), _big_png(16000, 16000, zeros=False),
             _big_png(4096, 2048, zeros=True), b"\x89PNG\r\n\x1a\n" + bytes(40)][choice]
    if seed.fmt == "sogdir":
        images = sorted(n for n in files if n.endswith(".webp"))
        files[images[int(rng.integers(len(images)))]] = image
        return files, {}
    members = rawzip.members_of(files["scene.sog"])
    target = int(rng.integers(1, len(members)))
    members[target] = rawzip.Member(members[target].name, image)
    files["scene.sog"] = rawzip.build(members)
    return files, {}


def _zip_edit(zip_name: str) -> Edit:
    """Structured lies of a zip (SOG bundle, .npz, torch checkpoint): names, methods, CRCs, sizes, bombs."""
    def edit(seed, files, rng):
        name = zip_name if zip_name in files else _only(seed, zip_name)
        members = rawzip.members_of(files[name])
        target = int(rng.integers(len(members)))
        member = members[target]
        choice = int(rng.integers(9))
        if choice == 0:
            members[target] = rawzip.replace(member, name=str(_pick(rng, ["../x", "/etc/passwd", "a/../../x", "..\\x",
                                                                          "C:/x", ""])) + member.name[-4:] * int(rng.integers(2)))
        elif choice == 1:
            members[target] = rawzip.replace(member, method=int(_pick(rng, [1, 6, 9, 12, 14, 93, 99])))
        elif choice == 2:
            members[target] = rawzip.replace(member, crc=(member.declared()[1] ^ 1))
        elif choice == 3:
            members[target] = rawzip.replace(member, size=int(_pick(rng, [0, len(member.stored) + 1, 2**31, 2**32 - 1])))
        elif choice == 4:  # a deflate bomb under a name the reader looks for
            raw_size = 256 << 20
            members[target] = rawzip.Member(member.name, _deflate_bomb(raw_size), method=8, size=raw_size,
                                            crc=0, raw=b"")
        elif choice == 5:
            members[target] = rawzip.deflated(member.name, member.stored)
            members[target] = rawzip.replace(members[target], stored=members[target].stored[: len(members[target].stored) // 2])
        elif choice == 6:
            members.extend(rawzip.Member(f"extra{i}.bin", b"") for i in range(int(_pick(rng, [10, 300, 5000]))))
        elif choice == 7:
            members[target] = rawzip.replace(member, flags=1)
        else:
            members.append(rawzip.replace(member))  # the same name twice
        files[name] = rawzip.build(members)
        return files, {}

    return edit


def _npy_header_edit(seed, files, rng):
    """A weights member whose .npy header declares a huge, negative or object shape/dtype."""
    name = _only(seed, ".npz")
    members = rawzip.members_of(files[name])
    target = int(rng.integers(len(members)))
    header = _pick(rng, [
        "{'descr': '<f4', 'fortran_order': False, 'shape': (1099511627776,), }",
        "{'descr': '<f4', 'fortran_order': False, 'shape': (1048576, 1048576), }",
        "{'descr': '<f4', 'fortran_order': False, 'shape': (-1,), }",
        "{'descr': '|O', 'fortran_order': False, 'shape': (1,), }",
        "{'descr': [('a', '<f4')], 'fortran_order': False, 'shape': (1,), }",
        "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 'x'), }",
        "{'descr': '<U100000000', 'fortran_order': False, 'shape': (1,), }",
        "__import__('os').system('true')",
    ])
    text = header.encode("latin-1")
    text += b" " * (-(len(text) + 11) % 64) + b"\n"
    body = b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text + bytes(int(_pick(rng, [0, 4, 64])))
    members[target] = rawzip.Member(members[target].name, body)
    files[name] = rawzip.build(members)
    return files, {}


def _json_edit(suffix: str) -> Edit:
    def edit(seed, files, rng):
        name = _only(seed, suffix)
        choice = int(rng.integers(6))
        if choice == 0:
            files[name] = b"[" * 100_000 + b"]" * 100_000
        elif choice == 1:
            files[name] = files[name].replace(b"2", b"9" * 400, 1)
        elif choice == 2:
            files[name] = files[name].replace(b"2", b"1e999", 1)
        elif choice == 3:
            files[name] = b'{"a": NaN, "b": Infinity}'
        elif choice == 4:
            files[name] = b" " * (2 << 20) + files[name]
        else:
            files[name] = _dump(_edit_value(json.loads(files[name]), rng))
        return files, {}

    return edit


def _symlink_out(seed, files, rng):
    """A member of an input folder that is a symlink leaving it (/proc/self/mem, /dev/zero, /etc/hostname)."""
    members = sorted(n for n in files if "/" in n)
    name = members[int(rng.integers(len(members)))]
    target = str(_pick(rng, ["/proc/self/mem", "/dev/zero", "/etc/hostname", "../outside", "/nonexistent"]))
    files.pop(name)
    return files, {name: target}


def _ply_header_edit(seed, files, rng):
    name = _only(seed, ".ply")
    data = files[name]
    end = data.index(b"end_header\n")
    header = data[:end].decode("ascii")
    choice = int(rng.integers(4))
    if choice == 0:
        header = header.replace("element vertex", f"element vertex {int(_pick(rng, _HUGE_COUNTS))} x", 1)
        header = header.replace(" x ", " ", 1).replace(" x\n", "\n", 1)
        lines = header.split("\n")
        header = "\n".join(line if not line.startswith("element vertex") else " ".join(line.split()[:3]) for line in lines)
    elif choice == 1:
        header = header.replace("\nformat", "\ncomment " + "x" * (1 << 20) + "\nformat", 1)
    elif choice == 2:
        header = header.replace("element chunk", f"element chunk {int(_pick(rng, _HUGE_COUNTS))}", 1)
        header = "\n".join(line if not line.startswith("element chunk") else " ".join(line.split()[:3])
                           for line in header.split("\n"))
    else:
        header = header.replace("float", str(_pick(rng, ["double", "uchar", "list uchar float"])), 1)
    files[name] = header.encode("ascii") + data[end:]
    return files, {}


def _pickle_payload(seed, files, rng):
    """A checkpoint (``ckpt.pt`` or a ``deform.pth``) whose data.pkl would create a file or run a command
    if unpickled."""
    import pickle

    class Evil:
        def __init__(self, call, args):
            self.call, self.args = call, args

        def __reduce__(self):
            return (self.call, self.args)

    marker = str(Path(tempfile.gettempdir()) / "gscodec-fuzz-pickle-ran")
    call = [Evil(open, (marker, "w")), Evil(os.system, (f"touch {marker}",)), Evil(eval, ("1+1",))][int(rng.integers(3))]
    name = "ckpt.pt" if "ckpt.pt" in files else _only(seed, ".pth")
    members = rawzip.members_of(files[name])
    for i, member in enumerate(members):
        if member.name.endswith("data.pkl"):
            members[i] = rawzip.Member(member.name, pickle.dumps({"splats": {"means": call}}, protocol=2))
    files[name] = rawzip.build(members)
    return files, {}


HOSTILE: dict[str, list[Edit]] = {
    "spz1": [_spz_header_edit, _spz_bomb],
    "spz2": [_spz_header_edit, _spz_bomb],
    "spz3": [_spz_header_edit, _spz_bomb],
    "spz4": [_spz4_edit],
    "splat": [_splat_values],
    "sog": [_sog_meta_edit, _sog_image_edit, _zip_edit("scene.sog")],
    "sogdir": [_sog_meta_edit, _sog_image_edit, _symlink_out],
    "cply": [_ply_header_edit],
    "pt": [_pickle_payload, _zip_edit("ckpt.pt")],
    "dynamic": [_zip_edit(".npz"), _npy_header_edit, _json_edit("deformation.json"), _symlink_out, _ply_header_edit],
    "d3dgs": [_zip_edit(".pth"), _pickle_payload, _ply_header_edit, _symlink_out],
}


# ------------------------------------------------------------------ targets
def read_target(path: Path) -> None:
    """What ``gscodec-shac info`` does with a model path (its summary made, not printed)."""
    from gscodec_shac.codec.summary import describe_cloud
    from gscodec_shac.deform_arch import is_dynamic_model
    from gscodec_shac.io.models import read_model

    if is_dynamic_model(path):
        from gscodec_shac.deform import load_dynamic_model

        cloud = load_dynamic_model(path).cloud
    else:
        cloud, _ = read_model(path)
    json.dumps(describe_cloud(cloud, str(path)))


def run_case(seed: Seed, files: dict[str, bytes], links: dict[str, str]) -> Outcome:
    """Write the case into a fresh folder and read it in this process; classify the outcome."""
    with tempfile.TemporaryDirectory(prefix="gscodec-fuzz-") as tmp:
        path = write_case(Path(tmp), seed, files, links)
        tic = time.perf_counter()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                read_target(path)
        except GscodecError as exc:
            return Outcome("error", f"{type(exc).__name__}: {_short(exc)}", time.perf_counter() - tic)
        except MemoryError as exc:
            return Outcome("memory", f"MemoryError: {_short(exc)}", time.perf_counter() - tic)
        except Exception as exc:  # noqa: BLE001 - anything else is an internal error
            return Outcome("internal", f"{type(exc).__name__}: {_short(exc)}", time.perf_counter() - tic)
        return Outcome("valid", "", time.perf_counter() - tic)


def run_cli(seed: Seed, files: dict[str, bytes], links: dict[str, str], *, timeout: float = 20.0,
            memory: str = "2G") -> Outcome:
    """``gscodec-shac info PATH`` on the case in a child process (see :func:`tests.fuzzlib.cli.run`)."""
    from tests.fuzzlib import cli

    with tempfile.TemporaryDirectory(prefix="gscodec-fuzz-") as tmp:
        path = write_case(Path(tmp), seed, files, links)
        return cli.run(["info", str(path)], Path(tmp), timeout=timeout, memory=memory)


def _short(exc: BaseException) -> str:
    text = str(exc).splitlines()
    return (text[0] if text else "")[:300]
