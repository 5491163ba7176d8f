"""Safe outputs and a quiet CLI: the umask, --force, inputs never overwritten, directories,
no temporary file after SIGINT/SIGTERM/SIGKILL, BrokenPipe, exit codes, --debug, warnings,
and byte-identical results across threads and workers."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import plyfile
import pytest

from gscodec_shac import atomic
from tests.fuzzlib import gsc as fuzz
from gscodec_shac.cli import main
from gscodec_shac.codec import Decoder, Encoder
from gscodec_shac.errors import OutputError
from gscodec_shac.io.ply import write_ply
from gscodec_shac.synthetic import make_synthetic_scene

REPO = Path(__file__).resolve().parents[1]


def cli(*args: str, umask: int | None = None, env: dict | None = None, **options) -> subprocess.CompletedProcess:
    """``gscodec-shac ARGS`` in a fresh process (this checkout's package)."""
    full_env = {**os.environ, "PYTHONPATH": str(REPO), **(env or {})}
    streams = {"stdout": options.pop("stdout", subprocess.PIPE), "stderr": subprocess.PIPE}
    return subprocess.run([sys.executable, "-m", "gscodec_shac", *args], text=True, cwd=REPO, env=full_env,
                          preexec_fn=(lambda: os.umask(umask)) if umask is not None else None, **streams, **options)


def hidden(folder: Path) -> list[str]:
    """Temporary files left behind (atomic writes name theirs ``.NAME.*.tmp``)."""
    return sorted(p.name for p in folder.rglob("*") if p.name.startswith(".") or p.name.endswith(".tmp"))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 400-Gaussian PLY and its .gsc (PNG codec: quick)."""
    folder = tmp_path_factory.mktemp("scene")
    cloud = make_synthetic_scene(400, seed=1, n_cameras=2, width=32, height=24).cloud
    write_ply(folder / "in.ply", cloud)
    (folder / "in.gsc").write_bytes(Encoder("gsplat_png").encode(cloud).to_bytes())
    return folder


def copy_inputs(scene: Path, tmp_path: Path) -> tuple[Path, Path]:
    ply, gsc = tmp_path / "in.ply", tmp_path / "in.gsc"
    ply.write_bytes((scene / "in.ply").read_bytes())
    gsc.write_bytes((scene / "in.gsc").read_bytes())
    return ply, gsc


# ------------------------------------------------------------------ the umask
@pytest.mark.parametrize("mask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_outputs_honour_the_umask(scene, tmp_path, mask, mode):
    ply, gsc = copy_inputs(scene, tmp_path)
    assert cli("decode", str(gsc), str(tmp_path / "out.ply"), umask=mask).returncode == 0
    assert cli("synthetic", str(tmp_path / "syn.ply"), "-n", "200", "--views", "2", umask=mask).returncode == 0
    for name in ("out.ply", "syn.ply", "cameras.json"):
        assert (tmp_path / name).stat().st_mode & 0o777 == mode, name


@pytest.mark.parametrize("unnamed", [True, False], ids=["O_TMPFILE", "named-temporary"])
def test_atomic_writes_honour_the_umask_on_both_paths(tmp_path, monkeypatch, unnamed):
    if not unnamed:  # the portable fallback, used where O_TMPFILE is missing
        monkeypatch.setattr(atomic, "_unnamed_file", lambda directory: None)
    old = os.umask(0o022)
    try:
        target = atomic.write_atomic(tmp_path / "a.bin", b"first")
        assert target.stat().st_mode & 0o777 == 0o644
        atomic.write_atomic(target, b"second")
        assert target.read_bytes() == b"second" and target.stat().st_mode & 0o777 == 0o644
    finally:
        os.umask(old)
    assert hidden(tmp_path) == []


# ------------------------------------------------------------------ --force, inputs, directories
FORCE_CASES = {
    "encode": (["encode", "{ply}", "{out}", "-r", "gsplat_png"], "out.gsc"),
    "decode": (["decode", "{gsc}", "{out}"], "out.ply"),
    "synthetic": (["synthetic", "{out}", "-n", "200", "--views", "2"], "out.ply"),
    "render": (["render", "{ply}", "--out", "{dir}", "--orbit-views", "1", "--width", "16", "--quiet"], "r/orbit_000.png"),
    "analyze": (["analyze", "{ply}", "--out", "{dir}"], "r/table.json"),
}


@pytest.mark.parametrize("command", list(FORCE_CASES))
def test_an_existing_output_is_refused_without_force(scene, tmp_path, command):
    ply, gsc = copy_inputs(scene, tmp_path)
    args, output = FORCE_CASES[command]
    target = tmp_path / output
    target.parent.mkdir(exist_ok=True)
    target.write_bytes(b"precious")
    names = {"ply": ply, "gsc": gsc, "out": target, "dir": tmp_path / "r"}
    argv = [a.format(**names) for a in args]
    result = cli(*argv)
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "exists; pass --force to replace it" in result.stderr and target.read_bytes() == b"precious"
    result = cli(*argv, "--force")
    assert result.returncode == 0, result.stderr
    assert target.read_bytes() != b"precious" and hidden(tmp_path) == []


@pytest.mark.parametrize(
    "args, existing",
    [
        (["train", "{missing}", "{dir}", "--iterations", "1"], "r/point_cloud.ply"),
        (["lst-finetune", "{ply}", "{dir}/out.ply", "--orbit", "2", "--steps", "1"], "r/out.ply"),
        (["rd-report", "{dir}"], "r/report/report.md"),
        (["rd", "{missing}", "--out", "{dir}"], "r/notes.txt"),
        (["demo", "--out", "{dir}"], "r/notes.txt"),
    ],
    ids=["train", "lst-finetune", "rd-report", "rd", "demo"],
)
def test_slow_commands_refuse_existing_outputs_before_the_work(scene, tmp_path, args, existing):
    ply, _ = copy_inputs(scene, tmp_path)
    target = tmp_path / existing
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_bytes(b"precious")
    tic = time.perf_counter()
    result = cli(*[a.format(ply=ply, dir=tmp_path / "r", missing=tmp_path / "none") for a in args])
    assert result.returncode == 2 and "--force" in result.stderr and target.read_bytes() == b"precious", result.stderr
    assert time.perf_counter() - tic < 30


def test_an_input_is_never_overwritten_even_with_force(scene, tmp_path):
    ply, gsc = copy_inputs(scene, tmp_path)
    before = {p: p.read_bytes() for p in (ply, gsc)}
    (tmp_path / "link.ply").symlink_to(ply)
    os.link(gsc, tmp_path / "hard.gsc")
    cases = [
        ["encode", str(ply), str(ply), "-r", "gsplat_png", "--force"],
        ["encode", str(ply), str(tmp_path / "link.ply"), "-r", "gsplat_png", "--force"],
        ["decode", str(gsc), str(gsc), "--force"],
        ["decode", str(tmp_path / "hard.gsc"), str(gsc), "--force"],
        ["lst-finetune", str(ply), str(ply), "--orbit", "2", "--steps", "1", "--force"],
    ]
    for argv in cases:
        result = cli(*argv)
        assert result.returncode == 2 and "refusing to write over an input (even with --force)" in result.stderr, argv
    assert {p: p.read_bytes() for p in (ply, gsc)} == before and hidden(tmp_path) == []


def test_render_never_overwrites_its_ground_truth_images(scene, tmp_path):
    from gscodec_shac.camera import orbit_cameras
    from gscodec_shac.io.inria_cameras import write_inria_cameras
    from gscodec_shac.render.output import save_png

    ply, _ = copy_inputs(scene, tmp_path)
    cameras = orbit_cameras([0, 0, 0], 4.0, 1, 16, 12, fov_y_deg=45.0)
    images = tmp_path / "images"
    images.mkdir()
    save_png(images / f"{cameras[0].name}.png", np.full((12, 16, 3), 0.5))
    write_inria_cameras(tmp_path / "cameras.json", cameras)
    before = (images / f"{cameras[0].name}.png").read_bytes()
    result = cli("render", str(ply), "--cameras", str(tmp_path / "cameras.json"), "--images-dir", str(images),
                 "--out", str(images), "--force", "--quiet")
    assert result.returncode == 2 and "is the input" in result.stderr
    assert (images / f"{cameras[0].name}.png").read_bytes() == before


def test_an_output_path_that_is_a_directory_is_one_clear_error(scene, tmp_path):
    ply, gsc = copy_inputs(scene, tmp_path)
    folder = tmp_path / "folder"
    folder.mkdir()
    for argv in (["encode", str(ply), str(folder), "-r", "gsplat_png"], ["decode", str(gsc), str(folder), "--force"]):
        result = cli(*argv)
        assert result.returncode == 2 and result.stderr == f"error: {folder}: the output path is a directory; " \
            "give a file name\n", result.stderr
    with pytest.raises(OutputError, match="is a directory"):
        atomic.write_atomic(folder, b"x", error=OutputError)


def test_an_input_that_is_a_directory_is_named_as_such(tmp_path):
    folder = tmp_path / "folder"
    folder.mkdir()
    for argv, status in ((["encode", str(folder), str(tmp_path / "x.gsc")], 2),
                         (["decode", str(folder), str(tmp_path / "x.ply")], 2), (["info", str(folder)], 2)):
        result = cli(*argv)
        assert result.returncode == status and "is a directory" in result.stderr and "no such file" not in result.stderr


# ------------------------------------------------------------------ interruptions
def _slow_encode_args(tmp_path: Path) -> list[str]:
    ply = tmp_path / "big.ply"
    if not ply.exists():
        write_ply(ply, make_synthetic_scene(80_000, seed=2, n_cameras=1).cloud)  # encodes for several seconds
    return ["encode", str(ply), str(tmp_path / "out.gsc"), "-r", "paper_table3:rp2", "--quiet", "--force"]


@pytest.mark.parametrize("signum, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143), (signal.SIGKILL, -9)],
                         ids=["SIGINT", "SIGTERM", "SIGKILL"])
def test_an_interrupted_encode_leaves_the_old_file_and_no_temporary(tmp_path, signum, status):
    args = _slow_encode_args(tmp_path)
    out = tmp_path / "out.gsc"
    out.write_bytes(b"old")
    for delay in (1.5, 4.0):
        process = subprocess.Popen([sys.executable, "-m", "gscodec_shac", *args], cwd=REPO, stderr=subprocess.PIPE,
                                   stdout=subprocess.DEVNULL, env={**os.environ, "PYTHONPATH": str(REPO)}, text=True)
        time.sleep(delay)
        process.send_signal(signum)
        _, stderr = process.communicate(timeout=120)
        if process.returncode == 0:  # finished before the signal: the new file is whole
            assert Decoder().decode(out.read_bytes()).num_gaussians > 0
            out.write_bytes(b"old")
            continue
        # -signum: the signal came before Python had installed our handlers (a loaded machine
        # can take longer than the delay to start); the file guarantees hold all the same.
        assert process.returncode in (status, -signum) and "Traceback" not in stderr, stderr
        assert hidden(tmp_path) == []
        data = out.read_bytes()
        if data != b"old":  # the signal came after the new file replaced the old one (one rename): it is whole
            assert Decoder().decode(data).num_gaussians > 0
            out.write_bytes(b"old")
        if signum != signal.SIGKILL and process.returncode == status:
            assert stderr.strip() == ("interrupted" if signum == signal.SIGINT else "terminated")


_ENTRY = """
import atexit, sys
from gscodec_shac import cli
atexit.register(print, "shut down")
def finished():
    cli._SIGNALS_RECEIVED.extend(int(s) for s in sys.argv[1:])
    print("work done", end="; ")
    return 143 if sys.argv[1:] else 0
cli.main = finished
cli.run()
"""


@pytest.mark.parametrize("signals, status, stdout", [([], 0, "work done; shut down\n"),
                                                     ([signal.SIGTERM], 143, "work done; ")],
                         ids=["no signal", "SIGTERM"])
def test_after_a_signal_the_cli_exits_without_the_interpreter_shutdown(signals, status, stdout):
    """``cli.run``: after SIGINT or SIGTERM (main's cleanup done) the process ends at once, its output
    flushed, without the interpreter's shutdown, where an interrupted encode's native threads crashed."""
    result = subprocess.run([sys.executable, "-c", _ENTRY, *map(str, map(int, signals))], capture_output=True,
                            text=True, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=120)
    assert (result.returncode, result.stdout) == (status, stdout), result.stderr


_WRITER = """
import sys, time
from gscodec_shac.atomic import atomic_output
with atomic_output(sys.argv[1]) as handle:
    handle.write(b"half of the new content")
    handle.flush()
    print("writing", flush=True)
    time.sleep(60)
"""


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL], ids=["SIGINT", "SIGTERM", "SIGKILL"])
def test_a_write_killed_half_way_leaves_no_temporary_file(tmp_path, signum):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    # SIGINT as a shell gives it (this process may ignore it by then, which a child would inherit)
    process = subprocess.Popen([sys.executable, "-c", _WRITER, str(target)], stdout=subprocess.PIPE, text=True,
                               cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, stderr=subprocess.DEVNULL,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert process.stdout.readline().strip() == "writing"
    process.send_signal(signum)
    process.wait(timeout=120)  # generous: a loaded 2-core machine starts Python slowly
    assert target.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["out.bin"]


# ------------------------------------------------------------------ the CLI's exits
def test_a_closed_output_pipe_is_a_quiet_exit(scene, tmp_path):
    _, gsc = copy_inputs(scene, tmp_path)
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader went away before we write: the first write fails with EPIPE
    try:
        result = cli("info", str(gsc), "--json", stdout=write_end)
    finally:
        os.close(write_end)
    assert result.returncode == 141 and result.stderr == ""
    shell = subprocess.run(["bash", "-c", f"{sys.executable} -m gscodec_shac info {gsc} --json | head -c 1; "
                            "echo \" ${PIPESTATUS[0]}\""], capture_output=True, text=True, cwd=REPO,
                           env={**os.environ, "PYTHONPATH": str(REPO)})
    assert shell.stderr == "" and shell.stdout.split()[-1] in ("0", "141")


def test_exit_codes_and_debug(scene, tmp_path):
    _, gsc = copy_inputs(scene, tmp_path)
    damaged = tmp_path / "bad.gsc"
    data = bytearray(gsc.read_bytes())
    data[40] ^= 0xFF
    damaged.write_bytes(bytes(data))
    result = cli("decode", str(damaged), str(tmp_path / "x.ply"))
    assert result.returncode == 3 and result.stderr.startswith("error: ") and result.stderr.count("\n") == 1
    result = cli("--debug", "decode", str(damaged), str(tmp_path / "x.ply"))
    assert result.returncode == 1 and "Traceback" in result.stderr and "BitstreamError" in result.stderr
    result = cli("decode", str(damaged), str(tmp_path / "x.ply"), env={"GSCODEC_DEBUG": "1"})
    assert "Traceback" in result.stderr
    result = cli("decode", str(gsc), str(tmp_path / "x.ply"), env={"GSCODEC_MAX_MEMORY": "64K"})
    assert result.returncode == 5 and "more than the 64.0 KiB" in result.stderr
    help_text = cli("--help").stdout
    for code in ("  2  ", "  3  ", "  4  ", "  5  ", " 70  ", "130  ", "141  ", "143  "):
        assert code in help_text, code


def test_a_missing_codec_exits_with_4(scene, tmp_path):
    from gscodec_shac.codec.grid.base import available_codecs

    if "hm" in available_codecs():
        pytest.skip("the HM reference codec is installed here")
    point = tmp_path / "hm.yaml"
    point.write_text("points:\n  a: {codec: hm, bits: 10}\n")
    ply, _ = copy_inputs(scene, tmp_path)
    result = cli("encode", str(ply), str(tmp_path / "x.gsc"), "-r", f"{point}:a")
    assert result.returncode == 4 and result.stderr.startswith("error: ") and result.stderr.count("\n") == 1


def test_an_internal_error_is_one_line_without_debug(monkeypatch, capsys):
    from gscodec_shac.commands import info

    def broken(args):
        raise RuntimeError("a bug")

    monkeypatch.setattr(info, "run", broken)
    assert main(["info", "x"]) == 70
    assert capsys.readouterr().err == ("error: internal error (RuntimeError: a bug); this is a bug, rerun with "
                                       "--debug and report the traceback\n")
    with pytest.raises(RuntimeError):
        main(["info", "x", "--debug"])


def test_warnings_become_one_line(scene, tmp_path):
    table = plyfile.PlyData.read(str(scene / "in.ply"))["vertex"].data
    extra = np.zeros(2, dtype=[("a", "<f4")])
    path = tmp_path / "extra.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(table, "vertex"), plyfile.PlyElement.describe(extra, "camera")]).write(
        str(path))
    result = cli("info", str(path))
    assert result.returncode == 0
    assert result.stderr == f"warning: {path}: PLY elements ['camera'] are not Gaussians and are ignored\n"


# ------------------------------------------------------------------ determinism
@pytest.mark.parametrize("stage", list(fuzz.SEED_STAGES))
def test_encoding_is_byte_identical_across_workers(stage):
    cloud = make_synthetic_scene(600, seed=4, n_cameras=1, width=32, height=24).cloud
    point = fuzz.SEED_STAGES[stage]
    params = {"trunc": {"degree": 1}, "vq": {"n_clusters": 64}, "vq-pca": {"n_clusters": 64}}.get(stage)
    digests = {hashlib.sha256(Encoder(point, sh_stage=stage, sh_params=params, workers=w,
                                      codec_options={"preset": "ultrafast"} if "hevc" in _codecs(point) else None)
                              .encode(cloud).to_bytes()).hexdigest() for w in (1, 2, 4)}
    assert len(digests) == 1


def _codecs(point: str) -> set[str]:
    from gscodec_shac.codec.rate_points import load_rate_point

    return {spec.codec for spec in load_rate_point(point).attributes.values()}


def test_decoding_is_identical_across_workers(scene):
    data = (scene / "in.gsc").read_bytes()
    one, three = Decoder(workers=1).decode(data), Decoder(workers=3).decode(data)
    assert one.equals(three)


def _cli_digests(ply: Path, folder: Path, envs: list[dict]) -> set[str]:
    digests = set()
    for index, env in enumerate(envs):
        out = folder / f"t{index}.gsc"
        result = cli("encode", str(ply), str(out), "-r", "paper_table3:rp2", "--sh", "pca", "--preset", "ultrafast",
                     "--force", env=env)
        assert result.returncode == 0, result.stderr
        digests.add(hashlib.sha256(out.read_bytes()).hexdigest())
    return digests


def test_the_cli_encode_is_byte_identical_across_thread_counts(scene, tmp_path):
    ply, _ = copy_inputs(scene, tmp_path)
    envs = [{"NUMBA_NUM_THREADS": t, "OMP_NUM_THREADS": t, "OPENBLAS_NUM_THREADS": "1"} for t in ("1", "2")]
    assert len(_cli_digests(ply, tmp_path, envs)) == 1


def test_the_cli_encode_is_byte_identical_across_blas_kernels_and_threads(scene, tmp_path):
    """SHAC-PCA's projection is accumulated in float64, so neither the BLAS thread count nor
    the CPU kernel OpenBLAS picks (forced here with OPENBLAS_CORETYPE) changes a byte."""
    ply, _ = copy_inputs(scene, tmp_path)
    envs = [{"OPENBLAS_NUM_THREADS": "1"}, {"OPENBLAS_NUM_THREADS": "2"},
            {"OPENBLAS_NUM_THREADS": "1", "OPENBLAS_CORETYPE": "Prescott"}]
    assert len(_cli_digests(ply, tmp_path, envs)) == 1


def test_rd_rows_are_identical_across_threads(tmp_path):
    from gscodec_shac.rd import parse_sweep, run_sweep

    spec = parse_sweep({
        "name": "threads", "rate_points": ["paper_table3:rp1"], "settings": {"preset": "ultrafast", "sort": "morton"},
        "scenes": [{"name": "syn", "synthetic": {"n": 1000, "seed": 0, "n_cameras": 8, "width": 48, "height": 32}}],
        "methods": ["baseline"],
    }, source="threads")
    rows = [run_sweep(spec, tmp_path / f"t{threads}", executor="serial", threads=threads, progress=False).rows[0]
            for threads in (1, 2)]
    for key in ("bytes", "psnr_gt", "psnr_ref", "ssim_gt", "sizes"):
        assert rows[0][key] == rows[1][key], key
