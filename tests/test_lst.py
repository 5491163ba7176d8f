"""SHAC-LST (paper Sec. V-B): layout, stage, torch module, schedule."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gscodec_shac import sh_index
from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.shac.base import StageState, make_stage, stage_from_state
from gscodec_shac.shac.lst import ShacLST, compression_ratio, lst_layout, num_transform_params, subset_coefficients
from gscodec_shac.shac.lst_torch import (
    DC_LR,
    SH_REST_LR,
    T_LR_FINAL,
    T_LR_PEAK,
    LSTConfig,
    LSTModule,
    lst_param_groups,
    make_lst_optimizer,
    t_learning_rate,
)


def _random_ac(n: int, degree: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.normal(0.0, 0.1, size=(n, sh_index.num_ac_columns(degree))).astype(np.float32)


# ----------------------------------------------------------------------------- layout
@pytest.mark.parametrize("degree", [2, 3, 4])
def test_parameter_count_matches_eq34(degree):
    expected = sum((3 * (2 * l - 1)) ** 2 for l in range(2, degree + 1))
    assert num_transform_params(degree) == expected
    assert num_transform_params(degree, "highest") == expected
    assert lst_layout(degree).d == 3 * (2 * degree + 1)


def test_eq34_values_from_the_brief():
    assert [num_transform_params(L) for L in (2, 3, 4)] == [81, 306, 747]


def test_subset_is_lowest_degree_per_order():
    members = subset_coefficients(3)
    assert members == ((1, -1), (1, 0), (1, 1), (2, -2), (2, 2), (3, -3), (3, 3))
    assert sorted(m for _, m in members) == list(range(-3, 4))  # one member per order


def test_block_inputs_are_same_orders_below_degree():
    layout = lst_layout(3)
    t2, t3 = layout.blocks
    assert t2.output_coeffs == ((2, -1), (2, 0), (2, 1))
    assert t2.input_coeffs == ((1, -1), (1, 0), (1, 1))
    assert t3.output_coeffs == tuple((3, m) for m in range(-2, 3))
    assert t3.input_coeffs == ((2, -2), (1, -1), (1, 0), (1, 1), (2, 2))
    for b in layout.blocks:
        assert b.shape == (3 * (2 * b.degree - 1),) * 2
        # Square blocks ordered by m with the channel fastest: same order/channel = diagonal.
        np.testing.assert_array_equal(b.same_order_mask(), np.eye(b.shape[0], dtype=bool))
        # Rows index S: the S columns they name are the AC columns of the input coefficients.
        expected = [sh_index.ac_column(l, m, c) for l, m in b.input_coeffs for c in range(3)]
        np.testing.assert_array_equal(layout.subset_columns[b.input_rows], expected)
    covered = np.sort(np.concatenate([layout.subset_columns] + [b.output_columns for b in layout.blocks]))
    np.testing.assert_array_equal(covered, np.arange(45))
    t4 = lst_layout(4).blocks[-1]
    assert t4.input_coeffs == ((3, -3), (2, -2), (1, -1), (1, 0), (1, 1), (2, 2), (3, 3))
    assert t4.output_coeffs == tuple((4, m) for m in range(-3, 4))


def test_highest_subset_selects_other_columns_with_same_d():
    low, high = lst_layout(3, "lowest"), lst_layout(3, "highest")
    assert low.d == high.d == 21
    assert not np.array_equal(low.subset_columns, high.subset_columns)
    assert all(l == 3 for l, _ in high.subset_coeffs)
    assert [b.degree for b in high.blocks] == [1, 2]


# ----------------------------------------------------------------------------- stage
def test_identity_part_reproduces_subset_columns_exactly():
    ac = _random_ac(200, 3)
    rng = np.random.default_rng(1)
    blocks = {b.key: rng.normal(size=b.shape) for b in lst_layout(3).blocks}
    stage = ShacLST.from_blocks(blocks, degree=3)
    s = stage.transform(ac)
    rec = stage.inverse_transform(s)
    np.testing.assert_array_equal(rec[:, lst_layout(3).subset_columns], ac[:, lst_layout(3).subset_columns])
    t = stage.transform_matrix()
    np.testing.assert_allclose(s.astype(np.float64) @ t, rec, rtol=1e-5, atol=1e-6)


def test_zero_T_is_truncation_to_subset():
    ac = _random_ac(100, 3)
    stage = ShacLST.zeros(3)
    rec = stage.inverse_transform(stage.transform(ac))
    expected = np.zeros_like(ac)
    cols = lst_layout(3).subset_columns
    expected[:, cols] = ac[:, cols]
    np.testing.assert_array_equal(rec, expected)


@pytest.mark.parametrize("subset", ["lowest", "highest"])
def test_ridge_fit_recovers_planted_T(subset):
    rng = np.random.default_rng(2)
    layout = lst_layout(3, subset)
    n = 4000
    s = rng.normal(0.0, 0.1, size=(n, layout.d))
    planted = {b.key: rng.normal(0.0, 0.5, size=b.shape) for b in layout.blocks}
    ac = s @ layout.transform_matrix(planted) + rng.normal(0.0, 1e-4, size=(n, 45))
    ac[:, layout.subset_columns] = s
    stage = ShacLST(subset=subset, ridge=0.0).fit(ac)
    for key, value in planted.items():
        np.testing.assert_allclose(stage.blocks_[key], value, atol=2e-3)
    assert stage.blocks_[layout.blocks[0].key].dtype == np.float32


def test_ridge_shrinks_blocks():
    ac = _random_ac(500, 3)
    ac[:, lst_layout(3).blocks[0].output_columns] += ac[:, :9]  # a real dependency to shrink
    loose = ShacLST(ridge=0.0).fit(ac)
    tight = ShacLST(ridge=1.0).fit(ac)
    assert np.linalg.norm(tight.blocks_["t_2"]) < 0.9 * np.linalg.norm(loose.blocks_["t_2"])


def test_state_round_trip_gives_identical_inverse():
    ac = _random_ac(300, 3, seed=3)
    stage = make_stage("lst", ridge=1e-3).fit(ac)
    restored = stage_from_state(StageState.from_bytes(stage.state().to_bytes()))
    assert isinstance(restored, ShacLST)
    s = stage.transform(ac)
    np.testing.assert_array_equal(restored.inverse_transform(s), stage.inverse_transform(s))


def test_compression_ratio_matches_bytes():
    stage = ShacLST.zeros(3)
    assert stage.state().nbytes() == 4 * 306
    for n in (1, 1000, 123_457):
        eq38 = (n * (3 + 21) + 306) / (n * 48)
        assert stage.compression_ratio(n) == pytest.approx(eq38, rel=1e-12)
        assert stage.compression_ratio_bytes(n) == pytest.approx(eq38, rel=1e-12)
        assert stage.compression_ratio_bytes(n, with_header=True) > stage.compression_ratio_bytes(n)
    assert compression_ratio(10**9, 3) == pytest.approx(2 / 4, rel=1e-6)  # eq. 39


def test_user_mistakes_raise_validation_errors():
    with pytest.raises(ValidationError):
        ShacLST(subset="middle")
    with pytest.raises(ValidationError):
        ShacLST(degree=2).fit(_random_ac(10, 3))
    with pytest.raises(ValidationError):
        ShacLST().transform(_random_ac(10, 3))
    with pytest.raises(ValidationError):
        ShacLST.from_blocks({2: np.zeros((9, 9))}, degree=3)
    with pytest.raises(ValidationError):
        ShacLST.from_blocks({2: np.zeros((9, 9)), 3: np.zeros((9, 9))}, degree=3)
    with pytest.raises(ValidationError):
        ShacLST.zeros(3).inverse_transform(np.zeros((4, 20), dtype=np.float32))
    with pytest.raises(ValidationError):
        LSTConfig(operator="vector", structure="dense")
    with pytest.raises(ValidationError):
        LSTModule(operator="linear", degree=1)
    bad = ShacLST.zeros(3).state()
    bad.arrays["t_3"] = np.zeros((3, 3), dtype=np.float32)
    with pytest.raises(GscodecError):
        stage_from_state(bad)


# ----------------------------------------------------------------------------- torch
def test_numpy_stage_and_torch_module_agree():
    rng = np.random.default_rng(4)
    layout = lst_layout(3)
    blocks = {b.key: rng.normal(size=b.shape).astype(np.float32) for b in layout.blocks}
    stage = ShacLST.from_blocks(blocks, degree=3)
    module = LSTModule.from_stage(stage)
    s = rng.normal(size=(64, 21)).astype(np.float32)
    with torch.no_grad():
        out = module(torch.from_numpy(s)).numpy()
    np.testing.assert_allclose(out, stage.inverse_transform(s), rtol=1e-5, atol=1e-5)
    for key, value in module.to_stage().blocks_.items():
        np.testing.assert_array_equal(value, blocks[key])


def test_separate_rgb_never_mixes_channels():
    module = LSTModule(rgb="separate")
    with torch.no_grad():
        for p in module.parameters():
            p.normal_()
    s = torch.zeros(1, 21)
    s[0, 0::3] = 1.0  # only R
    out = module(s)
    assert torch.all(out[0, 1::3] == 0) and torch.all(out[0, 2::3] == 0)
    assert torch.any(out[0, 0::3][3:] != 0)


@pytest.mark.parametrize(
    "overrides, expected",
    [
        ({}, 306),
        ({"rgb": "separate"}, 3 * (3 * 3 + 5 * 5)),
        ({"structure": "dense"}, 21 * 24),
        ({"structure": "dense", "rgb": "separate"}, 3 * 7 * 8),
        ({"init": "identity"}, 306),
        ({"subset": "highest"}, 306),
        ({"operator": "vector"}, 24),
        ({"operator": "vector", "init": "identity"}, 24),
        ({"operator": "linear"}, 21 * 24 + 24),
        ({"operator": "mlp"}, (21 * 48 + 48) + (48 * 48 + 48) + (48 * 24 + 24)),
    ],
)
def test_variant_trains_one_step(overrides, expected):
    torch.manual_seed(0)
    module = LSTModule(**overrides)
    assert module.n_params == expected
    subset = torch.nn.Parameter(torch.randn(32, 21) * 0.1)
    target = torch.randn(32, 45) * 0.1
    groups = lst_param_groups(module, [subset])
    optimizer, scheduler = make_lst_optimizer(groups, total_steps=20)
    before = [p.detach().clone() for p in module.parameters()]
    for _ in range(2):  # the first T step has lr 0 (warm-up from 0)
        optimizer.zero_grad()
        out = module(subset)
        assert out.shape == (32, 45)
        loss = (out - target).pow(2).mean() + module.penalty()
        loss.backward()
        assert all(p.grad is not None for p in module.parameters())
        optimizer.step()
        scheduler.step()
    assert any(not torch.equal(b, p) for b, p in zip(before, module.parameters()))
    with torch.no_grad():
        passed = module(subset)[:, module.subset_index]
    torch.testing.assert_close(passed, subset.detach(), rtol=0, atol=0)


def test_zero_init_starts_as_subset_truncation_and_identity_copies_same_order():
    s = torch.randn(8, 21)
    layout = lst_layout(3)
    for operator in ("matrix", "vector", "linear", "mlp"):
        module = LSTModule(operator=operator)
        out = module(s)
        assert torch.all(out[:, module.remaining_index] == 0), operator
    out = LSTModule(init="identity")(s)
    # (2, 1, G) is predicted as S(1, 1, G); (3, -2, B) as S(2, -2, B)
    assert out[0, sh_index.ac_column(2, 1, 1)] == s[0, list(layout.subset_columns).index(sh_index.ac_column(1, 1, 1))]
    assert out[0, sh_index.ac_column(3, -2, 2)] == s[0, list(layout.subset_columns).index(sh_index.ac_column(2, -2, 2))]


def test_regularization_is_eq36():
    module = LSTModule()
    with torch.no_grad():
        module.weights["t_2"].fill_(2.0)
        module.weights["t_3"].fill_(1.0)
    # ||t_2||^2 / 81 + ||t_3||^2 / 225 = 4 + 1
    assert module.regularization().item() == pytest.approx(5.0)
    assert module.penalty().item() == pytest.approx(5.0 * 5e-3)


def test_learning_rate_schedule_anchors():
    total = 1000
    assert t_learning_rate(0, total) == 0.0
    assert t_learning_rate(50, total) == pytest.approx(T_LR_PEAK)  # end of the 5 % warm-up
    assert t_learning_rate(25, total) == pytest.approx(T_LR_PEAK / 2)
    assert t_learning_rate(total - 1, total) == pytest.approx(T_LR_FINAL)
    values = [t_learning_rate(s, total) for s in range(50, total)]
    assert all(a >= b for a, b in zip(values, values[1:]))  # monotone cosine decay


def test_optimizer_groups_use_paper_rates():
    module = LSTModule()
    subset = torch.nn.Parameter(torch.zeros(4, 21))
    dc = torch.nn.Parameter(torch.zeros(4, 3))
    groups = lst_param_groups(module, [subset], [dc])
    optimizer, scheduler = make_lst_optimizer(groups, total_steps=100)
    lrs = {g["name"]: g["lr"] for g in optimizer.param_groups}
    assert lrs == {"sh_subset": pytest.approx(SH_REST_LR), "sh_dc": pytest.approx(DC_LR), "lst_T": 0.0}
    for _ in range(5):
        optimizer.step()
        scheduler.step()
    lrs = {g["name"]: g["lr"] for g in optimizer.param_groups}
    assert lrs["lst_T"] == pytest.approx(T_LR_PEAK)
    assert lrs["sh_subset"] == pytest.approx(1.25e-4)


def test_refit_subset_lowers_the_ac_error_and_projects_optimally():
    rng = np.random.default_rng(5)
    ac = (rng.normal(size=(2000, 21)) @ rng.normal(size=(21, 45)) * 0.05).astype(np.float32)  # generic rank 21
    err = {}
    for rounds in (0, 20):
        stage = ShacLST(refit_subset=rounds).fit(ac)
        s = stage.transform(ac)
        err[rounds] = np.linalg.norm(ac - stage.inverse_transform(s)) / np.linalg.norm(ac)
    assert err[20] < 0.8 * err[0]
    # transform() is the least-squares S for the fitted T: the residual is orthogonal to T's rows.
    t = stage.transform_matrix()
    residual = ac.astype(np.float64) - s.astype(np.float64) @ t
    assert np.abs(residual @ t.T).max() < 1e-4 * np.abs(ac.astype(np.float64) @ t.T).max()
    restored = stage_from_state(StageState.from_bytes(stage.state().to_bytes()))
    np.testing.assert_array_equal(restored.transform(ac), s)
