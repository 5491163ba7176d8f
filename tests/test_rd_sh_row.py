"""Issue 29's SH row and "Gaussians kept": the rate controller without an SH stage as a sweep method,
BD-rates of a method against its own anchor (``settings.compare``) and the kept count in the report."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gscodec_shac.codec import Decoder
from gscodec_shac.codec.container import Bitstream
from gscodec_shac.codec.rate_points import load_rate_point
from gscodec_shac.codec.rate_control import RateController, make_target
from gscodec_shac.rd import parse_sweep, run_sweep, write_report
from gscodec_shac.rd.methods import NO_SH_LADDER, template_without_sh
from gscodec_shac.rd.report import bd_table, kept_cell
from gscodec_shac.rd.spec import SweepSpecError
from tests.test_rd import tiny_spec

TARGETS = [150, 260]


def test_template_without_sh_codes_the_ac_coefficients_on_a_degree_ladder():
    point = template_without_sh("shac_auto:template")
    assert point.sh_stage == "none" and point.sh_params == {}
    base = point.attributes["sh_features"].qp_for_degree(1)
    assert point.attributes["sh_ac"].qp == tuple(base + step for step in NO_SH_LADDER)
    assert point.positions_as_set  # everything but the SH stage as the template


def test_controller_without_sh_stage_moves_the_ladder_and_meets_the_size(small_scene):
    cloud = small_scene.cloud
    controller = RateController(cloud, template_without_sh("shac_auto:template"), views=small_scene.cameras,
                                workers=1, importance_shares=()).fit()
    assert controller.sh_attribute == "sh_ac"
    target = make_target(cloud.num_gaussians, bpg=120)
    outcome = controller.encode(target)
    data = outcome.stream.to_bytes()
    assert 0.97 * target.value <= len(data) <= target.value
    header = Bitstream.from_bytes(data).header
    assert header["rate_point"]["sh"]["stage"] == "none"
    q = outcome.summary()["settings"]["sh"]
    assert header["rate_point"]["attributes"]["sh_ac"]["qp"] == [min(51, q + s) for s in NO_SH_LADDER]
    decoded = Decoder().decode(data)
    assert decoded.sh_degree == cloud.sh_degree and decoded.num_gaussians == cloud.num_gaussians


@pytest.fixture(scope="module")
def sh_row_run(tmp_path_factory):
    """SHAC-auto and the same controller without an SH stage on the tiny synthetic scene."""
    out = tmp_path_factory.mktemp("shrow") / "out"
    methods = [{"name": "auto", "recipe": "auto", "bpg": TARGETS},
               {"name": "auto-nosh", "recipe": "auto", "sh": "none", "bpg": TARGETS}]
    spec = parse_sweep(tiny_spec(out.parent, methods=methods, sort=None, compare={"auto": "auto-nosh"}),
                       source="shrow", base=out.parent)
    outcome = run_sweep(spec, out, executor="serial", threads=1, progress=False)
    return spec, out, outcome


def test_nosh_method_runs_without_sh_stage_and_keeps_other_keys(sh_row_run):
    spec, _, outcome = sh_row_run
    auto, nosh = spec.methods
    assert "sh" not in auto.params and nosh.params["sh"] == "none"  # runs without `sh` keep their keys
    rows = {(r["method"], r["rate_point"]): r for r in outcome.rows}
    assert all(r["status"] == "ok" for r in rows.values())
    for bpg in TARGETS:
        with_sh, without = rows[("auto", f"bpg-{bpg}")], rows[("auto-nosh", f"bpg-{bpg}")]
        assert without["extra"]["sh_features"] == 45  # every AC coefficient of SH degree 3
        # no PCA basis stored (stage none has no arrays, only its parameters); SHAC-auto stores one
        assert without["sizes"].get("sh_state", 0) < 200 < with_sh["sizes"]["sh_state"]
        assert float(without["bits_per_gaussian"]) <= bpg


def test_report_has_bd_against_own_anchor_and_kept_column(sh_row_run, tmp_path):
    _, out, outcome = sh_row_run
    table = bd_table(outcome.rows, "baseline", {"auto": "auto-nosh"})
    pairs = {(e["method"], e["anchor"]) for e in table}
    assert pairs == {("auto", "auto-nosh")}  # no baseline curve in this sweep: only the compared pair
    assert bd_table(outcome.rows, "baseline") == []
    paths = write_report(out, tmp_path / "report")  # compare read from the sweep's settings
    text = paths["markdown"].read_text()
    assert "| auto vs auto-nosh | PSNR vs uncompressed |" in text
    assert "G kept" in text
    bd = json.loads(paths["bd_json"].read_text())
    assert {e["anchor"] for e in bd} == {"auto-nosh"}
    for row in outcome.rows:
        assert kept_cell(row).startswith(f"{int(row['n_decoded']):,}")


@pytest.mark.parametrize("row, text", [
    ({"n_decoded": 45000, "n_gaussians": 75000,
      "extra": {"rate_control": {"settings": {"keep_share": 0.6, "min_opacity": 0.0}}}}, "45,000 (60%, keep 0.6)"),
    ({"n_decoded": 28118, "n_gaussians": 50000,
      "extra": {"rate_control": {"settings": {"min_opacity": 0.05}}}}, "28,118 (56%, opacity >= 0.05)"),
    ({"n_decoded": 50000, "n_gaussians": 50000, "extra": {}}, "50,000 (100%)"),
    ({"n_decoded": None, "n_gaussians": 50000}, "-"),
])
def test_kept_cell_names_count_share_and_pruning(row, text):
    assert kept_cell(row) == text


@pytest.mark.parametrize("params, message", [
    ({"bpg": [100], "sh": "pca"}, "'sh': must be one of none"),
    ({"bpg": [100], "sh": True}, "'sh': must be one of none"),
    ({"bpg": [100], "sh": {"spatial_clusters": 4}}, "stage"),
    ({"bpg": [100], "sh": {"stage": "pca-spatial", "spatial_clusters": 0}}, "spatial_clusters"),
])
def test_auto_sh_option_is_checked(tmp_path, params, message):
    with pytest.raises(SweepSpecError) as info:
        parse_sweep(tiny_spec(tmp_path, methods=[{"name": "a", "recipe": "auto", **params}]), source="bad.yaml",
                    base=tmp_path)
    assert message in str(info.value)


def test_auto_with_another_sh_stage_fits_the_controller_with_it(tmp_path, small_scene):
    from gscodec_shac.rd.methods import template_with_sh

    sh = {"stage": "pca-spatial", "spatial_clusters": 2, "energy_retention": 0.9999, "side_dtype": "float16"}
    spec = parse_sweep(tiny_spec(tmp_path, methods=[{"name": "sp", "recipe": "auto", "bpg": [100], "sh": sh}]),
                       source="sp.yaml", base=tmp_path)
    assert spec.methods[0].params["sh"] == sh
    point = template_with_sh("shac_auto:template", sh)
    assert point.sh_stage == "pca-spatial" and point.sh_params == {k: v for k, v in sh.items() if k != "stage"}
    assert point.attributes == load_rate_point("shac_auto:template").attributes  # only the stage differs
    cloud = small_scene.cloud
    controller = RateController(cloud, point, views=small_scene.cameras, workers=1, importance_shares=()).fit()
    outcome = controller.encode(make_target(cloud.num_gaussians, bpg=150))
    data = outcome.stream.to_bytes()
    assert Bitstream.from_bytes(data).header["sh"]["stage"] == "pca-spatial" and len(data) <= 150 * 2000 / 8
    decoded = Decoder().decode(data)
    assert decoded.sh_degree == 3 and decoded.num_gaussians == int(outcome.stream.header["num_gaussians"])
    truth = cloud.ac_matrix()[controller._last_order]  # every row decoded through its own region's basis
    error = float(np.linalg.norm(decoded.ac_matrix() - truth) / np.linalg.norm(truth))
    assert error < 0.5


def test_compare_setting_is_checked(tmp_path):
    with pytest.raises(SweepSpecError) as info:
        parse_sweep(tiny_spec(tmp_path, compare={"auto": "auto"}), source="bad.yaml", base=tmp_path)
    assert "settings.compare.auto" in str(info.value)
