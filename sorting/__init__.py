"""PLAS-like sorting of feature vectors onto 2-D grids, fast on a CPU.

A standalone package (numpy, numba, tqdm): no dependency on the codec.

    order = sort_to_grid(prepare_features({"xyz": xyz, "dc": dc}))   # (H*W,) rows per cell, -1 empty
    grid = apply_order(values, order, shape=(H, W))                  # (H, W, ...) grid of any attribute
"""

from sorting.api import METHODS, sort_to_grid
from sorting.errors import SortingError
from sorting.features import prepare_features
from sorting.grid import apply_order, grid_shape, grid_to_values, invert_order, select_for_grid
from sorting.metrics import neighbour_distance, vad
from sorting.morton import morton_order
from sorting.plas import PlasSchedule

__all__ = [
    "METHODS",
    "PlasSchedule",
    "SortingError",
    "apply_order",
    "grid_shape",
    "grid_to_values",
    "invert_order",
    "morton_order",
    "neighbour_distance",
    "prepare_features",
    "select_for_grid",
    "sort_to_grid",
    "vad",
]
