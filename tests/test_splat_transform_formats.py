"""Our model readers and writers against PlayCanvas splat-transform (npm), and the real scenes.

splat-transform reads our .spz, .splat and .sog and converts them to PLY: its values must
equal what our readers read from the same files (within the decode rounding where the two
readers differ). Our readers read its .spz, .compressed.ply and .sog: the values must equal
its own decoding of them. Skips with the reason where node or the package is missing.
The real-scene tests (``shared_data``) also run the CLI with node removed from PATH.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.models import read_model, write_model
from gscodec_shac.errors import PlyFormatError
from gscodec_shac.io.ply import read_ply, write_ply
from gscodec_shac.rd.external import read_decoded_ply
from tests.conftest import REPO_ROOT, shared_scene
from tests.test_splat_transform import splat_transform  # noqa: F401  (the fixture: installs or skips)

ATTRIBUTES = ("means", "scales", "sh_dc", "sh_rest")


def _run(tool: Path, *args: str | Path) -> None:
    result = subprocess.run([str(tool), "-w", "-q", *map(str, args)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]


def _cloud(n: int = 800, seed: int = 3) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    return GaussianCloud(
        means=rng.uniform(-2, 2, (n, 3)), scales=rng.uniform(-6, -1, (n, 3)), quats=rng.normal(size=(n, 4)),
        opacities=rng.uniform(-5, 7, n), sh_dc=rng.uniform(-1.5, 1.5, (n, 3)), sh_rest=rng.uniform(-0.9, 0.9, (n, 15, 3)),
    )


def _differences(ours: GaussianCloud, theirs: GaussianCloud) -> dict[str, float]:
    """Largest differences per attribute (rotations up to sign, opacity as alpha)."""
    assert ours.num_gaussians == theirs.num_gaussians and ours.sh_degree == theirs.sh_degree
    out = {name: float(np.abs(getattr(ours, name).astype(np.float64) - getattr(theirs, name)).max(initial=0.0))
           for name in ATTRIBUTES}
    a, b = ours.normalized_quats(), theirs.normalized_quats()
    out["quats"] = float(np.minimum(np.abs(a - b).max(axis=1), np.abs(a + b).max(axis=1)).max())
    alpha = lambda c: 1.0 / (1.0 + np.exp(-c.opacities.astype(np.float64)))  # noqa: E731
    out["alpha"] = float(np.abs(alpha(ours) - alpha(theirs)).max())
    return out


def _their_reading(tool: Path, source: Path, tmp_path: Path) -> GaussianCloud:
    target = tmp_path / f"{source.name}.st.ply"
    _run(tool, source, target)
    try:
        return read_ply(target)
    except PlyFormatError:  # infinite opacity logits (alpha 0 or 1): clamped as our readers do
        return read_decoded_ply(target)[0]


# ------------------------------------------------------------ our files, their reader
@pytest.mark.parametrize("name, options, tolerance", [
    ("v2.spz", {"version": 2}, {"quats": 1e-5}),
    ("v3.spz", {"version": 3}, {"quats": 1e-5}),
    ("v4.spz", {"version": 4}, {"quats": 1e-5}),
    ("scene.sog", {"iterations": 3}, {}),
    # .splat rotations: antimatter15 decodes (b - 128) / 128, splat-transform b / 255 * 2 - 1
    ("scene.splat", {}, {"quats": 1.0 / 128}),
    ("scene.compressed.ply", {}, {}),  # our writer: splat-transform decodes its chunk layout as we do
])
def test_splat_transform_reads_our_files(tmp_path, splat_transform, name, options, tolerance):  # noqa: F811
    path = tmp_path / name
    write_model(path, _cloud(), **options)
    ours, _ = read_model(path)
    theirs = _their_reading(splat_transform, path, tmp_path)
    for attribute, difference in _differences(ours, theirs).items():
        limit = tolerance.get(attribute, 1e-6)  # alpha: splat-transform clamps alpha to [1e-6, 1 - 1e-6]
        assert difference <= limit, (name, attribute, difference)


# ------------------------------------------------------------ their files, our reader
@pytest.mark.parametrize("name, arguments", [
    ("st.spz", ["--spz-version", "3"]),
    ("st.compressed.ply", []),
    ("st.sog", ["-g", "cpu", "-i", "3", "--max-workers", "1"]),
])
def test_we_read_splat_transform_files(tmp_path, splat_transform, name, arguments):  # noqa: F811
    source = tmp_path / "in.ply"
    write_ply(source, _cloud())
    coded = tmp_path / name
    _run(splat_transform, *arguments, source, coded)
    ours, _ = read_model(coded)
    theirs = _their_reading(splat_transform, coded, tmp_path)
    for attribute, difference in _differences(ours, theirs).items():
        assert difference <= 1e-6, (name, attribute, difference)


# ------------------------------------------------------------------- real scenes
@pytest.mark.shared_data
@pytest.mark.parametrize("scene, quats_tolerance", [
    (("playbot_sog_sh2", "meta.json"), 1e-6),
    (("plant_sh0", "plant.splat"), 1.0 / 128),  # the two .splat rotation decodings (see above)
])
def test_real_scenes_match_splat_transform(tmp_path, splat_transform, scene, quats_tolerance):  # noqa: F811
    path = shared_scene(*scene)
    ours, _ = read_model(path)
    theirs = _their_reading(splat_transform, path, tmp_path)
    differences = _differences(ours, theirs)
    assert differences.pop("quats") <= quats_tolerance
    assert all(d <= 1e-6 for d in differences.values()), differences


def _path_without_node() -> str:
    kept = [d for d in os.environ.get("PATH", "").split(os.pathsep) if d and not (Path(d) / "node").exists()]
    return os.pathsep.join(kept)


@pytest.mark.shared_data
@pytest.mark.slow
def test_encode_info_decode_real_scenes_without_node(tmp_path):
    plant, playbot = shared_scene("plant_sh0", "plant.splat"), shared_scene("playbot_sog_sh2")
    env = {**os.environ, "PATH": _path_without_node(), "PYTHONPATH": str(REPO_ROOT)}
    assert shutil.which("node", path=env["PATH"]) is None

    def cli(*args: str | Path) -> str:
        result = subprocess.run([sys.executable, "-m", "gscodec_shac", *map(str, args)], capture_output=True,
                                text=True, env=env, timeout=600)
        assert result.returncode == 0, result.stderr[-2000:]
        return result.stdout + result.stderr

    assert "113,648" in cli("info", plant) and "infinite opacity logit(s) clamped" in cli("info", plant)
    assert "500,000" in cli("info", playbot) and "SH degree         2" in cli("info", playbot)
    for source, n in ((plant, 113_648), (playbot, 500_000)):
        gsc = tmp_path / f"{source.stem or source.name}.gsc"
        cli("encode", source, gsc, "-q", "-r", "paper_table3:rp2", "--sort", "morton", "--preset", "ultrafast")
        for suffix in (".spz", ".splat", ".ply"):
            out = gsc.with_suffix(suffix)
            cli("decode", gsc, out, "-q")
            assert read_model(out)[0].num_gaussians == n
