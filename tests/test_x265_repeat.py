"""scripts/x265_repeat.py options: recorded streams coded again under other x265 parameters."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from gscodec_shac.codec.grid import get_codec
from tests.conftest import load_script


def test_options_recodes_the_recorded_streams_and_reports_bytes_and_psnr(tmp_path, monkeypatch, capsys):
    rng = np.random.default_rng(1)
    base = np.cumsum(np.cumsum(rng.normal(size=(48, 96)), 0), 1)
    planes = np.stack([base * (1 + 0.1 * k) for k in range(6)])
    planes = ((planes - planes.min()) / np.ptp(planes) * 1023).astype(np.uint16)
    monkeypatch.setenv("GSCODEC_X265_DUMP", str(tmp_path))
    monkeypatch.setenv("GSCODEC_X265_PROCESSES", "0")
    get_codec("hevc", layout="frames").encode(planes, 10, 20)
    monkeypatch.delenv("GSCODEC_X265_DUMP")
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
