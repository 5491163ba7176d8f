"""PLAS-like sorting of feature vectors onto 2-D grids, fast on a CPU.

A standalone package (numpy, numba, tqdm): no dependency on the codec.

    order = sort_to_grid(prepare_features({"xyz": xyz, "dc": dc}))   # (H*W,) rows per cell, -1 empty
    grid = apply_order(values, order, shape=(H, W))                  # (H, W, ...) grid of any attribute

The names below are imported on first use (PEP 562), so ``import sorting.morton`` or
``sorting.grid`` (pure numpy, what a decoder needs) does not import numba and the
compiled sorting kernels.
"""

from __future__ import annotations

import importlib
from typing import Any

#: Public name -> the submodule defining it.
_WHERE = {
    "METHODS": "api",
    "sort_to_grid": "api",
    "SortingError": "errors",
    "prepare_features": "features",
    "apply_order": "grid",
    "grid_shape": "grid",
    "grid_to_values": "grid",
    "invert_order": "grid",
    "select_for_grid": "grid",
    "neighbour_distance": "metrics",
    "vad": "metrics",
    "morton_order": "morton",
    "PlasSchedule": "plas",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module 'sorting' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"sorting.{_WHERE[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_WHERE))
