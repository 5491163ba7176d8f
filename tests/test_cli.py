"""The CLI: `info` on real and synthetic scenes, and one-line errors for user mistakes."""

import json
import subprocess
import sys

from gscodec_shac.cli import main
from gscodec_shac.io.ply import read_ply
from tests.conftest import shared_scene


def test_info_on_real_scene(capsys):
    path = shared_scene("kacy_sh3_9k", "point_cloud.ply")
    assert main(["info", str(path), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["num_gaussians"] == 9080
    assert summary["sh_degree"] == 3
    assert abs(summary["sh_share"] - 48 / 59) < 1e-12


def test_synthetic_then_info(tmp_path, capsys):
    out = tmp_path / "scene.ply"
    assert main(["synthetic", str(out), "-n", "1500", "--views", "4"]) == 0
    assert (tmp_path / "cameras.json").is_file()
    assert read_ply(out).num_gaussians == 1500
    capsys.readouterr()
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "Gaussians         1,500" in text and "SH 48 = 81.4%" in text


def test_user_mistake_is_one_line_without_traceback(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_text("not a ply")
    result = subprocess.run(
        [sys.executable, "-m", "gscodec_shac", "info", str(bad)], capture_output=True, text=True
    )
    assert result.returncode == 2
    assert result.stderr.strip() == f"error: {bad}: not a PLY file (it does not start with 'ply')"
    assert "Traceback" not in result.stderr
