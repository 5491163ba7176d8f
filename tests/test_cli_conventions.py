"""One CLI convention across commands: help with an example everywhere, old option spellings
still working, positional outputs, one-line errors, progress bars off when not a terminal, and
the ``rate-points`` command."""

import argparse
import ctypes
import io
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from gscodec_shac import cli as cli_module
from gscodec_shac.cli import _parse_args, build_parser, main
from gscodec_shac.codec.rate_points import builtin_rate_point_files, load_rate_point_file
from gscodec_shac.commands import _options
from gscodec_shac.commands._options import resolve_args
from gscodec_shac.io.inria_cameras import write_inria_cameras
from gscodec_shac.io.ply import write_ply
from gscodec_shac.synthetic import make_synthetic_scene

REPO = Path(__file__).resolve().parents[1]
PARSER = build_parser()
COMMANDS = dict(next(a for a in PARSER._actions if isinstance(a, argparse._SubParsersAction)).choices)


def parse(argv: list[str]) -> dict:
    """What a command line resolves to (the namespace ``run`` sees), without the bookkeeping."""
    args = resolve_args(_parse_args(build_parser(), argv))
    return {k: v for k, v in vars(args).items() if k not in ("out_option", "output_spec", "func", "quiet")}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("scene")
    made = make_synthetic_scene(400, seed=3, n_cameras=4, width=32, height=24)
    write_ply(root / "s.ply", made.cloud)
    write_inria_cameras(root / "cameras.json", made.cameras)
    return root


# ------------------------------------------------------------------ help
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_has_help_with_an_example(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    block = text.split("Example", 1)[1].split("\n\n", 1)[0]
    assert f"gscodec-shac {command}" in block, text
    for action in COMMANDS[command]._actions:
        assert action.help, f"{command}: {action.option_strings or action.dest} has no help"


def test_the_program_help_has_an_example_and_lists_rate_points(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "Example:\n  gscodec-shac encode" in text and "rate-points" in text


def test_shared_options_are_spelled_the_same_everywhere():
    for name, sub in COMMANDS.items():
        for action in sub._actions:
            if action.dest == "quiet":
                assert action.option_strings == ["-q", "--quiet"], name
            if action.dest == "threads":
                assert action.default is None and "all cores" in action.help, name
            if action.dest == "json":
                assert action.option_strings == ["--json"], name
        hidden = [a for a in sub._actions if a.help is argparse.SUPPRESS and a.option_strings and a.dest != "debug"]
        visible_strings = {s for a in sub._actions if a.help is not argparse.SUPPRESS for s in a.option_strings}
        assert not {"--images-dir", "--scale", "--out"} & visible_strings - ({"--out"} if name == "analyze" else set())
        for action in hidden:
            assert action.default is argparse.SUPPRESS or action.dest == "out_option", (name, action.option_strings)


# ------------------------------------------------------------------ old spellings
# One case per renamed option: the old spelling parses to what the new one does.
RENAMED = {
    "render --out": (["render", "s.ply", "--out", "r"], ["render", "s.ply", "r"]),
    "render --images-dir": (["render", "s.ply", "r", "--cameras", "c.json", "--images-dir", "img"],
                            ["render", "s.ply", "r", "--cameras", "c.json", "--images", "img"]),
    "render --scale": (["render", "s.ply", "r", "--scale", "0.5"],
                       ["render", "s.ply", "r", "--resolution-scale", "0.5"]),
    "lst-finetune --scale": (["lst-finetune", "a.ply", "b.ply", "--orbit", "4", "--scale", "0.5"],
                             ["lst-finetune", "a.ply", "b.ply", "--orbit", "4", "--resolution-scale", "0.5"]),
    "rd --out": (["rd", "sweep.yaml", "--out", "runs"], ["rd", "sweep.yaml", "runs"]),
    "rd-report --out": (["rd-report", "runs", "--out", "rep"], ["rd-report", "runs", "rep"]),
    "demo --out": (["demo", "--out", "d"], ["demo", "d"]),
    "render --quiet": (["render", "s.ply", "r", "--quiet"], ["render", "s.ply", "r", "-q"]),
    "train --quiet": (["train", "cap", "out", "--quiet"], ["train", "cap", "out", "-q"]),
    "lst-finetune --quiet": (["lst-finetune", "a.ply", "b.ply", "--quiet"], ["lst-finetune", "a.ply", "b.ply", "-q"]),
    "encode --quiet": (["encode", "a.ply", "b.gsc", "--quiet"], ["encode", "a.ply", "b.gsc", "-q"]),
}


@pytest.mark.parametrize("case", list(RENAMED))
def test_old_spelling_parses_like_the_new_one(case):
    old, new = RENAMED[case]
    assert parse(old) == parse(new)


def test_old_render_spellings_still_render(scene, tmp_path, capsys):
    images = tmp_path / "truth"
    assert main(["render", str(scene / "s.ply"), str(images), "--cameras", str(scene / "cameras.json")]) == 0
    assert main(["render", str(scene / "s.ply"), "--out", str(tmp_path / "old"), "--cameras",
                 str(scene / "cameras.json"), "--images-dir", str(images), "--scale", "0.5"]) == 0
    assert main(["render", str(scene / "s.ply"), str(tmp_path / "new"), "--cameras",
                 str(scene / "cameras.json"), "--images", str(images), "--resolution-scale", "0.5"]) == 0
    old, new = (json.loads((tmp_path / d / "metrics.json").read_text()) for d in ("old", "new"))
    assert old == new and old["mean"]["views"] == 4
    assert sorted(p.name for p in (tmp_path / "old").iterdir()) == sorted(p.name for p in (tmp_path / "new").iterdir())
    capsys.readouterr()


def test_old_rd_out_still_runs(tmp_path, capsys):
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text("name: t\nrate_points: [paper_table3:rp1]\nscenes:\n  - name: s\n    synthetic: {n: 1000}\n"
                     "methods: [baseline]\n")
    assert main(["rd", str(sweep), "--out", str(tmp_path / "o"), "--dry-run"]) == 0
    old = capsys.readouterr().out
    assert main(["rd", str(sweep), str(tmp_path / "o"), "--dry-run"]) == 0
    assert capsys.readouterr().out == old and "1 runs" in old


def test_an_optional_output_after_options_is_still_the_output():
    assert parse(["rd-report", "runs", "--x-axis", "bpg", "rep"])["out"] == "rep"
    assert parse(["render", "s.ply", "--cameras", "c.json", "r"])["out"] == "r"
    assert parse(["demo"])["out"] == "demo-output" and parse(["rd-report", "runs"])["out"] is None


@pytest.mark.parametrize("argv, message", [
    (["render", "s.ply"], "error: render needs an output OUT_DIR"),
    (["rd", "sweep.yaml"], "error: rd needs an output OUT_DIR"),
    (["render", "s.ply", "a", "--out", "b"], "error: the output is given twice (a and --out b)"),
    (["render", "s.ply", "a", "b"], "error: gscodec-shac render: unrecognized arguments: b"),
    (["render", "s.ply", "a", "--scale", "1", "--width", "8"], "not allowed with argument --scale"),
    (["encode", "s.ply"], "error: gscodec-shac encode: the following arguments are required: OUT.gsc"),
])
def test_command_line_mistakes_are_one_line(argv, message):
    result = subprocess.run([sys.executable, "-m", "gscodec_shac", *argv], capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert result.stderr.startswith("error: ") and message in result.stderr, result.stderr


def test_lst_finetune_threads_default_is_all_cores():
    args = resolve_args(_parse_args(build_parser(), ["lst-finetune", "a.ply", "b.ply", "--orbit", "4"]))
    assert args.threads is None and _options.all_cores() >= 1
    with pytest.raises(Exception, match="--threads must be at least 1"):
        _options.check_threads(0)


# ------------------------------------------------------------------ progress
class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_bars_are_off_under_q_and_without_a_terminal(monkeypatch):
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert resolve_args(argparse.Namespace(quiet=False)).quiet is True
    monkeypatch.setattr(sys, "stderr", _Terminal())
    assert resolve_args(argparse.Namespace(quiet=False)).quiet is False
    assert resolve_args(argparse.Namespace(quiet=True)).quiet is True
    progress_commands = {"encode", "decode", "render", "analyze", "synthetic", "train", "lst-finetune", "rd", "demo"}
    for name in progress_commands:
        assert any(a.dest == "quiet" for a in COMMANDS[name]._actions), name


def test_progress_bars_do_not_change_results(monkeypatch):
    from gscodec_shac.shac.vq import VectorQuantizer

    monkeypatch.setattr(sys, "stderr", _Terminal())
    quiet = make_synthetic_scene(3000, seed=1, n_cameras=2)
    shown = make_synthetic_scene(3000, seed=1, n_cameras=2, progress=True)
    assert (quiet.cloud.sh_rest == shown.cloud.sh_rest).all()
    ac = quiet.cloud.ac_matrix()[:2000]
    plain = VectorQuantizer(n_clusters=64, seed=0).fit(ac)
    barred = VectorQuantizer(n_clusters=64, seed=0)
    barred.progress = True
    barred.fit(ac)
    assert (plain.labels_ == barred.labels_).all() and (plain.codes_ == barred.codes_).all()
    assert "SH k-means" in sys.stderr.getvalue() and "synthetic scene" in sys.stderr.getvalue()


# ------------------------------------------------------------------ rate-points
def test_rate_points_lists_every_shipped_set(capsys):
    assert main(["rate-points"]) == 0
    text = capsys.readouterr().out
    for name in ("paper_table3", "mpeg_ctc_video", "shac_ladder", "shac_auto"):
        assert f"\n{name} " in text
    assert main(["rate-points", "--json"]) == 0
    sets = {entry["set"]: entry for entry in json.loads(capsys.readouterr().out)}
    assert set(sets) == set(builtin_rate_point_files())
    assert sets["paper_table3"]["points"] == ["rp1", "rp2", "rp3", "rp4"]
    assert sets["paper_table3"]["description"].startswith("Paper Table III QPs")


def table(text: str) -> dict[str, dict[str, str]]:
    """The rows of a set's table by point, cut at the header's column offsets."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("point "))
    header = lines[start]
    names = header.split()
    offsets = [header.index(f"{n} " if n != names[-1] else n) for n in names] + [None]
    rows = {}
    for line in lines[start + 1:]:
        if not line.strip():
            break
        cells = [line[a:b].strip() for a, b in zip(offsets, offsets[1:])]
        rows[cells[0]] = dict(zip(names, cells))
    return rows


def test_rate_points_of_a_set_shows_every_qp_and_bit_depth(capsys):
    assert main(["rate-points", "mpeg_ctc_video"]) == 0
    text = capsys.readouterr().out
    rows = table(text)
    assert list(rows) == ["rp01", "rp02", "rp03", "rp04"]
    assert list(rows["rp01"]) == ["point", "positions", "opacity", "rotation", "scale", "sh_dc", "sh_ac", "sh_features"]
    for name, point in load_rate_point_file(builtin_rate_point_files()["mpeg_ctc_video"]).items():
        cells = rows[name]
        for attribute in ("opacity", "rotation", "scale", "sh_dc"):
            spec = point.attributes[attribute]
            assert cells[attribute] == f"{spec.qp}/{spec.bits}"
        assert cells["sh_ac"] == ",".join(map(str, point.attributes["sh_ac"].qp)) + "/10"
        assert cells["positions"] == "hevc split8 lossless/16"
    assert "SH allocation:  degree" in text and "colour:         ycbcr" in text


def test_rate_points_shows_set_coded_positions_and_waterfill(capsys):
    assert main(["rate-points", "shac_auto"]) == 0
    text = capsys.readouterr().out
    assert table(text)["template"]["positions"] == "set lossless/14" and "SH allocation:  waterfill" in text
    assert "SH stage:       pca energy_retention=0.9999" in text
    assert main(["rate-points", "gsplat_png"]) == 0
    text = capsys.readouterr().out
    assert table(text)["default"]["positions"] == "png split8 lossless/16" and "sh_labels:      lossless/16" in text


def test_rate_points_json_of_one_point_is_the_resolved_point(capsys):
    assert main(["rate-points", "shac_ladder:rp4", "--json"]) == 0
    described = json.loads(capsys.readouterr().out)
    point = load_rate_point_file(builtin_rate_point_files()["shac_ladder"])["rp4"]
    assert described["set"] == "shac_ladder" and described["points"] == {"rp4": point.to_json()}


@pytest.mark.parametrize("reference, message", [
    ("nope", "unknown rate-point set 'nope'; shipped: gscodec_studio"),
    ("paper_table3:rp9", "no rate point 'rp9'; it has rp1, rp2, rp3, rp4"),
    ("missing.yaml", "missing.yaml: no such rate-point file"),
])
def test_rate_points_mistakes_are_one_line(reference, message, capsys):
    assert main(["rate-points", reference]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1


@pytest.mark.parametrize("signum, status, line", [(signal.SIGINT, 130, "interrupted"),
                                                  (signal.SIGTERM, 143, "terminated")])
def test_a_signal_swallowed_by_a_c_callback_still_ends_the_command_as_that_signal(signum, status, line, monkeypatch,
                                                                                  capfd):
    """numba compiles through ctypes callbacks: a Ctrl-C there raises inside the callback, ctypes
    prints and drops the exception, and the compiler then fails with an error of its own (seen in
    CI: 'no compiled object yet', exit 70 and a traceback)."""

    def command(args: argparse.Namespace) -> int:
        @ctypes.CFUNCTYPE(None)
        def callback() -> None:
            os.kill(os.getpid(), signum)  # our handler raises here, inside the callback

        callback()
        raise RuntimeError("no compiled object yet")  # what the C library does next

    real = cli_module.resolve_args
    monkeypatch.setattr(cli_module, "resolve_args", lambda args: argparse.Namespace(**{**vars(real(args)),
                                                                                       "func": command}))
    assert main(["info", "any.gsc"]) == status
    err = capfd.readouterr().err
    assert err.strip() == line and "Traceback" not in err
