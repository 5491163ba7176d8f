"""scripts/bench_speed.py: the fixed encode of a target's choice codes its chunks; the target pairs' commands and rows."""

from gscodec_shac.codec import Encoder, load_rate_point
from gscodec_shac.codec.rate_control import RateController, make_target
from tests.conftest import load_script

bench_speed = load_script("bench_speed")


def test_the_chosen_settings_as_a_rate_point_code_the_target_files_chunks(small_scene, tmp_path):
    cloud = small_scene.cloud
    controller = RateController(cloud, views=small_scene.cameras, workers=1)
    outcome = controller.encode(make_target(cloud.num_gaussians, bpg=60))
    aimed = tmp_path / "aimed.gsc"
    outcome.stream.write(aimed)
    chosen = bench_speed.chosen_rate_point(aimed, tmp_path / "chosen.yaml")
    point = load_rate_point(f"{chosen}:chosen")
    settings = outcome.plan.rate_point
    assert point.attributes["positions"].bits == settings.attributes["positions"].bits
    assert all(point.attributes[name].qp == settings.attributes[name].qp
               for name in ("opacity", "rotation", "scale", "sh_dc", "sh_features"))
    assert (point.min_opacity, point.keep_share) == (settings.min_opacity, settings.keep_share)
    fixed = tmp_path / "fixed.gsc"
    # with cameras the controller fits SHAC-PCA in their view metric (version 18), as `encode --cameras` does
    metric = controller._sh_metric()
    assert metric is not None
    plain = tmp_path / "plain.gsc"
    Encoder(point, workers=1).encode(cloud).write(plain)
    assert any(name.startswith("sh") for name in bench_speed.differing_chunks(aimed, plain))
    Encoder(point, workers=1, sh_metric=metric).encode(cloud).write(fixed)
    assert bench_speed.differing_chunks(aimed, fixed) == []
    assert bench_speed.chosen_rate_point(fixed, tmp_path / "again.yaml") is None  # not a controller's choice


def test_target_pairs_give_both_encodes_the_cameras_and_name_their_rows(tmp_path, monkeypatch, capsys):
    """``--repeat`` target pairs (issue 25): each target run, then the fixed encode of its choice; with
    ``--target-cameras`` both are given the cameras and their rows end in ``_cameras``."""
    import argparse

    commands: list[list[str]] = []
    walls = iter([30.0, 15.0, 20.0, 10.0])

    def fake_measured(command, nice, root=None, **_):
        commands.append(command)
        wall = next(walls)
        return {"wall_s": wall, "cpu_s": 2 * wall}

    monkeypatch.setattr(bench_speed, "measured", fake_measured)
    monkeypatch.setattr(bench_speed, "chosen_rate_point", lambda stream, out: out)
    monkeypatch.setattr(bench_speed, "differing_chunks", lambda a, b: [])
    rows: list[tuple[str, str]] = []

    def record(size, step, row):
        rows.append((size, step))
        return row

    args = argparse.Namespace(target_bpg=100.0, target_psnr=None, repeat=2, nice=0)
    cameras = tmp_path / "cams8" / "cameras.json"
    bench_speed.target_ratios("1M", tmp_path / "cams8" / "s1M.ply", args, ["gs"], record, "bpg", cameras)
    assert [step for _, step in rows] == ["target_bpg_cameras", "chosen_fixed_cameras"] * 2
    assert all(command[command.index("--cameras") + 1] == str(cameras) for command in commands)
    assert "--target-bpg" in commands[0] and "-r" in commands[1]
    printed = capsys.readouterr().out
    assert "(wall): 2.00, 2.00; of the medians 2.00" in printed and "the same chunks as the target file" in printed
    commands.clear(), rows.clear()
    walls = iter([30.0, 10.0])
    args.repeat = 1
    bench_speed.target_ratios("1M", tmp_path / "s1M.ply", args, ["gs"], record, "bpg")
    assert [step for _, step in rows] == ["target_bpg", "chosen_fixed"]
    assert not any("--cameras" in command for command in commands)
