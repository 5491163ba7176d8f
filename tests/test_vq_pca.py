"""The "vq-pca" SH stage: vq codebook compressed by SHAC-PCA (gsplat+SHAC-PCA, paper Fig. 4)."""

import zlib

import numpy as np
import pytest

from gscodec_shac.codec import Decoder, Encoder
from gscodec_shac.codec.rate_points import parse_rate_points
from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.shac.base import STAGES, StageState, make_stage, stage_from_state
from gscodec_shac.shac.vq import VectorQuantizer
from gscodec_shac.shac.vq_pca import VqPca


def _point(**sh):
    settings = {"codec": "png", "bits": 8, "sh": sh, "sort": {"method": "morton"}}
    return parse_rate_points({"points": {"p": settings}}, "test")["p"]


def test_registered_with_the_shared_flags():
    cls = STAGES.get("vq-pca")
    assert cls is VqPca and cls.feature_kind == "labels" and cls.rate_attribute == "sh_labels"
    flags = {p.flag for p in cls.params if p.flag}
    assert {"clusters", "er", "components", "centroid_bits"} <= flags


def test_fit_transform_inverse(small_cloud):
    ac = small_cloud.ac_matrix()
    stage = make_stage("vq-pca", n_clusters=300, energy_retention=0.99)
    labels = stage.fit_transform(ac)
    assert labels.shape == (2000, 1) and np.all(labels == np.round(labels))
    assert labels.min() >= 0 and labels.max() < 300 and stage.feature_bits == 9
    m = stage.n_components_
    assert 1 <= m < 45 and stage.codes_.shape == (300, m) and stage.codes_.dtype == np.uint8
    # the PCA keeps >= 99% of the codebook's standardised energy (eq. 26)
    assert stage.pca_.energy_[m - 1] >= 0.99 and (m == 1 or stage.pca_.energy_[m - 2] < 0.99)
    recon = stage.inverse_transform(labels)
    assert np.array_equal(recon, stage.codebook_[labels[:, 0].astype(int)])
    # close to plain vq at the same K: the PCA and 8-bit features add little error
    vq = VectorQuantizer(n_clusters=300, centroid_bits=8).fit(ac)
    err_vq = float(((ac - vq.codebook_[vq.labels_]) ** 2).mean())
    err = float(((ac - recon) ** 2).mean())
    assert err_vq <= err <= 1.3 * err_vq
    # transform of the fitted rows gives the fitted labels (down the same tree)
    assert np.array_equal(stage.transform(ac), labels)


def test_fewer_components_give_a_smaller_codebook(small_cloud):
    ac = small_cloud.ac_matrix()
    small = VqPca(n_clusters=256, n_components=4).fit(ac)
    large = VqPca(n_clusters=256, n_components=20).fit(ac)
    assert small.codes_.shape == (256, 4) and large.codes_.shape == (256, 20)
    assert small.side_info_bytes() < large.side_info_bytes()
    err = [float(((ac - s.codebook_[s.labels_]) ** 2).mean()) for s in (small, large)]
    assert err[1] < err[0]


def test_state_round_trip(small_cloud):
    ac = small_cloud.ac_matrix()
    stage = VqPca(n_clusters=128, centroid_bits=7).fit(ac)
    state = StageState.from_bytes(stage.state().to_bytes())
    rebuilt = stage_from_state(state)
    assert isinstance(rebuilt, VqPca) and rebuilt.centroid_bits == 7
    assert np.array_equal(rebuilt.codebook_, stage.codebook_)
    labels = stage.fit_transform(ac)
    assert np.array_equal(rebuilt.inverse_transform(labels), stage.inverse_transform(labels))
    # without the tree: exhaustive search, never worse than the tree's labels
    exact = rebuilt.transform(ac)[:, 0].astype(int)
    err_exact = ((ac - rebuilt.codebook_[exact]) ** 2).sum(axis=1)
    err_tree = ((ac - stage.codebook_[labels[:, 0].astype(int)]) ** 2).sum(axis=1)
    assert np.all(err_exact <= err_tree + 1e-6)
    # side information: K x M codes, two ranges of M, P (K' x M), mu and sigma (K') as float32
    m = stage.n_components_
    assert stage.side_info_bytes() == 128 * m + 2 * 4 * m + 4 * 45 * m + 2 * 4 * 45


def test_corrupt_states_are_refused(small_cloud):
    stage = VqPca(n_clusters=64).fit(small_cloud.ac_matrix())
    good = stage.state()
    bad_codes = StageState(good.name, good.params, {**good.arrays, "codes": good.arrays["codes"][:, :-1]})
    with pytest.raises(GscodecError, match="inconsistent"):
        stage_from_state(bad_codes)
    missing = StageState(good.name, {k: v for k, v in good.params.items() if k != "pca"}, good.arrays)
    with pytest.raises(GscodecError, match="incomplete"):
        stage_from_state(missing)
    wide = StageState(good.name, {**good.params, "centroid_bits": 2}, good.arrays)
    with pytest.raises(GscodecError, match="above 2 bits"):
        stage_from_state(wide)


def test_bad_parameters():
    with pytest.raises(ValidationError):
        VqPca(n_clusters=0)
    with pytest.raises(ValidationError):
        VqPca(centroid_bits=17)
    with pytest.raises(ValidationError):
        VqPca(energy_retention=1.5)
    with pytest.raises(ValidationError):
        VqPca(energy_retention=0.9, n_components=3)
    with pytest.raises(GscodecError, match="not fitted"):
        VqPca().inverse_transform(np.zeros((3, 1)))


def _low_rank(cloud, rank=6, seed=0):
    """The scene with an AC matrix of rank ``rank`` plus a little noise (real SH is low-rank, paper Sec. IV)."""
    rng = np.random.default_rng(seed)
    ac = cloud.ac_matrix()
    basis = rng.normal(size=(rank, ac.shape[1])) / np.sqrt(ac.shape[1])
    low = rng.normal(size=(ac.shape[0], rank)) @ basis * ac.std() + rng.normal(scale=1e-3 * ac.std(), size=ac.shape)
    return cloud.with_ac_matrix(low.astype(np.float32))


def test_encoder_decoder_round_trip_and_smaller_than_vq(small_cloud):
    sizes, errors = {}, {}
    small_cloud = _low_rank(small_cloud)
    ac = small_cloud.ac_matrix()
    for stage in ("vq", "vq-pca"):
        encoder = Encoder(_point(stage=stage, n_clusters=1024, centroid_bits=8))
        stream = encoder.encode(small_cloud)
        data = stream.to_bytes()
        sizes[stage] = len(data)
        decoded = Decoder().decode(data)
        assert stream.header["sh"]["stage"] == stage and stream.header["sh"]["lossless"] is True
        errors[stage] = float(((decoded.ac_matrix() - ac[encoder.order_]) ** 2).mean())
        if stage == "vq-pca":  # every decoded AC vector is a row of the rebuilt codebook
            codebook = stage_from_state(StageState.from_bytes(zlib.decompress(stream.chunk("sh_state").data))).codebook_
            rows = {row.tobytes() for row in codebook}
            assert all(row.tobytes() in rows for row in decoded.ac_matrix())
    assert sizes["vq-pca"] < sizes["vq"]  # same K, same 8-bit codebook precision: fewer codebook bytes
    assert errors["vq-pca"] <= 1.3 * errors["vq"]


def test_encode_command(tmp_path, small_scene):
    from gscodec_shac.cli import main
    from gscodec_shac.io.ply import write_ply

    ply, gsc = tmp_path / "in.ply", tmp_path / "out.gsc"
    write_ply(ply, small_scene.cloud)
    assert main(["encode", str(ply), str(gsc), "-r", "gsplat_png", "--sort", "none", "--sh", "vq-pca",
                 "--clusters", "256", "--er", "0.99", "-q"]) == 0
    assert main(["decode", str(gsc), str(tmp_path / "out.ply"), "-q"]) == 0
