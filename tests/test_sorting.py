"""The standalone `sorting` package: orders, grids, features, metrics, methods, errors."""

from __future__ import annotations

import numpy as np
import pytest

import sorting
from sorting import SortingError
from sorting import plas as plas_module
from sorting.morton import grid_z_cells, morton_codes_2d

METHODS = ("plas", "morton", "random", "none")


def smooth_features(n: int, seed: int = 0) -> np.ndarray:
    """Rows sampled from a smooth 2-D sheet in 6-D (a grid-sortable manifold), in random order."""
    rng = np.random.default_rng(seed)
    u, v = rng.random(n), rng.random(n)
    feats = np.stack(
        [u, v, np.sin(3 * u) * v, np.cos(2 * v), u * u, 0.5 * np.sin(4 * u + 2 * v)], axis=1
    )
    return feats.astype(np.float32)


def quality(features: np.ndarray, order: np.ndarray, shape: tuple[int, int]) -> float:
    grid = sorting.apply_order(features, order, shape=shape)
    return sorting.neighbour_distance(grid, (order >= 0).reshape(shape))


# ------------------------------------------------------------------ orders and grids


@pytest.mark.parametrize("method", METHODS)
def test_every_method_returns_a_permutation_plus_padding(method):
    feats = smooth_features(300)
    shape = (16, 24)  # non-square, 384 cells for 300 rows
    order = sorting.sort_to_grid(feats, shape, method=method)
    assert order.dtype == np.int64 and order.shape == (16 * 24,)
    assert np.array_equal(np.sort(order[order >= 0]), np.arange(300))
    assert np.count_nonzero(order == -1) == 16 * 24 - 300


def test_default_shape_is_grid_shape_with_padding():
    feats = smooth_features(1000)
    order = sorting.sort_to_grid(feats, method="morton")
    h, w = sorting.grid_shape(1000)
    assert order.shape == (h * w,) and h * w >= 1000 and h % 8 == 0 and w % 8 == 0


def test_apply_order_and_back_round_trip():
    rng = np.random.default_rng(3)
    values = rng.normal(size=(50, 3, 2))
    order = sorting.sort_to_grid(values.reshape(50, -1), (8, 8), method="random", seed=4)
    grid = sorting.apply_order(values, order, fill=-7.0, shape=(8, 8))
    assert grid.shape == (8, 8, 3, 2)
    assert np.all(grid.reshape(64, 3, 2)[order == -1] == -7.0)
    assert np.array_equal(sorting.grid_to_values(grid, order, 50), values)
    # a 2-D order carries its own shape
    assert np.array_equal(sorting.apply_order(values, order.reshape(8, 8), fill=-7.0), grid)
    cells = sorting.invert_order(order, 50)
    assert np.array_equal(order[cells], np.arange(50))


def test_bad_orders_are_rejected():
    values = np.zeros((4, 2))
    with pytest.raises(SortingError, match="exactly one cell"):
        sorting.invert_order(np.array([0, 0, 1, 2]), 4)
    with pytest.raises(SortingError, match="row numbers"):
        sorting.apply_order(values, np.array([0, 1, 2, 9]), shape=(2, 2))
    with pytest.raises(SortingError, match="needs shape"):
        sorting.apply_order(values, np.array([0, 1, 2, 3]))
    with pytest.raises(SortingError, match="has 4 cells"):
        sorting.apply_order(values, np.array([0, 1, 2, 3]), shape=(3, 3))


@pytest.mark.parametrize("n", [1, 63, 64, 65, 1000, 9080, 75_000, 1_000_000])
def test_grid_shape_pad_and_drop(n):
    h, w = sorting.grid_shape(n)
    assert h * w >= n and h % 8 == 0 and w % 8 == 0 and h <= w <= 1.5 * h
    # the smallest such area: no near-square shape with fewer cells holds n rows
    smaller = [(a, b) for a in range(8, h + 9, 8) for b in range(a, int(1.5 * a) + 1, 8) if n <= a * b < h * w]
    assert smaller == []
    if n >= 64:
        hd, wd = sorting.grid_shape(n, policy="drop")
        assert hd * wd <= n and hd % 8 == 0 and wd % 8 == 0 and hd <= wd <= 1.5 * hd
        larger = [(a, b) for a in range(8, hd + 9, 8) for b in range(a, int(1.5 * a) + 1, 8) if hd * wd < a * b <= n]
        assert larger == []


def test_grid_shape_errors():
    with pytest.raises(SortingError, match="policy"):
        sorting.grid_shape(100, policy="crop")
    with pytest.raises(SortingError, match="use policy='pad'"):
        sorting.grid_shape(10, policy="drop")
    with pytest.raises(SortingError, match="positive integer"):
        sorting.grid_shape(0)


def test_drop_policy_keeps_the_most_important_rows():
    n = 1000
    importance = np.random.default_rng(0).random(n)
    importance[[5, 6]] = 2.0  # a tie at the top
    h, w = sorting.grid_shape(n, policy="drop")
    keep = sorting.select_for_grid(importance, h * w)
    assert keep.shape == (h * w,) and np.all(np.diff(keep) > 0)
    dropped = np.setdiff1d(np.arange(n), keep)
    assert importance[keep].min() >= importance[dropped].max()
    assert {5, 6} <= set(keep.tolist())
    order = sorting.sort_to_grid(smooth_features(n)[keep], (h, w))
    assert np.count_nonzero(order == -1) == 0
    # ties go to the earlier row
    assert np.array_equal(sorting.select_for_grid(np.ones(5), 2), [0, 1])


# ------------------------------------------------------------------ quality


def test_plas_beats_random_and_morton_on_structured_input():
    feats = smooth_features(32 * 32)
    shape = (32, 32)
    scores = {m: quality(feats, sorting.sort_to_grid(feats, shape, method=m), shape) for m in METHODS}
    assert scores["plas"] < 0.8 * scores["morton"]
    assert scores["morton"] < 0.8 * scores["random"]


def test_plas_with_padding_and_non_square_grid_beats_morton():
    feats = smooth_features(700, seed=2)
    shape = (24, 40)
    plas = quality(feats, sorting.sort_to_grid(feats, shape), shape)
    morton = quality(feats, sorting.sort_to_grid(feats, shape, method="morton"), shape)
    assert plas < 0.85 * morton


def test_morton_uses_a_two_dimensional_z_layout():
    # points on an 8x8 lattice: Z-order on the grid puts every point next to its lattice neighbours
    yy, xx = np.mgrid[0:8, 0:8]
    points = np.stack([xx.ravel(), yy.ravel()], axis=1).astype(np.float64)
    rows = np.random.default_rng(0).permutation(64)
    order = sorting.morton_order(points[rows], (8, 8))
    grid = sorting.apply_order(points[rows], order, shape=(8, 8))
    assert sorting.neighbour_distance(grid) == pytest.approx(1.0)
    assert sorted(grid_z_cells((2, 2)).tolist()) == [0, 1, 2, 3]
    assert grid_z_cells((2, 2)).tolist() == [0, 1, 2, 3]  # (0,0) (0,1) (1,0) (1,1)



@pytest.mark.parametrize("shape", [(1, 1), (2, 1), (3, 5), (7, 3), (17, 16), (100, 33), (999, 1001), (1024, 1000),
                                   (5, 100), (1, 40), (513, 257)])
def test_grid_z_cells_is_the_grid_sorted_by_morton_code(shape):
    # the counting construction (and, for long thin grids, the sort) lists the cells by ascending code
    ys, xs = np.divmod(np.arange(shape[0] * shape[1], dtype=np.int64), shape[1])
    codes = morton_codes_2d(ys, xs)
    cells = grid_z_cells(shape)
    assert cells.dtype == np.int64 and sorted(cells.tolist()) == list(range(shape[0] * shape[1]))
    assert np.all(np.diff(codes[cells].astype(np.float64)) > 0)



@pytest.mark.parametrize("d", [1, 2, 3, 5, 9, 14, 21, 32, 63, 70])
def test_morton_codes_interleave_every_bit(d):
    # the table-driven interleave against its definition: bit b of dimension j at bit b * d + j
    rng = np.random.default_rng(d)
    points = rng.standard_normal((2000, d))
    codes = sorting.morton.morton_codes(points)
    kept = min(d, 63)
    bits = min(21, 63 // kept)
    x = points[:, :kept]
    span = np.where(np.ptp(x, axis=0) > 0, np.ptp(x, axis=0), 1.0)
    q = np.clip(np.rint((x - x.min(axis=0)) / span * ((1 << bits) - 1)), 0, (1 << bits) - 1).astype(np.uint64)
    want = np.zeros(len(points), dtype=np.uint64)
    for bit in range(bits):
        for dim in range(kept):
            want |= ((q[:, dim] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(bit * kept + dim)
    assert np.array_equal(codes, want)


# ------------------------------------------------------------------ reproducibility


def test_same_seed_same_order_other_seed_other_order():
    feats = smooth_features(500)
    a = sorting.sort_to_grid(feats, (24, 24), seed=7)
    b = sorting.sort_to_grid(feats, (24, 24), seed=7)
    c = sorting.sort_to_grid(feats, (24, 24), seed=8)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_auto_init_is_morton_exactly_when_the_first_radius_is_capped():
    feats = smooth_features(32 * 32, seed=1)
    shape = (32, 32)
    capped = sorting.sort_to_grid(feats, shape, max_start_radius=4)
    assert np.array_equal(capped, sorting.sort_to_grid(feats, shape, init="morton", start_radius=4))
    full = sorting.sort_to_grid(feats, shape, max_start_radius=None)
    assert np.array_equal(full, sorting.sort_to_grid(feats, shape, init="shuffle"))
    assert not np.array_equal(capped, full)


@pytest.mark.parametrize("tile_groups_above", [0, 64])
def test_threads_and_cache_warming_do_not_change_the_order(monkeypatch, tile_groups_above):
    """Serial and parallel kernels, block-by-block and whole-layout passes, with and without warming."""
    feats = smooth_features(32 * 32, seed=5)
    kwargs = dict(seed=3, radius_step=0.6, improvement_break=3e-3, tile_groups_above=tile_groups_above)
    monkeypatch.setattr(plas_module, "BLOCKWISE_GRID", 0)
    monkeypatch.setattr(plas_module, "PARALLEL_GROUPS", 1 << 40)
    serial = sorting.sort_to_grid(feats, (32, 32), **kwargs)
    monkeypatch.setattr(plas_module, "PARALLEL_GROUPS", 1)
    monkeypatch.setattr(sorting.blur, "PARALLEL_CELLS", 1)
    parallel = sorting.sort_to_grid(feats, (32, 32), **kwargs)
    monkeypatch.setattr(plas_module, "RUN_CELLS", 1)  # every block its own run of the parallel loop
    one_block_runs = sorting.sort_to_grid(feats, (32, 32), **kwargs)
    monkeypatch.setattr(plas_module, "WARM_GRID", 0)
    warmed = sorting.sort_to_grid(feats, (32, 32), **kwargs)
    monkeypatch.setattr(plas_module, "BLOCKWISE_BLOCKS", 1 << 40)
    whole_layout = sorting.sort_to_grid(feats, (32, 32), **kwargs)
    assert np.array_equal(serial, parallel)
    assert np.array_equal(serial, one_block_runs)
    assert np.array_equal(serial, warmed)
    assert np.array_equal(np.sort(whole_layout), np.arange(32 * 32))
    assert quality(feats, whole_layout, (32, 32)) < 1.2 * quality(feats, serial, (32, 32))


@pytest.mark.parametrize(
    "tiled, bh, bw",  # tiles need whole 8x8 tiles, an even number of them
    [(False, 4, 4), (False, 16, 48), (False, 30, 30), (True, 16, 48), (True, 32, 32)],
)
def test_block_positions_are_keyed_bijections(tiled, bh, bw):
    from sorting import _groups

    fill = _groups.tile_pair_positions_serial if tiled else _groups.block_positions_serial
    pos_y, pos_x = np.empty(bh * bw, np.int64), np.empty(bh * bw, np.int64)
    fill(pos_y, pos_x, bw, np.array([1, 2, 3, 4]))
    cells = pos_y * bw + pos_x
    assert np.array_equal(np.sort(cells), np.arange(bh * bw))
    assert pos_y.max() < bh and pos_x.max() < bw
    first = cells.copy()
    fill(pos_y, pos_x, bw, np.array([5, 6, 7, 8]))
    assert not np.array_equal(first, pos_y * bw + pos_x)
    if tiled:  # a group takes 2 cells of one tile and 2 of another
        tiles = ((pos_y // 8) * (bw // 8) + pos_x // 8).reshape(-1, 4)
        assert np.all(tiles[:, 0] == tiles[:, 1]) and np.all(tiles[:, 2] == tiles[:, 3])
        assert np.all(tiles[:, 0] != tiles[:, 2])


def test_radius_independent_blur_matches_the_gaussian_it_replaces():
    from scipy.ndimage import correlate1d

    from sorting.blur import blur_grid

    rng = np.random.default_rng(0)
    h, w, k = 21, 32, 3
    cells = rng.random((h * w, k)).astype(np.float32)
    for size_y, size_x in ((1, 1), (3, 5), (9, 21), (19, 31)):
        ours = blur_grid(cells, (h, w), size_y, size_x, "reflect", "circular").reshape(h, w, k)
        expected = cells.reshape(h, w, k).astype(np.float64)
        for axis, size, mode in ((1, size_x, "wrap"), (0, size_y, "mirror")):
            d = np.arange(size) - size // 2
            kernel = np.exp(-(d * d) / (2.0 * size * size))  # sigma = kernel size, as PLAS
            expected = correlate1d(expected, kernel / kernel.sum(), axis=axis, mode=mode)
        assert np.abs(ours - expected).max() < 2e-4


def _target_in_fresh_arrays(state, size: int, sched) -> np.ndarray:
    """PLAS's target as it was computed before the buffers were reused: a blur into fresh arrays."""
    from sorting.blur import blur_grid

    blurred = blur_grid(state.feat, state.shape, size, size, sched.border_y, sched.border_x)
    return plas_module.finish_target(blurred, state)


@pytest.mark.parametrize("n", [30 * 32, 30 * 32 - 37])  # a full grid and one with empty cells
def test_plas_target_in_reused_buffers_is_the_target_in_fresh_arrays(n):
    shape = (30, 32)
    rng = np.random.default_rng(0)
    state = plas_module.make_state(smooth_features(n, seed=4), shape, rng.permutation(30 * 32)[:n])
    sched = plas_module.make_schedule()
    for size in (9, 3, 9, 1):  # the buffers carry over from one radius to the next
        swap = rng.permutation(state.feat.shape[0])[:2]  # items move between radii
        state.feat[swap], state.idx[swap] = state.feat[swap[::-1]], state.idx[swap[::-1]]
        got = plas_module.blurred_target(state, size, size, sched)
        assert got is state.target
        assert got.tobytes() == _target_in_fresh_arrays(state, size, sched).tobytes()


@pytest.mark.parametrize("channels, n", [(6, 30 * 32), (6, 30 * 32 - 37), (14, 30 * 32 - 5), (20, 30 * 32)])
def test_parallel_target_is_the_numpy_target(monkeypatch, channels, n):
    from sorting.blur import blur_grid

    """sorting/_prep.py's finish (K = 8, 16, 24; full and padded grids) equals numpy's, bit for bit."""
    rng = np.random.default_rng(channels)
    feats = (rng.normal(size=(n, channels)) * 3).astype(np.float32)
    state = plas_module.make_state(feats, (30, 32), rng.permutation(30 * 32)[:n])
    blurred = blur_grid(state.feat, state.shape, 5, 7)
    monkeypatch.setattr(plas_module, "PARALLEL_ROWS", 1)
    got = plas_module.finish_target(blurred.copy(), state)
    monkeypatch.setattr(plas_module, "PARALLEL_ROWS", 1 << 40)
    assert got.tobytes() == plas_module.finish_target(blurred.copy(), state).tobytes()


#: The pinned orders, by the vector code the fast-math kernels are compiled to: the padded grid's
#: whole-layout sort differs between AVX2 (the machines up to 2026-11-28; also this one with
#: NUMBA_CPU_NAME=haswell) and AVX-512 (the Intel Xeon of 2026-11-29), everything else is the same.
#: An AMD EPYC (Zen 4, 2026-11-30) has AVX-512 and sorts as AVX2 does (probably LLVM's Zen 4 tuning,
#: which prefers 256-bit vectors; not checked). A CPU with AVX-512 may give either set; one without it
#: only the AVX2 set.
PLAS_ORDERS_AVX2 = ["1890e7ba7a745057", "f4c6f58236f7484f", "f4c6f58236f7484f",
                    "bc4b81024f1628d7", "444290ba5d0e0c67", "444290ba5d0e0c67"]
PLAS_ORDERS_AVX512 = ["1890e7ba7a745057", "9bd73a137db3ef1b", "9bd73a137db3ef1b",
                      "bc4b81024f1628d7", "444290ba5d0e0c67", "444290ba5d0e0c67"]


def _kernels_target_avx512() -> bool:
    """Whether numba compiles for a CPU with AVX-512: the host's, unless NUMBA_CPU_NAME names another."""
    import llvmlite.binding as ll
    from numba.core import config

    if config.CPU_NAME and config.CPU_NAME != "host":
        return "+avx512f" in (config.CPU_FEATURES or "")
    return bool(ll.get_host_cpu_features().get("avx512f"))


def test_plas_orders_are_those_of_the_sort_before_the_buffer_reuse(monkeypatch):
    """Pins the exact orders (sha256 prefixes) of a padded and a full grid, whole-layout and
    block-by-block, serial and parallel, as sorted at commit 482e7c8, before the blur reused its
    buffers and the kernel its scratch: a 1M-Gaussian
    ``paper_table3`` encode's bytes depend on these orders. (The numba kernels use fast-math:
    another CPU may sum in another order; the golden stream hashes of test_legacy_streams.py
    depend on the same kernels.)"""
    import hashlib

    def digest(order: np.ndarray) -> str:
        return hashlib.sha256(np.ascontiguousarray(order, np.int64).tobytes()).hexdigest()[:16]

    got = []
    for n, shape in ((1800, (48, 40)), (1024, (32, 32))):
        feats = smooth_features(n, seed=7)
        with monkeypatch.context() as patch:
            got.append(digest(sorting.sort_to_grid(feats, shape, seed=2)))
            patch.setattr(plas_module, "BLOCKWISE_GRID", 0)
            got.append(digest(sorting.sort_to_grid(feats, shape, seed=2)))
            patch.setattr(plas_module, "PARALLEL_GROUPS", 1)
            got.append(digest(sorting.sort_to_grid(feats, shape, seed=2)))
    if _kernels_target_avx512():
        assert got in (PLAS_ORDERS_AVX512, PLAS_ORDERS_AVX2)
    else:
        assert got == PLAS_ORDERS_AVX2


# ------------------------------------------------------------------ features and metrics


def test_prepare_features_normalises_and_weights_each_attribute():
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(100, 3)) * [10.0, 1.0, 1.0] + 5.0
    opacity = rng.normal(size=100)
    feats = sorting.prepare_features({"xyz": xyz, "opacity": opacity}, {"opacity": 2.0})
    assert feats.shape == (100, 4) and feats.dtype == np.float32
    # one scale per attribute: the widest xyz column spans [0, 1], the others keep their relative size
    assert np.ptp(feats[:, 0]) == pytest.approx(1.0, abs=1e-6)
    assert np.ptp(feats[:, 1]) < 0.5
    assert np.ptp(feats[:, 3]) == pytest.approx(2.0, abs=1e-6)
    std = sorting.prepare_features({"xyz": xyz}, normalize="std")
    assert np.sqrt((std.astype(np.float64) ** 2).mean()) == pytest.approx(1.0, rel=1e-5)
    assert sorting.prepare_features({"xyz": xyz, "opacity": opacity}, {"opacity": 0}).shape == (100, 3)


def _numpy_preparation(monkeypatch) -> None:
    for module in (sorting.features, sorting.morton, plas_module):
        monkeypatch.setattr(module, "PARALLEL_ROWS", 1 << 40)


def test_parallel_preparation_gives_the_numpy_values(monkeypatch):
    """Features, Morton codes and cell vectors of sorting/_prep.py equal the numpy ones bit for bit."""
    rng = np.random.default_rng(3)
    n = 5000
    attributes = {"xyz": (rng.normal(size=(n, 3)) * [30.0, 1.0, 0.1] + 7.0).astype(np.float32),
                  "opacity": rng.normal(size=n).astype(np.float32),
                  "dc": rng.random((n, 3)), "flat": np.full((n, 2), 3.0, np.float32)}
    weights = {"opacity": 2.5, "flat": 0.7, "dc": 0.0}
    shape = (72, 72)
    cells = rng.permutation(shape[0] * shape[1])[:n]
    for module in (sorting.features, sorting.morton, plas_module):
        monkeypatch.setattr(module, "PARALLEL_ROWS", 1)
    feats = sorting.prepare_features(attributes, weights)
    codes = [sorting.morton.morton_codes(x) for x in (feats, attributes["xyz"], attributes["dc"])]
    state = plas_module.make_state(feats, shape, cells)
    _numpy_preparation(monkeypatch)
    want = sorting.prepare_features(attributes, weights)
    assert feats.dtype == want.dtype and feats.tobytes() == want.tobytes()
    for got, x in zip(codes, (feats, attributes["xyz"], attributes["dc"])):
        assert np.array_equal(got, sorting.morton.morton_codes(x))
    want_state = plas_module.make_state(feats, shape, cells)
    assert state.feat.tobytes() == want_state.feat.tobytes() and np.array_equal(state.idx, want_state.idx)


def test_parallel_preparation_errors(monkeypatch):
    monkeypatch.setattr(sorting.features, "PARALLEL_ROWS", 1)
    xyz = np.zeros((10, 3), np.float32)
    with pytest.raises(SortingError, match="'xyz' contains NaN"):
        sorting.prepare_features({"xyz": np.full((10, 3), np.inf, np.float32)})
    with pytest.raises(SortingError, match="weight of 'xyz'"):
        sorting.prepare_features({"xyz": xyz}, {"xyz": -1.0})
    with pytest.raises(SortingError, match="every attribute has weight 0"):
        sorting.prepare_features({"xyz": xyz}, {"xyz": 0.0})


def test_prepare_features_errors():
    xyz = np.zeros((10, 3))
    with pytest.raises(SortingError, match="rows"):
        sorting.prepare_features({"xyz": xyz, "dc": np.zeros((9, 3))})
    with pytest.raises(SortingError, match="NaN"):
        sorting.prepare_features({"xyz": np.full((10, 3), np.nan)})
    with pytest.raises(SortingError, match="not given"):
        sorting.prepare_features({"xyz": xyz}, {"dc": 1.0})
    with pytest.raises(SortingError, match="normalize"):
        sorting.prepare_features({"xyz": xyz}, normalize="l2")
    with pytest.raises(SortingError, match=">= 0"):
        sorting.prepare_features({"xyz": xyz}, {"xyz": -1.0})


def test_neighbour_distance_and_vad_on_known_grids():
    ramp = np.arange(12, dtype=np.float64).reshape(3, 4)  # right neighbour +1, lower neighbour +4
    assert sorting.neighbour_distance(ramp) == pytest.approx((9 * 1 + 8 * 4) / 17)
    assert sorting.vad(ramp) == pytest.approx(0.0)
    mask = np.ones((3, 4), dtype=bool)
    mask[0, 0] = False  # drops one right and one lower pair
    assert sorting.neighbour_distance(ramp, mask) == pytest.approx((8 * 1 + 7 * 4) / 15)
    checker = (np.indices((4, 4)).sum(0) % 2).astype(float)
    assert sorting.neighbour_distance(checker) == pytest.approx(1.0)
    bumpy = np.array([[0.0, 1.0, 1.0]])  # |differences| 1, 0 -> variance 0.25 along x, none along y
    assert sorting.vad(bumpy) == pytest.approx(0.25)


# ------------------------------------------------------------------ bad input


def test_bad_inputs_raise_sorting_error():
    feats = smooth_features(100)
    with pytest.raises(SortingError, match="do not fit"):
        sorting.sort_to_grid(feats, (8, 8))
    bad = feats.copy()
    bad[3, 1] = np.nan
    with pytest.raises(SortingError, match="NaN"):
        sorting.sort_to_grid(bad, (16, 16))
    with pytest.raises(SortingError, match="2-D"):
        sorting.sort_to_grid(feats[:, 0], (16, 16))
    with pytest.raises(SortingError, match="2-D"):
        sorting.sort_to_grid(feats[None], (16, 16))
    with pytest.raises(SortingError, match="method"):
        sorting.sort_to_grid(feats, (16, 16), method="hilbert")
    with pytest.raises(SortingError, match="unknown schedule option"):
        sorting.sort_to_grid(feats, (16, 16), radius_stpe=0.9)
    with pytest.raises(SortingError, match="radius_step"):
        sorting.sort_to_grid(feats, (16, 16), radius_step=1.5)
    with pytest.raises(SortingError, match="pair"):
        sorting.sort_to_grid(feats, (16, 16, 1))
    with pytest.raises(SortingError, match="only to method='plas'"):
        sorting.sort_to_grid(feats, (16, 16), method="morton", radius_step=0.9)
    with pytest.raises(SortingError, match="importance"):
        sorting.select_for_grid(np.array([1.0, np.nan]), 1)


def test_sorting_does_not_import_the_codec():
    import subprocess
    import sys

    code = "import sys, sorting; sorting.sort_to_grid; print(any(m.startswith('gscodec_shac') for m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
