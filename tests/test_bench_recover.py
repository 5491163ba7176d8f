"""scripts/bench_recover.py: the commands it measures, the output it reads back, the ratios it prints."""

import sys

import pytest

from tests.conftest import load_script

bench_recover = load_script("bench_recover")
bench_speed = load_script("bench_speed")


def test_the_two_commands_differ_by_recover_only():
    plain = bench_recover.encode_command("m.ply", "o.gsc", 40.0, "cams.json", "1,1,1", recover=False)
    recover = bench_recover.encode_command("m.ply", "o.gsc", 40.0, "cams.json", "1,1,1", recover=True)
    assert recover == plain + ["--recover"]
    assert plain[plain.index("--target-bpg") + 1] == "40"
    assert plain[plain.index("--background") + 1] == "1,1,1"
    assert "--background" not in bench_recover.encode_command("m.ply", "o.gsc", 40.0, "cams.json", None, recover=False)


def test_measured_keeps_the_whole_standard_output_apart_from_the_messages():
    script = "import sys; print('{\"a\": 1,'); print(' \"b\": 2}'); print('progress', file=sys.stderr)"
    run = bench_speed.measured([sys.executable, "-c", script], 0, keep_output=True)
    assert run["stdout"] == '{"a": 1,\n "b": 2}\n'
    assert "progress" not in run["stdout"]
    assert "stdout" not in bench_speed.measured([sys.executable, "-c", script], 0)
    failing = "import sys; print('partial'); print('the reason', file=sys.stderr); sys.exit(3)"
    with pytest.raises(SystemExit, match="the reason"):
        bench_speed.measured([sys.executable, "-c", failing], 0, keep_output=True)


def test_ratios_are_of_the_medians_per_target():
    def row(bpg, kind, wall, cpu):
        return {"bpg_target": bpg, "kind": kind, "wall_s": wall, "cpu_s": cpu}

    rows = [row(40, "plain", 10, 18), row(40, "plain", 12, 20), row(40, "plain", 30, 21),
            row(40, "recover", 36, 60), row(40, "recover", 40, 70), row(40, "recover", 33, 66),
            row(100, "plain", 20, 30), row(100, "recover", 50, 90)]
    out = bench_recover.ratios(rows)
    assert sorted(out) == [40, 100]
    assert out[40]["plain"] == {"wall_s": 12, "cpu_s": 20}
    assert out[40]["recover"] == {"wall_s": 36, "cpu_s": 66}
    assert out[40]["ratio_wall"] == pytest.approx(3.0) and out[40]["ratio_cpu"] == pytest.approx(3.3)
    assert out[100]["ratio_wall"] == pytest.approx(2.5) and out[100]["ratio_cpu"] == pytest.approx(3.0)


def test_results_are_written_as_json_and_csv(tmp_path):
    import csv
    import json

    rows = [{"bpg_target": 40.0, "kind": "plain", "seconds": {"fit": 1.5}, "other": "left out of the CSV"}]
    bench_speed.write_results(tmp_path / "bench", {"rows": rows}, rows, ["bpg_target", "kind", "seconds"])
    assert json.loads((tmp_path / "bench.json").read_text()) == {"rows": rows}
    with open(tmp_path / "bench.csv", newline="") as handle:
        assert list(csv.DictReader(handle)) == [{"bpg_target": "40.0", "kind": "plain", "seconds": '{"fit": 1.5}'}]
