"""The RD sweep harness: spec validation, runs -> rows, resume, failures, sort cache, report, CLI."""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from gscodec_shac.cli import main
from gscodec_shac.rd import load_results, load_sweep, parse_sweep, run_sweep, write_report
from gscodec_shac.rd.results import LOG_NAME, ResultStore
from gscodec_shac.rd.spec import SweepSpecError

RATE_POINTS = ["paper_table3:rp1", "paper_table3:rp4"]


def tiny_spec(tmp_path: Path, methods=None, scenes=None, **settings) -> dict:
    """One ~2k-Gaussian synthetic scene at 64x48, 2 methods x 2 rate points, fast coding."""
    return {
        "name": "tiny",
        "rate_points": RATE_POINTS,
        "settings": {"preset": "ultrafast", "sort": "morton", **settings},
        "scenes": scenes or [{"name": "syn", "synthetic": {"n": 2000, "seed": 0, "n_cameras": 16, "width": 64, "height": 48}}],
        "methods": methods or ["baseline", {"name": "pca", "recipe": "pca", "energy_retention": 0.99}],
    }


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """The tiny sweep on two local worker processes (the default executor)."""
    out = tmp_path_factory.mktemp("rd") / "out"
    spec = parse_sweep(tiny_spec(out.parent), source="tiny")
    outcome = run_sweep(spec, out, executor="local", workers=2, threads=1, progress=False)
    return spec, out, outcome


def by(rows, method, point):
    return next(r for r in rows if r["method"] == method and r["rate_point"] == point)


# --------------------------------------------------------------------------- end to end
def test_tiny_sweep_rows_are_sane(tiny_run):
    spec, out, outcome = tiny_run
    assert outcome.planned == 4 and outcome.executed == 4 and outcome.failed == 0
    rows = outcome.rows
    assert [r["status"] for r in rows] == ["ok"] * 4, [r.get("error") for r in rows]
    for row in rows:
        assert row["bytes"] > 0 and sum(row["sizes"].values()) == row["bytes"]
        assert row["bits_per_gaussian"] == pytest.approx(8 * row["bytes"] / 2000)
        for column in ("psnr_gt", "psnr_ref", "ssim_gt", "ssim_ref"):
            assert math.isfinite(row[column]), column
        assert 0 < row["ssim_ref"] <= 1 and row["psnr_ref"] > 25
        assert row["n_views"] == 2 and row["has_gt"] is True and row["lpips_gt"] is None and row["lpips_note"]
    for point in RATE_POINTS:
        assert by(rows, "baseline", point)["bytes"] > by(rows, "pca", point)["bytes"]
    # finer quantisation (rp4) costs more bytes and is closer to the uncompressed model
    assert by(rows, "baseline", RATE_POINTS[1])["bytes"] > by(rows, "baseline", RATE_POINTS[0])["bytes"]
    assert by(rows, "baseline", RATE_POINTS[1])["psnr_ref"] > by(rows, "baseline", RATE_POINTS[0])["psnr_ref"]
    # the same rows in CSV and JSON
    assert load_results(out) == rows
    csv_lines = (out / "results.csv").read_text().splitlines()
    assert len(csv_lines) == 5 and "bytes_sh" in csv_lines[0] and "psnr_gt" in csv_lines[0]


def test_finished_rows_are_not_recomputed(tiny_run, tmp_path):
    spec, out, outcome = tiny_run
    again = run_sweep(spec, out, executor="serial", progress=False)
    assert again.executed == 0 and again.reused == 4
    assert again.rows == outcome.rows  # same rows, same finished_at: nothing ran

    # an interrupted sweep: one row never written, a torn last line; resume runs just that one
    copy = tmp_path / "copy"
    copy.mkdir()
    for name in ("sweep.json", "scenes", "cache"):
        src = out / name
        (copy / name).symlink_to(src, target_is_directory=src.is_dir())
    lines = (out / LOG_NAME).read_text().splitlines()
    (copy / LOG_NAME).write_text("\n".join(lines[:3]) + '\n{"key": "syn/pca/paper_ta')
    dropped = json.loads(lines[3])["key"]
    resumed = run_sweep(spec, copy, executor="serial", progress=False)
    assert resumed.executed == 1 and resumed.reused == 3
    assert [r["key"] for r in resumed.rows] == [r["key"] for r in outcome.rows]
    for new, old in zip(resumed.rows, outcome.rows):
        if new["key"] != dropped:
            assert new == old
        else:  # recomputed; SHAC-PCA's fit is not bit-identical across BLAS thread counts
            assert new["finished_at"] >= old["finished_at"]
            assert new["bytes"] == pytest.approx(old["bytes"], rel=1e-3)
    assert len(ResultStore(copy).latest()) == 4


def test_changed_settings_give_new_keys(tiny_run):
    spec, out, outcome = tiny_run
    other = parse_sweep(tiny_spec(out.parent, preset="veryfast"), source="tiny")
    from gscodec_shac.rd.scenes import prepare_scene
    from gscodec_shac.rd.sweep import plan

    tasks = plan(other, {s.name: prepare_scene(s, out) for s in other.scenes}, out, 1)
    assert not {t.key for t in tasks} & {r["key"] for r in outcome.rows}


def test_failing_runs_are_recorded_not_fatal(tmp_path):
    bad = tmp_path / "broken.ply"
    bad.write_text("not a ply at all\n")
    scenes = [
        {"name": "syn", "synthetic": {"n": 1000, "seed": 1, "n_cameras": 8, "width": 48, "height": 32}},
        {"name": "broken", "ply": str(bad), "orbit": {"n": 8, "width": 48, "height": 32}},
    ]
    methods = ["baseline", {"name": "flaky", "recipe": "fault", "mode": "raise", "times": 1},
               {"name": "doomed", "recipe": "fault", "mode": "raise", "times": 50}]
    spec = parse_sweep(tiny_spec(tmp_path, methods, scenes, retries=1), source="faults")
    spec = spec.__class__(**{**spec.__dict__, "rate_points": ("paper_table3:rp1",)})
    outcome = run_sweep(spec, tmp_path / "out", executor="serial", progress=False)
    rows = {(r["scene"], r["method"]): r for r in outcome.rows}
    assert rows[("syn", "baseline")]["status"] == "ok"
    assert rows[("syn", "flaky")]["status"] == "ok" and rows[("syn", "flaky")]["attempts"] == 2
    doomed = rows[("syn", "doomed")]
    assert doomed["status"] == "failed" and doomed["attempts"] == 2 and "injected fault" in doomed["error"]
    broken = rows[("broken", "baseline")]
    assert broken["status"] == "failed" and "broken.ply" in broken["error"]
    assert outcome.failed == 4  # doomed + the broken scene's three methods


def test_a_dying_worker_costs_only_its_run(tmp_path):
    methods = [{"name": "crash", "recipe": "fault", "mode": "exit", "times": 1},
               {"name": "crash-always", "recipe": "fault", "mode": "exit", "times": 50}]
    spec = parse_sweep(tiny_spec(tmp_path, methods, max_retries=1), source="crash")
    spec = spec.__class__(**{**spec.__dict__, "rate_points": ("paper_table3:rp1",),
                             "scenes": (spec.scenes[0].__class__(**{**spec.scenes[0].__dict__, "max_views": 1}),)})
    outcome = run_sweep(spec, tmp_path / "out", executor="local", workers=1, threads=1, progress=False)
    rows = {r["method"]: r for r in outcome.rows}
    assert rows["crash"]["status"] == "ok"  # re-queued once after its worker died
    failed = rows["crash-always"]
    assert failed["status"] == "failed" and "worker process died (exit code 17) 2 time(s)" in failed["error"]


def test_sort_cache_gives_identical_bytes(tmp_path, small_cloud):
    from gscodec_shac.codec import Encoder
    from gscodec_shac.rd.sortcache import cached_grid_order

    plain = Encoder("paper_table3:rp2", sh_stage="pca", sh_params={"energy_retention": 0.97}).encode(small_cloud)
    first = Encoder("paper_table3:rp2", sh_stage="pca", sh_params={"energy_retention": 0.97})
    grid, cached, _ = cached_grid_order(first, small_cloud, tmp_path)
    assert first.encode(small_cloud, grid=grid).to_bytes() == plain.to_bytes() and cached is False
    second = Encoder("paper_table3:rp2", sh_stage="none")
    grid, cached, _ = cached_grid_order(second, small_cloud, tmp_path)
    uncached_none = Encoder("paper_table3:rp2", sh_stage="none").encode(small_cloud).to_bytes()
    assert second.encode(small_cloud, grid=grid).to_bytes() == uncached_none and cached is True
    assert len(list(tmp_path.glob("sort-*.npz"))) == 1


# --------------------------------------------------------------------------- report
def test_report_tables_and_plots(tiny_run, tmp_path):
    spec, out, outcome = tiny_run
    paths = write_report(out, tmp_path / "report")
    figure = paths["figure:syn"]
    assert figure.stat().st_size < 200_000 and figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = paths["markdown"].read_text()
    assert "| baseline | rp1 |" in text and "BD against `baseline`" in text
    table = json.loads(paths["bd_json"].read_text())
    entry = next(e for e in table if e["method"] == "pca" and e["metric"] == "psnr_ref")
    assert entry["size_change_pct"] < 0 and entry["common_points"] == 2
    assert (entry["bd_rate_pct"] is None) == ("BD-rate: the curves do not overlap" in entry["note"])
    assert (entry["bd_quality"] is None) == ("BD-quality: the curves do not overlap" in entry["note"])


def test_cli_rd_report_and_dry_run(tiny_run, tmp_path, capsys):
    spec, out, outcome = tiny_run
    assert main(["rd-report", str(out), "--out", str(tmp_path / "r"), "--x-axis", "bpg"]) == 0
    assert (tmp_path / "r" / "report.md").is_file()
    # its own report is regenerated without --force (issue 26); a foreign report.md still needs it
    assert main(["rd-report", str(out), "--out", str(tmp_path / "r")]) == 0
    (tmp_path / "r2").mkdir()
    (tmp_path / "r2" / "report.md").write_text("mine")
    assert main(["rd-report", str(out), "--out", str(tmp_path / "r2")]) == 2
    sweep = tmp_path / "s.yaml"
    sweep.write_text(json.dumps(tiny_spec(tmp_path)))  # JSON is YAML
    assert main(["rd", str(sweep), "--out", str(tmp_path / "o"), "--dry-run"]) == 0
    assert "4 runs (1 scenes x 2 methods)" in capsys.readouterr().out


# --------------------------------------------------------------------------- validation
@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d.pop("scenes"), "'scenes': is required"),
        (lambda d: d.update(extra=1), "'extra': unknown key"),
        (lambda d: d.update(methods=[{"name": "x", "recipe": "magic"}]), "unknown recipe 'magic'"),
        (lambda d: d.update(methods=[{"name": "p", "recipe": "pca", "energy_retention": 1.5}]), "'energy_retention': must be a number in (0, 1], got 1.5"),
        (lambda d: d.update(methods=[{"name": "p", "recipe": "pca", "erergy": 0.9}]), "'erergy': unknown key"),
        (lambda d: d.update(methods=["baseline", "baseline"]), "'baseline' is used twice"),
        (lambda d: d.update(rate_points=["paper_table3:rp9"]), "no rate point 'rp9'"),
        (lambda d: d.update(rate_points=[]), "must be a non-empty list"),
        (lambda d: d.update(scenes=[{"name": "a", "ply": "missing.ply"}]), "missing.ply does not exist"),
        (lambda d: d.update(scenes=[{"name": "a/b", "synthetic": {}}]), "without '/'"),
        (lambda d: d.update(scenes=[{"name": "a", "synthetic": {"n": 10}}]), "'scenes[0].synthetic.n'"),
        (lambda d: d["settings"].update(sort="bogus"), "'settings.sort': must be one of"),
        (lambda d: d["settings"].update(retries=-1), "'settings.retries'"),
    ],
)
def test_bad_sweeps_raise_one_clear_error(tmp_path, change, message):
    data = tiny_spec(tmp_path)
    change(data)
    with pytest.raises(SweepSpecError, match=None) as info:
        parse_sweep(data, source="bad.yaml", base=tmp_path)
    assert message in str(info.value) and str(info.value).startswith("bad.yaml: ")
    assert "\n" not in str(info.value)


def test_bad_yaml_file_and_cli_message(tmp_path, capsys):
    path = tmp_path / "broken.yaml"
    path.write_text("scenes: [unclosed\n")
    with pytest.raises(SweepSpecError, match="not valid YAML at line"):
        load_sweep(path)
    assert main(["rd", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "broken.yaml" in err[0]
    assert main(["rd", str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "o")]) == 2
    assert "sweep file not found" in capsys.readouterr().err


def test_ray_executor_without_ray_says_how_to_install(monkeypatch, tmp_path):
    import builtins

    real_import = builtins.__import__

    def no_ray(name, *args, **kwargs):
        if name == "ray" or name.startswith("ray."):
            raise ImportError("No module named 'ray'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    from gscodec_shac.errors import GscodecError
    from gscodec_shac.rd.sweep import make_executor

    with pytest.raises(GscodecError, match=r'pip install "gscodec-shac\[distributed\]"'):
        make_executor("ray")


def test_orbit_cameras_for_a_scene_without_cameras(small_cloud):
    from gscodec_shac.rd.scenes import auto_orbit
    from gscodec_shac.rd.spec import OrbitSpec
    from gscodec_shac.render import render

    cameras = auto_orbit(small_cloud, OrbitSpec(n=4, width=48, height=32))
    assert len(cameras) == 4
    for camera in cameras:  # the scene fills a good part of every view
        alpha = render(small_cloud, camera).alpha
        assert 0.1 < float(np.mean(alpha > 0.5)) < 0.95


def test_demo_yaml_is_the_demo(tmp_path):
    from gscodec_shac.commands.demo import demo_sweep

    repo = Path(__file__).resolve().parents[1]
    shipped = load_sweep(repo / "sweeps" / "demo.yaml")
    built = parse_sweep(demo_sweep(30_000, 0), source="demo")
    assert shipped.scenes == built.scenes and shipped.methods == built.methods
    assert shipped.rate_points == built.rate_points and shipped.settings == built.settings


def test_demo_command_end_to_end(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "-n", "1000", "--workers", "1", "--preset", "ultrafast", "-q"]) == 0
    text = capsys.readouterr().out
    assert "shac-pca-er0.97 vs baseline" in text and "demo finished" in text
    for name in ("results.csv", "results.json", "bd_table.md", "bd_table.json", "report/rd_synthetic.png",
                 "report/report.html", "renders/synthetic/uncompressed.png", "renders/synthetic/ground_truth.png"):
        assert (out / name).is_file(), name
    rows = load_results(out)
    fixed = [r for r in rows if r["method"] != "shac-auto"]
    assert len(fixed) == 8 and all(r["status"] == "ok" and r["psnr_gt"] > 20 for r in fixed)
    auto = [r for r in rows if r["method"] == "shac-auto"]
    # 1,000 Gaussians cannot go as low as 40 bits each (side information): those targets are skipped
    assert len(auto) == 4 and any(r["status"] == "ok" for r in auto)
    assert all(r["status"] == "ok" or "smallest file" in r["error"] for r in auto)


def test_auto_recipe_runs_once_per_target_and_meets_it(tmp_path):
    """The rate controller as a sweep method: one row per target, each file at most its size."""
    methods = [{"name": "auto", "recipe": "auto", "bpg": [200, 320]}]
    spec = parse_sweep(tiny_spec(tmp_path, methods=methods, sort=None), source="auto", base=tmp_path)
    outcome = run_sweep(spec, tmp_path / "out", executor="serial", threads=1, progress=False)
    rows = {r["rate_point"]: r for r in outcome.rows}
    assert sorted(rows) == ["bpg-200", "bpg-320"] and all(r["status"] == "ok" for r in rows.values())
    for label, row in rows.items():
        target = float(label.split("-")[1])
        assert 0.97 * target <= float(row["bits_per_gaussian"]) <= target
    assert float(rows["bpg-320"]["psnr_ref"]) > float(rows["bpg-200"]["psnr_ref"])


@pytest.mark.parametrize("params, message", [
    ({"bpg": [100], "psnr": [30]}, "exactly one list of targets"),
    ({"sizes": ["2 parsecs"]}, "sizes[0]"),
    ({"bpg": []}, "non-empty list"),
])
def test_auto_recipe_parameters_are_checked(tmp_path, params, message):
    data = tiny_spec(tmp_path, methods=[{"name": "auto", "recipe": "auto", **params}])
    with pytest.raises(SweepSpecError) as info:
        parse_sweep(data, source="bad.yaml", base=tmp_path)
    assert message in str(info.value)


def test_sort_cache_keeps_set_coded_grids_of_different_bit_depths_apart(tmp_path, small_cloud):
    """Set-coded positions order the grid by their quantised Morton codes: each bit depth its own order."""
    from gscodec_shac.codec import Encoder
    from gscodec_shac.rd.sortcache import cached_grid_order

    for point in ("shac_ladder:rp1", "shac_ladder:rp2"):
        encoder = Encoder(point, sh_stage="none")
        grid, _, _ = cached_grid_order(encoder, small_cloud, tmp_path)
        assert encoder.encode(small_cloud, grid=grid).to_bytes() == Encoder(point, sh_stage="none").encode(small_cloud).to_bytes()
    assert len(list(tmp_path.glob("sort-*.npz"))) == 2


# --------------------------------------------------------------------------- the HTML page
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--hide-scrollbars"]


def _page(tiny_run, tmp_path):
    _, out, _ = tiny_run
    paths = write_report(out, tmp_path / "report")
    return paths, paths["html"].read_text()


def test_report_html_is_self_contained_with_bd_numbers_and_renders(tiny_run, tmp_path):
    import re

    from gscodec_shac.rd.renders import reference_paths, run_render_path

    _, out, outcome = tiny_run
    for row in outcome.rows:  # every run kept its decoded render of the first test view
        assert run_render_path(out, "syn", row["method"], row["rate_point"]).is_file(), row["key"]
    assert all(p.is_file() for p in reference_paths(out, "syn"))  # uncompressed render, ground truth
    paths, page = _page(tiny_run, tmp_path)
    sources = re.findall(r'<img src="([^"]*)"', page)
    assert sources and all(s.startswith("data:image/png;base64,") for s in sources)
    assert "http" not in page.replace("http-equiv", "")  # nothing fetched from elsewhere
    # the RD figure + per method (2 rate points x decoded over uncompressed, + uncompressed, + ground truth)
    assert len(sources) == 1 + 2 * (2 * 2 + 2)
    for entry in json.loads(paths["bd_json"].read_text()):
        if entry["bd_rate_pct"] is not None:
            assert f"{entry['bd_rate_pct']:+.1f}%" in page
        if entry["bd_quality"] is not None and entry["metric"].startswith("psnr"):
            assert f"{entry['bd_quality']:+.3f} dB" in page


def _chromium(*args: str, tmp_path) -> subprocess.CompletedProcess:
    import shutil
    import tempfile

    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip("chromium is not installed (Debian: apt-get install chromium)")
    profile = tempfile.mkdtemp(dir=tmp_path)
    return subprocess.run([browser, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", *args],
                          capture_output=True, text=True, timeout=180)


def test_report_html_opens_in_headless_chromium(tiny_run, tmp_path):
    """The page in a real browser: every image decodes (the page's script counts them into the
    DOM) and the screenshot holds the plot and the renders, not a blank page."""
    import re

    import cv2

    paths, page = _page(tiny_run, tmp_path)
    url = paths["html"].resolve().as_uri()
    dom = _chromium("--virtual-time-budget=10000", "--dump-dom", url, tmp_path=tmp_path)
    assert dom.returncode == 0, dom.stderr[-2000:]
    counted = re.search(r'data-images="(\d+)/(\d+)"', dom.stdout)
    assert counted, dom.stdout[:500]
    decoded, total = map(int, counted.groups())
    assert total == page.count("<img ") and decoded == total
    shot = tmp_path / "shot.png"
    result = _chromium("--window-size=1200,1600", "--virtual-time-budget=10000", f"--screenshot={shot}", url,
                       tmp_path=tmp_path)
    assert result.returncode == 0 and shot.is_file(), result.stderr[-2000:]
    image = cv2.imread(str(shot))
    assert image is not None and image.shape[:2] == (1600, 1200)
    not_white = (image.min(axis=2) < 200).mean()
    colourful = (image.max(axis=2).astype(int) - image.min(axis=2) > 40).mean()  # plot lines and renders
    assert not_white > 0.2 and colourful > 0.02, (not_white, colourful)
