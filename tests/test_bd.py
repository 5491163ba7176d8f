"""Bjontegaard metrics: known shifts give known BD-rate / BD-PSNR values."""

import math

import numpy as np
import pytest

from gscodec_shac.rd.bd import bd_psnr, bd_rate

# A realistic 4-point RD curve: bytes and PSNR (dB), quality rising with rate but not linearly.
RATES = np.array([1.2e6, 1.6e6, 2.3e6, 3.1e6])
PSNR = np.array([30.1, 31.6, 32.9, 33.5])


def test_curve_against_itself_is_zero():
    assert bd_rate(RATES, PSNR, RATES, PSNR).value == pytest.approx(0.0, abs=1e-9)
    assert bd_psnr(RATES, PSNR, RATES, PSNR).value == pytest.approx(0.0, abs=1e-9)


def test_half_the_bytes_is_minus_50_percent():
    result = bd_rate(RATES, PSNR, RATES / 2, PSNR)
    assert result.value == pytest.approx(-50.0, abs=1e-9)
    assert bd_rate(RATES, PSNR, RATES * 2, PSNR).value == pytest.approx(100.0, abs=1e-9)


def test_one_db_better_is_plus_one_db():
    assert bd_psnr(RATES, PSNR, RATES, PSNR + 1.0).value == pytest.approx(1.0, abs=1e-9)
    assert bd_psnr(RATES, PSNR, RATES, PSNR - 0.25).value == pytest.approx(-0.25, abs=1e-9)


def test_log_linear_curve_matches_the_closed_form():
    # PSNR = 10 log10(R) + c is reproduced exactly by a piecewise-cubic Hermite interpolant,
    # so +1 dB at equal rate is 10^(-1/10) of the rate at equal PSNR: -20.567 %.
    rates = np.array([1e5, 3e5, 1e6, 4e6])
    psnr = 10 * np.log10(rates) - 20
    assert bd_rate(rates, psnr, rates, psnr + 1).value == pytest.approx((10 ** -0.1 - 1) * 100, abs=1e-9)


def test_point_order_and_partial_overlap():
    shuffled = [2, 0, 3, 1]
    rates = np.array([1e5, 3e5, 1e6, 4e6])
    psnr = 8 * np.log10(rates) - 10  # log-linear: exact under PCHIP on any subset of points
    # the test curve covers only part of the anchor's quality range: integrate over the overlap
    test_rates, test_psnr = rates[1:] * 0.8, psnr[1:]
    a = bd_rate(rates, psnr, test_rates, test_psnr)
    b = bd_rate(rates[shuffled], psnr[shuffled], test_rates[::-1], test_psnr[::-1])
    assert a.value == pytest.approx(b.value, abs=1e-12)
    assert a.value == pytest.approx(-20.0, abs=1e-9)
    assert a.overlap == pytest.approx((psnr[1], psnr[-1]))
    # order does not matter for a general curve either
    assert bd_psnr(RATES, PSNR, RATES[shuffled] * 0.7, PSNR[shuffled]).value == pytest.approx(
        bd_psnr(RATES, PSNR, RATES * 0.7, PSNR).value, abs=1e-12)


def test_unusable_curves_give_nan_with_a_reason():
    apart = bd_rate(RATES, PSNR, RATES, PSNR + 10)
    assert math.isnan(apart.value) and "overlap" in apart.reason
    single = bd_rate(RATES, PSNR, RATES[:1], PSNR[:1])
    assert math.isnan(single.value) and "2 points" in single.reason
    zero = bd_psnr(RATES, PSNR, np.array([0.0, 1.0]), np.array([30.0, 31.0]))
    assert math.isnan(zero.value) and "positive" in zero.reason


def test_non_monotonic_curve_is_flagged():
    bumpy = np.array([30.1, 31.6, 31.2, 33.5])
    assert bd_rate(RATES, PSNR, RATES, bumpy).monotonic is False
    assert bd_rate(RATES, PSNR, RATES * 0.9, PSNR).monotonic is True


def test_report_flags_bd_over_a_narrow_overlap():
    from gscodec_shac.rd.report import bd_table

    def rows(method, rates, psnrs):
        return [{"scene": "s", "method": method, "rate_point": f"rp{i}", "status": "ok", "bytes": r, "psnr_ref": q}
                for i, (r, q) in enumerate(zip(rates, psnrs))]

    anchor = rows("baseline", [100, 200, 400, 800], [30.0, 33.0, 36.0, 39.0])
    wide = rows("wide", [90, 180, 360, 720], [30.5, 33.5, 36.5, 39.5])
    narrow = rows("narrow", [20, 40, 80, 110], [20.0, 24.0, 28.0, 31.0])  # meets the anchor only at its low end
    table = {e["method"]: e for e in bd_table(anchor + wide + narrow) if e["metric"] == "psnr_ref"}
    assert "indicative" not in table["wide"]["note"]
    assert "BD-quality over" in table["narrow"]["note"] and "indicative only" in table["narrow"]["note"]


# A curve above the anchor at every rate whose quality dips once with rate (as PSNR against a
# noise-free ground truth does when compression removes noise): the demo's opposite signs.
HUMP_RATES = np.array([1e5, 2e5, 4e5, 8e5, 1.6e6])
ANCHOR_PSNR = np.array([28.0, 30.0, 32.0, 34.0, 36.0])
HUMP_PSNR = np.array([31.0, 34.5, 33.0, 35.5, 37.5])


def test_monotone_hull_drops_dominated_points():
    from gscodec_shac.rd.bd import monotone_hull

    rates, quality = monotone_hull(HUMP_RATES[::-1], HUMP_PSNR[::-1])
    assert rates.tolist() == [1e5, 2e5, 8e5, 1.6e6]
    assert quality.tolist() == [31.0, 34.5, 35.5, 37.5]
    # equal rates keep the better point; equal quality at a higher rate is dominated
    rates, quality = monotone_hull([1, 1, 2, 3], [5.0, 6.0, 6.0, 7.0])
    assert rates.tolist() == [1, 3] and quality.tolist() == [6.0, 7.0]


def test_a_curve_above_the_anchor_with_a_dip_gets_agreeing_signs():
    assert np.all(HUMP_PSNR > ANCHOR_PSNR)
    rate = bd_rate(HUMP_RATES, ANCHOR_PSNR, HUMP_RATES, HUMP_PSNR)
    quality = bd_psnr(HUMP_RATES, ANCHOR_PSNR, HUMP_RATES, HUMP_PSNR)
    assert rate.monotonic is False and rate.dropped == 1
    assert quality.value > 0 and rate.value < 0
    # the hull is what was measured: the same numbers as the curve without its dominated point
    keep = [0, 1, 3, 4]
    assert rate.value == pytest.approx(bd_rate(HUMP_RATES, ANCHOR_PSNR, HUMP_RATES[keep], HUMP_PSNR[keep]).value)


def test_opposite_signs_are_explained_in_the_report():
    from gscodec_shac.rd.bd import opposite_sign_reason
    from gscodec_shac.rd.report import bd_table

    def rows(method, rates, psnrs):
        return [{"scene": "s", "method": method, "rate_point": f"rp{i}", "status": "ok", "bytes": r, "psnr_ref": q}
                for i, (r, q) in enumerate(zip(rates, psnrs))]

    hump = {e["method"]: e for e in bd_table(rows("baseline", HUMP_RATES, ANCHOR_PSNR) + rows("t", HUMP_RATES, HUMP_PSNR))}
    assert hump["t"]["bd_rate_pct"] < 0 < hump["t"]["bd_quality"]
    assert "monotone hulls (1 dominated point left out)" in hump["t"]["note"] and "disagree" not in hump["t"]["note"]
    # two monotone curves that cross: the metrics may disagree, and the note says why
    anchor_rates, anchor_psnr = np.array([1e5, 1e6]), np.array([30.0, 40.0])
    # better than the anchor at low rates, flat above: cheaper over the common PSNR range [33, 35] but
    # worse on average over the common rate range
    cross_rates, cross_psnr = np.array([1e5, 1.2e5, 1e6]), np.array([33.0, 34.5, 35.0])
    rate = bd_rate(anchor_rates, anchor_psnr, cross_rates, cross_psnr)
    quality = bd_psnr(anchor_rates, anchor_psnr, cross_rates, cross_psnr)
    assert rate.value < 0 and quality.value < 0
    assert "curves cross" in opposite_sign_reason(rate, quality)
    table = {e["method"]: e for e in bd_table(rows("baseline", anchor_rates, anchor_psnr) + rows("c", cross_rates, cross_psnr))}
    assert "curves cross" in table["c"]["note"]
