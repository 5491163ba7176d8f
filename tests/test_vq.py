"""The "vq" SH stage: k-means tree codebook, quantised centroids, integer labels."""

import numpy as np
import pytest

from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.shac.base import StageState, make_stage, stage_from_state
from gscodec_shac.shac.vq import VectorQuantizer, _kmeans, _nearest, _share


def _clusters(n=6000, k=40, dim=45, noise=1e-3, seed=0):
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(k, dim)).astype(np.float32)
    labels = rng.integers(0, k, size=n)
    return (centres[labels] + rng.normal(scale=noise, size=(n, dim))).astype(np.float32), centres


def test_recovers_well_separated_clusters():
    x, _ = _clusters()
    stage = VectorQuantizer(n_clusters=40, centroid_bits=8, init="kmeans++").fit(x)
    recon = stage.inverse_transform(stage.fit_transform(x))
    step = (stage.hi_ - stage.lo_) / 255
    assert np.abs(recon - x).max() <= step.max() / 2 + 5e-3


def test_tree_is_close_to_flat_kmeans(small_cloud):
    ac = small_cloud.ac_matrix()
    flat = _kmeans(ac.copy(), 128, np.random.default_rng(0), 10, "random")
    flat_error = float(((ac - flat[_nearest(ac, flat)]) ** 2).mean())
    tree = VectorQuantizer(n_clusters=128, centroid_bits=16, leaf_work=2000).fit(ac)  # forces several levels
    tree_error = float(((ac - tree.codebook_[tree.labels_]) ** 2).mean())
    assert tree_error <= 1.25 * flat_error
    assert np.array_equal(tree.transform(ac)[:, 0], tree.labels_)  # descending the tree finds the same leaves


def test_features_are_one_integer_label_column(small_cloud):
    ac = small_cloud.ac_matrix()
    stage = make_stage("vq", n_clusters=300, centroid_bits=6)
    assert stage.feature_kind == "labels"
    features = stage.fit_transform(ac)
    assert features.shape == (2000, 1) and stage.n_features == 1
    assert np.all(features == np.round(features)) and features.min() >= 0 and features.max() < 300
    assert stage.feature_bits == 9
    assert stage.codes_.dtype == np.uint8 and stage.codes_.max() < 64
    assert np.array_equal(stage.inverse_transform(features), stage.codebook_[features[:, 0].astype(int)])


def test_centroid_quantisation_error_is_half_a_step(small_cloud):
    ac = small_cloud.ac_matrix()
    exact = VectorQuantizer(n_clusters=64, centroid_bits=16, seed=3).fit(ac)
    coarse = VectorQuantizer(n_clusters=64, centroid_bits=6, seed=3).fit(ac)
    step = (coarse.hi_.astype(np.float64) - coarse.lo_) / 63
    assert np.all(np.abs(coarse.codebook_ - exact.codebook_) <= step / 2 + 1e-4)


def test_state_round_trip_and_exact_search(small_cloud):
    ac = small_cloud.ac_matrix()
    stage = VectorQuantizer(n_clusters=100).fit(ac)
    rebuilt = stage_from_state(StageState.from_bytes(stage.state().to_bytes()))
    assert isinstance(rebuilt, VectorQuantizer)
    assert np.array_equal(rebuilt.codebook_, stage.codebook_)
    labels = stage.fit_transform(ac)
    assert np.array_equal(rebuilt.inverse_transform(labels), stage.inverse_transform(labels))
    exact = rebuilt.transform(ac)[:, 0].astype(int)  # no tree after a state: exhaustive search
    err_exact = ((ac - rebuilt.codebook_[exact]) ** 2).sum(axis=1)
    err_tree = ((ac - stage.codebook_[labels[:, 0].astype(int)]) ** 2).sum(axis=1)
    assert np.all(err_exact <= err_tree + 1e-7)
    assert stage.side_info_bytes() == stage.codes_.nbytes + 2 * 45 * 4


def test_seeded_determinism(small_cloud):
    ac = small_cloud.ac_matrix()
    a, b = VectorQuantizer(n_clusters=200, seed=5).fit(ac), VectorQuantizer(n_clusters=200, seed=5).fit(ac)
    assert np.array_equal(a.codes_, b.codes_) and np.array_equal(a.labels_, b.labels_)
    c = VectorQuantizer(n_clusters=200, seed=6).fit(ac)
    assert not np.array_equal(a.codes_, c.codes_)


def test_more_clusters_than_rows_and_degenerate_rows():
    x = np.random.default_rng(0).normal(size=(50, 9)).astype(np.float32)
    stage = VectorQuantizer(n_clusters=65536).fit(x)
    assert stage.codebook_.shape == (50, 9) and np.array_equal(stage.labels_, np.arange(50))
    same = np.ones((5000, 9), dtype=np.float32)
    flat = VectorQuantizer(n_clusters=1000, leaf_work=10_000).fit(same)  # no split possible: must terminate
    assert np.allclose(flat.inverse_transform(flat.fit_transform(same)), same)


def test_share_keeps_budget_and_bounds():
    counts = np.array([1000, 1, 0, 10, 300])
    alloc = _share(counts, 50)
    assert alloc.sum() == 50 and alloc[2] == 0 and np.all(alloc[counts > 0] >= 1) and np.all(alloc <= counts)


def test_bad_parameters_and_input():
    with pytest.raises(ValidationError):
        VectorQuantizer(n_clusters=0)
    with pytest.raises(ValidationError):
        VectorQuantizer(centroid_bits=17)
    with pytest.raises(ValidationError):
        VectorQuantizer(init="maxmin")
    with pytest.raises(GscodecError, match="not fitted"):
        VectorQuantizer().transform(np.zeros((3, 9), np.float32))
    stage = VectorQuantizer(n_clusters=4).fit(np.random.default_rng(0).normal(size=(40, 9)))
    with pytest.raises(ValidationError, match="0..3"):
        stage.inverse_transform(np.array([[4.0]]))
    with pytest.raises(ValidationError, match="integers"):
        stage.inverse_transform(np.array([[1.5]]))
    with pytest.raises(ValidationError):
        VectorQuantizer().fit(np.zeros((10, 0), np.float32))
