"""scripts/rate_control_tables.py: the tables of docs/rate_control.md from a sweep's rows."""

import math

import pytest

from tests.conftest import load_script


@pytest.fixture(scope="module")
def script():
    return load_script("rate_control_tables")


def _row(method: str, size: float, psnr: float, **extra) -> dict:
    return {"scene": "s", "method": method, "status": "ok", "bytes": size, "n_gaussians": 1000, "n_decoded": 1000,
            "psnr_ref": psnr, "psnr_gt": math.nan, "encode_s": 2.0, "extra": extra}


def _controlled(encodes: int, tiered: list[int]) -> dict:
    return {"rate_control": {"encodes": encodes, "trials": [{"tiered": float(t)} for t in tiered]}}


def test_encodes_are_summed_and_targets_that_left_the_tiers_counted(script):
    rows = [_row("auto", 1, 30, **_controlled(3, [1, 0, 0])), _row("auto", 2, 35, **_controlled(1, [1])),
            _row("auto", 3, 40, **_controlled(2, [0, 0])), _row("auto", 4, 45, **_controlled(2, [1, 1]))]
    assert script.encodes(rows) == (8, 1)
    assert script.encodes([_row("baseline", 1, 30)]) is None  # no rate control


def test_the_tables_name_each_curves_encodes_beside_its_bd_rate(script):
    rows = [_row("baseline", b, q) for b, q in ((1000, 30), (2000, 34), (4000, 38), (8000, 42))]
    rows += [_row("shac-auto", 900, 32, **_controlled(4, [1, 1, 0, 0])), _row("shac-auto", 1800, 36, **_controlled(1, [1])),
             _row("shac-auto", 3600, 40, **_controlled(2, [1, 1]))]
    text = script.tables(rows)
    assert "| shac-auto | 3 |" in text and "%" in text.split("| shac-auto | 3 |")[1].splitlines()[0]
    assert "shac-auto 7 (1)" in text and "baseline" not in text.split("Rate-control encodes")[1].splitlines()[0]
