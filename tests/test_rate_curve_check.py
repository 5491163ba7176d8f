"""scripts/rate_curve_check.py: the rate curves between the probe's QPs against the probe coded there."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gscodec_shac.io.ply import write_ply
from tests.conftest import load_script


def test_each_curve_is_scored_against_the_probe_coded_at_more_qps(small_scene, tmp_path, monkeypatch):
    from gscodec_shac.codec import rate_control
    from gscodec_shac.codec.rate_control import PROBE_QPS, RateController

    script = load_script("rate_curve_check")
    monkeypatch.setattr(rate_control, "PROBE_MIN", 500)  # a probe smaller than the cloud
    controller = RateController(small_scene.cloud, views=small_scene.cameras, importance_shares=(), workers=2).fit()
    fitted, fitted_sh, rates, sh_points = script.coded_points(controller, (10, 24))
    assert sorted(fitted["opacity"]) == list(PROBE_QPS) and {10, 24} <= set(rates["opacity"])
    assert any(len(points) > len(fitted_sh.get(feature, {})) for feature, points in sh_points.items())
    # straight segments in log(bytes), by hand, for opacity at QPs 10 and 24
    qps = sorted(fitted["opacity"])
    logs = np.log([fitted["opacity"][q] for q in qps])
    by_hand = np.exp(np.interp([10, 24], qps, logs))
    predicted, coded = script._compare(script.curves()["straight segments"], fitted["opacity"], rates["opacity"])
    assert predicted == pytest.approx(by_hand, rel=1e-12)
    assert coded.tolist() == [rates["opacity"][10], rates["opacity"][24]]


def test_the_command_writes_one_row_per_curve(small_scene, tmp_path, monkeypatch, capsys):
    from gscodec_shac.codec import rate_control

    script = load_script("rate_curve_check")
    ply, out = tmp_path / "scene.ply", tmp_path / "curves.json"
    write_ply(ply, small_scene.cloud)
    with pytest.raises(SystemExit) as exit_info:  # the probe is the whole cloud: nothing is interpolated
        script.main([str(ply), "--out", str(out)])
    assert exit_info.value.code == 2 and "the probe is the whole cloud" in capsys.readouterr().err
    assert not out.exists()
    monkeypatch.setattr(rate_control, "PROBE_MIN", 500)
    assert script.main([str(ply), "--out", str(out)]) == 0
    table = json.loads(out.read_text())
    assert list(table) == ["pchip (used)", "straight segments", "akima", "natural cubic spline"]
    for row in table.values():
        assert row["qp_attributes_mean_abs_log_error"] >= 0 and 0.2 < row["qp_attributes_sum_ratio"] < 5
        assert 0.2 < row["sh_features_sum_ratio"] < 5
