"""scripts/plan_marginals.py: one step of each attribute around a size target's plan, judged on held-out views."""

import json

import pytest

from tests.conftest import load_script


@pytest.fixture(scope="module")
def script():
    return load_script("plan_marginals")


def _row(move, attribute, direction, d_bytes, d_mse):
    return {"move": move, "attribute": attribute, "direction": direction, "d_bytes": d_bytes, "judges_d_mse": d_mse}


def test_the_best_swap_spends_what_the_cheaper_loss_saves_on_the_larger_gain(script):
    import math

    rows = [_row("rotation finer", "rotation", "finer", 100, -500.0),    # gains 5 per byte
            _row("rotation coarser", "rotation", "coarser", -100, 100.0),  # loses 1 per byte
            _row("scale finer", "scale", "finer", 300, -300.0),          # gains 1 per byte
            _row("scale coarser", "scale", "coarser", -50, 100.0)]       # loses 2 per byte
    swap = script.best_swap(rows, "judges_d_mse", 1e4)
    # rotation finer paid by scale coarser: (5 - 2) per byte over min(100, 50) bytes; one attribute's own pair
    # (rotation finer and coarser: 4 per byte over 100 bytes) is no exchange, and scale finer / rotation
    # coarser gains nothing
    assert (swap["finer"], swap["coarser"]) == ("rotation finer", "scale coarser")
    assert swap["bytes_moved"] == 50 and swap["mse_removed"] == pytest.approx(150.0)
    assert swap["db_at_equal_size"] == pytest.approx(10 * math.log10(1e4 / (1e4 - 150.0)))


def test_no_swap_when_every_gain_is_below_every_loss(script):
    rows = [_row("rotation finer", "rotation", "finer", 100, -100.0),
            _row("scale coarser", "scale", "coarser", -100, 300.0),
            _row("sh finer", "sh", "finer", 0, -5.0)]                    # no bytes: no rate to compare
    assert script.best_swap(rows, "judges_d_mse", 1e4) is None


def test_the_plan_recoded_is_the_target_file_and_each_move_is_one_step(tmp_path, small_scene, script):
    from gscodec_shac.io.inria_cameras import write_inria_cameras
    from gscodec_shac.io.ply import write_ply

    ply, cameras = tmp_path / "in.ply", tmp_path / "cameras.json"
    write_ply(ply, small_scene.cloud)
    write_inria_cameras(cameras, small_scene.cameras)
    document = script.main([str(ply), "--cameras", str(cameras), "--test-every", "4", "--bpg", "120",
                            "--codec-options", "preset=fast", "--codec-options", "loop_filters=false", "--out", str(tmp_path / "pm")])
    assert document["bytes"] == document["target_bytes"]  # the controller is deterministic: the same file
    assert document["judges"] == 2  # 8 cameras, every 4th held out
    plan, rows = document["plan"], document["rows"]
    assert {row["attribute"] for row in rows} == set(plan) - {"prune", "dc_only"}
    for row in rows:
        assert row["bytes"] - row["d_bytes"] == document["bytes"]
        assert row["setting"] != plan[row["attribute"]]
        if row["attribute"] == "positions":
            assert row["setting"] - plan["positions"] == (1 if row["direction"] == "finer" else -1)
        else:  # a finer QP is a lower one
            assert (row["setting"] < plan[row["attribute"]]) == (row["direction"] == "finer")
    assert sum(row["d_bytes"] > 0 for row in rows if row["direction"] == "finer") >= len(rows) // 2 - 1
    saved = json.loads((tmp_path / "pm.json").read_text())
    assert saved["rows"] == rows and (tmp_path / "pm.csv").read_text().count("\n") == len(rows) + 1
    fast, unfiltered = document["codec_options"]
    assert fast["codec_options"] == {"preset": "fast"} and unfiltered["codec_options"] == {"loop_filters": False}
    assert document["bytes"] not in (fast["bytes"], unfiltered["bytes"])  # other x265 options, other bytes


def test_codec_options_parse_yaml_values_and_refuse_a_bare_word(script):
    assert script.codec_options("preset=placebo,loop_filters=false") == {"preset": "placebo", "loop_filters": False}
    with pytest.raises(ValueError, match="'placebo' is not KEY=VALUE"):
        script.codec_options("placebo")


def test_sh_stage_at_plan_codes_the_plan_with_each_stage_and_scores_it(tmp_path, small_scene):
    script = load_script("sh_stage_at_plan")
    from gscodec_shac.io.inria_cameras import write_inria_cameras
    from gscodec_shac.io.ply import write_ply

    assert script.stage_variant("pca-spatial:spatial_clusters=2,side_dtype=float16") == \
        ("pca-spatial", {"spatial_clusters": 2, "side_dtype": "float16"})
    with pytest.raises(ValueError, match="names no SH stage"):
        script.stage_variant(":spatial_clusters=2")
    ply, cameras = tmp_path / "in.ply", tmp_path / "cameras.json"
    write_ply(ply, small_scene.cloud)
    write_inria_cameras(cameras, small_scene.cameras)
    document = script.main([str(ply), "--cameras", str(cameras), "--test-every", "4", "--bpg", "120",
                            "--stage", "pca-spatial:spatial_clusters=2", "--sh-offsets=-2,0,2",
                            "--out", str(tmp_path / "st")])
    rows = document["rows"]
    assert [row["stage"] for row in rows] == [document["template_stage"]] * 3 + ["pca-spatial"] * 3
    for curve in (rows[:3], rows[3:]):  # a coarser SH base QP, a smaller file
        assert [row["sh"] - document["plan"]["sh"] for row in curve] == [-2, 0, 2]
        assert curve[0]["bytes"] > curve[1]["bytes"] > curve[2]["bytes"]
    # one basis against two: the second one's state is larger, and the BD-rate is measured on both curves
    assert rows[4]["sh_state_bytes"] > rows[1]["sh_state_bytes"] > 0
    assert document["bd_rates"][0]["bd_rate_percent"] == pytest.approx(script.bd_against(rows[:3], rows[3:]))
    assert (tmp_path / "st.csv").read_text().count("\n") == 7


def test_photos_structure_moves_and_ac_gains(tmp_path, small_scene, script):
    """Photos with 1.5x the model's view-dependent colour: the model scaled by 1.5 matches them better
    than the model itself; each other pruning choice and DC-only bar is one coded variant."""
    import cv2
    import numpy as np

    from gscodec_shac.io.inria_cameras import write_inria_cameras
    from gscodec_shac.io.ply import write_ply
    from gscodec_shac.render import Renderer

    ply, cameras, photos = tmp_path / "in.ply", tmp_path / "cameras.json", tmp_path / "photos"
    write_ply(ply, small_scene.cloud)
    write_inria_cameras(cameras, small_scene.cameras)
    photos.mkdir()
    brighter = Renderer(script.with_ac_gain(small_scene.cloud, 1.5))
    for camera in small_scene.cameras:
        image = np.clip(brighter.render(camera).image, 0, 1)
        cv2.imwrite(str(photos / f"{camera.name}.png"), np.round(image[:, :, ::-1] * 255).astype(np.uint8))
    document = script.main([str(ply), "--cameras", str(cameras), "--test-every", "4", "--judge-images", str(photos),
                            "--bpg", "120", "--no-moves", "--structure-moves", "--ac-gains", "1.5",
                            "--out", str(tmp_path / "pm")])
    plan = document["plan"]
    others = {(row["attribute"], row["setting"]) for row in document["rows"]}
    assert all(row["direction"] == "other" and row["photos_psnr"] is not None for row in document["rows"])
    assert ("prune", plan["prune"]) not in others and ("dc_only", plan["dc_only"]) not in others
    assert sum(attribute == "prune" for attribute, _ in others) >= 1
    assert document["photos_psnr"] < document["model_photos_psnr"]  # coding adds error against the photos too
    model_gain = next(row for row in document["ac_gains"] if row["source"] == "model")
    assert model_gain["photos_psnr"] > document["model_photos_psnr"] + 3  # the photos' own colour: 8-bit close
    assert model_gain["judges_psnr"] < 60  # and no longer the model


def test_ac_gains_need_photos(tmp_path, script, capsys):
    with pytest.raises(SystemExit):
        script.main(["m.ply", "--cameras", "c.json", "--test-every", "4", "--bpg", "100", "--ac-gains", "1.1",
                     "--out", str(tmp_path / "x")])
    assert "--ac-gains needs --judge-images" in capsys.readouterr().err
