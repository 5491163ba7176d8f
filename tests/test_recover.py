"""Pruning with recovery: the fine-tune restores the renders, the controller keeps the best source."""

from __future__ import annotations

import numpy as np
import pytest

from gscodec_shac.cli import main
from gscodec_shac.codec.importance import gaussian_importance, keep_count, most_important_counts
from gscodec_shac.codec.rate_control import make_target
from gscodec_shac.codec.rate_recover import RecoveringController, _Coded
from gscodec_shac.errors import ValidationError
from gscodec_shac.io.ply import read_ply, write_ply
from gscodec_shac.rd.methods import Auto, MethodError
from gscodec_shac.train.recover import DEFAULT_ITERATIONS, prune_and_recover


@pytest.fixture(scope="module")
def recovered(small_scene):
    return prune_and_recover(small_scene.cloud, small_scene.cameras, keep_share=0.5, iterations=40)


def test_recovery_keeps_the_share_and_restores_the_renders(small_scene, recovered):
    assert recovered.kept == keep_count(2_000, 0.5) == recovered.cloud.num_gaussians
    assert recovered.dropped == 2_000 - recovered.kept
    # the fine-tune moves the kept Gaussians towards the whole model's renders
    assert recovered.psnr_recovered > recovered.psnr_pruned + 1.0
    assert recovered.summary()["iterations"] == 40
    unmeasured = prune_and_recover(small_scene.cloud, small_scene.cameras, keep_share=0.5, iterations=0).summary()
    assert unmeasured["psnr_pruned"] is None and unmeasured["psnr_recovered"] is None  # valid JSON, not NaN


def test_recovery_is_deterministic(small_scene, recovered):
    again = prune_and_recover(small_scene.cloud, small_scene.cameras, keep_share=0.5, iterations=40, measure=False)
    for name in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"):
        np.testing.assert_array_equal(getattr(again.cloud, name), getattr(recovered.cloud, name))


def test_no_iterations_is_importance_pruning_alone(small_scene):
    cloud, views = small_scene.cloud, small_scene.cameras
    result = prune_and_recover(cloud, views, keep_share=0.3, iterations=0)
    rows = most_important_counts(gaussian_importance(cloud, views), [keep_count(cloud.num_gaussians, 0.3)])[0]
    np.testing.assert_array_equal(result.cloud.means, cloud.means[rows])
    np.testing.assert_array_equal(result.cloud.sh_rest, cloud.sh_rest[rows])


def test_learning_rates_can_be_given_and_are_checked(small_scene, recovered):
    reference = {"lr_means": 1.6e-5, "lr_means_final": 1.6e-6, "lr_opacity": 0.05, "lr_scales": 5e-3}
    other = prune_and_recover(small_scene.cloud, small_scene.cameras, keep_share=0.5, iterations=40, measure=False,
                              learning_rates=reference)
    assert not np.array_equal(other.cloud.opacities, recovered.cloud.opacities)  # the rates reach the trainer
    for bad, match in (({"lr_bogus": 1.0}, "unknown learning rate 'lr_bogus'"), ({"lr_opacity": -1.0}, "positive"),
                       ({"lr_scales": float("nan")}, "positive")):
        with pytest.raises(ValidationError, match=match):
            prune_and_recover(small_scene.cloud, small_scene.cameras, keep_share=0.5, iterations=1, learning_rates=bad)


@pytest.mark.parametrize("share, steps, match", [(0.0, 10, "keep share"), (1.5, 10, "keep share"),
                                                 (float("nan"), 10, "keep share"), (0.5, -1, "iterations")])
def test_bad_recovery_settings_are_clear_errors(small_scene, share, steps, match):
    with pytest.raises(ValidationError, match=match):
        prune_and_recover(small_scene.cloud, small_scene.cameras, keep_share=share, iterations=steps)


# ------------------------------------------------------------------ the controller's choice
@pytest.fixture(scope="module")
def chooser(small_scene):
    return RecoveringController(small_scene.cloud, views=small_scene.cameras, shares=(0.5,), iterations=40,
                                controller_options={"workers": 2}).fit()


def test_the_chooser_keeps_the_best_measured_file_under_a_size(small_scene, chooser):
    target = make_target(2_000, bpg=60)
    outcome = chooser.encode(target)
    rows = outcome.recovery["sources"]
    assert [row["keep"] for row in rows] == [1.0, 0.5]
    coded = [row for row in rows if "measured_psnr" in row]
    assert coded, rows
    best = max(coded, key=lambda row: row["measured_psnr"])
    assert outcome.recovery["keep"] == best["keep"]
    assert outcome.stream.total_bytes() == best["bytes"] <= target.value
    assert outcome.recovery["judged_psnr"] == pytest.approx(best["measured_psnr"], abs=1e-3)
    # reported as a plain target reports it: against the model on the controller's views
    assert outcome.measured_psnr == pytest.approx(best["psnr_controller_views"], abs=1e-3)
    assert outcome.summary()["recovery"]["keep"] == best["keep"]
    assert outcome.stream.header["num_gaussians"] == (2_000 if best["keep"] == 1.0 else 1_000) or \
        outcome.stream.header["num_gaussians"] < 2_000  # the controller may prune a source further


def test_a_recovered_source_gets_the_error_its_recovery_left(chooser):
    recovered = chooser.sources_[1]
    assert 0 < recovered.controller_psnr < 200 and chooser.sources_[0].controller_psnr == float("inf")
    below = recovered.controller_psnr - 3.0
    wanted = chooser._source_target(recovered, make_target(2_000, psnr=below))
    # MSEs add, on the controller's views: 10^(-T/10) = 10^(-R/10) + 10^(-S/10) for the recovery R
    assert 10 ** (-below / 10) == pytest.approx(10 ** (-recovered.controller_psnr / 10) + 10 ** (-wanted.value / 10))
    assert chooser._source_target(recovered, make_target(2_000, psnr=recovered.controller_psnr + 0.1)) is None
    assert chooser._source_target(chooser.sources_[0], make_target(2_000, psnr=below)).value == below


def test_a_psnr_target_keeps_the_smallest_file_as_good_as_the_models(chooser):
    outcome = chooser.encode(make_target(2_000, psnr=30.0))
    model, *recovered = outcome.recovery["sources"]
    assert model["keep"] == 1.0 and "bytes" in model  # the plain controller's answer is always there
    as_good = [row for row in [model, *recovered] if row.get("measured_psnr", -1) >= model["measured_psnr"]]
    best = min(as_good, key=lambda row: row["bytes"])
    assert outcome.stream.total_bytes() == best["bytes"] and outcome.recovery["keep"] == best["keep"]
    assert outcome.measured_psnr >= 30.0  # whichever source: the target met where the controller measures it


def test_a_recovered_file_below_the_target_on_the_controllers_views_is_not_kept(chooser):
    from types import SimpleNamespace

    def coded(source, size, judged, on_controller_views):
        stream = SimpleNamespace(total_bytes=lambda: size)
        return _Coded(source, SimpleNamespace(stream=stream), judged, on_controller_views)

    model, recovered = chooser.sources_
    target = make_target(2_000, psnr=38.0)
    files = [coded(model, 1_000, 37.86, 38.20), coded(recovered, 800, 37.88, 37.95)]
    assert chooser._best(files, target).source is model  # smaller and better on the judges, but 37.95 < 38
    files[1] = coded(recovered, 800, 37.88, 38.05)
    assert chooser._best(files, target).source is recovered
    files[1] = coded(recovered, 800, 37.80, 38.05)
    assert chooser._best(files, target).source is model  # worse than the model's file on the judges


def test_a_recovered_source_below_the_models_file_is_neither_fitted_nor_coded(small_scene):
    fresh = RecoveringController(small_scene.cloud, views=small_scene.cameras, shares=(0.5,), iterations=10,
                                 controller_options={"workers": 2}).fit()
    recovered = fresh.sources_[1]
    assert recovered.controller is None and "fit_0.5" not in fresh.seconds_  # fitted on first use only
    # 120 bits/G: the model's file measures above the recovered model itself, whose files can only be worse
    model, row = fresh.encode(make_target(2_000, bpg=120)).recovery["sources"]
    assert row["source_psnr"] < model["measured_psnr"] and "bytes" not in row
    assert f"{row['source_psnr']:.2f} dB on the judges" in row["skipped"] and recovered.controller is None
    # 30 bits/G: the model's file is far below it, so the recovered source is fitted and coded (and wins here)
    outcome = fresh.encode(make_target(2_000, bpg=30))
    model, row = outcome.recovery["sources"]
    assert model["measured_psnr"] < row["source_psnr"]
    assert recovered.controller is not None and "fit_0.5" in fresh.seconds_
    assert row["measured_psnr"] < row["source_psnr"]  # the rule's premise: coding adds error
    assert outcome.recovery["keep"] == 0.5
    assert {"fit_model", "recover_0.5", "fit_0.5"} <= set(outcome.recovery["seconds"])  # where the time went


# ------------------------------------------------------------------ the command and the sweep recipe
def test_prune_command_writes_the_recovered_model(tmp_path, small_scene, capsys):
    source, out = tmp_path / "in.ply", tmp_path / "pruned.ply"
    write_ply(source, small_scene.cloud)
    assert main(["prune", str(source), str(out), "--keep", "0.25", "--recover", "5", "-q"]) == 0
    assert read_ply(out).num_gaussians == keep_count(2_000, 0.25)
    assert "kept 500 of 2,000 Gaussians; recovered in 5 steps" in capsys.readouterr().out


@pytest.mark.parametrize("extra, match", [(["--keep", "0"], "keep share"), (["--keep", "0.5", "--recover", "-2"],
                                          "iterations"), (["--keep", "0.5", "--split", "train"], "needs --cameras")])
def test_prune_command_refuses_bad_settings_and_writes_nothing(tmp_path, small_scene, capsys, extra, match):
    source, out = tmp_path / "in.ply", tmp_path / "pruned.ply"
    write_ply(source, small_scene.cloud)
    assert main(["prune", str(source), str(out), *extra]) == 2
    err = capsys.readouterr().err
    assert match in err and "Traceback" not in err
    assert not out.exists()


def test_prune_command_refuses_a_gsc_output(tmp_path, small_scene, capsys):
    source = tmp_path / "in.ply"
    write_ply(source, small_scene.cloud)
    assert main(["prune", str(source), str(tmp_path / "x.gsc"), "--keep", "0.5"]) == 2
    assert "gscodec-shac encode" in capsys.readouterr().err


def test_sweep_recipe_checks_its_recover_settings(tmp_path):
    recipe = Auto()
    assert recipe.check({"bpg": [50], "recover": {"keep": 0.6}}, tmp_path)["recover"] == \
        {"keep": 0.6, "iterations": DEFAULT_ITERATIONS}
    assert recipe.check({"bpg": [50], "recover": {"keep": [0.6, 0.45], "iterations": 50}}, tmp_path)["recover"] == \
        {"choose": [0.6, 0.45], "iterations": 50}
    for bad, match in (({"iterations": 10}, "keep"), ({"keep": [0.6, 2]}, r"keep\[1\]"), ({"keep": 0.5, "x": 1}, "x"),
                       ([0.5], "mapping"), ({"keep": 0.5, "iterations": -1}, "iterations")):
        with pytest.raises(MethodError, match=match):
            recipe.check({"bpg": [50], "recover": bad}, tmp_path)


def test_encode_to_a_target_with_recover(tmp_path, small_scene, capsys):
    import json

    from gscodec_shac.io.inria_cameras import write_inria_cameras

    ply, cameras, out = tmp_path / "in.ply", tmp_path / "cameras.json", tmp_path / "out.gsc"
    write_ply(ply, small_scene.cloud)
    write_inria_cameras(cameras, small_scene.cameras)
    assert main(["encode", str(ply), str(out), "--target-bpg", "60", "--cameras", str(cameras), "--recover",
                 "--recover-steps", "60", "--json", "-q"]) == 0
    summary = json.loads(capsys.readouterr().out)
    recovery = summary["rate_control"]["recovery"]
    assert [row["keep"] for row in recovery["sources"]] == [1.0, 0.45]  # RECOVER_SHARES
    assert recovery["steps"] == 60 != DEFAULT_ITERATIONS  # --recover-steps reached the recovery
    assert recovery["keep"] in (1.0, 0.45) and recovery["iterations"] in (0, 60)
    assert 0.97 * 60 <= 8 * out.stat().st_size / 2_000 <= 60  # bits per *input* Gaussian, whichever source


def test_recover_without_a_target_is_a_clear_error(tmp_path, small_scene, capsys):
    ply = tmp_path / "in.ply"
    write_ply(ply, small_scene.cloud)
    assert main(["encode", str(ply), str(tmp_path / "out.gsc"), "--recover"]) == 2
    err = capsys.readouterr().err
    assert "--recover applies to a target" in err and "Traceback" not in err
    assert not (tmp_path / "out.gsc").exists()


def test_a_sweep_scene_can_name_its_calibration_cameras(tmp_path, small_scene):
    """NeRF-Synthetic's test views are a file of their own: the controller and the recovery then need
    the training cameras, not the test views (``calibration``)."""
    from gscodec_shac.io.inria_cameras import write_inria_cameras
    from gscodec_shac.rd import parse_sweep
    from gscodec_shac.rd.scenes import calibration_views, prepare_scene
    from gscodec_shac.rd.spec import SweepSpecError

    ply, tests, calibration = tmp_path / "s.ply", tmp_path / "test.json", tmp_path / "train.json"
    write_ply(ply, small_scene.cloud)
    write_inria_cameras(tests, small_scene.cameras[:3])
    write_inria_cameras(calibration, small_scene.cameras[3:])
    scene = {"name": "s", "ply": str(ply), "cameras": str(tests), "test_every": 1}

    def prepared(**extra):
        spec = parse_sweep({"name": "c", "rate_points": ["shac_ladder:rp1"], "methods": ["baseline"],
                            "scenes": [{**scene, **extra}]}, source="c.yaml", base=tmp_path)
        return prepare_scene(spec.scenes[0], tmp_path / "out")

    plain, named = prepared(), prepared(calibration=str(calibration))
    assert [c.name for c in calibration_views(plain)] == [c.name for c in small_scene.cameras[:3]]  # the test views
    assert [c.name for c in calibration_views(named)] == [c.name for c in small_scene.cameras[3:]]
    assert plain.fingerprint != named.fingerprint and plain.fingerprint == prepared().fingerprint
    with pytest.raises(SweepSpecError, match="need the scene's 'cameras'"):
        parse_sweep({"name": "c", "rate_points": ["shac_ladder:rp1"], "methods": ["baseline"],
                     "scenes": [{"name": "s", "ply": str(ply), "calibration": str(calibration)}]}, source="c.yaml")


def test_recover_checks_rates_option_names_a_malformed_item():
    import argparse

    from tests.conftest import load_script

    recover_check = load_script("recover_check")
    parser = argparse.ArgumentParser()
    assert recover_check.parse_rates(parser, "lr_opacity=0.015, lr_scales=2.5e-3,") == {"lr_opacity": 0.015,
                                                                                        "lr_scales": 2.5e-3}
    for bad in ("lr_opacity", "lr_scales=abc"):
        with pytest.raises(SystemExit):
            recover_check.parse_rates(parser, bad)


@pytest.mark.parametrize("args, message", [(["--recover-steps", "50"], "give --recover too"),
                                           (["--recover", "--recover-steps", "-1"], "0 or more")])
def test_encode_refuses_recover_steps_without_recover_or_below_zero(tmp_path, small_scene, capsys, args, message):
    ply, out = tmp_path / "in.ply", tmp_path / "out.gsc"
    write_ply(ply, small_scene.cloud)
    assert main(["encode", str(ply), str(out), "--target-bpg", "60", *args]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and not out.exists()
