"""RD sweeps on Ray: same rows as the local executor, bounded retries, resume.

Skipped (with the reason) when Ray is not installed: ``pip install "gscodec-shac[distributed]"``.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

ray = pytest.importorskip("ray", reason='Ray is not installed (pip install "gscodec-shac[distributed]")')

from gscodec_shac.rd import parse_sweep, run_sweep  # noqa: E402
from gscodec_shac.rd.ray_executor import RayExecutor  # noqa: E402
from gscodec_shac.rd.results import LOG_NAME  # noqa: E402

COMPARED = ("key", "status", "bytes", "sizes", "n_decoded", "psnr_gt", "ssim_gt", "psnr_ref", "ssim_ref", "n_views")


@pytest.fixture(scope="module")
def local_ray():
    """A local 2-CPU Ray instance for the module (no dashboard), shut down afterwards."""
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def spec_for(methods, rate_points=("paper_table3:rp1", "paper_table3:rp4"), **settings):
    return parse_sweep({
        "name": "ray-tiny",
        "rate_points": list(rate_points),
        "settings": {"preset": "ultrafast", "sort": "morton", **settings},
        "scenes": [{"name": "syn", "synthetic": {"n": 1500, "seed": 2, "n_cameras": 16, "width": 48, "height": 32}}],
        "methods": methods,
    }, source="ray-tiny")


def test_ray_gives_the_same_rows_as_local_processes(local_ray, tmp_path):
    spec = spec_for(["baseline", {"name": "pca", "recipe": "pca", "energy_retention": 0.99}])
    local = run_sweep(spec, tmp_path / "local", executor="local", workers=2, threads=1, progress=False)
    on_ray = run_sweep(spec, tmp_path / "ray", executor=RayExecutor(workers=2, threads=1), progress=False)
    assert on_ray.executed == 4 and on_ray.failed == 0
    assert [{k: r[k] for k in COMPARED} for r in on_ray.rows] == [{k: r[k] for k in COMPARED} for r in local.rows]


def test_a_raising_run_is_retried_then_recorded(local_ray, tmp_path):
    methods = ["baseline", {"name": "flaky", "recipe": "fault", "mode": "raise", "times": 1},
               {"name": "doomed", "recipe": "fault", "mode": "raise", "times": 50},
               {"name": "lost-once", "recipe": "fault", "mode": "exit", "times": 1}]
    spec = spec_for(methods, rate_points=("paper_table3:rp1",), retries=2, max_retries=1)
    outcome = run_sweep(spec, tmp_path / "out", executor=RayExecutor(workers=2, threads=1, max_retries=1),
                        progress=False)
    rows = {r["method"]: r for r in outcome.rows}
    assert rows["baseline"]["status"] == "ok"
    assert rows["flaky"]["status"] == "ok" and rows["flaky"]["attempts"] == 2
    assert rows["doomed"]["status"] == "failed" and rows["doomed"]["attempts"] == 3
    assert "injected fault" in rows["doomed"]["error"]
    assert rows["lost-once"]["status"] == "ok"  # its worker died; Ray ran the task again
    assert outcome.failed == 1


def test_an_interrupted_ray_sweep_resumes(local_ray, tmp_path):
    spec = spec_for(["baseline"])
    out = tmp_path / "out"
    first = run_sweep(spec, out, executor=RayExecutor(workers=2, threads=1), progress=False)
    assert first.executed == 2
    log = out / LOG_NAME
    lines = log.read_text().splitlines()
    log.write_text(lines[0] + "\n" + lines[1][: len(lines[1]) // 2])  # killed while writing row 2
    again = run_sweep(spec, out, executor=RayExecutor(workers=2, threads=1), progress=False)
    assert again.executed == 1 and again.reused == 1
    kept = json.loads(lines[0])
    assert next(r for r in again.rows if r["key"] == kept["key"])["finished_at"] == kept["finished_at"]
    assert [r["status"] for r in again.rows] == ["ok", "ok"]


def test_cli_ray_executor_runs(local_ray, tmp_path, capsys):
    from gscodec_shac.cli import main

    sweep = Path(tmp_path / "s.yaml")
    sweep.write_text(json.dumps({
        "rate_points": ["paper_table3:rp1"], "settings": {"preset": "ultrafast", "sort": "morton"},
        "scenes": [{"name": "syn", "synthetic": {"n": 1000, "n_cameras": 8, "width": 32, "height": 24}}],
        "methods": ["baseline"],
    }))
    assert main(["rd", str(sweep), "--out", str(tmp_path / "o"), "--executor", "ray", "--workers", "2",
                 "--threads", "1", "--quiet", "--no-report"]) == 0
    assert "1 executed" in capsys.readouterr().out
