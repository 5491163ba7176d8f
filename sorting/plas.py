"""PLAS-style sorting of feature vectors onto a 2-D grid, on the CPU.

Follows the published Parallel Linear Assignment Sorting scheme: for a
shrinking blur radius, blur the current grid to get a smooth target, then
repeatedly improve the assignment block by block (random groups of 4 cells try
all 24 permutations) until the relative improvement falls below a threshold,
trying several random block offsets per radius. Differences: non-square grids,
empty cells that cost nothing, a radius-independent blur (see ``blur.py``),
reflecting borders on both axes by default, and numba kernels.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np
from tqdm.auto import tqdm

from sorting import _groups, _kernels
from sorting._prep import finish_target as parallel_finish
from sorting._prep import scatter_centred
from sorting.blur import BORDERS, blur_grid
from sorting.errors import SortingError
from sorting.grid import PARALLEL_ROWS, invert_order
from sorting.morton import morton_order


INITS = ("auto", "shuffle", "morton")

#: The published PLAS schedule (slow on a CPU; for comparisons).
PLAS_REFERENCE = {
    "radius_step": 0.95, "improvement_break": 1e-4, "min_block_size": 16, "block_scale": 1.0,
    "border_x": "circular", "tile_groups_above": 0, "max_start_radius": None, "init": "shuffle",
}


@dataclass(frozen=True)
class PlasSchedule:
    """Knobs of the sort; every field can be passed to ``sort_to_grid`` as a keyword."""

    radius_step: float = 0.9  #: radius multiplier per stage, < 1 (PLAS: 0.95)
    improvement_break: float = 1e-3  #: end a block offset when a pass improves less than this, relative (PLAS: 1e-4 .. 1e-5)
    min_radius: float = 1.0  #: last blur radius
    start_radius: float | None = None  #: first blur radius; default min(max(H, W) / 2 - 1, max_start_radius)
    max_start_radius: float | None = 128.0  #: cap of the default first radius (None: no cap, as PLAS)
    min_block_size: int = 4  #: smallest block side, even (PLAS: 16)
    block_scale: float = 0.5  #: block side = block_scale * (blur kernel size + 1), >= min_block_size (PLAS: 1)
    min_offsets: int = 4  #: block offsets tried per radius before giving up (as PLAS)
    max_passes: int = 200  #: safety cap on passes per radius
    border_y: str = "reflect"  #: blur border along rows: "reflect" or "circular" (as PLAS: reflect)
    border_x: str = "reflect"  #: blur border along columns (PLAS: circular)
    init: str = "auto"  #: "shuffle" (seeded random, as PLAS), "morton", or "auto": morton when the first radius is capped
    repeat_radii: bool = True  #: run a stage again when int(radius) repeats (as PLAS)
    tile_groups_above: int = 4096  #: blocks with more cells draw groups from pairs of 8x8 tiles (0 = never)

    def validated(self) -> PlasSchedule:
        """Return self, or raise :class:`SortingError` naming the bad field."""
        if not 0.0 < self.block_scale <= 4.0:
            raise SortingError(f"block_scale must be in (0, 4], got {self.block_scale!r}")
        if not 0.0 < self.radius_step < 1.0:
            raise SortingError(f"radius_step must be in (0, 1), got {self.radius_step!r}")
        if not self.improvement_break >= 0.0:
            raise SortingError(f"improvement_break must be >= 0, got {self.improvement_break!r}")
        if not self.min_radius >= 0.5:
            raise SortingError(f"min_radius must be >= 0.5, got {self.min_radius!r}")
        if self.start_radius is not None and not self.start_radius >= self.min_radius:
            raise SortingError(f"start_radius must be >= min_radius, got {self.start_radius!r}")
        if self.max_start_radius is not None and not self.max_start_radius >= self.min_radius:
            raise SortingError(f"max_start_radius must be >= min_radius or None, got {self.max_start_radius!r}")
        for name in ("min_block_size", "min_offsets", "max_passes"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise SortingError(f"{name} must be a positive integer, got {value!r}")
        if self.min_block_size % 2:
            raise SortingError(f"min_block_size must be even, got {self.min_block_size}")
        if self.init not in INITS:
            raise SortingError(f"init must be one of {INITS}, got {self.init!r}")
        for name in ("border_y", "border_x"):
            if getattr(self, name) not in BORDERS:
                raise SortingError(f"{name} must be one of {sorted(BORDERS)}, got {getattr(self, name)!r}")
        return self


def make_schedule(**overrides: object) -> PlasSchedule:
    """A :class:`PlasSchedule` with the given fields changed; unknown names raise."""
    names = {f.name for f in dataclasses.fields(PlasSchedule)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise SortingError(f"unknown schedule option(s): {', '.join(unknown)}; known: {', '.join(sorted(names))}")
    return PlasSchedule(**overrides).validated()  # type: ignore[arg-type]


def radii(start: float, stop: float, step: float) -> list[int]:
    """Integer blur radii from ``start`` shrinking by ``step`` while ``>= stop`` (duplicates kept)."""
    out = []
    r = float(start)
    while r >= stop:
        out.append(max(1, int(r)))
        r *= step
    return out or [max(1, int(stop))]


def _odd_size(radius: int, side: int) -> int:
    size = min(side - 1, 2 * radius + 1)
    if size % 2 == 0:
        size -= 1
    return max(size, 1)


def _block_side(size: int, side: int, min_block: int, scale: float = 1.0) -> int:
    b = max(min(int(scale * (size + 1)), side) // 2 * 2, min_block)
    return max(2, min(b, side // 2 * 2))


@dataclass
class PlasState:
    """The grid being sorted: cell vectors (cells, K) float32 and the row in each cell (-1 = empty).

    ``target`` / ``scratch``: the blur's buffers, allocated once and reused for every radius
    (no fresh 64 MB pages per radius at 1M cells).
    """

    feat: np.ndarray
    idx: np.ndarray
    shape: tuple[int, int]
    target: np.ndarray | None = None
    scratch: np.ndarray | None = None

    @property
    def valid(self) -> np.ndarray:
        return self.idx >= 0


def make_state(features: np.ndarray, shape: tuple[int, int], cells: np.ndarray) -> PlasState:
    """Place row ``i`` of ``features`` in cell ``cells[i]``.

    Cell vectors are the centred features padded to a multiple of 8 channels
    with at least two spare ones: channel ``K-2`` is 1 for an item and 0 for an
    empty cell, channel ``K-1`` stays 0 (the target keeps its squared norm there).
    """
    h, w = shape
    n, c = features.shape
    k = -(-(c + 2) // 8) * 8
    feat = np.zeros((h * w, k), dtype=np.float32)
    if n >= PARALLEL_ROWS:  # the same values without float64 copies, on all threads
        scatter_centred(feat, np.ascontiguousarray(cells, dtype=np.int64), features,
                        features.astype(np.float64).mean(axis=0))
    else:
        centred = features.astype(np.float64) - features.astype(np.float64).mean(axis=0)
        feat[cells, :c] = centred.astype(np.float32)
        feat[cells, k - 2] = 1.0
    idx = np.full(h * w, -1, dtype=np.int64)
    idx[cells] = np.arange(n, dtype=np.int64)
    return PlasState(feat, idx, (h, w))


def blurred_target(state: PlasState, size_y: int, size_x: int, sched: PlasSchedule) -> np.ndarray:
    """Blur of the items, divided by the blurred item flag (so empty cells do not pull towards 0).

    Channel ``K-2`` of the target is 0, channel ``K-1`` its squared norm (see :func:`make_state`).
    """
    h, w = state.shape
    if state.target is None:
        state.target, state.scratch = np.empty_like(state.feat), np.empty_like(state.feat)
    blurred = blur_grid(state.feat, (h, w), size_y, size_x, sched.border_y, sched.border_x,
                        out=state.target, tmp=state.scratch)
    return finish_target(blurred, state)


def finish_target(blurred: np.ndarray, state: PlasState) -> np.ndarray:
    """The blurred cells (H*W, K) made the target, in place: divided by the blurred item flag when
    cells are empty, channel ``K-2`` zeroed, channel ``K-1`` set to the squared norm."""
    k = blurred.shape[1]
    if blurred.shape[0] >= PARALLEL_ROWS:  # the same values on all threads, without temporaries
        parallel_finish(blurred, not state.valid.all())
        return blurred
    if not state.valid.all():
        weight = blurred[:, k - 2 : k - 1].copy()
        np.divide(blurred, weight, out=blurred, where=weight > 1e-6)
        blurred[(weight <= 1e-6)[:, 0]] = 0.0
    blurred[:, k - 2 :] = 0.0
    blurred[:, k - 1] = np.einsum("ij,ij->i", blurred, blurred)
    return blurred


#: Passes over at least this many groups run on all threads; smaller ones on one
#: (thread hand-offs cost more than they save: on a busy 2-core machine a 75k-cell
#: sort took 3x longer on 2 threads than on 1).
PARALLEL_GROUPS = 65536


def _tiled(bh: int, bw: int, above: int) -> bool:
    t = _groups.TILE
    return 0 < above < bh * bw and bh % t == 0 and bw % t == 0 and (bh // t) * (bw // t) % 2 == 0


#: Blocks of at most WARM_CELLS and at least WARM_MIN_CELLS cells are read row by row before their
#: random groups (the groups then hit the cache; 4x4 blocks were faster without: 1M cells,
#: radii 1-4 of paper_table3, 0.82-0.90 s against 1.02-1.15 s, one thread) ...
WARM_CELLS = 32768
WARM_MIN_CELLS = 64
#: ... in grids of at least this many cells (smaller grids stay in the cache anyway).
WARM_GRID = 131072
#: In grids of at least BLOCKWISE_GRID cells, layouts with at least BLOCKWISE_BLOCKS blocks
#: of at most BLOCKWISE_CELLS cells run block by block (each block stays in the cache for
#: all its passes; one parallel region per offset). Smaller grids are in the cache anyway
#: and sort a little better with whole-layout passes.
BLOCKWISE_GRID = 262144
BLOCKWISE_BLOCKS = 4
BLOCKWISE_CELLS = 65536
#: ... handed out to the threads in runs of about this many cells (one scratch per run: at 1M
#: cells, radii 1-4 have 62,500 blocks of 16 cells each).
RUN_CELLS = 4096
#: Distinct random groupings per radius in block-by-block mode (pass p uses grouping p % TABLES).
TABLES = 16


def sort_radius(state: PlasState, radius: int, sched: PlasSchedule, rng: np.random.Generator) -> float:
    """All passes for one blur radius; returns the number of passes run (per block)."""
    h, w = state.shape
    size_y, size_x = _odd_size(radius, h), _odd_size(radius, w)
    target = blurred_target(state, size_y, size_x, sched)
    bh = _block_side(size_y, h, sched.min_block_size, sched.block_scale)
    bw = _block_side(size_x, w, sched.min_block_size, sched.block_scale)
    if 0 < sched.tile_groups_above < bh * bw and bh >= 16 and bw >= 16:
        bh, bw = bh // 16 * 16, bw // 16 * 16  # whole 8x8 tiles, an even number of them
    tiled = _tiled(bh, bw, sched.tile_groups_above)
    nby, nbx = h // bh, w // bw
    n_blocks = nby * nbx
    n_groups = n_blocks * (bh * bw // 4)
    warm = WARM_MIN_CELLS <= bh * bw <= WARM_CELLS and h * w >= WARM_GRID
    geom = np.array([h, w, bh, bw, 0, 0, nbx, n_groups, sched.max_passes, warm], dtype=np.int64)
    keys = rng.integers(0, 1 << 31, size=(sched.max_passes, 4), dtype=np.int64)
    shifts = np.stack(
        [rng.integers(0, bh, size=sched.max_passes), rng.integers(0, bw, size=sched.max_passes)], axis=1
    ).astype(np.int64)
    parallel = n_groups >= PARALLEL_GROUPS
    if h * w >= BLOCKWISE_GRID and n_blocks >= BLOCKWISE_BLOCKS and bh * bw <= BLOCKWISE_CELLS:
        rows = min(TABLES, sched.max_passes)
        pos_y = np.empty((rows, bh * bw), dtype=np.int64)
        pos_x = np.empty((rows, bh * bw), dtype=np.int64)
        for row in range(rows):
            _groups.fill_positions(pos_y, pos_x, row, bw, keys[row], tiled, False)
        stats = np.zeros((n_blocks, 3), dtype=np.float64)
        return float(
            _kernels.sort_one_radius_blockwise(
                state.feat, state.idx, target, pos_y, pos_x, geom, stats, shifts,
                float(sched.improvement_break), int(sched.min_offsets), parallel, max(1, RUN_CELLS // (bh * bw)),
            )
        )
    n_chunks = -(-n_groups // _kernels.CHUNK)
    before = np.zeros(n_chunks, dtype=np.float64)
    after = np.zeros(n_chunks, dtype=np.float64)
    pos_y = np.empty((1, bh * bw), dtype=np.int64)
    pos_x = np.empty((1, bh * bw), dtype=np.int64)
    return float(
        _kernels.sort_one_radius(
            state.feat, state.idx, target, pos_y, pos_x, geom, before, after, keys, shifts,
            float(sched.improvement_break), int(sched.min_offsets), parallel, tiled,
        )
    )


def initial_cells(features: np.ndarray, shape: tuple[int, int], init: str, rng: np.random.Generator) -> np.ndarray:
    """Starting cell of each row: a seeded random placement, or the Morton order of the features."""
    h, w = shape
    if init == "morton":
        return invert_order(morton_order(features, shape), features.shape[0])
    return rng.permutation(h * w)[: features.shape[0]]


def plas_sort(
    features: np.ndarray,
    shape: tuple[int, int],
    rng: np.random.Generator,
    sched: PlasSchedule,
    progress: bool = False,
    cells: np.ndarray | None = None,
    callback: Callable[[int, float, np.ndarray], None] | None = None,
) -> np.ndarray:
    """Sort (N, C) float32 ``features`` onto ``shape``; returns the order (cells,) int64.

    ``cells`` is the starting cell of each row (default: as ``sched.init`` says).
    ``callback(radius, passes, order)`` is called after each radius (for
    convergence plots; ``order`` is a live view, copy it to keep it).
    """
    h, w = shape
    full = max(h, w) / 2 - 1  # PLAS's first radius
    start = sched.start_radius
    if start is None:
        start = full if sched.max_start_radius is None else min(full, sched.max_start_radius)
    init = sched.init if sched.init != "auto" else ("morton" if start < full else "shuffle")
    if cells is None:
        cells = initial_cells(features, shape, init, rng)
    state = make_state(features, shape, cells)
    stages = radii(max(start, sched.min_radius), sched.min_radius, sched.radius_step)
    if not sched.repeat_radii:
        stages = sorted(set(stages), reverse=True)
    bar = tqdm(stages, desc=f"sorting {h}x{w}", unit="radius", disable=not progress, leave=False)
    for radius in bar:
        # parallel work is handed out chunk by chunk (blocks need different numbers of
        # passes, and on a busy machine one thread may stall)
        with numba.parallel_chunksize(1):
            passes = sort_radius(state, radius, sched, rng)
        bar.set_postfix(radius=radius, passes=round(passes, 1))
        if callback is not None:
            callback(radius, passes, state.idx)
    bar.close()
    return state.idx.copy()
