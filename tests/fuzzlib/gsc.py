"""Fuzzing the ``.gsc`` readers: seed streams, reproducible mutations, one case, its outcome.

(The test suite's fuzz library, :mod:`tests.fuzzlib`; it is not part of the installed package.)

A case is ``(family, seed, index)``: the ``index``-th mutation of the seed stream ``seed``
by ``family``, always the same bytes (the random generator is seeded by all three). The
families (docs/reliability.md, "Fuzzing"):

=============== ========================================================================
``truncate``    the first ``index`` bytes of the seed (every offset is one case)
``bytes``       1-8 random byte edits anywhere (flip, set, insert, delete, repeat); the
                CRCs are left as they are, so most end at a CRC check
``resigned``    1-8 random byte edits inside the header text or one chunk, then every
                CRC and size recomputed (an attacker's edit: reaches JSON, codecs, stage)
``header``      one structured edit of a parsed header value (wrong type, boundary or
                huge number, NaN, deep nesting, removal, unknown key), re-signed
``state``       one edit of the SH stage state (its JSON or its arrays), re-deflated, re-signed
``resize``      a consistent lie about the size: Gaussians, grid and every chunk shape
                scaled up together (the payloads stay small), re-signed
=============== ========================================================================

:func:`run_case` feeds the bytes to a target (``decode``: :class:`~gscodec_shac.codec.Decoder`;
``info``: what ``gscodec-shac info`` does) and classifies the outcome: ``valid``, ``error``
(one :class:`~gscodec_shac.errors.GscodecError`, the clean refusal) or ``crash`` (any other
exception, i.e. a traceback a user would see). ``tests/test_fuzz.py`` runs a sample on every
test run; ``scripts/fuzz.py`` runs the long version in child processes with per-case time and
memory limits.
"""

from __future__ import annotations

import copy
import json
import re
import struct
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from gscodec_shac.codec.container import MAGIC, PREAMBLE_SIZE
from gscodec_shac.errors import GscodecError

FAMILIES = ("truncate", "bytes", "resigned", "header", "state", "resize")
TARGETS = ("decode", "info")
#: The SH stages of the synthetic seeds, and the rate point each is coded with.
SEED_STAGES = {"none": "paper_table3:rp2", "trunc": "mpeg_ctc_video:rp01", "pca": "shac_recommended:rp2",
               "lst": "shac_recommended:rp3", "vq": "gsplat_png", "vq-pca": "gsplat_png",
               "pca-spatial": "shac_recommended:rp2"}
_PREAMBLE = struct.Struct("<8sHHII")
_DEEP = "__deep_nesting__"
_DEEP_TOKEN = re.compile(f'"{_DEEP}(\\d+)"')
#: Values a structured edit puts in place of a header value.
_INTERESTING: tuple[Any, ...] = (
    None, True, False, 0, -1, 1, 2, 7, 255, 65535, 2**31, -2**31, 2**63, 2**64 + 1, 10**12, -10**12, 10**40,
    10**400, -10**400, 0.5, -0.0, 1e-300, 1e308, -1e308, float("nan"), float("inf"), float("-inf"), "", "x", "-1", "1e9", "rgb",
    "mask", "tail", "hevc", "png", "zlib", "sh", "hi", "lo", "all", [], {}, [0], [1, 2], [-1, 0], [0, 2**40],
    {"a": 1}, [None], "\u0000", "\ud7ff" * 3,
)


@dataclass(frozen=True)
class Outcome:
    """What one target made of one case: ``valid``, ``error`` or ``crash``, with the detail."""

    kind: str
    detail: str
    seconds: float


# ------------------------------------------------------------------ seeds
def seed_streams(n: int = 300, seed: int = 0, fixtures: str | Path | None = None) -> dict[str, bytes]:
    """One small stream per SH stage (:data:`SEED_STAGES`) of an ``n``-Gaussian synthetic
    scene, plus every ``.gsc`` under ``fixtures`` (the legacy streams) when given."""
    from gscodec_shac.codec import Encoder
    from gscodec_shac.synthetic import make_synthetic_scene

    cloud = make_synthetic_scene(n, seed=seed, n_cameras=1, width=32, height=24).cloud
    params = {"trunc": {"degree": 1}, "pca": {"n_components": 6}, "vq": {"n_clusters": 32},
              "vq-pca": {"n_clusters": 32}, "pca-spatial": {"spatial_clusters": 2, "n_components": 6}}
    seeds = {
        f"stage_{stage}": Encoder(point, sh_stage=stage, sh_params=params.get(stage), workers=1,
                                  codec_options={"preset": "ultrafast"} if "mpeg" in point or "paper" in point else None)
        .encode(cloud).to_bytes()
        for stage, point in SEED_STAGES.items()
    }
    if fixtures is not None:
        for path in sorted(Path(fixtures).rglob("*.gsc")):
            seeds[f"{path.parent.name}/{path.stem}"] = path.read_bytes()
    return seeds


# ------------------------------------------------------------------ cases
def case_count(family: str, data: bytes) -> int | None:
    """How many cases a family has for a seed (``truncate``: one per offset; others: unbounded)."""
    return len(data) if family == "truncate" else None


def make_case(family: str, data: bytes, seed_index: int, index: int) -> bytes:
    """The bytes of case ``index`` of ``family`` on seed stream ``data`` (reproducible)."""
    if family == "truncate":
        return data[:index]
    rng = np.random.default_rng([FAMILIES.index(family), seed_index, index])
    if family == "bytes":
        return _edit_bytes(bytearray(data), rng, header_bias=True)
    raw_header, payloads, version = _split(data)
    if family == "resigned":
        target = int(rng.integers(-1, len(payloads)))
        if target < 0 or not payloads:
            return _pack(_edit_bytes(bytearray(raw_header), rng, header_bias=False), payloads, resign_table=False,
                         version=version)
        payloads = list(payloads)
        payloads[target] = _edit_bytes(bytearray(payloads[target]), rng, header_bias=False)
        return _pack(raw_header, payloads, version=version)
    header = json.loads(raw_header)
    if family == "header":
        return _pack(_dump(_edit_value(header, rng)), payloads, resign_table=False, version=version)
    if family == "state":
        return _edit_state(header, list(payloads), rng, version)
    if family == "resize":
        return _resize(header, payloads, rng, version)
    raise ValueError(f"unknown fuzz family {family!r}; known: {', '.join(FAMILIES)}")


def _edit_bytes(buf: bytearray, rng: np.random.Generator, header_bias: bool) -> bytes:
    for _ in range(int(rng.integers(1, 9))):
        if not buf:
            buf += bytes([int(rng.integers(256))])
            continue
        end = min(len(buf), 4096) if header_bias and rng.random() < 0.5 else len(buf)
        pos = int(rng.integers(end))
        op = int(rng.integers(6))
        if op == 0:
            buf[pos] ^= 1 << int(rng.integers(8))
        elif op == 1:
            buf[pos] = int(rng.choice([0, 1, 0x7F, 0x80, 0xFF, int(rng.integers(256))]))
        elif op == 2:
            buf[pos:pos] = rng.integers(0, 256, int(rng.integers(1, 17)), dtype=np.uint8).tobytes()
        elif op == 3:
            del buf[pos : pos + int(rng.integers(1, 65))]
        elif op == 4:
            span = bytes(buf[pos : pos + int(rng.integers(1, 65))])
            buf[pos:pos] = span * int(rng.integers(1, 5))
        else:
            width = int(rng.choice([2, 4]))
            value = int(rng.choice([0, 1, 0x7FFF, 0xFFFF, 0x7FFFFFFF, 0xFFFFFFFF]))
            buf[pos : pos + width] = value.to_bytes(4, "little")[:width]
    return bytes(buf)


def _split(data: bytes) -> tuple[bytes, list[bytes], tuple[int, int]]:
    """(header JSON bytes, chunk payloads, version) of a valid seed stream (a 2.0 header inflated)."""
    _, major, minor, header_len, _ = _PREAMBLE.unpack_from(data)
    stored = data[PREAMBLE_SIZE : PREAMBLE_SIZE + header_len]
    header = zlib.decompress(stored) if major >= 2 else stored
    offset, payloads = PREAMBLE_SIZE + header_len, []
    for entry in json.loads(header)["chunks"]:
        payloads.append(data[offset : offset + entry["size"]])
        offset += entry["size"]
    return header, payloads, (major, minor)


def _pack(header: bytes, payloads: list[bytes], resign_table: bool = True, version: tuple[int, int] = (1, 0)) -> bytes:
    """A container of ``header`` (JSON; deflated for version 2) and ``payloads``, CRCs computed;
    ``resign_table`` also rewrites each chunk's size and CRC in the table (when the header parses)."""
    if resign_table:
        try:
            parsed = json.loads(header)
            for entry, payload in zip(parsed["chunks"], payloads):
                entry["size"], entry["crc32"] = len(payload), zlib.crc32(payload)
            header = _dump(parsed)
        except (ValueError, KeyError, TypeError):
            pass
    stored = zlib.compress(header, 9) if version[0] >= 2 else header
    preamble = _PREAMBLE.pack(MAGIC, *version, len(stored), zlib.crc32(stored))
    return b"".join([preamble, stored, *payloads])


def _dump(value: Any) -> bytes:
    """Compact JSON; a ``_DEEP<n>`` string becomes lists nested ``n`` deep (too deep to build in Python)."""
    text = json.dumps(value, separators=(",", ":"))
    return _DEEP_TOKEN.sub(lambda m: "[" * int(m.group(1)) + "]" * int(m.group(1)), text).encode("utf-8")


def _paths(value: Any, prefix: tuple = ()) -> list[tuple]:
    """Every path (tuple of keys/indices) into a JSON value, the root excluded."""
    out = []
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, child in items:
        out.append(prefix + (key,))
        out.extend(_paths(child, prefix + (key,)))
    return out


def _edit_value(document: Any, rng: np.random.Generator) -> Any:
    """One structured edit of a JSON document (a deep copy is edited)."""
    document = copy.deepcopy(document)
    paths = _paths(document)
    path = paths[int(rng.integers(len(paths)))]
    parent = document
    for key in path[:-1]:
        parent = parent[key]
    key, old = path[-1], parent[path[-1]]
    op = int(rng.integers(8))
    if op == 0 and isinstance(parent, dict):
        del parent[key]
    elif op == 1 and isinstance(parent, dict):
        parent[f"unknown_{int(rng.integers(100))}"] = _INTERESTING[int(rng.integers(len(_INTERESTING)))]
    elif op == 2:
        parent[key] = f"{_DEEP}{int(rng.choice([10, 63, 65, 1000, 50_000]))}"  # expanded by _dump
    elif op == 3 and isinstance(old, (int, float)) and not isinstance(old, bool):
        parent[key] = _tweak_number(old, rng)
    elif op == 4 and isinstance(old, list) and old:
        parent[key] = old * int(rng.choice([2, 3, 100])) if rng.random() < 0.5 else old[: int(rng.integers(len(old)))]
    elif op == 5 and isinstance(parent, list) and len(parent) > 1:
        other = int(rng.integers(len(parent)))
        parent[key], parent[other] = parent[other], parent[key]
    elif op == 6:
        parent[key] = "A" * int(rng.choice([1000, 100_000]))
    else:
        parent[key] = _INTERESTING[int(rng.integers(len(_INTERESTING)))]
    return document


def _tweak_number(value: float, rng: np.random.Generator) -> float:
    choice = int(rng.integers(7))
    if choice == 0:
        return value + 1
    if choice == 1:
        return value - 1
    if choice == 2:
        return -value
    if choice == 3:
        return value * int(rng.choice([2, 16, 1000, 10**6]))
    if choice == 4:
        return value // 2 if isinstance(value, int) else value / 2
    if choice == 5:
        return float(value) + 0.5
    return value * 10**9


def _edit_state(header: dict, payloads: list[bytes], rng: np.random.Generator, version: tuple[int, int]) -> bytes:
    """Edit the ``sh_state`` chunk (its JSON or array bytes), re-deflate, fix raw_size and CRCs."""
    names = [entry["name"] for entry in header["chunks"]]
    if "sh_state" not in names:
        return _pack(_dump(_edit_value(header, rng)), payloads, resign_table=False, version=version)
    index = names.index("sh_state")
    raw = zlib.decompress(payloads[index])
    (length,) = struct.unpack_from("<I", raw, 4)
    state_json, arrays = json.loads(raw[8 : 8 + length]), raw[8 + length :]
    if rng.random() < 0.6:
        state_json = _edit_value(state_json, rng)
    else:
        arrays = _edit_bytes(bytearray(arrays), rng, header_bias=False)
    text = _dump(state_json)
    raw = raw[:4] + struct.pack("<I", len(text)) + text + arrays
    payloads[index] = zlib.compress(raw, 9)
    header["chunks"][index]["raw_size"] = len(raw)
    return _pack(_dump(header), payloads, version=version)


def _resize(header: dict, payloads: list[bytes], rng: np.random.Generator, version: tuple[int, int]) -> bytes:
    """Scale the declared Gaussians, grid and chunk shapes up together, consistently enough to pass
    every header check (a matching grid mask is made); the plane payloads stay small."""
    factor = int(rng.choice([2, 16, 1000, 10**5, 10**7]))
    outer, prefix, slots = header, "", list(range(len(header["chunks"])))
    if isinstance(header.get("tiers"), list) and header["tiers"]:  # a tiered stream: its first tier grows
        outer, header, prefix = header, header["tiers"][0], "t0."
        slots = [i for i, e in enumerate(outer["chunks"]) if e["name"].startswith(prefix)]
        header["chunks"] = [dict(outer["chunks"][i], name=outer["chunks"][i]["name"][len(prefix):]) for i in slots]
    height, width = header["grid"]["height"], header["grid"]["width"]
    root = max(1, int(np.sqrt(factor)))
    new_h, new_w = height * root, width * max(1, factor // root)
    cells = new_h * new_w
    n = cells - int(rng.integers(0, min(cells, 4096)))
    header["num_gaussians"] = header["input_gaussians"] = n
    header["grid"].update(height=new_h, width=new_w)
    for index, entry in enumerate(header["chunks"]):
        if "shape" in entry:
            entry["shape"] = [entry["shape"][0], new_h, new_w]
        if entry["name"] == "grid_mask":  # the first n cells occupied
            size = (cells + 7) // 8
            if size <= 1 << 24:
                packed = b"\xff" * (n // 8) + (bytes([(0xFF00 >> (n % 8)) & 0xFF]) if n % 8 else b"")
                payloads[slots[index]] = zlib.compress(packed + bytes(size - len(packed)), 9)
            entry["raw_size"] = size
    if prefix:  # back into the file's table (the entries were copies) and its count
        grown = {prefix + e["name"]: e for e in header.pop("chunks")}
        outer["chunks"] = [dict(grown.get(e["name"], e), name=e["name"]) for e in outer["chunks"]]
        outer["num_gaussians"] = sum(int(t.get("num_gaussians", 0)) for t in outer["tiers"])
        header = outer
    return _pack(_dump(header), list(payloads), version=version)


# ------------------------------------------------------------------ targets
def target_decode(data: bytes) -> None:
    """What ``gscodec-shac decode`` does with the bytes (in one thread)."""
    from gscodec_shac.codec import Decoder

    Decoder(workers=1).decode(data)


def target_info(data: bytes) -> None:
    """What ``gscodec-shac info`` does with the bytes (text and JSON output, not printed)."""
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.commands.info import describe_gsc, format_gsc_summary

    summary = describe_gsc(Bitstream.from_bytes(data), "case.gsc")
    format_gsc_summary(summary)
    json.dumps(summary)


TARGET_FUNCTIONS: dict[str, Callable[[bytes], None]] = {"decode": target_decode, "info": target_info}


def run_case(target: str, data: bytes) -> Outcome:
    """Feed ``data`` to ``target`` and classify what happened (nothing escapes but BaseExceptions
    that are not errors, such as KeyboardInterrupt)."""
    tic = time.perf_counter()
    try:
        TARGET_FUNCTIONS[target](data)
    except GscodecError as exc:
        return Outcome("error", f"{type(exc).__name__}: {_short(exc)}", time.perf_counter() - tic)
    except Exception as exc:  # noqa: BLE001 - the point: anything else is a crash
        return Outcome("crash", f"{type(exc).__name__}: {_short(exc)}", time.perf_counter() - tic)
    return Outcome("valid", "", time.perf_counter() - tic)


def _short(exc: BaseException) -> str:
    text = str(exc).splitlines()
    return (text[0] if text else "")[:300]
