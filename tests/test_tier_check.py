"""scripts/tier_check.py: importance tiers against the one-grid curve of a size target's plan."""

import json
import math

import pytest

from tests.conftest import load_script


@pytest.fixture(scope="module")
def script():
    return load_script("tier_check")


def test_tier_settings_parse_into_shares_and_offsets(script):
    assert script.parse_tiers("0.5,0.5@-3,8; 0.3,0.7@-3,5@importance;") == [
        ((0.5, 0.5), (-3, 8), None), ((0.3, 0.7), (-3, 5), "importance")]
    with pytest.raises(ValueError, match="SPREAD"):
        script.parse_tiers("0.5,0.5@-3,8@opacity")
    with pytest.raises(ValueError):
        script.parse_tiers("0.5,0.5@-3,x")


def test_the_one_grid_size_is_log_interpolated_and_extrapolated_from_the_nearest_points(script):
    curve = [(1000, 40.0), (2000, 42.0), (8000, 46.0)]
    assert script.one_grid_bytes(curve, 41.0) == pytest.approx(math.sqrt(1000 * 2000))
    assert script.one_grid_bytes(curve, 38.0) == pytest.approx(500.0)  # the first two: x2 per 2 dB
    assert script.one_grid_bytes(curve, 48.0) == pytest.approx(16000.0)  # the last two: x4 per 4 dB


def test_a_tier_setting_is_read_against_the_curve_of_the_plan(tmp_path, small_scene, script):
    from gscodec_shac.io.inria_cameras import write_inria_cameras
    from gscodec_shac.io.ply import write_ply

    ply, cameras = tmp_path / "in.ply", tmp_path / "cameras.json"
    write_ply(ply, small_scene.cloud)
    write_inria_cameras(cameras, small_scene.cameras)
    rows = script.main([str(ply), "--cameras", str(cameras), "--test-every", "4", "--bpg", "120",
                        "--curve=-2,2", "--tiers", "0.5,0.5@0,0", "--out", str(tmp_path / "tc")])
    grid, tiered = rows[:2], rows[2]
    assert [row["kind"] for row in rows] == ["one grid", "one grid", "tiers"]
    assert grid[0]["bytes"] > grid[1]["bytes"] and grid[0]["psnr"] > grid[1]["psnr"]  # 4 QPs apart
    expected = script.one_grid_bytes([(r["bytes"], r["psnr"]) for r in grid], tiered["psnr"])
    assert tiered["saving"] == pytest.approx(1 - tiered["bytes"] / expected)
    assert json.loads((tmp_path / "tc.json").read_text())["rows"][2]["setting"] == "0.5,0.5@+0,+0"
