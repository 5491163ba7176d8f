"""Rate control (SHAC-auto) and water-filled SH QPs: targets met, clear errors, determinism."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from gscodec_shac.cli import main
from gscodec_shac.codec import Decoder, Encoder, load_rate_point
from gscodec_shac.codec.rate_points import parse_rate_points
from gscodec_shac.codec.allocation import MAX_QP, waterfill_qps
from gscodec_shac.codec.importance import keep_count
from gscodec_shac.codec.rate_control import (
    IMPORTANCE_SHARES,
    MAX_ENCODES,
    PSNR_WINDOW,
    SIZE_TOLERANCE,
    VISIBILITY_BOUNDS,
    RateController,
    Target,
    TargetUnreachableError,
    _key,
    make_target,
    parse_size,
)
from gscodec_shac.errors import RatePointError, ValidationError
from gscodec_shac.io.ply import write_ply


@pytest.fixture(scope="module")
def controller(small_scene):
    return RateController(small_scene.cloud, views=small_scene.cameras, workers=2).fit()


# ---------------------------------------------------------------- targets
@pytest.mark.parametrize("text, value", [("2.5MB", 2.5e6), ("800kB", 8e5), ("1200000", 1.2e6), ("1 KiB", 1024),
                                         ("3mib", 3 * 1024**2), ("10 bytes", 10)])
def test_sizes_parse_with_units(text, value):
    assert parse_size(text) == pytest.approx(value)


@pytest.mark.parametrize("text", ["", "2.5 parsecs", "-3MB", "MB", "0"])
def test_bad_sizes_are_clear_errors(text):
    with pytest.raises(ValidationError, match="size"):
        parse_size(text)


def test_exactly_one_target():
    assert make_target(1000, bpg=80) == Target("bytes", 10_000)
    with pytest.raises(ValidationError, match="exactly one"):
        make_target(1000, size="1MB", psnr=40)
    with pytest.raises(ValidationError, match="exactly one"):
        make_target(1000)


# ------------------------------------------------------------ water-filling
def test_waterfill_gives_equal_weighted_steps_and_drops_weak_features():
    ranges = np.array([8.0, 4.0, 2.0, 1.0, 1e-6])
    qps = waterfill_qps(ranges, None, base_qp=20)
    assert qps == [20, 26, 32, 38]  # 6 QP per halving of the range; the last one dropped (QP > 51)
    weighted = waterfill_qps(np.array([1.0, 1.0]), np.array([1.0, 4.0]), base_qp=30)
    assert weighted == [36, 30]  # twice the error weight: the same step needs a range twice as fine
    assert all(q <= MAX_QP for q in waterfill_qps(np.array([1.0, 1e-3, 1.0]), None, 45))


def test_waterfilled_pca_stream_round_trips_with_a_qp_per_component(small_cloud):
    point = dataclasses.replace(load_rate_point("shac_auto:template"), tiers=None)  # one stream's chunks
    stream = Encoder(point).encode(small_cloud)
    qps = [stream.chunk(c).meta["qp"] for c in stream.header["attributes"]["sh"]["chunks"]]
    assert len(set(qps)) > 3 and qps[0] == point.attributes["sh_features"].qp
    decoded = Decoder().decode(stream.to_bytes())
    assert decoded.num_gaussians == small_cloud.num_gaussians
    coarse = Encoder(point.with_overrides(codec_options={"preset": "ultrafast"}))
    assert coarse.encode(small_cloud).header["sh"]["features"] <= stream.header["sh"]["features"]



def test_a_fractional_base_qp_moves_only_the_features_whose_offsets_round_up():
    """Version 17: between two whole base QPs the features' QPs are each the lower or the higher one's,
    more of them the higher one's as the base rises, and a whole base is unchanged."""
    rng = np.random.default_rng(3)
    ranges = rng.uniform(0.05, 4.0, 40)
    low, high = waterfill_qps(ranges, None, 20), waterfill_qps(ranges, None, 21)
    assert waterfill_qps(ranges, None, 20.0) == low
    moved = []
    for base in (20.25, 20.5, 20.75):
        qps = waterfill_qps(ranges, None, base)
        assert all(q in (a, b) for q, a, b in zip(qps, low, high))
        moved.append(sum(q != a for q, a in zip(qps, low)))
    assert 0 < moved[0] < moved[1] < moved[2] < len(low)


def test_the_sh_error_model_reads_a_fractional_base_where_the_features_qps_have_moved_to():
    """A quarter step of the base that raises most features' QPs counts as most of a whole step."""
    from gscodec_shac.codec.allocation import whole_base_equivalent

    ranges = np.random.default_rng(3).uniform(0.05, 4.0, 40)
    bases = np.arange(20.0, 21.01, 0.25)
    equivalent = whole_base_equivalent(ranges, None, bases)
    low, qps = np.array(waterfill_qps(ranges, None, 20)), [np.array(waterfill_qps(ranges, None, b)) for b in bases]
    moved = [float(np.mean(q[: low.size] - low)) for q in qps[:-1]]  # no feature is dropped below 21 here
    assert equivalent[0] == 20 and equivalent[-1] == 21
    assert np.allclose(equivalent[:-1], 20 + np.array(moved)) and np.all(np.diff(equivalent) > 0)
    assert not np.allclose(equivalent, bases)  # not the base itself: the features' offsets are not evenly spread


def test_a_fractional_base_qp_is_a_waterfill_rate_point_setting_only():
    def point(qp: dict, allocation: str = "waterfill") -> object:
        return parse_rate_points({"defaults": {"codec": "hevc", "sh": {"stage": "pca"},
                                               "attributes": {"sh_features": {"allocation": allocation}}},
                                  "points": {"p": {"qp": {"opacity": 20, "rotation": 20, "scale": 20, "sh_dc": 20,
                                                          "sh_ac": 20, **qp}}}}, "test")["p"]

    assert point({"sh_features": 20.75}).attributes["sh_features"].qp == 20.75
    whole = point({"sh_features": 21.0}).attributes["sh_features"].qp
    assert whole == 21 and isinstance(whole, int)
    for qp, allocation, says in [({"sh_features": 20.5}, "degree", "allocation: waterfill"),
                                 ({"sh_features": 20.3}, "waterfill", "multiple of 0.25"),
                                 ({"opacity": 20.5}, "waterfill", "an integer")]:
        with pytest.raises(RatePointError, match=says):
            point(qp, allocation)


def test_the_controller_chooses_the_waterfilled_base_in_quarter_steps_and_codes_them(controller, small_cloud):
    """The SH features' base QP is chosen in quarter steps (the degree ladder without an SH stage stays
    whole), and a plan's fractional base codes each feature at its water-filled QP."""
    choices = controller.models_["sh"].choices
    assert np.allclose(np.diff(choices), 0.25) and choices[0] == 0 and choices[-1] == MAX_QP
    assert all(np.allclose(m.choices, np.round(m.choices)) for n, m in controller.models_.items() if n != "sh")
    hull = controller._hull()
    assert any(not float(p.settings["sh"]).is_integer() for p in hull)
    plan = next(p for p in hull if not float(p.settings["sh"]).is_integer() and p.settings["prune"] == 0)
    point = plan.rate_point
    assert point.attributes["sh_features"].qp == plan.settings["sh"]
    stream = Encoder(point, sh_stage=controller.stage_, fit_stage=False).encode(small_cloud)
    coded = [q for c in stream.header["attributes"]["sh"]["chunks"]
             for q in [stream.chunk(c).meta["qp"]] * (stream.chunk(c).meta["channels"][1]
                                                     - stream.chunk(c).meta["channels"][0])]
    below = waterfill_qps(controller._sh_ranges, controller.stage_.feature_weights(), math.floor(plan.settings["sh"]))
    above = waterfill_qps(controller._sh_ranges, controller.stage_.feature_weights(), math.ceil(plan.settings["sh"]))
    assert all(a <= q <= b for q, a, b in zip(coded, below, above)) and coded != below[:len(coded)]


def test_template_codes_at_12_bits_which_qp_0_decodes_closer_than_10(small_cloud):
    """Version 15: x265's QP 0 is no finer at 12 bits, but the 10-bit rounding no longer adds to its error."""
    template = load_rate_point("shac_auto:template")
    lossy = [name for name, spec in template.attributes.items() if spec.codec == "hevc" and not spec.lossless]
    assert set(lossy) >= {"opacity", "rotation", "scale", "sh_dc", "sh_features"}
    assert all(template.attributes[name].bits == 12 for name in lossy)
    errors, sizes = {}, {}
    for bits in (10, 12):
        point = parse_rate_points({"points": {"p": {
            "codec": "hevc", "codec_options": {"preset": "ultrafast"}, "bits": bits, "sort": {"method": "none"},
            "qp": {"opacity": 0, "rotation": 0, "scale": 0, "sh_dc": 0, "sh_ac": 0}}}}, "t")["p"]
        stream = Encoder(point).encode(small_cloud)
        decoded = Decoder().decode(stream.to_bytes())  # no sort: the rows come back in the input's order
        errors[bits] = {"scale": np.mean((decoded.scales - small_cloud.scales) ** 2),
                        "sh_dc": np.mean((decoded.sh_dc - small_cloud.sh_dc) ** 2)}
        sizes[bits] = sum(len(stream.chunk(c).data) for name in ("scale", "sh_dc")
                          for c in stream.header["attributes"][name]["chunks"])
    for name in ("scale", "sh_dc"):  # 0.92 of the 10-bit error here, in as many bytes
        assert errors[12][name] < 0.95 * errors[10][name], name
    assert sizes[12] < 1.1 * sizes[10]


def test_the_hull_is_the_per_multiplier_search_done_at_once(controller):
    """The hull takes every attribute's choice for all multipliers at once and shares each attribute's
    bytes and MSE between its plans: the same plans, bytes and MSE as one search per multiplier."""
    lams = np.geomspace(1e-3, 1e15, 400)
    for model in controller.models_.values():
        assert model.best_choices(lams).tolist() == [float(model.choices[np.argmin(model.bytes + lam * model.mse)])
                                                     for lam in lams]
    reference: dict[tuple, object] = {}
    positions = controller.models_["positions"]
    for index, (_, kept, _) in enumerate(controller.prune_):
        position_bytes = np.array([controller._position_bytes(int(b), index) for b in positions.choices])
        for dc in range(len(controller.dc_only_)):
            models = controller._dc_models(dc)
            for lam in lams:
                settings = {name: float(m.choices[np.argmin(m.bytes + lam / (kept * controller._prune_factor(index, name))
                                                          * m.mse)])
                            for name, m in models.items() if name != "positions"}
                settings |= {"positions": float(positions.choices[np.argmin(position_bytes + lam * positions.mse)]),
                             "prune": index, "dc_only": dc}
                reference.setdefault(tuple(sorted(settings.items())), controller._predict(settings))
    hull = controller._hull()
    assert [(p.settings, p.predicted_bytes, p.predicted_mse) for p in hull] == \
        [(p.settings, p.predicted_bytes, p.predicted_mse) for p in reference.values()]
    assert hull[0].rate_point == controller._rate_point(hull[0].settings)  # built when asked for


# ------------------------------------------------------------ controller
@pytest.mark.parametrize("bits_per_gaussian", [160, 320])
def test_size_target_is_met_from_below_within_tolerance(controller, small_cloud, bits_per_gaussian):
    target = Target("bytes", bits_per_gaussian * small_cloud.num_gaussians / 8)
    outcome = controller.encode(target)
    size = len(outcome.stream.to_bytes())
    assert (1 - SIZE_TOLERANCE) * target.value <= size <= target.value
    assert outcome.stream.header["rate_control"]["target"] == {"kind": "bytes", "value": target.value}
    assert outcome.measured_psnr == pytest.approx(controller.measured_psnr(outcome.stream))


def test_more_bytes_buy_more_quality(controller, small_cloud):
    low = controller.encode(Target("bytes", 140 * small_cloud.num_gaussians / 8))
    high = controller.encode(Target("bytes", 400 * small_cloud.num_gaussians / 8))
    assert high.measured_psnr > low.measured_psnr + 3


@pytest.mark.parametrize("psnr", [34.0, 38.0])
def test_psnr_target_lands_within_its_window(controller, psnr):
    outcome = controller.encode(Target("psnr", psnr))
    assert psnr <= outcome.measured_psnr <= psnr + PSNR_WINDOW
    assert outcome.measured_psnr == pytest.approx(controller.measured_psnr(outcome.stream))
    trials = outcome.summary()["trials"]
    assert len(trials) == outcome.encodes <= controller.max_encodes
    assert trials[-1]["bytes"] == len(outcome.stream.to_bytes())  # the last encode is the one kept
    assert all({"predicted_psnr", "model_psnr", "measured_psnr", "predicted_bytes"} <= set(t) for t in trials)
    assert outcome.summary()["probe_visibility"] == round(controller.probe_visibility_, 3) == 1.0  # the probe is the cloud
    # the file kept is the smallest that met the target (a bigger one in the window does not stop the search)
    assert len(outcome.stream.to_bytes()) == min(t["bytes"] for t in trials if t["measured_psnr"] >= psnr)


def test_a_psnr_search_tries_single_steps_from_a_start_whose_own_prediction_is_stale(controller):
    """Version 10: a start plan's own byte prediction dates from before its encode (bonsai's 37.5 dB first
    plan: predicted 395,002 bytes, coded 483,227); its single steps are compared with the start's bytes
    as the corrected models predict them now, so they stay candidates (before, none was tried and the
    search ended outside the window)."""
    import dataclasses

    target = Target("psnr", 38.0)
    start = controller.plan(target)
    below = controller._step(start, cheaper=True)
    stale = dataclasses.replace(start, predicted_bytes=0.5 * start.predicted_bytes)
    measured = [(stale, int(start.predicted_bytes), target.value + PSNR_WINDOW + 0.2),
                (below, math.ceil(below.predicted_bytes), target.value - 0.5)]  # the chain ends at it
    found = controller._next_for_quality(target, measured, {_key(start), _key(below)})
    assert found is not None
    singles = {_key(p) for p in controller._single_steps(start) if p.predicted_bytes < start.predicted_bytes}
    assert _key(found[0]) in singles - {_key(below)}


def test_a_bigger_encode_below_the_target_does_not_bound_the_chain(controller):
    """Version 19: an encode below the target with more bytes than the smallest one above the window
    (another QP mix; on bonsai 0.9 dB lower at the same size) is no bracket along the chain: the next
    plan is the one chosen without it (before, it stopped the chain after one step each time)."""
    target = Target("psnr", 38.0)
    start = controller.plan(target)
    size = math.ceil(start.predicted_bytes)
    above = (start, size, target.value + PSNR_WINDOW + 0.6)
    bigger_below = (controller._step(start, cheaper=False), size + 1000, target.value - 0.3)
    tried = {_key(start), _key(bigger_below[0])}
    alone = controller._next_for_quality(target, [above], tried)
    assert alone is not None
    assert controller._next_for_quality(target, [above, bigger_below], tried) == alone
    smaller_below = (controller._step(start, cheaper=True), size - 1000, target.value - 0.3)
    bracketed = controller._next_for_quality(target, [above, smaller_below], tried | {_key(smaller_below[0])})
    assert bracketed != alone  # a consistent bracket still bounds and scales the chain


def test_a_target_stops_at_its_encode_cap_and_keeps_the_smallest_file_that_met_it(controller, monkeypatch):
    """At most ``max_encodes`` encodes per target (version 20: :data:`MAX_ENCODES`, 8; 6 before); when they
    run out, the smallest file that met the target is kept."""
    target = Target("psnr", 40.0)
    assert controller.max_encodes == MAX_ENCODES
    assert controller.encode(target).encodes > 2, "this target must need more than the cap below"
    monkeypatch.setattr(controller, "max_encodes", 2)
    outcome = controller.encode(target)
    trials = outcome.summary()["trials"]
    assert outcome.encodes == len(trials) == 2
    assert outcome.measured_psnr >= target.value
    assert len(outcome.stream.to_bytes()) == min(t["bytes"] for t in trials if t["measured_psnr"] >= target.value)


def test_unreachable_targets_name_the_reachable_limit(controller):
    with pytest.raises(TargetUnreachableError, match=r"smallest file .* \(about [\d,]+ bytes"):
        controller.plan(Target("bytes", 100))
    with pytest.raises(TargetUnreachableError, match=r"best quality .* \(about [\d.]+ dB"):
        controller.plan(Target("psnr", 150))


def test_same_input_and_target_give_the_same_bytes(small_scene):
    first = RateController(small_scene.cloud, views=small_scene.cameras, workers=1).fit()
    again = RateController(small_scene.cloud, views=small_scene.cameras, workers=2).fit()
    for target in (Target("bytes", 200 * small_scene.cloud.num_gaussians / 8), Target("psnr", 36.0)):
        assert first.encode(target).stream.to_bytes() == again.encode(target).stream.to_bytes()


def test_cli_target_writes_nothing_when_unreachable(tmp_path, small_cloud, capsys):
    ply = tmp_path / "in.ply"
    write_ply(ply, small_cloud)
    out = tmp_path / "out.gsc"
    assert main(["encode", str(ply), str(out), "--target-size", "200B"]) == 2
    assert "smallest file" in capsys.readouterr().err and not out.exists()
    assert list(tmp_path.iterdir()) == [ply]
    assert main(["encode", str(ply), str(out), "--target-bpg", "100", "--sh", "pca"]) == 2
    assert "cannot be combined with a target" in capsys.readouterr().err
    assert main(["encode", str(ply), str(out), "--target-bpg", "250", "--json", "-q"]) == 0
    assert 0.97 * 250 <= 8 * out.stat().st_size / small_cloud.num_gaussians <= 250


def test_probe_of_a_large_cloud_spans_every_coded_channel():
    """A probe (a share of the cloud plus the Gaussians at each channel's extremes) quantises over the
    whole cloud's ranges, so its steps and water-filled QPs are the ones the real encode uses."""
    from gscodec_shac.codec.attributes import coded_attributes
    from gscodec_shac.codec.rate_control import PROBE_MIN, _extreme_rows, _probe_rows
    from gscodec_shac.synthetic import make_synthetic_scene

    cloud = make_synthetic_scene(PROBE_MIN + 5_000, seed=1, n_cameras=1, width=8, height=8).cloud
    runs = _probe_rows(cloud)
    assert runs.size < cloud.num_gaussians
    features = cloud.ac_matrix()[:, :5]
    for form in ("quaternion", "vector"):  # the rotation's extremes in the form it is coded in
        rows = np.union1d(runs, _extreme_rows(cloud, features, form))
        for ycbcr in (False, True):
            for name in ("rotation", "scale", "opacity", "sh_dc"):
                values = coded_attributes(form)[name].forward(cloud, ycbcr)
                assert np.array_equal(values[rows].min(axis=0), values.min(axis=0)), (form, name)
                assert np.array_equal(values[rows].max(axis=0), values.max(axis=0)), (form, name)
    assert np.array_equal(np.ptp(features[rows], axis=0), np.ptp(features, axis=0))
    assert not np.array_equal(np.ptp(features[runs], axis=0), np.ptp(features, axis=0))  # the runs alone do not


def test_importance_pruning_is_a_candidate_next_to_the_opacity_thresholds(controller, small_cloud):
    n = small_cloud.num_gaussians
    by_importance = [(prune, kept, mse) for prune, kept, mse in controller.prune_ if prune["keep_share"] < 1]
    assert [p["keep_share"] for p, _, _ in by_importance] == list(IMPORTANCE_SHARES)
    assert all(kept == keep_count(n, p["keep_share"]) / n and mse > 0 for p, kept, mse in by_importance)
    mses = [mse for _, _, mse in by_importance]
    assert mses == sorted(mses)  # keeping fewer costs more
    index = controller.prune_.index(by_importance[1])
    plan = controller._predict({**controller.plan(Target("bytes", 150 * n / 8)).settings, "prune": index})
    assert plan.rate_point.keep_share == IMPORTANCE_SHARES[1] and plan.rate_point.min_opacity == 0.0
    stream = controller._encode(plan, Target("bytes", 150 * n / 8))
    assert Decoder().decode(stream.to_bytes()).num_gaussians == keep_count(n, IMPORTANCE_SHARES[1])
    assert stream.header["prune"]["keep_share"] == IMPORTANCE_SHARES[1]


def test_calibration_renders_from_one_frame_are_those_of_fresh_renders(controller, small_scene):
    """The references, pruned subsets and recoloured probes (DC, SH features as decoded) are rendered
    from one prepared frame of the cloud per view: their rendered MSEs are those of fresh renders."""
    from gscodec_shac.codec.rate_control import _with_decoded

    cloud = small_scene.cloud
    candidates = controller._prune_candidates()
    assert len(candidates) == len(controller.prune_) - 1 > 0
    for (settings, keep), (prune, kept, mse) in zip(candidates, controller.prune_[1:]):
        assert settings == prune and kept == np.count_nonzero(keep) / cloud.num_gaussians
        assert mse == controller._rendered_mse(cloud.select(keep))
    rows, decoded = controller._probe_decoded
    for name in ("sh_dc", "sh"):
        assert controller.rendered_mse_[name] == controller._rendered_mse(_with_decoded(cloud, name, rows, decoded)) > 0


def test_without_importance_shares_only_opacity_thresholds_are_candidates(small_scene):
    bare = RateController(small_scene.cloud, views=small_scene.cameras, importance_shares=())
    assert all(prune["keep_share"] == 1.0 for prune, _ in bare._prune_candidates())


def test_importance_is_ranked_on_cameras_the_pruning_error_is_not_judged_on(controller, small_scene):
    judged = {view.name for view in controller.views}
    ranked = {view.name for view in controller.importance_views}
    assert ranked and not ranked & judged and ranked | judged == {c.name for c in small_scene.cameras}


# ------------------------------------------------------------ reuse between encodes
def test_a_recoded_trial_gives_the_bytes_of_a_fresh_encode(controller, small_cloud):
    """A later trial takes its placement, SH features, position chunk and unchanged chunks from the
    controller's cache and codes only the chunks whose QP moved: the bytes of a fresh encode."""
    target = Target("bytes", 200 * small_cloud.num_gaussians / 8)
    first = controller.plan(target)
    moved = {"opacity": min(51, first.settings["opacity"] + 3), "sh": min(51, first.settings["sh"] + 2)}
    second = controller._predict({**first.settings, **moved})
    controller._encode(first, target)
    before = set(controller._cache)
    recoded = controller._encode(second, target)
    new = {key[0] for key in set(controller._cache) - before}
    assert new and all(name == "opacity" or name.startswith("sh") for name in new)  # only the moved chunks
    for plan, stream in ((second, recoded), (first, controller._encode(first, target))):
        # the plan as the controller codes it (a 2,000-Gaussian cloud: one grid, no importance tiers)
        point = dataclasses.replace(plan.rate_point, tiers=controller.tiers if controller._tiered(plan, target) else None)
        fresh = Encoder(point, sh_stage=controller.stage_, fit_stage=False,
                        importance=controller.importance_).encode(small_cloud)
        fresh.header["rate_control"] = stream.header["rate_control"]
        assert stream.to_bytes() == fresh.to_bytes()


def test_the_fits_position_chunks_are_the_ones_an_encode_codes(controller, small_cloud):
    from gscodec_shac.codec.encoder import position_set_cache_key
    from gscodec_shac.codec.rate_control import POSITION_BITS

    settings = controller.plan(Target("bytes", 200 * small_cloud.num_gaussians / 8)).settings
    for bits in (POSITION_BITS[0], POSITION_BITS[-1]):
        point = controller._rate_point({**settings, "positions": bits, "prune": 0})
        seeded = controller._cache[position_set_cache_key(point, bits)]
        assert len(seeded) == controller.models_["positions"].bytes[POSITION_BITS.index(bits)]
        assert Encoder(point, sh_stage=controller.stage_, fit_stage=False).encode(small_cloud).chunk(
            "positions").data == seeded


def test_the_probe_has_a_fixed_size_whatever_the_clouds(monkeypatch):
    from gscodec_shac.codec import rate_control
    from gscodec_shac.synthetic import make_synthetic_scene

    monkeypatch.setattr(rate_control, "PROBE_MIN", 500)
    for n in (2_000, 40_000):  # version 5 probed 1/16 of a cloud above 16 x PROBE_MIN: 2,500 here
        cloud = make_synthetic_scene(n, seed=1, n_cameras=1, width=8, height=8).cloud
        rows = rate_control._probe_rows(cloud)
        assert rows.size == 500 and np.unique(rows).size == 500


def test_the_first_plan_spends_the_gap_below_the_next_hull_point(controller, small_cloud):
    """The hull's points lie far apart; single QP steps fill the plan up to the window's middle."""
    target = Target("bytes", 200 * small_cloud.num_gaussians / 8)
    middle = target.value * (1 - SIZE_TOLERANCE / 2)
    hull_point = controller.plan(Target("bytes", middle))
    first = controller._first_plan(target)
    assert hull_point.predicted_bytes <= first.predicted_bytes <= middle
    assert controller._step(first, cheaper=False, limit=middle) is None  # no single step fits any more


@pytest.mark.parametrize("share, cost, kept", [(0.95, math.inf, True), (0.70, math.inf, False), (0.95, -1.0, False)])
def test_near_a_size_target_the_next_plan_keeps_the_sh_base_qp(controller, small_cloud, monkeypatch, share, cost, kept):
    """Within FINE_BAND of the target the correction moves the other attributes' QPs (one chunk each),
    not the water-filled SH features' base QP (every SH chunk), unless that costs more than
    FINE_PSNR_COST of predicted PSNR; further away every QP may move."""
    from gscodec_shac.codec import rate_control

    monkeypatch.setattr(rate_control, "FINE_PSNR_COST", cost)
    target = Target("bytes", 200 * small_cloud.num_gaussians / 8)
    limit = target.value * (1 - SIZE_TOLERANCE / 2)
    controller._exact = {}
    plan = controller._first_plan(target)
    try:  # as if an encode of the plan had measured `share` of each attribute's predicted bytes
        controller._exact = {name: {plan.settings[name]: share * controller._bytes(name, plan.settings[name])}
                             for name in controller.models_ if name != "positions"}
        nxt = controller._next_for_size(plan, int(share * plan.predicted_bytes), target, {_key(plan)})
        free = controller._adjust(plan, limit=limit)
    finally:
        controller._exact = {}
    assert nxt is not None and share * plan.predicted_bytes < nxt.predicted_bytes <= limit
    assert (1 - share <= rate_control.FINE_BAND) == (share == 0.95)
    if kept:
        assert nxt.settings["sh"] == plan.settings["sh"] and nxt.settings != plan.settings
    else:
        assert nxt.settings == free.settings


# ------------------------------------------------------- probe visibility
def test_probe_visibility_is_the_probes_mean_importance_over_the_clouds(small_scene):
    """Version 11: the probe's rows are a few places in the scene; their render sensitivity is weighed
    by how much more (or less) they show than the average Gaussian, unless that is near 1."""
    controller = RateController(small_scene.cloud, views=small_scene.cameras)
    n = small_scene.cloud.num_gaussians
    importance = np.ones(n)
    rows = np.arange(0, n, 10)
    controller.importance_ = importance.copy()
    controller.importance_[rows] = 3.0  # the probe shows 3x as much as the others
    ratio = 3.0 / np.mean(controller.importance_)
    assert controller._probe_visibility(rows) == pytest.approx(ratio)
    controller.importance_[rows] = 1.1  # inside the band: the proxy's scatter, taken as 1
    assert controller._probe_visibility(rows) == 1.0
    controller.importance_[rows] = 0.4  # less visible than the rest
    assert controller._probe_visibility(rows) == pytest.approx(0.4 / np.mean(controller.importance_))
    controller.importance_[rows] = 1e4  # clipped
    assert controller._probe_visibility(rows) == VISIBILITY_BOUNDS[1]
    assert controller._probe_visibility(np.arange(n)) == 1.0  # the probe is the cloud
    controller.importance_ = np.zeros(n)  # nothing visible: no evidence
    assert controller._probe_visibility(rows) == 1.0


def test_the_render_sensitivities_are_divided_by_the_probes_visibility(small_scene, monkeypatch):
    """The QP attributes' rendered errors scale by 1 / visibility; the positions (rendered with the
    whole cloud moved) and the pruning (exact renders) do not."""
    def fitted(visibility: float) -> RateController:
        monkeypatch.setattr(RateController, "_probe_visibility", lambda self, rows: visibility)
        return RateController(small_scene.cloud, views=small_scene.cameras, importance_shares=(),
                              workers=2).fit()

    plain, visible = fitted(1.0), fitted(2.0)
    assert visible.probe_visibility_ == 2.0
    for name in ("opacity", "rotation", "scale", "sh_dc", "sh"):
        np.testing.assert_allclose(visible.models_[name].mse, plain.models_[name].mse / 2.0, rtol=1e-9)
        np.testing.assert_array_equal(visible.models_[name].bytes, plain.models_[name].bytes)
    np.testing.assert_allclose(visible.models_["positions"].mse, plain.models_["positions"].mse, rtol=1e-9)
    assert [p[2] for p in visible.prune_] == [p[2] for p in plain.prune_]


# ------------------------------------------------- rescale by the first encode
def test_a_psnr_targets_models_are_rescaled_by_the_first_encodes_renders(controller):
    """Version 12: after a PSNR target's first encode, each attribute holding a fair share of the
    plan's error predicts, at the plan's QP, what the whole cloud rendered with that attribute as
    decoded; the fitted models come back after the target."""
    from gscodec_shac.codec.rate_control import RESCALE_SHARE, RESCALE_WITHIN, _decoded, _with_decoded

    fitted = {name: model.mse.copy() for name, model in controller.models_.items()}
    target = Target("psnr", 34.0)  # four attributes above RESCALE_SHARE in its plan (at 36 dB two are near it)
    plan = controller._first_plan(target)
    decoded = _decoded(controller._encode(plan, target), None)
    try:
        count = controller._rescale_models(plan, decoded)
        assert count >= 2
        checked = 0
        for name in ("opacity", "rotation", "scale", "sh_dc", "sh"):
            index = np.searchsorted(controller.models_[name].choices, plan.settings[name])
            before = fitted[name][index]
            if before < RESCALE_SHARE * plan.predicted_mse or (name == "sh" and plan.settings["dc_only"]):
                np.testing.assert_array_equal(controller.models_[name].mse, fitted[name])  # not rendered
                continue
            same = None if name in ("rotation", "scale") else slice(None)
            rendered = controller._rendered_mse(_with_decoded(controller.cloud, name, controller._last_order, decoded), same)
            assert controller.models_[name].mse[index] == pytest.approx(rendered, rel=1e-9)
            np.testing.assert_allclose(controller.models_[name].mse / fitted[name], rendered / before, rtol=1e-9)
            checked += 1
        assert checked == count
    finally:
        for name, mse in fitted.items():
            controller.models_[name] = dataclasses.replace(controller.models_[name], mse=mse)
    outcome = controller.encode(target)
    assert all(np.array_equal(controller.models_[name].mse, fitted[name]) for name in fitted)
    first = outcome.trials[0]
    near = abs(first["measured_psnr"] - target.value - PSNR_WINDOW / 2) <= RESCALE_WITHIN
    assert first.get("rescaled", 0) == (count if outcome.encodes > 1 and near else 0)


# ----------------------------------------------------- probe at the first plan
def test_a_size_target_codes_the_probe_at_its_first_plan_and_plans_again(small_scene, monkeypatch):
    """Version 13: the probe coded at the first plan's QPs puts that point on each QP attribute's rate
    curve (its bytes there, scaled to the whole cloud), the other points stay the probe's; the first
    trial is the plan made with those curves, and the fitted models come back after the target."""
    from gscodec_shac.codec import rate_control
    from gscodec_shac.codec.rate_control import PROBE_QPS

    monkeypatch.setattr(rate_control, "PROBE_MIN", 500)  # a probe smaller than the cloud
    controller = RateController(small_scene.cloud, views=small_scene.cameras, importance_shares=(), workers=2).fit()
    n = small_scene.cloud.num_gaussians
    assert controller._probe_rows.size < n
    target = make_target(n, bpg=140)  # one probe at the plan is enough here (at 120 and 150 a second one runs)
    plan = controller._first_plan(target)
    fitted = {name: model.bytes.copy() for name, model in controller.models_.items()}
    sh_points = {feature: dict(points) for feature, points in controller._sh_points.items()}
    probe_rates = {name: dict(points) for name, points in controller._probe_rates.items()}
    try:
        assert controller._probe_at(plan)
        probe = small_scene.cloud.select(controller._probe_rows)  # coded at the plan's QPs, here too
        names = ("opacity", "rotation", "scale", "sh_dc")
        point = controller._rate_point({name: plan.settings[name] for name in (*names, "sh")} | {"positions": 16})
        sizes = Encoder(point, sh_stage=controller.stage_, fit_stage=False).encode(probe).attribute_sizes()
        for name in names:
            model = controller.models_[name]
            at = np.searchsorted(model.choices, plan.settings[name])
            assert model.bytes[at] == pytest.approx(sizes[name] * n / probe.num_gaussians, rel=1e-9)
            for qp in PROBE_QPS:  # the probe's own points stay
                assert model.bytes[qp] == pytest.approx(fitted[name][qp], rel=1e-9)
        assert controller._sh_points != sh_points  # the SH features' points at the plan's QPs joined them
        replanned = controller._first_plan(target)
    finally:
        for name, data in fitted.items():
            controller.models_[name] = dataclasses.replace(controller.models_[name], bytes=data)
        controller._sh_points = {feature: dict(points) for feature, points in sh_points.items()}
        controller._probe_rates = {name: dict(points) for name, points in probe_rates.items()}
    outcome = controller.encode(target)
    assert all(np.array_equal(controller.models_[name].bytes, fitted[name]) for name in fitted)
    assert controller._sh_points == sh_points and controller._probe_rates == probe_rates  # the fit's again
    assert controller._prune_factors == {}
    assert outcome.trials[0]["first_plan_bytes"] == pytest.approx(plan.predicted_bytes)
    assert outcome.trials[0]["predicted_bytes"] == pytest.approx(replanned.predicted_bytes)
    assert "plan_probe" in outcome.seconds
    assert (1 - SIZE_TOLERANCE) * target.value <= outcome.stream.total_bytes() <= target.value
    quality = controller.encode(Target("psnr", 36.0))  # a PSNR target does not
    assert "plan_probe" not in quality.seconds and "first_plan_bytes" not in quality.trials[0]



def test_a_size_target_probes_again_when_its_plan_moves_the_sh_off_the_qps_coded(small_scene, monkeypatch):
    """Version 16: after a probe at the plan, a plan whose SH features the probe has not all coded at the
    plan's QPs is probed too (at most PLAN_PROBES probes); with probes to spare, the first encode's features
    are each at a QP the probe coded (version 17: feature by feature, so a quarter step between two bases
    probed counts as coded)."""
    from gscodec_shac.codec import rate_control

    monkeypatch.setattr(rate_control, "PROBE_MIN", 500)  # a probe smaller than the cloud
    monkeypatch.setattr(rate_control, "PRUNE_THRESHOLDS", (0.0,))  # no pruning: a second probe is for the SH only
    controller = RateController(small_scene.cloud, views=small_scene.cameras, importance_shares=(), workers=2).fit()
    probed: list[tuple[float, bool]] = []  # the SH base QP of each plan probed, and whether it was measured
    encoded: list[tuple[float, bool]] = []  # ... of each plan encoded
    probe_at, encode = controller._probe_at, controller._encode

    def record(log: list, plan) -> None:
        log.append((plan.settings["sh"], controller._sh_measured(plan)))

    monkeypatch.setattr(controller, "_probe_at", lambda plan: record(probed, plan) or probe_at(plan))
    monkeypatch.setattr(controller, "_encode", lambda plan, target, **grid: record(encoded, plan)
                        or encode(plan, target, **grid))
    probed_again = 0
    for bpg in (70, 90, 120, 160, 220):
        probed.clear(), encoded.clear()
        controller.encode(make_target(controller.cloud.num_gaussians, bpg=bpg))
        assert 1 <= len(probed) <= rate_control.PLAN_PROBES
        if len(probed) < rate_control.PLAN_PROBES:
            assert encoded[0][1]
        assert not any(measured for _, measured in probed[1:])  # probed again only for an SH not coded
        probed_again += len(probed) > 1
    assert probed_again  # the case happens on this scene


def test_the_probe_encodes_share_a_cache_and_measure_what_fresh_encodes_measure(small_scene, monkeypatch):
    """Issue 25: the probe's encodes share a chunk cache, so the DC-only bars' probes (at probe QPs) and a
    size target's plan probes code only the chunks whose settings are new. The models, the pruning factors
    and the file are those of a controller whose probe encodes are all fresh, with fewer HEVC encodes."""
    from gscodec_shac.codec import rate_control
    from gscodec_shac.codec.grid.hevc import HevcCodec

    monkeypatch.setattr(rate_control, "PROBE_MIN", 500)  # a probe smaller than the cloud: plan probes run
    encodes = [0]
    encode_parts = HevcCodec.encode_parts

    def counted(self, *args, **kwargs):
        encodes[0] += 1
        return encode_parts(self, *args, **kwargs)

    monkeypatch.setattr(HevcCodec, "encode_parts", counted)
    probe_encoder = RateController._probe_encoder
    n = small_scene.cloud.num_gaussians

    def run(sharing: bool) -> tuple[dict, int]:
        encodes[0] = 0

        def encoder(self, point, *, cached: bool = True):
            return probe_encoder(self, point, cached=sharing and cached)

        monkeypatch.setattr(RateController, "_probe_encoder", encoder)
        controller = RateController(small_scene.cloud, views=small_scene.cameras, importance_shares=(0.6,),
                                    workers=2).fit()
        factors: list[dict] = []
        at = controller._probe_at
        monkeypatch.setattr(controller, "_probe_at", lambda plan: at(plan) and not factors.append(
            dict(controller._prune_factors)) or True)
        outcome = controller.encode(make_target(n, bpg=30))  # a plan that prunes: the kept rows are probed too
        measured = {"rates": controller._probe_rates, "sh": controller._sh_points, "prune": controller.prune_,
                    "dc_only": controller.dc_only_, "models": {k: (m.bytes.tolist(), m.mse.tolist())
                                                              for k, m in controller.models_.items()},
                    "factors": factors, "file": outcome.stream.to_bytes(), "trials": len(outcome.trials)}
        return measured, encodes[0]

    cached, with_cache = run(True)
    fresh, without = run(False)
    assert cached.keys() == fresh.keys()
    for key in cached:
        assert cached[key] == fresh[key], key
    assert cached["factors"][-1]  # the pruned probe ran (its rows are another cloud: not cached)
    assert with_cache < without


def test_the_sh_counts_as_measured_feature_by_feature(controller, small_cloud):
    """Version 17: a base QP is measured when every feature it keeps is at a QP the probe coded: a whole
    base probed is, the next one is not, and once it is coded too the quarter steps between them are."""
    settings = controller._hull()[0].settings
    saved = {feature: dict(points) for feature, points in controller._sh_points.items()}
    try:
        def measured(base: float) -> bool:
            return controller._sh_measured(controller._predict({**settings, "sh": base}))

        assert measured(18) and not measured(19) and not measured(18.5)
        stream = Encoder(controller._rate_point({**settings, "sh": 19}), sh_stage=controller.stage_,
                         fit_stage=False).encode(small_cloud)
        controller._record_sh_chunks(stream, 1.0)
        assert measured(19) and measured(18.25) and measured(18.5) and measured(18.75) and not measured(19.25)
    finally:
        controller._sh_points = saved


def test_the_fit_times_its_importance_renders_inside_the_calibration(controller, small_scene):
    """``rate_control.seconds.importance``: the importance renders, part of ``calibrate`` (with a capture's
    cameras most of the fit); absent when the controller has no importance choices and no tiers."""
    assert 0 < controller.seconds_["importance"] <= controller.seconds_["calibrate"]
    one_grid = dataclasses.replace(load_rate_point("shac_auto:template"), tiers=None)
    plain = RateController(small_scene.cloud, one_grid, views=small_scene.cameras[:2], importance_shares=(),
                           workers=2)
    plain._prune_candidates()
    assert "importance" not in plain.seconds_


def test_no_probe_at_the_plan_when_the_probe_is_the_whole_cloud(controller):
    target = make_target(controller.cloud.num_gaussians, bpg=120)
    assert controller._probe_rows.size == controller.cloud.num_gaussians
    assert not controller._probe_at(controller._first_plan(target))
    assert "plan_probe" not in controller.encode(target).seconds


# ------------------------------------------------- what a kept Gaussian costs
@pytest.fixture()
def pruning_controller(small_scene, monkeypatch):
    """A controller whose probe is smaller than the cloud and which has three pruning choices (by importance:
    the synthetic scene's opacities are all above the thresholds)."""
    from gscodec_shac.codec import rate_control

    monkeypatch.setattr(rate_control, "PROBE_MIN", 500)
    controller = RateController(small_scene.cloud, views=small_scene.cameras, importance_shares=(0.8, 0.6, 0.4),
                                workers=2).fit()
    assert len(controller.prune_) > 2 and controller._probe_rows.size < small_scene.cloud.num_gaussians
    return controller


def test_the_probe_pruned_as_the_plan_prunes_measures_what_a_kept_gaussian_costs(pruning_controller):
    """Version 14: each QP attribute's bytes per Gaussian of the probe's kept Gaussians, against the whole
    probe's per Gaussian at the same QPs, both coded for real; the plan's bytes scale by it."""
    controller = pruning_controller
    target = make_target(controller.cloud.num_gaussians, bpg=120)
    plan = controller._predict({**controller._first_plan(target).settings, "prune": 2})
    rows = controller._probe_rows
    kept = rows[controller._prune_masks[2][rows]]
    assert 0 < kept.size < rows.size
    names = list(controller._probe_rates)
    point = controller._rate_point({name: plan.settings[name] for name in names} | {"positions": 16})
    whole, pruned = (Encoder(point, sh_stage=controller.stage_, fit_stage=False).encode(
        controller.cloud.select(r)).attribute_sizes() for r in (rows, kept))
    before = {name: controller._attribute_bytes(plan.settings, name) / controller._bytes(name, plan.settings[name])
              for name in names}
    assert controller._probe_at(plan)
    factors = controller._prune_factors[2]
    for name in names:
        expected = (pruned[name] / kept.size) / (whole[name] / rows.size)
        assert factors[name] == pytest.approx(expected, rel=1e-9)
        share = controller._attribute_bytes(plan.settings, name) / controller._bytes(name, plan.settings[name])
        assert share == pytest.approx(before[name] * factors[name], rel=1e-9)
    assert controller._predict({**plan.settings, "prune": 0}).predicted_bytes > 0  # no pruning: no factor
    assert all(controller._prune_factor(0, name) == 1.0 for name in names)


def test_an_unmeasured_pruning_choice_interpolates_in_the_share_kept(pruning_controller):
    controller = pruning_controller
    controller.prune_ = [controller.prune_[0]] + [(settings, kept, mse) for (settings, _, mse), kept
                                                  in zip(controller.prune_[1:4], (0.9, 0.6, 0.3))]
    assert controller._prune_factor(1, "sh") == 1.0  # nothing measured yet
    controller._prune_factors = {2: {"sh": 1.4, "scale": 1.1}}
    assert controller._prune_factor(2, "sh") == 1.4
    assert controller._prune_factor(1, "sh") == pytest.approx(1.0 + 0.4 * 0.1 / 0.4)  # between 1 at 1.0 and 1.4 at 0.6
    assert controller._prune_factor(3, "sh") == pytest.approx(1.4)  # past the last measured: constant
    assert controller._prune_factor(3, "scale") == pytest.approx(1.1)
    assert controller._prune_factor(2, "positions") == 1.0  # set coding has its own model of the gaps


def test_an_encode_of_a_pruned_plan_is_learnt_through_the_same_factor(pruning_controller):
    """The bytes an encode measured come back exactly as the prediction of the same settings: :meth:`_learn`
    divides by the factor :meth:`_predict` multiplies by."""
    controller = pruning_controller
    target = make_target(controller.cloud.num_gaussians, bpg=120)
    plan = controller._predict({**controller._first_plan(target).settings, "prune": 2})
    controller._exact = {}
    controller._probe_at(plan)
    assert controller._prune_factors[2]["sh"] != 1.0
    plan = controller._predict(plan.settings)
    stream = controller._encode(plan, target)
    controller._learn(plan, stream)
    assert controller._predict(plan.settings).predicted_bytes == pytest.approx(stream.total_bytes(), rel=1e-9)


def test_a_size_target_measures_the_pruning_it_plans_before_its_first_encode(pruning_controller, monkeypatch):
    """The size target's plans are probed until the plan's pruning is measured (at most PLAN_PROBES times);
    the factors belong to the target: the next starts without them."""
    from gscodec_shac.codec import rate_control

    controller = pruning_controller
    probed: list[int] = []  # the pruning choice of each plan probed
    measured: list[set[int]] = []  # the choices measured when the first encode starts
    probe_at, encode = controller._probe_at, controller._encode

    def recording_probe_at(plan):
        probed.append(plan.settings["prune"])
        return probe_at(plan)

    def recording_encode(plan, target, **grid):
        if not encoded:  # the first encode of the target
            measured.append(set(controller._prune_factors))
        encoded.append(plan.settings["prune"])
        return encode(plan, target, **grid)

    monkeypatch.setattr(controller, "_probe_at", recording_probe_at)
    monkeypatch.setattr(controller, "_encode", recording_encode)
    pruned_somewhere = False
    for bpg in (40, 60, 120):
        probed.clear(), measured.clear()
        encoded: list[int] = []
        controller.encode(make_target(controller.cloud.num_gaussians, bpg=bpg))
        assert 1 <= len(probed) <= rate_control.PLAN_PROBES
        assert measured[0] == {p for p in probed if p}  # every pruning probed was measured, no other
        if len(probed) < rate_control.PLAN_PROBES:
            assert encoded[0] in {0, *probed}  # the plan encoded prunes as measured
        pruned_somewhere |= any(probed)
        assert controller._prune_factors == {}
    assert pruned_somewhere


def test_the_probes_extreme_rows_are_argmin_and_argmax_of_each_column():
    from gscodec_shac.codec.rate_control import _first_extremes

    values = np.random.default_rng(5).integers(-3, 4, size=(500, 7)).astype(np.float32)  # many ties
    assert _first_extremes(values).tolist() == [*np.argmin(values, axis=0), *np.argmax(values, axis=0)]


# ---------------------------------------------------------------- version 18: the view metric
def test_the_sh_stage_is_fitted_in_the_view_metric_of_the_callers_cameras(controller, small_scene):
    from gscodec_shac.shac.view_metric import footprints, view_metric

    cloud = small_scene.cloud
    expected = view_metric(cloud.means, small_scene.cameras, cloud.sh_degree,
                           footprints=footprints(cloud.scales, cloud.activated_opacities()))
    np.testing.assert_array_equal(controller.stage_.metric_, expected)
    np.testing.assert_allclose(controller.stage_.feature_weights(), 1.0, rtol=1e-2)  # float16 side information
    # orbit views are the controller's guess, not where the scene is seen from: no metric
    assert RateController(cloud, workers=2)._sh_metric() is None
    assert RateController(cloud, views=small_scene.cameras, workers=2, view_metric=False)._sh_metric() is None


# ---------------------------------------------------------------- version 23: tiers checked against one grid
def _tiered_controller(controller, monkeypatch, offsets: tuple[int, int]):
    """The fitted controller with two fixed tiers (``offsets``) coding every plan of its 2,000 Gaussians."""
    from gscodec_shac.codec import rate_control
    from gscodec_shac.codec.rate_points import TierSpec

    monkeypatch.setattr(rate_control, "TIER_MIN_GAUSSIANS", 0)
    monkeypatch.setattr(controller, "tiers", TierSpec((0.5, 0.5), offsets))
    return controller


def test_tiers_that_render_below_the_one_grid_prediction_send_the_target_to_one_grid(controller, monkeypatch):
    """The less important half 30 QPs coarser renders far below the plan's one-grid prediction: the size
    target is searched again in one grid and the file that renders better on the controller's views lands."""
    from gscodec_shac.codec import tiers

    tiered = _tiered_controller(controller, monkeypatch, (0, 30))
    target = make_target(tiered.cloud.num_gaussians, bpg=120)
    outcome = tiered.encode(target)
    rows = outcome.trials
    first_grid = next(i for i, row in enumerate(rows) if not row["tiered"])
    assert first_grid >= 1 and not any(row["tiered"] for row in rows[first_grid:])
    finalists = [row for row in rows if "measured_psnr" in row]
    assert len(finalists) == 2 and finalists[0]["tiered"] and not finalists[1]["tiered"]
    assert finalists[0]["measured_psnr"] < finalists[0]["model_psnr"]  # why one grid was searched
    assert outcome.measured_psnr == pytest.approx(max(row["measured_psnr"] for row in finalists))
    assert tiers.is_tiered(outcome.stream) == (finalists[0]["measured_psnr"] > finalists[1]["measured_psnr"])
    assert outcome.stream.total_bytes() <= target.value
    assert outcome.measured_psnr == pytest.approx(tiered.measured_psnr(outcome.stream))
    assert tiered._tiered(outcome.plan, target)  # the plan itself qualifies for the tiers: only the search left them


def test_tiers_that_render_at_the_one_grid_prediction_are_kept_without_a_one_grid_search(controller, monkeypatch):
    from gscodec_shac.codec import tiers
    from gscodec_shac.codec.rate_control import _Encoded

    tiered = _tiered_controller(controller, monkeypatch, (0, 30))
    target = make_target(tiered.cloud.num_gaussians, bpg=120)
    plan = tiered._first_plan(target)
    stream = tiered._encode(plan, target)
    assert tiers.is_tiered(stream)
    measured = tiered.measured_psnr(stream)
    trials = [{"tiered": 1.0}]
    predicting_less = dataclasses.replace(plan, predicted_mse=10 ** (-(measured - 0.01) / 10))
    kept = tiered._checked_tiers(_Encoded(stream, predicting_less, None, 0), predicting_less, target, trials,
                                 bar=None)
    assert kept.stream is stream and kept.measured == pytest.approx(measured) and len(trials) == 1
    assert trials[0]["measured_psnr"] == pytest.approx(measured)
    predicting_more = dataclasses.replace(plan, predicted_mse=10 ** (-(measured + 0.01) / 10))
    assert tiered._falls_short(_Encoded(stream, predicting_more, None, 0), trials)
