"""The "pca-spatial" SH stage: one SHAC-PCA basis per spatial k-means region (paper Sec. IX)."""

import zlib

import numpy as np
import pytest

from gscodec_shac.codec import Decoder, Encoder
from gscodec_shac.codec.rate_points import parse_rate_points
from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.shac.base import STAGES, StageState, make_stage, stage_from_state
from gscodec_shac.shac.pca import ShacPCA
from gscodec_shac.shac.spatial_pca import SpatialPCA, cluster_positions


def _two_regions(cloud, rank=3, seed=0):
    """The scene with a rank-``rank`` AC matrix whose basis differs between its two spatial k-means regions."""
    rng = np.random.default_rng(seed)
    ac = cloud.ac_matrix()
    left = cluster_positions(cloud.means, 2) == 0
    out = np.empty(ac.shape)
    for side in (left, ~left):
        basis = rng.normal(size=(rank, ac.shape[1])) / np.sqrt(ac.shape[1])
        out[side] = rng.normal(size=(side.sum(), rank)) @ basis * ac.std()
    out += rng.normal(scale=1e-3 * ac.std(), size=ac.shape)
    return cloud.with_ac_matrix(out.astype(np.float32))


def test_registered_with_its_flags():
    cls = STAGES.get("pca-spatial")
    assert cls is SpatialPCA and cls.uses_positions and cls.feature_kind == "components"
    assert {p.flag for p in cls.params if p.flag} >= {"spatial_clusters", "er", "components"}


def test_regions_are_spatial_and_consecutive(small_cloud):
    labels = cluster_positions(small_cloud.means, 8)
    assert labels.min() == 0 and set(np.unique(labels)) == set(range(labels.max() + 1)) and labels.max() <= 7
    assert np.all(np.bincount(labels) >= 64)
    assert np.array_equal(labels, cluster_positions(small_cloud.means, 8))  # seeded
    order = np.random.default_rng(1).permutation(2000)
    assert np.array_equal(labels[order], cluster_positions(small_cloud.means[order], 8))  # row order does not matter
    assert np.all(cluster_positions(small_cloud.means, 1) == 0)
    assert np.all(cluster_positions(small_cloud.means[:100], 8) == 0)  # too few rows per region: one region


def test_spatial_bases_beat_a_global_basis_on_spatially_varying_sh(small_cloud):
    cloud = _two_regions(small_cloud)
    ac = cloud.ac_matrix()
    stage = SpatialPCA(spatial_clusters=2, n_components=3)
    stage.set_positions(cloud.means)
    recon = stage.inverse_transform(stage.fit_transform(ac))
    glob = ShacPCA(n_components=3).fit(ac)
    err_spatial = float(((recon - ac) ** 2).mean())
    err_global = float(((glob.inverse_transform(glob.transform(ac)) - ac) ** 2).mean())
    assert stage.ranks() == [3, 3] and err_spatial < 0.01 * err_global
    # ER mode: each region keeps the fewest components reaching the target
    er = SpatialPCA(spatial_clusters=2, energy_retention=0.99)
    er.set_positions(cloud.means)
    er.fit(ac)
    assert all(m <= 4 for m in er.ranks()) and er.n_features == max(er.ranks())
    er.keep_features(2)
    assert er.ranks() == [2, 2] and er.transform(ac).shape == (2000, 2)


def test_state_round_trip_and_probe(small_cloud):
    ac = small_cloud.ac_matrix()
    stage = make_stage("pca-spatial", spatial_clusters=4, energy_retention=0.9)
    stage.set_positions(small_cloud.means)
    features = stage.fit_transform(ac)
    rebuilt = stage_from_state(StageState.from_bytes(stage.state().to_bytes()))
    assert isinstance(rebuilt, SpatialPCA) and rebuilt.ranks() == stage.ranks()
    assert np.allclose(rebuilt.inverse_transform(features), stage.inverse_transform(features), atol=1e-5)
    assert rebuilt.inverse_transform(np.zeros((1, stage.n_features), np.float32)).shape == (1, 45)  # decoder probe
    bad = stage.state()
    bad.arrays["labels"] = np.full(2000, 9, np.uint8)
    with pytest.raises(GscodecError, match="inconsistent"):
        stage_from_state(bad)


def test_needs_positions_and_valid_parameters(small_cloud):
    with pytest.raises(ValidationError, match="positions"):
        SpatialPCA().fit(small_cloud.ac_matrix())
    for bad in ({"spatial_clusters": 0}, {"spatial_clusters": 256}, {"energy_retention": 2.0},
                {"energy_retention": 0.9, "n_components": 3}):
        with pytest.raises(ValidationError):
            SpatialPCA(**bad)


def test_encoder_decoder_round_trip(small_cloud):
    cloud = _two_regions(small_cloud)
    point = parse_rate_points({"points": {"p": {"codec": "raw", "bits": 16, "sort": {"method": "morton"}}}}, "t")["p"]
    errors, sizes = {}, {}
    for stage, params in (("pca", {"n_components": 3}), ("pca-spatial", {"n_components": 3, "spatial_clusters": 2})):
        encoder = Encoder(point, sh_stage=stage, sh_params=params)
        stream = encoder.encode(cloud)
        decoded = Decoder().decode(stream.to_bytes())
        errors[stage] = float(((decoded.ac_matrix() - cloud.ac_matrix()[encoder.order_]) ** 2).mean())
        sizes[stage] = len(stream.to_bytes())
        assert stream.header["sh"]["stage"] == stage and stream.header["sh"]["features"] == 3
    state = StageState.from_bytes(zlib.decompress(stream.chunk("sh_state").data))
    assert state.arrays["labels"].shape == (2000,)  # the region of every coded Gaussian travels in the state
    assert errors["pca-spatial"] < 0.2 * errors["pca"]
    assert sizes["pca-spatial"] < sizes["pca"] + 4000  # the labels and a second basis cost little here


def _unit_error_per_region(stage, ac, channel, metric=None):
    """The rendered SH error (in ``metric``, else the plain sum of squares) that one unit of error on
    ``channel`` causes in the rows of each region, averaged over the region's rows."""
    features = stage.transform(ac)
    moved = features.copy()
    moved[:, channel] += 1.0
    delta = (stage.inverse_transform(moved) - stage.inverse_transform(features)).astype(np.float64)
    cost = np.einsum("nk,kl,nl->n", delta, metric, delta) if metric is not None else (delta ** 2).sum(axis=1)
    return np.array([cost[stage.labels_ == region].mean() for region in range(len(stage.pcas_))])


@pytest.mark.parametrize("with_metric", [False, True])
def test_unit_weights_make_a_unit_error_cost_the_same_in_every_region(small_cloud, with_metric):
    cloud = _two_regions(small_cloud)
    ac = cloud.ac_matrix()
    rng = np.random.default_rng(3)
    root = rng.normal(size=(45, 45))
    metric = root @ root.T / 45 + np.eye(45) if with_metric else None
    costs = {}
    for unit in (True, False):
        stage = SpatialPCA(spatial_clusters=2, n_components=3, unit_weights=unit)
        stage.set_positions(cloud.means)
        stage.set_metric(metric)
        stage.fit(ac)
        costs[unit] = np.array([_unit_error_per_region(stage, ac, j, metric) for j in range(3)])
        if unit:
            assert np.allclose(stage.feature_weights(), 1.0)
    assert np.allclose(costs[True], 1.0, rtol=1e-3)  # every channel, every region: one unit of rendered error
    if with_metric:  # SHAC-PCA in a metric already scales its components to unit error: the gains are 1
        assert np.allclose(costs[False], 1.0, rtol=1e-3)
    else:  # the fitted scores of the paper's metric: a unit error costs each region its own amount
        assert not np.allclose(costs[False], costs[False][:, :1], rtol=0.05)


def test_unit_weight_gains_travel_in_the_state_and_need_format_2_5(small_cloud):
    cloud = _two_regions(small_cloud)
    point = parse_rate_points({"points": {"p": {"codec": "raw", "bits": 16, "sort": {"method": "morton"}}}}, "t")["p"]
    for unit, side in ((True, "float16"), (False, "float32")):
        params = {"n_components": 3, "spatial_clusters": 2, "unit_weights": unit, "side_dtype": side}
        encoder = Encoder(point, sh_stage="pca-spatial", sh_params=params)
        stream = encoder.encode(cloud)
        state = StageState.from_bytes(zlib.decompress(stream.chunk("sh_state").data))
        assert ("g0" in state.arrays) is unit and state.params.get("unit_weights") is (True if unit else None)
        assert state.arrays["r0_components"].dtype == np.dtype(side)
        assert ("sh_spatial_unit_weights" in stream.features) is unit
        decoded = Decoder().decode(stream.to_bytes())
        error = float(((decoded.ac_matrix() - cloud.ac_matrix()[encoder.order_]) ** 2).mean())
        assert error < 1e-3 * float((cloud.ac_matrix() ** 2).mean())
    # a state whose gains do not fit its components is refused, naming the stage
    stage = SpatialPCA(spatial_clusters=2, n_components=3)
    stage.set_positions(cloud.means)
    bad = stage.fit(cloud.ac_matrix()).state()
    bad.arrays["g1"] = bad.arrays["g1"][:2]
    with pytest.raises(GscodecError, match="pca-spatial state is inconsistent"):
        stage_from_state(bad)


def test_a_decoder_without_the_unit_weights_feature_refuses_the_stream(small_cloud, monkeypatch):
    from gscodec_shac.codec import Bitstream, container
    from gscodec_shac.errors import BitstreamError

    point = parse_rate_points({"points": {"p": {"codec": "raw", "bits": 16, "sort": {"method": "morton"}}}}, "t")["p"]
    data = Encoder(point, sh_stage="pca-spatial", sh_params={"n_components": 3, "spatial_clusters": 2}) \
        .encode(small_cloud).to_bytes()
    assert Bitstream.from_bytes(data).version == (2, 5)
    monkeypatch.delitem(container.FEATURES, "sh_spatial_unit_weights")
    with pytest.raises(BitstreamError, match="sh_spatial_unit_weights"):
        Decoder().decode(data)


def test_a_fitted_stage_codes_other_rows_and_orders_with_their_own_regions(small_cloud):
    """The rate controller fits the stage once on the whole cloud and codes it in grid order (its features
    given) and codes samples of it (the probe): each coded row must travel with its own region."""
    cloud = _two_regions(small_cloud)
    ac = cloud.ac_matrix()
    point = parse_rate_points({"points": {"p": {"codec": "raw", "bits": 16, "sort": {"method": "morton"}}}}, "t")["p"]
    stage = SpatialPCA(spatial_clusters=2, n_components=3)
    stage.set_positions(cloud.means)
    features = stage.fit_transform(ac)
    rows = np.sort(np.random.default_rng(5).choice(cloud.num_gaussians, 700, replace=False))
    for sample, given in ((np.arange(cloud.num_gaussians), features), (rows, None)):
        encoder = Encoder(point, sh_stage=stage, fit_stage=False, stage_features=given)
        decoded = Decoder().decode(encoder.encode(cloud.select(sample)).to_bytes())
        truth = ac[sample][encoder.order_]
        assert float(((decoded.ac_matrix() - truth) ** 2).mean()) < 1e-3 * float((truth ** 2).mean())
    assert stage.labels_.size == cloud.num_gaussians  # the caller's stage keeps its own rows
    # the probe's rows take the regions they were fitted in
    probe = SpatialPCA(spatial_clusters=2, n_components=3)
    probe.set_positions(cloud.means)
    probe.fit(ac)
    probe.locate_rows(cloud.means[rows])
    assert np.array_equal(probe.labels_, stage.labels_[rows])
