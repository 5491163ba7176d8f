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
    assert math.isnan(single.value) and "2 distinct points" in single.reason
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
