"""scripts/bench_probe_cache.py: its fresh-probe controller bypasses the cache, and a run compares both."""

import json

from tests.conftest import load_script

bench_probe_cache = load_script("bench_probe_cache")


def test_the_fresh_controller_codes_every_probe_without_the_cache_and_both_write_one_file(tmp_path):
    from gscodec_shac.codec.rate_control import RateController
    from gscodec_shac.io.ply import write_ply
    from gscodec_shac.synthetic import make_synthetic_scene

    cloud = make_synthetic_scene(600, seed=3, n_cameras=2, width=16, height=12).cloud
    fresh, cached = bench_probe_cache.FreshProbes(cloud), RateController(cloud)
    assert fresh._probe_encoder(fresh.template)._chunk_cache is None
    assert cached._probe_encoder(cached.template)._chunk_cache is cached._probe_cache  # what the fresh one leaves out
    write_ply(tmp_path / "m.ply", cloud)
    assert bench_probe_cache.main([str(tmp_path / "m.ply"), "--bpg", "80", "--repeat", "1", "--out", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "bench_probe_cache.json").read_text())["rows"]
    assert sorted(row["kind"] for row in rows) == ["cached", "fresh"]
    assert rows[0]["sha256"] == rows[1]["sha256"] and rows[0]["bytes"] > 0
    assert (tmp_path / "bench_probe_cache.csv").read_text().startswith("kind,round,wall_s")

