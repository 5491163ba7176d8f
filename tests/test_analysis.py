"""Low-rank analysis (paper eq. 23-26, Table I) against direct numpy computations, and the CLI."""

import csv
import json

import numpy as np
import pytest

from gscodec_shac.cli import main
from gscodec_shac.errors import ValidationError
from gscodec_shac.io.ply import read_ply, write_ply
from gscodec_shac.shac import analysis
from tests.conftest import shared_scene


@pytest.fixture(scope="module")
def ac(small_cloud):
    return small_cloud.ac_matrix()


def _svd_curve(matrix):
    s2 = np.linalg.svd(np.asarray(matrix, dtype=np.float64), compute_uv=False) ** 2
    return np.cumsum(s2) / s2.sum()


def test_standardize_is_eq23(ac):
    a_std, mean, scale = analysis.standardize(ac)
    a64 = ac.astype(np.float64)
    assert np.allclose(mean, a64.mean(0)) and np.allclose(scale, a64.std(0, ddof=1))
    assert np.allclose(a_std, (a64 - a64.mean(0)) / a64.std(0, ddof=1))


def test_correlation_matches_numpy(ac):
    corr = analysis.correlation_matrix(ac)
    assert np.allclose(corr, np.corrcoef(ac.astype(np.float64).T), atol=1e-10)
    a_std, _, _ = analysis.standardize(ac)
    assert np.allclose(corr, a_std.T @ a_std / (len(ac) - 1), atol=1e-10)  # eq. 24


@pytest.mark.parametrize("mode", ["standardized", "centred", "raw"])
def test_svd_energy_curve_matches_numpy_svd(ac, mode):
    a64 = ac.astype(np.float64)
    reference = {
        "standardized": (a64 - a64.mean(0)) / a64.std(0, ddof=1),
        "centred": a64 - a64.mean(0),
        "raw": a64,
    }[mode]
    assert np.allclose(analysis.svd_energy_curve(ac, mode), _svd_curve(reference), atol=1e-10)
    s2 = np.linalg.svd(reference, compute_uv=False) ** 2
    assert np.allclose(analysis.squared_singular_values(ac, mode), s2, rtol=1e-8, atol=1e-10 * s2[0])


def test_rank_and_energy_at_k_match_numpy(ac):
    a64 = ac.astype(np.float64)
    curve = _svd_curve((a64 - a64.mean(0)) / a64.std(0, ddof=1))
    ours = analysis.svd_energy_curve(ac)
    for target in (0.5, 0.9, 0.95, 0.99):
        rank = analysis.rank_for_energy(ours, target)
        assert rank == int(np.argmax(curve >= target)) + 1
        assert curve[rank - 1] >= target and (rank == 1 or curve[rank - 2] < target)
    for k in (1, 10, 24, 45):
        assert analysis.energy_at(ours, k) == pytest.approx(curve[k - 1], abs=1e-10)


def test_truncation_curves(ac):
    a64 = ac.astype(np.float64)
    raw = np.cumsum((a64**2).sum(0)) / (a64**2).sum()
    centred_cols = ((a64 - a64.mean(0)) ** 2).sum(0)
    assert np.allclose(analysis.truncation_energy_curve(ac, "raw"), raw, atol=1e-12)
    assert np.allclose(analysis.truncation_energy_curve(ac, "centred"), np.cumsum(centred_cols) / centred_cols.sum())
    # On the standardised matrix every column holds the same energy: k / K' for any scene.
    assert np.allclose(analysis.truncation_energy_curve(ac, "standardized"), np.arange(1, 46) / 45)


def test_moments_are_chunk_independent_and_stable_under_offsets():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3000, 6)) + np.array([1e4, -3e3, 0, 5, 1e5, 0.1])
    a = analysis.column_moments(x)
    b = analysis.column_moments(x, chunk=7)
    centred = x - x.mean(0)
    for m in (a, b):
        assert np.allclose(m.mean, x.mean(0), rtol=1e-13)
        assert np.allclose(m.scatter, centred.T @ centred, rtol=1e-9, atol=1e-9 * len(x))
        assert np.allclose(m.raw_gram, x.T @ x, rtol=1e-12)


def test_zero_variance_column_gives_no_nan():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(200, 9))
    x[:, 4] = 0.25
    a_std, _, scale = analysis.standardize(x)
    corr = analysis.correlation_matrix(x)
    assert np.isfinite(a_std).all() and np.isfinite(corr).all() and scale[4] == 1.0
    assert corr[4, 4] == 1.0 and not corr[4, np.arange(9) != 4].any()
    assert np.isfinite(analysis.svd_energy_curve(x)).all()


def test_table_row_and_average(ac):
    row = analysis.table_row("s", ac, er=0.95, k=24)
    curve = analysis.svd_energy_curve(ac)
    assert row.svd_rank == analysis.rank_for_energy(curve, 0.95)
    assert row.svd_energy == pytest.approx(curve[23])
    assert row.trunc_std_rank == 43 and row.trunc_std_energy == pytest.approx(24 / 45)
    assert sum(row.degree_energy_raw) == pytest.approx(1.0) and len(row.degree_energy_raw) == 3
    assert row.degree_energy_raw[0] + row.degree_energy_raw[1] == pytest.approx(row.trunc_raw_energy)
    other = analysis.table_row("t", ac[:500], er=0.95, k=24)
    average = analysis.average_row([row, other])
    assert average["svd_rank"] == pytest.approx((row.svd_rank + other.svd_rank) / 2)
    with pytest.raises(ValidationError, match="k must be"):
        analysis.table_row("s", ac, k=46)
    with pytest.raises(ValidationError, match="energy retention"):
        analysis.rank_for_energy(curve, 0.0)


def test_averages_never_mix_sh_degrees(ac):
    sh3 = [analysis.table_row("a", ac, er=0.95, k=8), analysis.table_row("b", ac[:600], er=0.95, k=8)]
    sh2 = analysis.table_row("c", ac[:, :24], er=0.95, k=8)  # degree 2: the first 8 AC coefficients per colour
    assert [analysis.row_degree(r) for r in sh3 + [sh2]] == [3, 3, 2]
    single = analysis.average_rows(sh3)
    assert [a["scene"] for a in single] == ["Average"] and single[0]["n_scenes"] == 2
    mixed = analysis.average_rows(sh3 + [sh2])
    assert [(a["scene"], a["sh_degree"], a["n_scenes"]) for a in mixed] == [
        ("Average (SH 2)", 2, 1), ("Average (SH 3)", 3, 2)]
    assert mixed[0]["svd_rank"] == sh2.svd_rank
    assert mixed[1]["svd_rank"] == pytest.approx((sh3[0].svd_rank + sh3[1].svd_rank) / 2)
    with pytest.raises(ValidationError, match="average per degree"):
        analysis.average_row(sh3 + [sh2])


def test_correlation_groups_pick_the_right_pairs():
    corr = np.zeros((9, 9))  # degree 1: (l, m) = (1,-1), (1,0), (1,1)
    corr[0, 1] = corr[1, 0] = 0.9  # R and G of (1,-1): inter-component
    corr[0, 3] = corr[3, 0] = 0.3  # R of (1,-1) and R of (1,0): different order
    groups = analysis.correlation_groups(corr)
    assert groups["rgb"] == pytest.approx(0.9 / 9)  # 9 RGB pairs
    assert groups["other_order"] == pytest.approx(0.3 / 9)  # 3 channels x 3 pairs of orders
    assert np.isnan(groups["same_order"])  # one degree: no same-m pairs across degrees
    full = np.eye(45)
    full[3 * 1, 3 * 5] = full[3 * 5, 3 * 1] = 1.0  # R of (1,0) and R of (2,0): same order m = 0
    assert analysis.correlation_groups(full)["same_order"] > 0


def test_untouched_mask():
    x = np.ones((5, 9))
    x[[1, 3]] = 0.0
    x[4, 2] = 0.0
    assert analysis.untouched_mask(x).tolist() == [False, True, False, True, False]


def test_cli_analyze_writes_json_csv_and_pngs(tmp_path, small_cloud, capsys):
    ply = tmp_path / "scene.ply"
    cloud = small_cloud.copy()
    cloud.sh_rest[:300] = 0.0  # "untouched" Gaussians
    write_ply(ply, cloud)
    out = tmp_path / "out"
    assert main(["analyze", str(ply), "--synthetic", "1000", "--out", str(out)]) == 0
    table = json.loads((out / "table.json").read_text())
    assert [r["scene"] for r in table["rows"]] == ["scene", "synthetic_1000_s0"]
    assert table["rows"][0]["n_untouched"] == 300 and table["rows"][0]["n_gaussians"] == len(cloud)
    expected = analysis.table_row("scene", read_ply(ply).ac_matrix())
    assert table["rows"][0]["svd_rank"] == expected.svd_rank
    assert table["average"]["n_gaussians"] == pytest.approx((len(cloud) + 1000) / 2)
    with open(out / "table.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [r["scene"] for r in rows] == ["scene", "synthetic_1000_s0", "Average"]
    for name in ("correlation_scene.png", "correlation_synthetic_1000_s0.png", "er_curves.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "Average" in capsys.readouterr().out

    assert main(["analyze", str(ply), "--drop-untouched", "--out", str(out)]) == 2  # outputs exist
    assert main(["analyze", str(ply), "--drop-untouched", "--out", str(out), "--force"]) == 0
    row = json.loads((out / "table.json").read_text())["rows"][0]
    assert row["n_gaussians"] == len(cloud) - 300 and row["scene"] == "scene (touched)"
    assert (out / "correlation_scene_touched.png").is_file()


def test_cli_analyze_user_mistakes(capsys):
    assert main(["analyze"]) == 2
    assert "SCENE.ply or --synthetic" in capsys.readouterr().err
    assert main(["analyze", "--synthetic", "1000", "--er", "1.5"]) == 2
    assert main(["analyze", "--synthetic", "1000", "--k", "50"]) == 2
    assert "exceeds" in capsys.readouterr().err


def test_real_scene_structure():
    """On a real trained scene the low-rank SVD needs far fewer components than truncation."""
    cloud = read_ply(shared_scene("kacy_sh3_9k", "point_cloud.ply"))
    row = analysis.table_row("kacy", cloud.ac_matrix())
    assert row.svd_rank < row.trunc_raw_rank and row.svd_energy > row.trunc_raw_energy
    assert row.trunc_std_rank == 43
