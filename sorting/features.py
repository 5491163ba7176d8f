"""Feature vectors to sort by: chosen attributes, each normalised, then weighted."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from sorting.errors import SortingError
from sorting.grid import PARALLEL_ROWS

NORMALIZATIONS = ("minmax", "std")


def _normalise(name: str, values: np.ndarray, normalize: str) -> np.ndarray:
    """One attribute (N, k) scaled as a whole: one scale for all its columns keeps its geometry.

    ``minmax``: columns shifted to start at 0, divided by the widest column range.
    ``std``: columns centred, divided by the attribute's root-mean-square deviation.
    """
    x = values.astype(np.float64)
    if normalize == "minmax":
        lo = x.min(axis=0)
        scale = float((x.max(axis=0) - lo).max())
    else:
        lo = x.mean(axis=0)
        scale = float(np.sqrt(((x - lo) ** 2).mean()))
    return (x - lo) / _usable_scale(scale)


def _usable_scale(scale: float) -> float:
    """``scale``, or 1 when it is not positive and finite (a constant attribute carries no ordering information)."""
    return scale if scale > 0 and np.isfinite(scale) else 1.0


def _check_weight(name: str, weight: object) -> None:
    if not isinstance(weight, (int, float, np.number)) or not np.isfinite(weight) or weight < 0:
        raise SortingError(f"weight of {name!r} must be a finite number >= 0, got {weight!r}")


def prepare_features(
    attributes: Mapping[str, np.ndarray],
    weights: Mapping[str, float] | None = None,
    normalize: str = "minmax",
) -> np.ndarray:
    """Stack attributes into (N, C) float32 sorting features.

    ``attributes`` maps a name to (N,) or (N, k) values, e.g. ``{"xyz": means,
    "scale": log_scales, "opacity": logits, "rotation": quats, "dc": sh_dc}``;
    columns follow the mapping's order. Each attribute is normalised as a whole
    (``"minmax"`` to [0, 1] by its widest column, or ``"std"`` to unit RMS) and
    multiplied by ``weights[name]`` (default 1; 0 leaves it out).
    """
    if normalize not in NORMALIZATIONS:
        raise SortingError(f"normalize must be one of {NORMALIZATIONS}, got {normalize!r}")
    if not isinstance(attributes, Mapping) or not attributes:
        raise SortingError("attributes must be a non-empty mapping of name -> (N,) or (N, k) array")
    weights = dict(weights or {})
    unknown = sorted(set(weights) - set(attributes))
    if unknown:
        raise SortingError(f"weights name attributes that are not given: {', '.join(map(str, unknown))}")
    if _fast_path(attributes, normalize):
        return _prepare_parallel(attributes, weights)
    n = None
    columns = []
    for name, raw in attributes.items():
        arr = np.asarray(raw)
        if arr.ndim == 1:
            arr = arr[:, None]
        if arr.ndim != 2 or arr.shape[0] == 0 or arr.shape[1] == 0:
            raise SortingError(f"attribute {name!r} must be (N,) or (N, k) with N, k > 0, got shape {np.shape(raw)}")
        if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
            raise SortingError(f"attribute {name!r} must be real numbers, got dtype {arr.dtype}")
        if n is None:
            n = arr.shape[0]
        elif arr.shape[0] != n:
            raise SortingError(f"attribute {name!r} has {arr.shape[0]} rows, the first attribute has {n}")
        if not np.all(np.isfinite(arr)):
            raise SortingError(f"attribute {name!r} contains NaN or infinite values")
        weight = weights.get(name, 1.0)
        _check_weight(name, weight)
        if weight == 0:
            continue
        columns.append(_normalise(name, arr, normalize) * float(weight))
    if not columns:
        raise SortingError("every attribute has weight 0: nothing to sort by")
    return np.ascontiguousarray(np.concatenate(columns, axis=1), dtype=np.float32)


def _fast_path(attributes: Mapping[str, np.ndarray], normalize: str) -> bool:
    """Many rows of float32/float64 (N,) or (N, k) arrays, min-max scaled: the kernels of ``_prep.py``."""
    arrays = [np.asarray(a) for a in attributes.values()]
    return (normalize == "minmax" and all(a.dtype in (np.float32, np.float64) and a.ndim in (1, 2) and a.size
                                          for a in arrays)
            and len({a.shape[0] for a in arrays}) == 1 and arrays[0].shape[0] >= PARALLEL_ROWS)


def _prepare_parallel(attributes: Mapping[str, np.ndarray], weights: Mapping[str, float]) -> np.ndarray:
    """:func:`prepare_features` with ``minmax`` on all threads, without float64 copies (the same values)."""
    from sorting._prep import column_ranges, scale_into

    arrays = {name: np.asarray(raw) for name, raw in attributes.items()}
    arrays = {name: (arr[:, None] if arr.ndim == 1 else arr) for name, arr in arrays.items()}
    ranges = {}
    for name, arr in arrays.items():
        lo, hi, finite = column_ranges(arr)
        if not finite:
            raise SortingError(f"attribute {name!r} contains NaN or infinite values")
        _check_weight(name, weights.get(name, 1.0))
        ranges[name] = (lo, hi)
    kept = [name for name in arrays if weights.get(name, 1.0) != 0]
    if not kept:
        raise SortingError("every attribute has weight 0: nothing to sort by")
    n = next(iter(arrays.values())).shape[0]
    out = np.empty((n, sum(arrays[name].shape[1] for name in kept)), dtype=np.float32)
    col = 0
    for name in kept:
        lo, hi = ranges[name]
        scale = _usable_scale(float((hi - lo).max()))
        scale_into(out, col, arrays[name], lo, scale, float(weights.get(name, 1.0)))
        col += arrays[name].shape[1]
    return out
