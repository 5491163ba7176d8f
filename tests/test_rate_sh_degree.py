"""The DC-only energy bar as a rate-control choice (codec/rate_sh_degree.py): measured per bar, chosen
where the scene's view-dependent colour is concentrated, and coded as planned."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gscodec_shac.codec import Decoder, load_rate_point
from gscodec_shac.codec.rate_control import TEMPLATE, RateController, Target
from gscodec_shac.codec.rate_sh_degree import DC_ONLY_BARS, RATIO_QPS, whole_cloud_flags


@pytest.fixture(scope="module")
def half_flat(small_scene):
    """The small scene with the AC coefficients of every other Gaussian zeroed (half of bonsai's
    Gaussians hold 2% of its view-dependent energy; here half hold none)."""
    ac = small_scene.cloud.ac_matrix().copy()
    ac[::2] = 0.0
    return small_scene.cloud.with_ac_matrix(ac)


@pytest.fixture(scope="module")
def controller(half_flat, small_scene):
    return RateController(half_flat, views=small_scene.cameras, workers=2).fit()


def zeroed(cloud, bar: float):
    """``cloud`` with the AC coefficients of the Gaussians the bar flags zeroed (the reference)."""
    ac = cloud.ac_matrix().copy()
    ac[whole_cloud_flags(cloud, bar)] = 0.0
    return cloud.with_ac_matrix(ac)


def test_zeroing_errors_rendered_from_one_frame_are_those_of_fresh_renders(controller, half_flat):
    """Each bar's zeroing error under each pruning choice, rendered from the cloud's prepared frames,
    is that of a fresh render of the pruned cloud with the bar's AC zeroed."""
    kept = [np.arange(half_flat.num_gaussians)] + [np.flatnonzero(keep) for _, keep in controller._prune_candidates()]
    assert len(kept) == len(controller.prune_) > 1
    for choice in controller.dc_only_[1:]:
        for j, (rows, (_, _, prune_mse)) in enumerate(zip(kept, controller.prune_)):
            fresh = controller._rendered_mse(zeroed(half_flat.select(rows), choice.bar), rows)
            assert controller._zeroed_mse[(choice.bar, j)] == fresh
            assert choice.zeroing(j) == max(fresh - prune_mse, 0.0)
        assert choice.zeroing(0) > 0


def test_every_bar_is_measured(controller, half_flat):
    choices = controller.dc_only_
    assert [c.bar for c in choices] == list(DC_ONLY_BARS)
    assert choices[0].share == 0.0 and choices[0].bytes_factor(30) == 1.0 and choices[0].zeroing(0) == 0.0
    for choice in choices[1:]:
        assert choice.share == pytest.approx(whole_cloud_flags(half_flat, choice.bar).mean())
        assert choice.share >= 0.5  # at least the Gaussians without AC
        assert choice.qps == RATIO_QPS and choice.flag_bytes > 0
        assert all(0 < r < 1 for r in choice.bytes_ratios)  # half the AC planes gone
        ends = choice.bytes_factor(np.array([0, 51]))
        assert tuple(ends) == (choice.bytes_ratios[0], choice.bytes_ratios[-1])  # the end values beyond
    for choice in choices[1:]:  # one zeroing error per pruning candidate, measured on what it keeps
        assert len(choice.zeroed_mse) == len(controller.prune_) and choice.zeroing(0) > 0
        assert all(e >= 0 for e in choice.zeroed_mse)


def test_the_plan_leaves_the_flat_gaussians_dc_only_and_the_stream_codes_them(controller, half_flat):
    target = Target("bytes", 160 * half_flat.num_gaussians / 8)  # 200 kept the AC from v19 on
    plan = controller.plan(target)
    assert plan.settings["dc_only"] > 0
    bar = controller.dc_only_[plan.settings["dc_only"]].bar
    assert plan.rate_point.dc_only_energy == bar
    outcome = controller.encode(target)
    assert outcome.summary()["settings"]["dc_only_energy"] > 0
    stream = outcome.stream
    headers = stream.header.get("tiers", [stream.header])  # the template's importance tiers: each counts its own
    dc_only = sum((header.get("sh") or {}).get("dc_only", 0) for header in headers)
    assert dc_only > 0
    decoded = Decoder().decode(stream.to_bytes())
    assert np.count_nonzero(~decoded.ac_matrix().any(axis=1)) >= dc_only
    assert 0.97 * target.value <= stream.total_bytes() <= target.value


def test_a_learned_encode_predicts_its_own_bytes(controller, half_flat):
    """The SH bytes an encode under a bar measured are stored as if without it (divided by the bar's
    ratio), so the same plan is then predicted at the bytes it had."""
    target = Target("bytes", 200 * half_flat.num_gaussians / 8)
    plan = controller.plan(target)
    stream = controller._encode(plan, target)
    controller._learn(plan, stream)
    assert controller._predict(plan.settings).predicted_bytes == pytest.approx(stream.total_bytes(), rel=0.01)
    controller._exact = {}


def test_a_template_with_its_own_dc_only_setting_is_kept(half_flat, small_scene):
    template = dataclasses.replace(load_rate_point(TEMPLATE), dc_only_energy=0.02)
    fixed = RateController(half_flat, template, views=small_scene.cameras, workers=2).fit()
    assert [c.bar for c in fixed.dc_only_] == [0.0]
    plan = fixed.plan(Target("bytes", 200 * half_flat.num_gaussians / 8))
    assert plan.rate_point.dc_only_energy == 0.02


def test_the_same_fit_gives_the_same_bytes(half_flat, small_scene, controller):
    again = RateController(half_flat, views=small_scene.cameras, workers=1).fit()
    target = Target("bytes", 200 * half_flat.num_gaussians / 8)
    assert again.encode(target).stream.to_bytes() == controller.encode(target).stream.to_bytes()


@pytest.mark.parametrize("bar", [0.01, 0.3, 1.0])
def test_kept_flags_from_the_whole_clouds_order_are_those_of_sorting_the_kept_rows(bar):
    """The controller ranks the energies once for every pruning choice: the kept rows in that order are the
    rows, and the order, that sorting their own energies gives (ties by row; equal energies on purpose)."""
    from gscodec_shac.codec.rate_sh_degree import kept_flags
    from gscodec_shac.codec.sh_degree import dc_only_flags

    rng = np.random.default_rng(2)
    energy = np.round(rng.exponential(1.0, 5_000), 1)  # many ties
    order = np.argsort(energy, kind="stable")
    for kept in (np.arange(energy.size), np.flatnonzero(rng.random(energy.size) < 0.6), np.array([7]),
                 np.array([], dtype=np.int64)):
        assert np.array_equal(kept_flags(energy, kept, bar, order), kept[dc_only_flags(energy[kept], 0.0, bar)])
