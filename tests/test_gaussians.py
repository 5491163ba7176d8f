"""GaussianCloud: validation messages, derived SH degree and reorder/select/concat helpers."""

import numpy as np
import pytest

from gscodec_shac.errors import ValidationError
from gscodec_shac.gaussians import GaussianCloud


def make_arrays(n=6, degree=3, seed=0):
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return dict(
        means=rng.normal(size=(n, 3)),
        scales=rng.normal(size=(n, 3)),
        quats=rng.normal(size=(n, 4)),
        opacities=rng.normal(size=n),
        sh_dc=rng.normal(size=(n, 3)),
        sh_rest=rng.normal(size=(n, k, 3)),
    )


@pytest.mark.parametrize("degree", range(5))
def test_degree_is_derived_from_shape(degree):
    cloud = GaussianCloud(**make_arrays(degree=degree))
    assert cloud.sh_degree == degree
    assert cloud.means.dtype == np.float32
    assert cloud.num_parameters_per_gaussian == 14 + 3 * (degree + 1) ** 2 - 3


def test_sh_share_matches_paper_for_degree_3():
    cloud = GaussianCloud(**make_arrays(degree=3))
    assert cloud.num_parameters_per_gaussian == 59
    assert cloud.num_sh_parameters_per_gaussian == 48


def test_bad_shapes_and_dtypes_are_named():
    arrays = make_arrays()
    with pytest.raises(ValidationError, match=r"quats must have shape \(N, 4\)"):
        GaussianCloud(**{**arrays, "quats": arrays["quats"][:, :3]})
    with pytest.raises(ValidationError, match="opacities has 5 rows but means has 6"):
        GaussianCloud(**{**arrays, "opacities": arrays["opacities"][:5]})
    with pytest.raises(ValidationError, match="floating-point"):
        GaussianCloud(**{**arrays, "sh_dc": arrays["sh_dc"].astype(np.int32)})
    with pytest.raises(ValidationError, match="fit no SH degree"):
        GaussianCloud(**{**arrays, "sh_rest": arrays["sh_rest"][:, :14]})


def test_non_finite_values_report_count_and_rows():
    arrays = make_arrays()
    arrays["scales"][2, 1] = np.nan
    arrays["scales"][4, 0] = np.inf
    arrays["scales"][4, 2] = -np.inf
    with pytest.raises(ValidationError, match=r"scales has 3 non-finite value\(s\).*in 2 Gaussian\(s\), rows 2, 4"):
        GaussianCloud(**arrays)


def test_select_reorder_concat():
    cloud = GaussianCloud(**make_arrays(n=6), extra={"nx": np.arange(6, dtype=np.float32)})
    perm = np.array([5, 4, 3, 2, 1, 0])
    rev = cloud.reorder(perm)
    np.testing.assert_array_equal(rev.means, cloud.means[::-1])
    np.testing.assert_array_equal(rev.extra["nx"], np.arange(6)[::-1])
    assert rev.reorder(perm).equals(cloud)
    with pytest.raises(ValidationError, match="permutation"):
        cloud.reorder(np.array([0, 0, 1, 2, 3, 4]))
    mask = np.array([True, False] * 3)
    assert cloud.select(mask).num_gaussians == 3
    both = GaussianCloud.concat([cloud.select(slice(0, 2)), cloud.select(slice(2, 6))])
    assert both.equals(cloud)
    with pytest.raises(ValidationError, match="SH degrees"):
        GaussianCloud.concat([cloud, cloud.truncate_sh(1)])


def test_ac_matrix_round_trip_and_truncation():
    cloud = GaussianCloud(**make_arrays())
    assert cloud.ac_matrix().shape == (6, 45)
    assert cloud.with_ac_matrix(cloud.ac_matrix()).equals(cloud)
    low = cloud.truncate_sh(2)
    assert low.sh_degree == 2
    np.testing.assert_array_equal(low.ac_matrix(), cloud.ac_matrix()[:, :24])
