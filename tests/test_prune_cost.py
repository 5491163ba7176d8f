"""scripts/prune_cost.py: what a Gaussian left by each pruning choice costs, per attribute."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from gscodec_shac.io.ply import write_ply
from tests.conftest import load_script


def test_each_pruning_choice_gets_the_factor_of_its_kept_gaussians(small_scene, tmp_path):
    script = load_script("prune_cost")
    ply, out = tmp_path / "scene.ply", tmp_path / "rows.json"
    write_ply(ply, small_scene.cloud)
    assert script.main([str(ply), "--out", str(out)]) == 0  # orbit views: importance shares prune
    rows = json.loads(out.read_text())
    assert [row["pruning"]["keep_share"] for row in rows] == [0.8, 0.6, 0.45, 0.3]
    qps = script.parse_qps(script.DEFAULT_QPS)
    controller_rows = script.measure(small_scene.cloud, None, qps)
    first = controller_rows[0]
    assert first["kept"] == pytest.approx(0.8)
    # the factor by hand: the kept rows coded alone against the whole cloud, at the same QPs
    from gscodec_shac.codec.encoder import Encoder
    from gscodec_shac.codec.importance import keep_count, most_important
    from gscodec_shac.codec.rate_control import RateController, fitted_stage

    controller = RateController(small_scene.cloud)
    encoder = Encoder(controller._rate_point({**qps, "positions": 16}),
                      sh_stage=fitted_stage(controller.template, small_scene.cloud), fit_stage=False)
    controller._prune_candidates()
    n = small_scene.cloud.num_gaussians
    kept = most_important(controller.importance_, np.arange(n), keep_count(n, 0.8))
    whole = script.per_gaussian_bytes(small_scene.cloud, encoder)
    alone = script.per_gaussian_bytes(small_scene.cloud.select(kept), encoder)
    for name, factor in first["factors"].items():
        assert factor == pytest.approx(alone[name] / whole[name], rel=1e-9)
    assert set(first["random_factors"]) == set(first["factors"])


@pytest.mark.parametrize("text", ["opacity=11", "opacity=11,rotation=16,scale=9,sh_dc=16,sh=52", "x"])
def test_qps_must_name_every_attribute_once(text):
    with pytest.raises(argparse.ArgumentTypeError):
        load_script("prune_cost").parse_qps(text)
