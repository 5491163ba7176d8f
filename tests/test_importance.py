"""Render-based importance (summed blending weights) and pruning by it (rate point ``prune.keep_share``)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from gscodec_shac.camera import look_at
from gscodec_shac.cli import main
from gscodec_shac.codec import Decoder, Encoder, load_rate_point
from gscodec_shac.codec.importance import gaussian_importance, importance_views, keep_count, most_important
from gscodec_shac.codec.rate_points import load_rate_point_file
from gscodec_shac.errors import RatePointError, ValidationError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.ply import write_ply
from gscodec_shac.render import Renderer

UP = np.array([0.0, 0.0, 1.0])


def _camera(name: str = "front"):
    """At y = -4 looking at the origin along +y, 64x48 pixels."""
    return look_at(name, np.array([0.0, -4.0, 0.0]), np.zeros(3), UP, 64, 48, 60.0)


def _scene() -> GaussianCloud:
    """0: a large opaque disc facing the camera; 1: a small one right behind its centre (hidden);
    2: one far outside the view; 3: one like 1 in view, uncovered; 4: a faint one in view."""
    means = np.array([[0.0, 0.0, 0.0], [0.0, 0.5, 0.0], [30.0, 0.0, 0.0], [1.7, 0.0, 1.2], [-1.7, 0.0, -1.2]])
    scales = np.log(np.array([[0.5, 0.05, 0.5], [0.04, 0.04, 0.04], [0.1, 0.1, 0.1], [0.04, 0.04, 0.04],
                              [0.1, 0.1, 0.1]]))
    opacity = np.array([0.999, 0.99, 0.99, 0.99, 0.03])
    return GaussianCloud(
        means=means, scales=scales, quats=np.tile([1.0, 0.0, 0.0, 0.0], (5, 1)),
        opacities=np.log(opacity / (1 - opacity)), sh_dc=np.full((5, 3), 0.5), sh_rest=np.zeros((5, 0, 3)),
    )


def test_importance_is_zero_when_hidden_or_out_of_view_and_high_for_a_large_opaque_one():
    cloud = _scene()
    importance = gaussian_importance(cloud, [_camera()])
    large, hidden, outside, visible, faint = importance
    assert outside == 0.0
    assert hidden < 0.015 * visible  # about what the disc's capped alpha (0.99) lets through
    assert large > 0.08  # ~ its screen area (2 pi sigma^2 = 350 of 3072 pixels) at alpha near 1
    assert large > visible > faint > 0.0
    assert list(most_important(importance, np.arange(5), 3)) == [0, 3, 4]


def test_contributions_are_the_column_sums_of_the_blending_weights(small_scene):
    renderer = Renderer(small_scene.cloud)
    camera = small_scene.cameras[0]
    weights, _ = renderer.weights(camera)
    sums = np.asarray(weights.sum(axis=0)).ravel()
    totals = renderer.contributions(camera)
    assert totals.shape == (small_scene.cloud.num_gaussians,) and sums.max() > 1.0
    np.testing.assert_allclose(totals, sums, rtol=1e-9, atol=1e-9)


def test_importance_shows_a_bar_over_its_views_when_asked_and_measures_the_same(small_scene, capsys):
    """A scene's cameras make the importance renders long (up to 512 views), so a progress bar counts them."""
    views = small_scene.cameras[:3]
    quiet = gaussian_importance(small_scene.cloud, views)
    assert "importance" not in capsys.readouterr().err
    shown = gaussian_importance(small_scene.cloud, views, progress=True)
    bar = capsys.readouterr().err
    assert "importance" in bar and "/3 " in bar  # the views counted
    np.testing.assert_array_equal(shown, quiet)


def test_views_are_the_cameras_capped_and_narrowed_else_orbit_views(small_scene):
    wide = [c.resized(400, 300) for c in small_scene.cameras]
    views = importance_views(small_scene.cloud, wide, width=100)
    assert len(views) == len(wide) and all(v.width == 100 and v.height == 75 for v in views)
    orbit = importance_views(small_scene.cloud, None, width=64)
    assert len(orbit) > 1 and all(v.width == 64 for v in orbit)


@pytest.mark.parametrize("share", [0.5, 0.3])
def test_pruning_keeps_the_share_of_the_most_important(small_scene, share):
    cloud = small_scene.cloud
    point = load_rate_point("shac_ladder:rp5")
    point = point.with_overrides(keep_share=share)
    encoder = Encoder(point, sh_stage="pca", sh_params={"energy_retention": 0.99}, views=small_scene.cameras)
    stream = encoder.encode(cloud)
    decoded = Decoder().decode(stream.to_bytes())
    n = cloud.num_gaussians
    survivors = np.flatnonzero(cloud.activated_opacities() >= point.min_opacity)
    expected = min(keep_count(n, share), survivors.size)
    assert decoded.num_gaussians == expected == stream.header["num_gaussians"]
    assert stream.header["prune"] == {"min_opacity": point.min_opacity, "keep_share": share, "pruned": n - expected}
    assert stream.header["rate_point"]["prune"]["keep_share"] == share
    importance = gaussian_importance(cloud, importance_views(cloud, small_scene.cameras))
    kept = np.zeros(n, dtype=bool)
    kept[encoder.order_] = True
    assert importance[kept].min() >= importance[survivors[~kept[survivors]]].max()


def test_pruning_without_views_uses_orbit_views_and_a_given_importance_wins(small_cloud):
    point = load_rate_point("shac_ladder:rp5").with_overrides(keep_share=0.4)
    order = Encoder(point, sh_stage="none").encode(small_cloud)  # orbit views
    assert order.header["num_gaussians"] == keep_count(small_cloud.num_gaussians, 0.4)
    favourite = np.zeros(small_cloud.num_gaussians)
    chosen = np.flatnonzero(small_cloud.activated_opacities() >= point.min_opacity)[:10]
    favourite[chosen] = 1.0
    tiny = load_rate_point("shac_ladder:rp5").with_overrides(keep_share=10 / small_cloud.num_gaussians)
    encoder = Encoder(tiny, sh_stage="none", importance=favourite)
    encoder.encode(small_cloud)
    assert sorted(encoder.order_.tolist()) == chosen.tolist()


@pytest.mark.parametrize("value", [0, 1.5, -0.2, "half", True, float("nan")])
def test_bad_keep_share_is_one_clear_error(tmp_path, value):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"points": {"a": {"prune": {"keep_share": value}}}}))
    with pytest.raises(RatePointError, match=r"prune\.keep_share.*\(0, 1\]"):
        load_rate_point_file(path)
    with pytest.raises(RatePointError, match=r"\(0, 1\]"):
        load_rate_point("shac_ladder:rp5").with_overrides(keep_share=value)


def test_cli_prune_keep(tmp_path, small_scene, capsys):
    ply = tmp_path / "in.ply"
    write_ply(ply, small_scene.cloud)
    out = tmp_path / "out.gsc"
    assert main(["encode", str(ply), str(out), "--prune-keep", "0", "-q"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "(0, 1]" in err and "Traceback" not in err and not out.exists()
    assert main(["encode", str(ply), str(out), "--prune-keep", "0.5", "--target-bpg", "100"]) == 2
    assert "--prune-keep cannot be combined with a target" in capsys.readouterr().err
    assert main(["encode", str(ply), str(out), "--prune-keep", "0.5", "-q", "--json"]) == 0
    import json

    summary = json.loads(capsys.readouterr().out)
    assert summary["num_gaussians"] == keep_count(small_scene.cloud.num_gaussians, 0.5)


def test_importance_from_a_given_renderer_is_the_same(small_scene):
    """The rate controller ranks with the renderer it calibrates with (whose colours another view left
    set: the weights do not depend on them)."""
    cloud, views = small_scene.cloud, small_scene.cameras[:3]
    renderer = Renderer(cloud)
    renderer.render(small_scene.cameras[-1])
    assert np.array_equal(gaussian_importance(cloud, views, renderer=renderer), gaussian_importance(cloud, views))
    with pytest.raises(ValidationError, match="another cloud"):
        gaussian_importance(cloud.select(np.arange(10)), views, renderer=renderer)


def test_the_most_important_rows_for_several_counts_are_those_of_one_count_at_a_time():
    from gscodec_shac.codec.importance import most_important, most_important_counts

    rng = np.random.default_rng(4)
    importance = np.round(rng.random(2_000), 2)  # ties
    counts = [1_600, 1_200, 900, 2_000, 2_500, 1]
    everything = np.arange(importance.size)
    for rows, count in zip(most_important_counts(importance, counts), counts):
        assert np.array_equal(rows, most_important(importance, everything, count))
