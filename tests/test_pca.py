"""SHAC-PCA (paper eq. 23-30): optimality, rank choice, side information, state, ablations."""

import numpy as np
import pytest

from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.shac.base import StageState, make_stage, stage_from_state
from gscodec_shac.shac.pca import ShacPCA


@pytest.fixture(scope="module")
def ac64(small_cloud):
    return small_cloud.ac_matrix().astype(np.float64)


def _standardized_svd(a):
    """Reference: singular values of eq. 23's A' from a direct numpy SVD."""
    a_std = (a - a.mean(0)) / a.std(0, ddof=1)
    return np.linalg.svd(a_std, compute_uv=False)


def _first_reaching(curve, target):
    return int(np.argmax(curve >= target - 1e-12)) + 1


@pytest.mark.parametrize("m", [1, 5, 24, 44])
def test_reconstruction_error_equals_discarded_energy(ac64, m):
    """Eckart-Young: ||A' - F P^T||^2 = sum of the discarded s_k^2 (eq. 25-29)."""
    pca = ShacPCA(n_components=m, side_dtype="float64").fit(ac64)
    rec = pca.inverse_transform(pca.transform(ac64))
    err = (((ac64 - rec) / pca.scale_) ** 2).sum()
    s = _standardized_svd(ac64)
    assert np.allclose(pca.singular_values_, s, rtol=1e-7, atol=1e-9 * s[0])
    assert err == pytest.approx((s[m:] ** 2).sum(), rel=1e-6, abs=1e-9 * (s**2).sum())


def test_without_standardisation_error_is_discarded_centred_energy(ac64):
    pca = ShacPCA(n_components=10, standardize=False, side_dtype="float64").fit(ac64)
    rec = pca.inverse_transform(pca.transform(ac64))
    s = np.linalg.svd(ac64 - ac64.mean(0), compute_uv=False)
    assert ((ac64 - rec) ** 2).sum() == pytest.approx((s[10:] ** 2).sum(), rel=1e-6)
    assert "scale" not in pca.state().arrays


def test_full_energy_reconstructs_exactly(ac64):
    pca = ShacPCA(energy_retention=1.0, side_dtype="float64").fit(ac64)
    rec = pca.inverse_transform(pca.transform(ac64))
    assert np.abs(rec - ac64).max() < 1e-10
    pca32 = ShacPCA(energy_retention=1.0).fit(ac64)  # float32 side info: exact to float32 precision
    assert np.abs(pca32.inverse_transform(pca32.transform(ac64)) - ac64).max() < 1e-5 * np.abs(ac64).max()


@pytest.mark.parametrize("target", [0.3, 0.8, 0.9, 0.95, 0.97, 0.99, 0.999])
def test_chosen_rank_is_the_smallest_reaching_the_target(ac64, target):
    pca = ShacPCA(energy_retention=target).fit(ac64)
    m = pca.n_components_
    s2 = _standardized_svd(ac64) ** 2
    curve = np.cumsum(s2) / s2.sum()
    assert m == _first_reaching(curve, target)
    assert curve[m - 1] >= target - 1e-9
    if m > 1:
        assert curve[m - 2] < target
    assert pca.energy_[m - 1] >= target - 1e-12 and (m == 1 or pca.energy_[m - 2] < target)
    assert pca.n_features == m and pca.transform(ac64).shape == (len(ac64), m)


@pytest.mark.parametrize("side_dtype,itemsize", [("float32", 4), ("float16", 2)])
def test_eq30_matches_serialised_side_information(ac64, side_dtype, itemsize):
    n, k_ac, m = len(ac64), ac64.shape[1], 24
    pca = ShacPCA(n_components=m, side_dtype=side_dtype).fit(ac64)
    state = pca.state()
    assert state.nbytes() == itemsize * (k_ac * m + 2 * k_ac)  # P, mu, sigma (eq. 30)
    assert pca.n_side_parameters() == k_ac * m + 2 * k_ac
    assert pca.compression_ratio(n) == pytest.approx((n * (3 + m) + k_ac * m + 2 * k_ac) / (n * (k_ac + 3)))
    blob = state.to_bytes()
    expected = (n * (3 + m) * 4 + len(blob)) / (n * (k_ac + 3) * 4)
    assert pca.compression_ratio_bytes(n) == pytest.approx(expected)
    assert len(blob) > state.nbytes()  # the JSON header is counted too
    # Eq. 31: the side information vanishes for large N.
    assert pca.compression_ratio(10**9) == pytest.approx((3 + m) / (k_ac + 3), rel=1e-6)


def test_per_channel_side_information_is_compact(ac64):
    pca = ShacPCA(n_components=12, joint_rgb=False).fit(ac64)
    assert pca.state().nbytes() == 4 * (15 * 12 + 2 * 45)
    assert pca.compression_ratio(100) == pytest.approx((100 * 15 + 15 * 12 + 90) / (100 * 48))


@pytest.mark.parametrize(
    "params",
    [
        {"n_components": 24},
        {"energy_retention": 0.95, "side_dtype": "float16"},
        {"n_components": 9, "joint_rgb": False},
        {"n_components": 27, "include_dc": True},
        {"n_components": 7, "standardize": False},
    ],
)
def test_state_round_trip_gives_identical_reconstruction(small_cloud, params):
    ac = small_cloud.ac_matrix()
    stage = make_stage("pca", **params)
    x = np.concatenate([small_cloud.sh_dc, ac], axis=1) if stage.uses_dc else ac
    features = stage.fit_transform(x)
    rebuilt = stage_from_state(StageState.from_bytes(stage.state().to_bytes()))
    assert isinstance(rebuilt, ShacPCA) and rebuilt.uses_dc == stage.uses_dc
    assert np.array_equal(rebuilt.inverse_transform(features), stage.inverse_transform(features))
    assert np.array_equal(rebuilt.transform(x), features)
    assert rebuilt.compression_ratio_bytes(len(x)) == stage.compression_ratio_bytes(len(x))


def test_zero_variance_columns_give_no_nan():
    rng = np.random.default_rng(1)
    ac = rng.normal(size=(500, 45)).astype(np.float32)
    ac[:, 7] = 0.0
    ac[:, 20] = np.float32(0.1)  # constant, not exactly representable
    for params in ({"n_components": 10}, {"energy_retention": 1.0}, {"n_components": 5, "joint_rgb": False}):
        pca = ShacPCA(**params).fit(ac)
        rec = pca.inverse_transform(pca.transform(ac))
        assert np.isfinite(rec).all() and np.isfinite(pca.energy_).all()
        assert pca.scale_[7] == 1.0 and pca.scale_[20] == 1.0
        assert np.abs(rec[:, [7, 20]] - ac[:, [7, 20]]).max() < 1e-6


def test_all_zero_matrix_is_handled():
    pca = ShacPCA(energy_retention=0.95).fit(np.zeros((50, 9)))
    assert pca.n_components_ == 1
    assert np.array_equal(pca.inverse_transform(pca.transform(np.zeros((3, 9)))), np.zeros((3, 9)))


def test_including_dc_hurts_dc_fidelity(small_cloud):
    """Sec. VII-D1: DC inside the PCA is reconstructed far worse than the AC."""
    ac = small_cloud.ac_matrix().astype(np.float64)
    dc = small_cloud.sh_dc.astype(np.float64)
    x = np.concatenate([dc, ac], axis=1)
    base = ShacPCA(n_components=12).fit(ac)
    base_ac_rmse = np.sqrt(((ac - base.inverse_transform(base.transform(ac))) ** 2).mean())
    for m in (12, 15):  # equal M, and equal per-Gaussian budget (M + 3 DC values)
        with_dc = ShacPCA(n_components=m, include_dc=True).fit(x)
        assert with_dc.uses_dc and not base.uses_dc
        err = x - with_dc.inverse_transform(with_dc.transform(x))
        dc_rmse = np.sqrt((err[:, :3] ** 2).mean())
        assert dc_rmse > 10 * base_ac_rmse  # the baseline codes DC exactly (error 0)
        assert dc_rmse > 10 * np.sqrt((err[:, 3:] ** 2).mean())


def test_separate_rgb_needs_more_components_and_does_worse(ac64):
    joint = ShacPCA(n_components=45, side_dtype="float64").fit(ac64)
    split = ShacPCA(n_components=45, joint_rgb=False, side_dtype="float64").fit(ac64)
    # Joint PCA is optimal over all rank-r projections: its ER curve dominates.
    assert np.all(joint.energy_ >= split.energy_ - 1e-12)
    for target in (0.9, 0.95, 0.99):
        m_joint = ShacPCA(energy_retention=target).fit(ac64).n_components_
        m_split = ShacPCA(energy_retention=target, joint_rgb=False).fit(ac64).n_components_
        assert m_split > m_joint
    errors = {}
    for joint_rgb in (True, False):
        pca = ShacPCA(n_components=12, joint_rgb=joint_rgb).fit(ac64)
        errors[joint_rgb] = (((ac64 - pca.inverse_transform(pca.transform(ac64))) / pca.scale_) ** 2).sum()
    assert errors[False] > 1.5 * errors[True]


def test_per_channel_components_stay_in_their_channel(ac64):
    pca = ShacPCA(n_components=20, joint_rgb=False).fit(ac64)
    for j, c in enumerate(pca.component_channels_):
        others = [r for r in range(45) if r % 3 != c]
        assert np.all(pca.components_[others, j] == 0)
    s2 = pca.singular_values_**2
    assert np.all(np.diff(s2) <= 1e-9 * s2[0])  # merged in global eigenvalue order


def test_float16_side_information_halves_bytes_with_small_effect(ac64):
    p32 = ShacPCA(n_components=24).fit(ac64)
    p16 = ShacPCA(n_components=24, side_dtype="float16").fit(ac64)
    e32 = np.sqrt(((ac64 - p32.inverse_transform(p32.transform(ac64))) ** 2).mean())
    e16 = np.sqrt(((ac64 - p16.inverse_transform(p16.transform(ac64))) ** 2).mean())
    assert p16.state().nbytes() * 2 == p32.state().nbytes()
    assert e32 <= e16 * (1 + 1e-6) and e16 < 1.05 * e32


def test_chunking_does_not_change_the_fit(ac64):
    a = ShacPCA(n_components=10, side_dtype="float64").fit(ac64)
    b = ShacPCA(n_components=10, side_dtype="float64", chunk_size=97).fit(ac64)
    assert np.allclose(a.components_, b.components_, atol=1e-9)
    assert np.allclose(a.transform(ac64), b.transform(ac64), atol=1e-9)


def test_float32_in_float32_out(small_cloud):
    ac = small_cloud.ac_matrix()
    pca = ShacPCA(n_components=8).fit(ac)
    features = pca.transform(ac)
    assert features.dtype == np.float32 and pca.inverse_transform(features).dtype == np.float32


def test_user_mistakes_raise_validation_errors(ac64):
    with pytest.raises(ValidationError, match="not both"):
        ShacPCA(n_components=3, energy_retention=0.9)
    with pytest.raises(ValidationError, match="energy retention"):
        ShacPCA(energy_retention=1.5)
    with pytest.raises(ValidationError, match="positive integer"):
        ShacPCA(n_components=0)
    with pytest.raises(ValidationError, match="side_dtype"):
        ShacPCA(side_dtype="int8")
    with pytest.raises(ValidationError, match="exceeds"):
        ShacPCA(n_components=46).fit(ac64)
    with pytest.raises(ValidationError, match="not fitted"):
        ShacPCA().transform(ac64)
    pca = ShacPCA(n_components=4).fit(ac64)
    with pytest.raises(ValidationError, match="45 columns"):
        pca.transform(ac64[:, :24])
    with pytest.raises(ValidationError, match="bad parameters"):
        make_stage("pca", n_componentz=3)


def test_inconsistent_state_is_rejected(ac64):
    state = ShacPCA(n_components=4).fit(ac64).state()
    state.arrays["components"] = state.arrays["components"][:, :3]
    with pytest.raises(GscodecError, match="inconsistent"):
        stage_from_state(state)
