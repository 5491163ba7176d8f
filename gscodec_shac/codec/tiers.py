"""Importance tiers: the Gaussians that show most coded finer than those that show least.

A rate point with ``tiers`` (:class:`~gscodec_shac.codec.rate_points.TierSpec`) splits the Gaussians
it keeps by their render-based importance (:mod:`.importance`), most important first, and codes each
tier as a stream of its own: its own positions set and grid, its own quantiser ranges, and every lossy
QP moved by the tier's offset. A Gaussian's share of the rendered error grows with how much of the
views it covers, so the least important half can take several QPs more than the rest for the same
rendered error (docs/rate_control.md, "Controller version 21: importance tiers").

Format 2.6, feature ``tiers``. The file is one container whose header lists the tiers' headers
(``header["tiers"]``, each a complete stream header with its ``features``) and whose chunks are the
tiers' chunks, named ``t<k>.<name>``. SHAC-PCA tiers share one fitted basis: its state is stored once
(chunk ``sh_state``, the tier keeping the most features), and a tier that water-filling left fewer
features reads the first of them. Decoding gives the tiers' Gaussians one tier after the other.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from gscodec_shac.codec.container import Bitstream, Chunk
from gscodec_shac.codec.rate_points import MAX_TIERS
from gscodec_shac.errors import BitstreamError

#: The container feature of a tiered stream.
FEATURE = "tiers"
#: The shared SH stage state's chunk.
SHARED_STATE = "sh_state"
#: Stages whose tiers can share one state (their states differ only in how many features they keep).
SHARED_STAGES = ("pca",)


def tier_rows(importance: np.ndarray, kept: np.ndarray, shares: Sequence[float]) -> list[np.ndarray]:
    """``kept`` rows split by descending ``importance`` (ties by row) into consecutive groups of
    ``shares`` of them, one per share (a few Gaussians may leave one empty); each sorted by row."""
    kept = np.asarray(kept, dtype=np.int64)
    ranked = kept[np.argsort(-np.asarray(importance, dtype=np.float64)[kept], kind="stable")]
    bounds = np.rint(np.cumsum(shares) * kept.size).astype(np.int64)
    bounds[-1] = kept.size
    return [np.sort(group) for group in np.split(ranked, bounds[:-1])]


def importance_spread(importance: np.ndarray, groups: Sequence[np.ndarray]) -> float:
    """The QPs between the first tier and the last that importance asks for: ``3 log2(m_first / m_last)``
    with ``m`` a tier's mean importance (0 when either tier is empty or shows nothing).

    If a Gaussian's rendered error is its coding error times its importance ``w``, and each QP step
    multiplies the step size by ``2^(1/6)``, the steps that spend bits where they remove most error
    satisfy ``step^2 ~ 1 / w`` (reverse water-filling, as the SH features' QPs, :mod:`.allocation`):
    ``QP_last - QP_first = 6 log2(step_last / step_first) = 3 log2(w_first / w_last)``. Measured at the
    plans of size targets (docs/rate_control.md, "Controller version 22"): the chair's halves 8-9x
    apart (about 9.5 QPs; -3 / +7 and -3 / +8 measured best), bonsai's 85-100x (about 19; -5 / +14 best)."""
    importance = np.asarray(importance, dtype=np.float64)
    first, last = groups[0], groups[-1]
    if not first.size or not last.size:
        return 0.0
    high, low = float(importance[first].mean()), float(importance[last].mean())
    return 3.0 * math.log2(high / low) if high > 0 and low > 0 else 0.0


def _chunk_prefix(index: int) -> str:
    return f"t{index}."


def join(streams: Sequence[Bitstream], header: dict[str, Any], indices: Sequence[int] | None = None) -> Bitstream:
    """One tiered stream of the tier ``streams`` (most important first) under the outer ``header``
    (producer, counts, pruning, rate point); ``indices``: each stream's tier in the rate point (default
    0, 1, ...; an empty tier has no stream). SHAC-PCA tiers keep one ``sh_state``."""
    indices = list(range(len(streams))) if indices is None else list(indices)
    out = Bitstream()
    stages = {(s.header.get("sh") or {}).get("stage") for s in streams}
    shared = len(stages) == 1 and stages <= set(SHARED_STAGES)
    if shared:  # the state of the tier keeping the most features; the others keep a prefix of them
        holder = max(streams, key=lambda s: s.header["sh"]["features"])
        state = holder.chunk(SHARED_STATE)
    tiers = []
    for index, stream in enumerate(streams):
        for chunk in stream.chunks:
            if shared and chunk.name == SHARED_STATE:
                continue
            out.add_chunk(_chunk_prefix(index) + chunk.name, chunk.data, **chunk.meta)
        # the file's header holds the producer and the rate point (the tiers' are its own, QPs moved)
        inner = {key: value for key, value in stream.header.items() if key not in ("producer", "rate_point")}
        tiers.append({**inner, "tier": indices[index], "features": sorted(stream.features)})
        for feature in stream.features:
            out.require(feature)
    if shared:
        out.add_chunk(SHARED_STATE, state.data, **state.meta)
    out.require(FEATURE)
    out.header = {**header, "tiers": tiers}
    return out


def split(stream: Bitstream) -> list[Bitstream]:
    """The tier streams of a tiered ``stream``, each with its chunks under their own names (and the
    shared SH state); one :class:`BitstreamError` for an inconsistent layout. Each tier's header is
    then checked by :func:`~gscodec_shac.codec.header.read_header` like any stream's."""
    tiers = stream.header.get("tiers")
    if not isinstance(tiers, list) or not 1 <= len(tiers) <= MAX_TIERS:
        raise BitstreamError(f"corrupt .gsc file: header 'tiers' must list 1 to {MAX_TIERS} tier headers")
    total = stream.header.get("num_gaussians")
    degree = stream.header.get("sh_degree")
    shared = stream.chunk(SHARED_STATE) if stream.has_chunk(SHARED_STATE) else None
    owned: set[str] = set() if shared is None else {SHARED_STATE}
    parts, counted = [], 0
    for index, raw in enumerate(tiers):
        if not isinstance(raw, dict):
            raise BitstreamError(f"corrupt .gsc file: tiers[{index}] is not a header")
        header = dict(raw)
        header.pop("tier", None)
        features = header.pop("features", [])
        if not isinstance(features, list) or not all(isinstance(f, str) for f in features) \
                or FEATURE in features or not set(features) <= stream.features:
            raise BitstreamError(f"corrupt .gsc file: tiers[{index}].features must name features the file has "
                                 "(and not 'tiers')")
        if header.get("sh_degree") != degree:
            raise BitstreamError(f"corrupt .gsc file: tiers[{index}] has SH degree {header.get('sh_degree')!r}, "
                                 f"the file {degree!r}")
        prefix = _chunk_prefix(index)
        chunks = [Chunk(c.name[len(prefix):], c.data, c.meta) for c in stream.chunks if c.name.startswith(prefix)]
        owned.update(prefix + c.name for c in chunks)
        if shared is not None and header.get("sh") is not None and not any(c.name == SHARED_STATE for c in chunks):
            chunks.append(shared)
        count = header.get("num_gaussians")
        counted += count if isinstance(count, int) and not isinstance(count, bool) else 0
        parts.append(Bitstream(header, chunks, stream.version, set(features)))
    stray = [c.name for c in stream.chunks if c.name not in owned]
    if stray:
        raise BitstreamError(f"corrupt .gsc file: chunk {stray[0]!r} belongs to no tier")
    if counted != total:
        raise BitstreamError(f"corrupt .gsc file: the tiers hold {counted:,} Gaussians, the header says {total!r}")
    return parts


def is_tiered(stream: Bitstream) -> bool:
    """Whether ``stream`` is a tiered one (feature ``tiers``)."""
    return FEATURE in stream.features


def sh_features(stream: Bitstream) -> int | None:
    """How many SH features ``stream`` codes (its tiers': the most any keeps); None without an SH stage."""
    headers = stream.header.get("tiers") if is_tiered(stream) else [stream.header]
    counts = [(header.get("sh") or {}).get("features") for header in headers or [] if isinstance(header, dict)]
    counts = [count for count in counts if isinstance(count, int)]
    return max(counts) if counts else None


def read_headers(stream: Bitstream) -> list[Any]:
    """The checked views (:class:`~gscodec_shac.codec.header.StreamHeader`) of ``stream``: its own, or one
    per tier of a tiered stream."""
    from gscodec_shac.codec.header import read_header

    return [read_header(part) for part in split(stream)] if is_tiered(stream) else [read_header(stream)]


def describe(stream: Bitstream) -> dict[str, Any]:
    """``gscodec-shac info``'s summary of a tiered stream (:func:`.header.describe`'s keys), each tier
    checked like a stream of its own; ``tiers`` lists the tiers' Gaussians, grids and QP offsets."""
    from gscodec_shac.codec.header import describe as describe_view

    parts = [describe_view(view) for view in read_headers(stream)]
    header = stream.header
    total = stream.total_bytes()
    n = sum(part["num_gaussians"] for part in parts)
    given = header.get("input_gaussians")
    per = given if isinstance(given, int) and not isinstance(given, bool) and given >= n else n
    offsets = ((header.get("rate_point") or {}).get("tiers") or {}).get("qp_offsets") or []
    sizes = stream.attribute_sizes()
    plans = {f"{_chunk_prefix(i)}{chunk['name']}": chunk for i, part in enumerate(parts) for chunk in part["chunks"]}
    first = parts[0]
    prune = header.get("prune") or {}
    target = (header.get("rate_control") or {}).get("target")
    return {
        **first,
        "bytes": total,
        "format_version": "%d.%d" % stream.version,
        "producer": header.get("producer"),
        "num_gaussians": n,
        "input_gaussians": per,
        "pruned": prune.get("pruned", 0) if isinstance(prune.get("pruned", 0), int) else 0,
        "dropped": sum(part["dropped"] for part in parts),
        "sh_features": max((part["sh_features"] or 0 for part in parts), default=0) or None,
        "sh_dc_only": sum(part["sh_dc_only"] or 0 for part in parts) if any(
            part["sh_dc_only"] is not None for part in parts) else None,
        "grid": " + ".join(part["grid"] for part in parts),
        "rate_point": (header.get("rate_point") or {}).get("name"),
        "target": target if isinstance(target, dict) else None,
        "bits_per_gaussian": 8.0 * total / per,
        "bits_per_gaussian_of": "input" if per == given else "decoded",
        "decoded_bytes": sum(part["decoded_bytes"] for part in parts),
        "attributes": {name: {"bytes": size, "bits_per_gaussian": 8.0 * size / per} for name, size in sizes.items()},
        "chunks": [{"name": chunk.name, "bytes": len(chunk.data), "attribute": str(chunk.meta.get("attribute", chunk.name)),
                    "bits": plans.get(chunk.name, {}).get("bits"), "qp": plans.get(chunk.name, {}).get("qp"),
                    "codec": plans.get(chunk.name, {}).get("codec")} for chunk in stream.chunks],
        "tiers": [{"num_gaussians": part["num_gaussians"], "grid": part["grid"], "qp_offset": _offset(offsets, raw),
                   "sh_features": part["sh_features"]} for part, raw in zip(parts, header["tiers"])],
    }


def _offset(offsets: Sequence[Any], tier: dict[str, Any]) -> Any:
    """The QP offset of a tier header's tier in the rate point's list (None when it does not say)."""
    index = tier.get("tier")
    return offsets[index] if isinstance(index, int) and 0 <= index < len(offsets) else None
