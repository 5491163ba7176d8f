"""scripts/x265_repeat.py options: recorded streams coded again under other x265 parameters."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from gscodec_shac.codec.grid import get_codec
from tests.conftest import load_script


def _recorded_frames_stream(folder, monkeypatch, qp=20, seed=1):
    """Record (GSCODEC_X265_DUMP) one 6-frame ``frames`` stream of smooth 10-bit planes at ``qp``."""
    rng = np.random.default_rng(seed)
    base = np.cumsum(np.cumsum(rng.normal(size=(48, 96)), 0), 1)
    planes = np.stack([base * (1 + 0.1 * k) for k in range(6)])
    planes = ((planes - planes.min()) / np.ptp(planes) * 1023).astype(np.uint16)
    monkeypatch.setenv("GSCODEC_X265_DUMP", str(folder))
    monkeypatch.setenv("GSCODEC_X265_PROCESSES", "0")
    get_codec("hevc", layout="frames").encode(planes, 10, qp)
    monkeypatch.delenv("GSCODEC_X265_DUMP")


def test_options_recodes_the_recorded_streams_and_reports_bytes_and_psnr(tmp_path, monkeypatch, capsys):
    _recorded_frames_stream(tmp_path, monkeypatch)
    recorded = [json.loads(line) for p in tmp_path.glob("x265-*.jsonl") for line in p.read_text().splitlines()]
    assert len(recorded) == 1

    load_script("x265_repeat").options(str(tmp_path), [":qp=40"])
    rows = [line for line in capsys.readouterr().out.splitlines() if " B " in line]
    assert [row.split()[0] for row in rows] == ["(recorded)", ":qp=40"]
    sizes = [int(row.split()[1].replace(",", "")) for row in rows]
    psnrs = [float(re.search(r"([\d.]+) dB \(10-bit peak\)", row).group(1)) for row in rows]
    assert sizes[0] == recorded[0]["bytes"]  # the recorded settings code the recorded bytes again
    assert sizes[1] < sizes[0] and psnrs[1] < psnrs[0] < 99  # a coarser QP appended: fewer bytes, lower PSNR


def test_options_on_a_folder_without_records_is_one_clear_error(tmp_path):
    with pytest.raises(SystemExit, match="no x265 records"):
        load_script("x265_repeat").options(str(tmp_path), [":me=star"])


def test_curve_gives_each_setting_its_bd_rate_against_the_recorded_options(tmp_path, monkeypatch, capsys):
    """A no-op parameter codes the same curve (BD-rate 0); 4x4 transforms only on smooth planes cost bytes."""
    _recorded_frames_stream(tmp_path, monkeypatch, seed=2)
    result = load_script("x265_repeat").curve(str(tmp_path), 0, [-3, 0, 3], [":cbqpoffs=0", ":max-tu-size=4"])
    assert result["(recorded)"] == (0.0, 1.0)
    assert result[":cbqpoffs=0"][0] == pytest.approx(0.0, abs=1e-9)
    assert result[":max-tu-size=4"][0] > 1.0
    assert "BD-rate" in capsys.readouterr().out


def test_curve_refuses_qps_outside_x265s_range_and_a_missing_piece(tmp_path, monkeypatch):
    _recorded_frames_stream(tmp_path, monkeypatch, qp=1, seed=2)
    script = load_script("x265_repeat")
    with pytest.raises(SystemExit, match="range 0-51"):
        script.curve(str(tmp_path), 0, [-2, 0], [])
    with pytest.raises(SystemExit, match="--piece must be 0-0"):
        script.curve(str(tmp_path), 3, [0], [])


@pytest.mark.parametrize("text, expected", [
    ("rd=2", ":rd=2"), (":rd=2", ":rd=2"), ("rd=2:ctu=32", ":rd=2:ctu=32"), (":me=dia:rect=0", ":me=dia:rect=0"),
    ("zones=0,0,q=27", ":zones=0,0,q=27"), ("", ""),
])
def test_extra_parameters_always_start_with_a_colon(text, expected):
    """Without it the first parameter ran into the recorded last one (``frame-threads=1rd=2``), which
    x265 took for ``frame-threads=1`` without a word: the setting was never applied."""
    assert load_script("x265_repeat").x265_params(text) == expected


@pytest.mark.parametrize("text", ["rd", "rd=2:ctu", "rd 2", ":=2"])
def test_extra_parameters_without_name_and_value_are_refused(text):
    import argparse

    with pytest.raises(argparse.ArgumentTypeError, match="NAME=VALUE"):
        load_script("x265_repeat").x265_params(text)


def test_extra_without_a_colon_changes_the_stream_as_with_one(tmp_path, monkeypatch, capsys):
    """On the command line ``--extra max-tu-size=4`` is applied (it costs bytes on smooth planes)."""
    import sys

    _recorded_frames_stream(tmp_path, monkeypatch, seed=2)
    script = load_script("x265_repeat")
    monkeypatch.setattr(sys, "argv", ["x265_repeat.py", "options", str(tmp_path), "--extra", "max-tu-size=4"])
    script.main()
    rows = [line for line in capsys.readouterr().out.splitlines() if " B " in line]
    sizes = [int(row.split()[1].replace(",", "")) for row in rows]
    assert [row.split()[0] for row in rows] == ["(recorded)", ":max-tu-size=4"]
    assert sizes[1] > sizes[0]
