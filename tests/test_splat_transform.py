"""A real outside client reads our decoded PLY: PlayCanvas splat-transform (npm).

The tool is looked for as the project finds it (:func:`gscodec_shac.rd.external.find_splat_transform`:
``$GSCODEC_SHAC_SPLAT_TRANSFORM``, then ``splat-transform`` on ``PATH``, then ``~/.cache/gscodec-shac/npm``,
override with ``GSCODEC_SHAC_NPM_PREFIX``); only when none is found and ``npm`` is available does the
test try ``npm install --prefix <cache> @playcanvas/splat-transform`` once, and it skips with the
reason when node, npm or the network is missing.
"""

import csv
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from gscodec_shac import sh_index
from gscodec_shac.io.ply import read_ply
from gscodec_shac.codec import Encoder, decode_file

PACKAGE = "@playcanvas/splat-transform"
PREFIX = Path(os.environ.get("GSCODEC_SHAC_NPM_PREFIX", Path.home() / ".cache" / "gscodec-shac" / "npm"))


@pytest.fixture(scope="module")
def splat_transform() -> Path:
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    from gscodec_shac.rd.external import find_splat_transform

    found = find_splat_transform()
    if found is not None:
        return found
    tool = PREFIX / "node_modules" / ".bin" / "splat-transform"
    if not tool.exists():
        npm = shutil.which("npm")
        if npm is None:
            pytest.skip(f"{PACKAGE} is not installed in {PREFIX} and npm is not available")
        try:
            subprocess.run([npm, "install", "--prefix", str(PREFIX), PACKAGE], capture_output=True, timeout=240, check=True)
        except (subprocess.SubprocessError, OSError) as exc:
            pytest.skip(f"could not install {PACKAGE} into {PREFIX} (offline?): {type(exc).__name__}")
    if not tool.exists():
        pytest.skip(f"{PACKAGE} did not install a splat-transform binary in {PREFIX}")
    return tool


def _run(tool: Path, *args: str) -> str:
    result = subprocess.run([str(tool), "-w", *args], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


def test_splat_transform_reads_decoded_ply_exactly(tmp_path, small_cloud, splat_transform):
    stream = Encoder("paper_table3:rp2", sh_stage="pca", sort="morton").encode(small_cloud)
    stream.write(tmp_path / "x.gsc")
    decode_file(tmp_path / "x.gsc", tmp_path / "x.ply")
    ours = read_ply(tmp_path / "x.ply")

    _run(splat_transform, str(tmp_path / "x.ply"), str(tmp_path / "x.csv"))
    with open(tmp_path / "x.csv", newline="") as handle:
        rows = list(csv.reader(handle))
    header, values = rows[0], np.array(rows[1:], dtype=np.float64)
    assert values.shape[0] == ours.num_gaussians
    column = {name: values[:, i].astype(np.float32) for i, name in enumerate(header)}
    f_rest = sh_index.inria_rest_from_sh_rest(ours.sh_rest)
    expected = {"x": ours.means[:, 0], "z": ours.means[:, 2], "opacity": ours.opacities, "scale_1": ours.scales[:, 1],
                "rot_0": ours.quats[:, 0], "f_dc_2": ours.sh_dc[:, 2], "f_rest_0": f_rest[:, 0], "f_rest_44": f_rest[:, 44]}
    for name, want in expected.items():
        assert np.array_equal(column[name], want), name

    # its own compressed format (lossy, its own quantiser), read back by the same tool: count kept
    _run(splat_transform, str(tmp_path / "x.ply"), str(tmp_path / "x.compressed.ply"))
    _run(splat_transform, str(tmp_path / "x.compressed.ply"), str(tmp_path / "y.csv"))
    with open(tmp_path / "y.csv", newline="") as handle:
        assert sum(1 for _ in handle) == ours.num_gaussians + 1
