"""The view metric of the SH AC coefficients and SHAC-PCA fitted in it (rate controller version 18)."""

from __future__ import annotations

import numpy as np
import pytest

from gscodec_shac.camera import look_at
from gscodec_shac.errors import ValidationError
from gscodec_shac.sh import sh_basis
from gscodec_shac.shac.pca import ShacPCA
from gscodec_shac.shac.view_metric import IDENTITY_SHARE, footprints, view_metric


def _sphere(count: int, radius: float) -> np.ndarray:
    """``count`` points spread evenly on a sphere (Fibonacci lattice)."""
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    phi = np.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    return radius * np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _ac(rows: int = 4000, columns: int = 45, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(rows, columns)) @ rng.normal(size=(columns, columns)) * 0.1 + rng.normal(size=columns)


def test_cameras_all_around_weigh_every_coefficient_alike():
    means = np.random.default_rng(1).normal(scale=1e-3, size=(200, 3))
    metric = view_metric(means, _sphere(2000, 100.0), 3, identity_share=0.0)
    assert np.abs(metric - np.eye(45)).max() < 0.02


def test_the_metric_is_the_mean_squared_colour_error_over_gaussians_and_cameras():
    rng = np.random.default_rng(2)
    means, centres = rng.normal(size=(50, 3)), np.array([[6.0, 0.5, 1.0], [0.0, -5.0, 2.0], [-4.0, 3.0, -1.0]])
    metric = view_metric(means, centres, 2, identity_share=0.0)
    error = rng.normal(size=(8, 3))  # (coefficients, RGB), coefficient-major as the AC matrix
    shown = []
    for centre in centres:
        basis = sh_basis(means - centre, 2)[:, 1:]
        shown.append(((basis @ error) ** 2).sum(axis=1))
    expected = np.mean(shown) * 8 / np.trace(_gram(means, centres, 2))  # normalised to a mean eigenvalue of 1
    assert error.reshape(-1) @ metric @ error.reshape(-1) == pytest.approx(expected, rel=1e-9)
    assert np.all(metric[0::3, 1::3] == 0) and np.all(metric[1::3, 2::3] == 0)  # R, G, B apart


def _gram(means: np.ndarray, centres: np.ndarray, degree: int) -> np.ndarray:
    basis = np.concatenate([sh_basis(means - c, degree)[:, 1:] for c in centres])
    return basis.T @ basis / basis.shape[0]


def test_a_ring_of_cameras_weighs_the_coefficients_unevenly_and_the_identity_share_bounds_it():
    means = np.random.default_rng(3).normal(scale=0.1, size=(500, 3))
    ring = _sphere(400, 10.0)
    ring = ring[np.abs(ring[:, 2]) < 1.0]  # cameras near the horizon only
    pure = np.linalg.eigvalsh(view_metric(means, ring, 3, identity_share=0.0)[::3, ::3])
    mixed = np.linalg.eigvalsh(view_metric(means, ring, 3)[::3, ::3])
    assert pure.max() / pure.min() > 10
    assert mixed.min() >= IDENTITY_SHARE - 1e-9 and mixed.mean() == pytest.approx(1.0)


def test_gaussians_count_by_their_share_of_the_picture():
    rng = np.random.default_rng(5)
    means = rng.normal(size=(40, 3))
    centres = np.array([[7.0, 1.0, 0.5], [-2.0, 6.0, 1.0]])
    weights = rng.uniform(0.5, 2.0, size=40)
    hidden = weights.copy()
    hidden[20:] = 0.0  # transparent or tiny: shows in no pixel
    np.testing.assert_allclose(view_metric(means, centres, 3, footprints=hidden),
                               view_metric(means[:20], centres, 3, footprints=weights[:20]), rtol=1e-12)
    # a Gaussian twice as far from a camera fills a quarter of the pixels
    one = np.array([[0.0, 0.0, 0.0]])
    near_far = view_metric(one, np.array([[2.0, 0.0, 0.0], [0.0, 4.0, 0.0]]), 1, footprints=np.ones(1),
                           identity_share=0.0)[::3, ::3]
    # SH degree 1 (y, z, x order): the +x camera weighs 4x the +y camera's
    assert near_far[2, 2] / near_far[0, 0] == pytest.approx(4.0)


def test_footprints_are_opacity_times_the_two_largest_axes():
    log_scales = np.log(np.array([[1.0, 2.0, 3.0], [4.0, 0.5, 1.0]]))
    np.testing.assert_allclose(footprints(log_scales, np.array([0.5, 1.0])), [0.5 * 6.0, 4.0])


def test_a_camera_counts_only_the_gaussians_in_its_picture():
    means = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 20.0]])  # the second is behind the camera
    camera = look_at("front", [0.0, 0.0, 10.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], width=64, height=48, fx=60.0)
    np.testing.assert_allclose(view_metric(means, [camera], 2),
                               view_metric(means[:1], np.array([camera.center]), 2), rtol=1e-12)


def test_cameras_that_frame_no_gaussian_are_a_clear_error():
    camera = look_at("away", [0.0, 0.0, 10.0], [0.0, 0.0, 20.0], [0.0, 1.0, 0.0], width=64, height=48, fx=60.0)
    with pytest.raises(ValidationError, match="none of the 1 cameras frames"):
        view_metric(np.zeros((5, 3)), [camera], 3)


@pytest.mark.parametrize("kwargs, message", [
    ({"centres": np.zeros((0, 3))}, "camera"),
    ({"degree": 0}, "degree"),
    ({"identity_share": 1.5}, "identity_share"),
])
def test_bad_metric_inputs_are_clear_errors(kwargs, message):
    args = {"means": np.ones((10, 3)), "centres": np.array([[5.0, 0.0, 0.0]]), "degree": 3, **kwargs}
    with pytest.raises(ValidationError, match=message):
        view_metric(args.pop("means"), args.pop("centres"), args.pop("degree"), **args)


# ---------------------------------------------------------------- SHAC-PCA in a metric
def _metric(seed: int = 4) -> np.ndarray:
    means = np.random.default_rng(seed).normal(size=(300, 3))
    return view_metric(means, np.array([[8.0, 0.0, 0.5], [0.0, 8.0, 0.3], [-8.0, 1.0, 0.0]]), 3)


def test_a_unit_error_on_any_component_costs_one_unit_of_the_metric():
    ac, metric = _ac(), _metric()
    stage = ShacPCA(energy_retention=1.0, side_dtype="float64")
    stage.set_metric(metric)
    stage.fit(ac)
    np.testing.assert_allclose(stage.feature_weights(), 1.0, rtol=1e-9)
    features = stage.transform(ac)
    np.testing.assert_allclose(stage.inverse_transform(features), ac, atol=1e-9)
    bumped = features.copy()
    bumped[:, 7] += 0.5
    error = stage.inverse_transform(bumped) - ac
    assert np.einsum("ni,ij,nj->n", error, metric, error) == pytest.approx(np.full(len(ac), 0.25), rel=1e-6)


def test_the_metric_orders_the_components_by_what_it_weighs():
    ac = _ac()
    metric = np.eye(45)
    metric[:3, :3] *= 1000.0  # the first coefficient (R, G, B) weighs most
    stage = ShacPCA(n_components=3, side_dtype="float64")
    stage.set_metric(metric)
    stage.fit(ac)
    # the three leading components reconstruct that coefficient (nearly) exactly
    error = stage.inverse_transform(stage.transform(ac)) - ac
    assert np.abs(error[:, :3]).max() < 0.05 * np.abs(ac[:, :3] - ac[:, :3].mean(0)).max()
    plain = ShacPCA(n_components=3, side_dtype="float64").fit(ac)
    plain_error = plain.inverse_transform(plain.transform(ac)) - ac
    assert np.abs(plain_error[:, :3]).max() > 5 * np.abs(error[:, :3]).max()


def test_decoders_invert_a_metric_stage_from_its_state_as_the_encoder_does():
    ac = _ac()
    stage = ShacPCA(energy_retention=0.999, side_dtype="float16")
    stage.set_metric(_metric())
    stage.fit(ac)
    features = stage.transform(ac)
    rebuilt = ShacPCA.from_state(type(stage.state()).from_bytes(stage.state().to_bytes()))
    np.testing.assert_array_equal(rebuilt.inverse_transform(features), stage.inverse_transform(features))


def test_without_a_metric_the_stage_is_the_papers():
    ac = _ac()
    paper = ShacPCA(energy_retention=0.99).fit(ac)
    reset = ShacPCA(energy_retention=0.99)
    reset.set_metric(_metric())
    reset.set_metric(None)
    reset.fit(ac)
    np.testing.assert_array_equal(reset.components_, paper.components_)
    np.testing.assert_array_equal(reset.transform(ac), paper.transform(ac))


@pytest.mark.parametrize("stage, metric, message", [
    (lambda: ShacPCA(joint_rgb=False), np.eye(45), "joint-RGB"),
    (lambda: ShacPCA(include_dc=True), np.eye(48), "joint-RGB"),
    (lambda: ShacPCA(), np.triu(np.ones((45, 45))), "symmetric"),
])
def test_metrics_a_stage_cannot_take_are_clear_errors(stage, metric, message):
    with pytest.raises(ValidationError, match=message):
        stage().set_metric(metric)


def test_a_metric_of_the_wrong_size_is_a_clear_error_at_fit():
    stage = ShacPCA()
    stage.set_metric(np.eye(24))
    with pytest.raises(ValidationError, match="24 x 24"):
        stage.fit(_ac())


def test_the_energy_retention_keeps_the_papers_rank_in_a_metric():
    ac, metric = _ac(), _metric()
    paper = ShacPCA(energy_retention=0.95).fit(ac)
    weighed = ShacPCA(energy_retention=0.95)
    weighed.set_metric(metric)
    weighed.fit(ac)
    assert weighed.n_components_ == paper.n_components_ < 45
    np.testing.assert_array_equal(weighed.energy_, paper.energy_)  # the SH's own spectrum
    assert not np.allclose(np.abs(weighed.components_), np.abs(paper.components_))  # another basis


# ---------------------------------------------------------------- fixed rate points with cameras
def test_cli_encode_with_cameras_fits_shac_pca_in_their_view_metric(tmp_path, capsys):
    import json

    from gscodec_shac.cli import main
    from gscodec_shac.codec import Decoder, Encoder
    from gscodec_shac.io.cameras import load_cameras
    from gscodec_shac.io.ply import read_ply

    ply, cameras = tmp_path / "scene.ply", tmp_path / "cameras.json"
    assert main(["synthetic", str(ply), "-n", "1500", "--views", "4"]) == 0
    weighed, plain = tmp_path / "weighed.gsc", tmp_path / "plain.gsc"
    point = ["-r", "shac_ladder:rp4", "--sh", "pca", "-q"]
    capsys.readouterr()
    assert main(["encode", str(ply), str(weighed), "--cameras", str(cameras), "--json", *point]) == 0
    assert json.loads(capsys.readouterr().out)["sh_view_metric_cameras"] == 4
    assert main(["encode", str(ply), str(plain), *point]) == 0
    cloud = read_ply(ply)
    metric = view_metric(cloud.means, load_cameras(cameras), cloud.sh_degree,
                         footprints=footprints(cloud.scales, cloud.activated_opacities()))
    expected = Encoder("shac_ladder:rp4", sh_stage="pca", sh_metric=metric).encode(cloud).to_bytes()
    assert weighed.read_bytes() == expected
    assert weighed.read_bytes() != plain.read_bytes()
    assert Decoder().decode(weighed.read_bytes()).num_gaussians == cloud.num_gaussians
    # a stage that cannot take the metric: one clear error, nothing written
    other = tmp_path / "other.gsc"
    assert main(["encode", str(ply), str(other), "--cameras", str(cameras), "-r", "shac_ladder:rp4", "--sh", "lst"]) == 2
    assert "SHAC-PCA" in capsys.readouterr().err and not other.exists()


def test_an_encoder_metric_for_a_stage_that_cannot_take_it_is_a_clear_error(small_cloud):
    from gscodec_shac.codec import Encoder

    with pytest.raises(ValidationError, match="cannot weigh"):
        Encoder("shac_ladder:rp4", sh_stage="vq", sh_metric=np.eye(45)).encode(small_cloud)


def test_cameras_an_sh0_model_cannot_use_are_named_in_a_note(tmp_path, capsys):
    from gscodec_shac.cli import main
    from gscodec_shac.io.ply import read_ply, write_ply

    ply, cameras = tmp_path / "scene.ply", tmp_path / "cameras.json"
    assert main(["synthetic", str(ply), "-n", "800", "--views", "3"]) == 0
    flat = tmp_path / "flat.ply"
    write_ply(flat, read_ply(ply).truncate_sh(0))
    capsys.readouterr()
    assert main(["encode", str(flat), str(tmp_path / "flat.gsc"), "--cameras", str(cameras), "-q"]) == 0
    assert "the cameras are not used: the model has no view-dependent colour" in capsys.readouterr().err
