"""The synthetic scene: seeded, plausible, and correlated like real SH (paper Sec. IV-B)."""

import numpy as np
import pytest

from gscodec_shac import sh_index
from gscodec_shac.synthetic import make_synthetic_scene


def test_same_seed_same_scene_other_seed_differs():
    a = make_synthetic_scene(1_000, seed=3).cloud
    b = make_synthetic_scene(1_000, seed=3).cloud
    c = make_synthetic_scene(1_000, seed=4).cloud
    assert a.equals(b)
    assert not np.array_equal(a.means, c.means)


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_every_degree(degree):
    cloud = make_synthetic_scene(1_000, sh_degree=degree).cloud
    assert cloud.sh_degree == degree and cloud.num_gaussians == 1_000


def test_values_are_plausible(small_scene):
    cloud = small_scene.cloud
    colour = cloud.sh_dc * 0.28209479177387814 + 0.5
    assert 0.0 <= np.percentile(colour, 1) and np.percentile(colour, 99) <= 1.3
    assert np.abs(cloud.sh_rest).max() < 2.0 and np.abs(cloud.sh_rest).mean() > 1e-3
    assert 0.5 < cloud.activated_opacities().mean() < 0.95
    assert len(small_scene.cameras) == 8


@pytest.fixture(scope="module")
def stats_cloud():
    """20k Gaussians: enough for stable correlation statistics."""
    return make_synthetic_scene(20_000, seed=0, n_cameras=1).cloud


def test_rgb_of_one_coefficient_are_strongly_correlated(stats_cloud):
    corr = np.corrcoef(stats_cloud.ac_matrix().T)
    rgb_pairs = [corr[3 * j, 3 * j + 1] for j in range(15)] + [corr[3 * j + 1, 3 * j + 2] for j in range(15)]
    other_pairs = np.abs(corr[np.triu_indices(45, 3)])
    assert np.median(rgb_pairs) > 0.8
    assert np.median(rgb_pairs) > 3 * np.median(other_pairs)


def test_same_order_coefficients_are_correlated(stats_cloud):
    """Coefficients (l1, m) and (l2, m) of the same order m correlate more than across orders.

    Measured mean |r| ratios (same order / other orders, same channel): trained bonsai 2.0,
    kacy 1.6, this generator 1.44.
    """
    corr = np.abs(np.corrcoef(stats_cloud.ac_matrix().T))
    same, cross = [], []
    for k1 in range(1, 16):
        for k2 in range(k1 + 1, 16):
            (l1, m1), (l2, m2) = sh_index.degree_order(k1), sh_index.degree_order(k2)
            if l1 == l2:
                continue
            value = np.mean([corr[3 * (k1 - 1) + c, 3 * (k2 - 1) + c] for c in range(3)])
            (same if m1 == m2 else cross).append(value)
    assert np.mean(same) > 1.3 * np.mean(cross)


def test_ac_matrix_is_low_rank_like_real_scenes(stats_cloud):
    """Paper Table I averages: rank 22.6 at 95% energy, 95.5% energy in 24 components.

    Uncorrelated columns would need rank 43 and keep 24/45 = 53% in 24 components.
    """
    ac = stats_cloud.ac_matrix().astype(np.float64)
    z = (ac - ac.mean(0)) / ac.std(0)
    energy = np.cumsum(np.linalg.svd(z, compute_uv=False) ** 2)
    energy /= energy[-1]
    rank95 = int(np.searchsorted(energy, 0.95) + 1)
    assert 15 <= rank95 <= 30
    assert energy[23] > 0.9
