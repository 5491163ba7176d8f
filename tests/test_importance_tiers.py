"""Importance tiers (codec/tiers.py, format 2.6): the most important Gaussians coded finer, in one file."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gscodec_shac.cli import main
from gscodec_shac.codec import Decoder, Encoder, load_rate_point
from gscodec_shac.codec import tiers
from gscodec_shac.codec.container import Bitstream, Chunk
from gscodec_shac.codec.importance import gaussian_importance, importance_views
from gscodec_shac.codec.rate_points import TierSpec, parse_rate_points
from gscodec_shac.errors import BitstreamError, RatePointError
from gscodec_shac.io.ply import write_ply

TIERS = {"shares": [0.5, 0.5], "qp_offsets": [-2, 10]}


@pytest.fixture(scope="module")
def tiered(small_cloud):
    """(importance, encoder, stream) of the template with two tiers, the second 12 QPs coarser."""
    importance = gaussian_importance(small_cloud, importance_views(small_cloud, None))
    encoder = Encoder(load_rate_point("shac_auto:template").with_overrides(tiers=TIERS), importance=importance)
    return importance, encoder, encoder.encode(small_cloud)


def _point(extra: dict) -> dict:
    return {"points": {"p": {"qp": {"opacity": 20, "rotation": 20, "scale": 20, "sh_dc": 20, "sh_ac": 20}, **extra}}}


def test_a_rate_point_reads_its_tiers_and_each_tier_moves_every_lossy_qp():
    point = parse_rate_points(_point({"tiers": {"shares": [0.3, 0.7], "qp_offsets": [-25, 40]}}), "t.yaml")["p"]
    assert point.tiers == TierSpec((0.3, 0.7), (-25, 40))
    assert point.to_json()["tiers"] == {"shares": [0.3, 0.7], "qp_offsets": [-25, 40]}
    first, second = point.tier_point(0), point.tier_point(1)
    assert first.attributes["opacity"].qp == 0 and second.attributes["opacity"].qp == 51  # clamped
    assert first.attributes["positions"] == point.attributes["positions"]  # lossless: untouched
    assert second.tiers is None and second.keep_share == 1.0 and second.min_opacity == 0.0
    assert "tiers" not in parse_rate_points(_point({}), "t.yaml")["p"].to_json()  # other streams keep their bytes


def test_where_a_qp_is_too_fine_for_the_finest_tier_every_tier_moves_less():
    point = parse_rate_points({"points": {"p": {
        "qp": {"opacity": 0, "rotation": 2, "scale": 3, "sh_dc": 20, "sh_ac": 20},
        "tiers": {"shares": [0.5, 0.5], "qp_offsets": [-3, 8]}}}}, "t.yaml")["p"]
    qps = [{name: point.tier_point(i).attributes[name].qp for name in ("opacity", "rotation", "scale", "sh_dc")}
           for i in (0, 1)]
    assert qps[0] == {"opacity": 0, "rotation": 0, "scale": 0, "sh_dc": 17}
    assert qps[1] == {"opacity": 0, "rotation": 7, "scale": 11, "sh_dc": 28}  # QP 2: 2/3 of +8 (5); QP 0: none



def test_tiers_spread_by_importance_scale_their_offsets_to_three_log2_of_the_importance_ratio():
    point = parse_rate_points(_point({"tiers": {"shares": [0.5, 0.5], "qp_offsets": [-3, 8],
                                                "spread": "importance"}}), "t.yaml")["p"]
    assert point.tiers.spread == "importance" and point.to_json()["tiers"]["spread"] == "importance"
    importance = np.array([8.0, 8.0, 1.0, 1.0, 0.0])  # the halves' means 8 and 1: 3 log2 8 = 9 QPs apart
    groups = tiers.tier_rows(importance, np.arange(4), (0.5, 0.5))
    assert tiers.importance_spread(importance, groups) == pytest.approx(9.0)
    assert point.tiers.with_spread(9.0) == TierSpec((0.5, 0.5), (-2, 7))  # (-3, 8) * 9 / 11, rounded
    assert point.tiers.with_spread(19.2).qp_offsets == (-5, 14)
    assert point.tiers.with_spread(1e9).qp_offsets == (-9, 24)  # at most 3x the given offsets
    unseen = np.array([8.0, 8.0, 0.0, 0.0])  # a tier that shows nothing: no spread to read
    assert tiers.importance_spread(unseen, tiers.tier_rows(unseen, np.arange(4), (0.5, 0.5))) == 0.0
    assert "spread" not in TierSpec((0.5, 0.5), (-2, 7)).to_json()


def test_a_tiered_encode_records_the_offsets_its_importance_gave(small_cloud, tiered):
    importance = tiered[0]
    spec = {"shares": [0.5, 0.5], "qp_offsets": [-3, 8], "spread": "importance"}
    encoder = Encoder(load_rate_point("shac_auto:template").with_overrides(tiers=spec), importance=importance)
    stream = encoder.encode(small_cloud)
    groups = tiers.tier_rows(importance, np.arange(small_cloud.num_gaussians), (0.5, 0.5))
    expected = TierSpec((0.5, 0.5), (-3, 8)).with_spread(tiers.importance_spread(importance, groups))
    assert stream.header["rate_point"]["tiers"] == expected.to_json()
    assert expected.qp_offsets != (-3, 8) and Decoder().decode(stream.to_bytes()).num_gaussians == small_cloud.num_gaussians


@pytest.mark.parametrize("value, problem", [
    ({"shares": [1.0], "qp_offsets": [0]}, "2 to 8"),
    ({"shares": [0.5, 0.4], "qp_offsets": [0, 1]}, "add up to 1"),
    ({"shares": [0.5, 0.5], "qp_offsets": [0]}, "one per share"),
    ({"shares": [0.5, 0.5], "qp_offsets": [0, 60]}, "integers in"),
    ({"shares": [0.5, 0.5], "qp_offsets": [0, True]}, "integers in"),
    ({"shares": [0.5, 0.5], "qp_offsets": [0, 1], "share": 1}, "share"),
    ({"shares": [0, 1.0], "qp_offsets": [0, 1]}, "numbers in (0, 1]"),
    ({"shares": [0.5, 0.5], "qp_offsets": [0, 1], "spread": "opacity"}, "one of importance"),
    ({"shares": [0.5, 0.5], "qp_offsets": [2, 2], "spread": "importance"}, "must rise"),
])
def test_bad_tiers_are_one_clear_error(value, problem):
    with pytest.raises(RatePointError, match="tiers") as info:
        parse_rate_points(_point({"tiers": value}), "t.yaml")
    assert problem in str(info.value)


def test_tier_rows_split_the_kept_rows_by_descending_importance():
    importance = np.array([5.0, 1.0, 9.0, 3.0, 7.0, 0.0])
    kept = np.array([0, 2, 3, 4, 5])  # row 1 was pruned
    first, second = tiers.tier_rows(importance, kept, (0.4, 0.6))
    assert first.tolist() == [2, 4] and second.tolist() == [0, 3, 5]
    assert [g.tolist() for g in tiers.tier_rows(importance, kept[:1], (0.5, 0.5))] == [[], [0]]


def test_a_tier_left_empty_by_a_few_gaussians_is_skipped_and_the_others_keep_their_offsets(small_cloud, tmp_path):
    point = load_rate_point("shac_auto:template").with_overrides(tiers={"shares": [0.5, 0.5], "qp_offsets": [-2, 9]})
    encoder = Encoder(point, importance=np.ones(1))
    stream = encoder.encode(small_cloud.select(np.array([5])))  # rint(0.5) = 0: the first tier is empty
    assert [tier["tier"] for tier in stream.header["tiers"]] == [1]
    assert Decoder().decode(stream.to_bytes()).num_gaussians == 1
    stream.write(tmp_path / "one.gsc")
    assert main(["info", str(tmp_path / "one.gsc")]) == 0


def test_a_tiered_stream_round_trips_its_gaussians_with_the_important_ones_finer(tiered, small_cloud):
    importance, encoder, stream = tiered
    data = stream.to_bytes()
    assert Bitstream.from_bytes(data).version == (2, 6) and tiers.FEATURE in stream.features
    decoded = Decoder().decode(data)
    order = encoder.order_
    assert decoded.num_gaussians == small_cloud.num_gaussians and sorted(order) == list(range(small_cloud.num_gaussians))
    half = small_cloud.num_gaussians // 2
    assert importance[order[:half]].min() >= importance[order[half:]].max()  # the first tier: the most important
    source = small_cloud.select(order)
    error = np.abs(decoded.sh_dc - source.sh_dc).mean(axis=1)
    assert error[:half].mean() < 0.5 * error[half:].mean()
    assert np.abs(decoded.means - source.means).max() < 0.05 * np.ptp(source.means)
    features = [tier["sh"]["features"] for tier in stream.header["tiers"]]
    assert features[0] > features[1]  # the coarser tier dropped features and reads the shared state's first ones
    assert sum(chunk.name == "sh_state" for chunk in stream.chunks) == 1



def _dc_only_rows(encoder: Encoder, stream: Bitstream) -> set[int]:
    """The input rows the decoded ``stream`` gives no view-dependent colour."""
    decoded = Decoder().decode(stream.to_bytes())
    return set(encoder.order_[np.flatnonzero(~decoded.sh_rest.reshape(decoded.num_gaussians, -1).any(axis=1))].tolist())


def test_the_tiers_choose_their_dc_only_gaussians_over_all_rows_as_one_grid_does(tiered, small_cloud):
    importance = tiered[0]
    point = dataclasses.replace(load_rate_point("shac_auto:template").with_overrides(dc_only_energy=0.05), tiers=None)
    one_grid = Encoder(point, importance=importance)
    expected = _dc_only_rows(one_grid, one_grid.encode(small_cloud))
    assert 0 < len(expected) < small_cloud.num_gaussians
    split = Encoder(point.with_overrides(tiers={"shares": [0.5, 0.5], "qp_offsets": [0, 0]}), importance=importance)
    stream = split.encode(small_cloud)
    assert _dc_only_rows(split, stream) == expected  # not a bar of each tier's own energy
    assert sum(tier["sh"].get("dc_only", 0) for tier in stream.header["tiers"]) == len(expected)


def test_a_tier_the_bar_would_leave_without_sh_keeps_its_row_of_most_energy(small_cloud):
    ac_norm = np.linalg.norm(small_cloud.ac_matrix(), axis=1)
    importance = ac_norm + 1.0  # the least important half has the least view-dependent energy too
    point = load_rate_point("shac_auto:template").with_overrides(
        dc_only_energy=0.6, tiers={"shares": [0.5, 0.5], "qp_offsets": [0, 0]})
    encoder = Encoder(point, importance=importance)
    kept = np.arange(small_cloud.num_gaussians)
    split = tiers.tier_rows(importance, kept, (0.5, 0.5))
    flags = encoder._tier_dc_only(small_cloud, kept, split)
    assert flags[split[0]].any() and not flags[split[0]].all()
    coded = split[1][~flags[split[1]]]
    assert coded.tolist() == [split[1][np.argmax(ac_norm[split[1]] ** 2 * small_cloud.activated_opacities()[split[1]])]]


def _corrupted(stream: Bitstream, change) -> bytes:
    copy = Bitstream(dict(stream.header), list(stream.chunks), stream.version, set(stream.features))
    change(copy)
    return copy.to_bytes()


def _rename_first(copy: Bitstream) -> None:
    first = copy.chunks[0]
    copy.chunks[0] = Chunk("t7.positions", first.data, first.meta)


def _miscount(copy: Bitstream) -> None:
    copy.header["num_gaussians"] += 1


def _drop_shared_state(copy: Bitstream) -> None:
    copy.chunks = [c for c in copy.chunks if c.name != "sh_state"]


def _tier_claims_tiers(copy: Bitstream) -> None:
    copy.header["tiers"] = [{**copy.header["tiers"][0], "features": ["tiers"]}, *copy.header["tiers"][1:]]


def _no_tier_list(copy: Bitstream) -> None:
    copy.header["tiers"] = {"oops": 1}


@pytest.mark.parametrize("change, message", [
    (_rename_first, "belongs to no tier"),
    (_miscount, "the tiers hold"),
    (_drop_shared_state, "sh_state"),
    (_tier_claims_tiers, "features"),
    (_no_tier_list, "tier headers"),
])
def test_a_corrupt_tiered_stream_is_one_clear_error(tiered, change, message):
    with pytest.raises(BitstreamError, match="corrupt .gsc file") as info:
        Decoder().decode(_corrupted(tiered[2], change))
    assert message in str(info.value)


def test_a_truncated_tiered_file_is_refused(tiered):
    data = tiered[2].to_bytes()
    with pytest.raises(BitstreamError, match="truncated"):
        Decoder().decode(data[: len(data) - 100])


def test_encode_info_and_decode_of_a_tiered_file(tmp_path, small_cloud, capsys):
    ply, gsc, out = tmp_path / "in.ply", tmp_path / "tiered.gsc", tmp_path / "out.ply"
    write_ply(ply, small_cloud)
    point = tmp_path / "tiered.yaml"
    point.write_text("defaults: {codec: hevc, bits: 12, attributes: {positions: {layout: set, bits: 14}}}\n"
                     "points:\n  p:\n    qp: {opacity: 20, rotation: 20, scale: 20, sh_dc: 10, sh_ac: 25}\n"
                     "    tiers: {shares: [0.25, 0.75], qp_offsets: [-4, 6]}\n")
    assert main(["encode", str(ply), str(gsc), "--rate-point", str(point)]) == 0
    capsys.readouterr()
    assert main(["info", str(gsc)]) == 0
    text = capsys.readouterr().out
    assert "format 2.6" in text and "tiers             2 by importance" in text and "QP offset +6" in text
    assert "t1.sh_dc" in text
    assert main(["decode", str(gsc), str(out)]) == 0
    assert out.is_file()


def test_the_controller_codes_its_plans_in_the_templates_tiers_from_enough_gaussians(small_scene, monkeypatch):
    from gscodec_shac.codec import rate_control
    from gscodec_shac.codec.rate_control import RateController, make_target

    template = dataclasses.replace(load_rate_point("shac_auto:template"), tiers=TierSpec((0.5, 0.5), (-3, 8)))
    controller = RateController(small_scene.cloud, template, views=small_scene.cameras, importance_shares=(),
                                workers=2)
    target = make_target(small_scene.cloud.num_gaussians, bpg=120)
    assert rate_control.TIER_MIN_GAUSSIANS > small_scene.cloud.num_gaussians
    one_grid = controller.encode(target)
    assert not tiers.is_tiered(one_grid.stream) and "tiers" not in one_grid.summary()  # too few Gaussians
    monkeypatch.setattr(rate_control, "TIER_MIN_GAUSSIANS", small_scene.cloud.num_gaussians // 2)
    outcome = controller.encode(target)
    assert outcome.trials[0]["tiered"] == 1.0 and outcome.stream.total_bytes() <= target.value
    finalists = [row for row in outcome.trials if "measured_psnr" in row]
    if tiers.is_tiered(outcome.stream) and len(finalists) == 1:  # it rendered at least its one-grid prediction
        assert finalists[0]["measured_psnr"] >= finalists[0]["model_psnr"]
    elif tiers.is_tiered(outcome.stream):  # it did not, but rendered better than the one-grid file
        assert finalists[0]["measured_psnr"] >= finalists[1]["measured_psnr"]
    else:  # version 23: on 2,000 Gaussians the tiers render below one grid's prediction and its file
        assert finalists[0]["measured_psnr"] < finalists[0]["model_psnr"]
        assert finalists[1]["measured_psnr"] > finalists[0]["measured_psnr"] and not finalists[1]["tiered"]
    tiered = controller._encode(outcome.plan, target)  # the plan in the tiers, as its first encode was coded
    expected = {"shares": [0.5, 0.5], "qp_offsets": [-3, 8]}
    assert tiers.is_tiered(tiered) and tiered.header["rate_point"]["tiers"] == expected
    assert rate_control.Outcome(tiered, outcome.plan, target, 1).summary()["tiers"] == expected  # encode --json
    assert not tiers.is_tiered(controller.encode(rate_control.Target("psnr", 40.0)).stream)  # PSNR: one grid
    assert controller.importance_ is not None  # measured for the tiers, though no importance pruning is tried


def test_rate_points_lists_the_templates_tiers(capsys):
    assert main(["rate-points", "shac_auto"]) == 0
    assert ("tiers:          by importance: 50% QP -3, then 50% QP +8, the offsets scaled by the scene's importance"
            in capsys.readouterr().out)
    assert main(["rate-points", "shac_ladder"]) == 0
    assert "tiers:" not in capsys.readouterr().out
