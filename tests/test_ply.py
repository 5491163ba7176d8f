"""Inria PLY I/O: bit-exact round trips (synthetic degrees 0-4, real scene) and bad inputs."""

from pathlib import Path

import numpy as np
import plyfile
import pytest

from gscodec_shac import sh_index
from gscodec_shac.errors import PlyFormatError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.ply import read_ply, write_ply
from tests.conftest import shared_scene


def random_cloud(n=50, degree=3, seed=0):
    rng = np.random.default_rng(seed)
    return GaussianCloud(
        means=rng.normal(size=(n, 3)) * 3,
        scales=rng.normal(-4, 1, size=(n, 3)),
        quats=rng.normal(size=(n, 4)),
        opacities=rng.normal(size=n),
        sh_dc=rng.normal(size=(n, 3)),
        sh_rest=rng.normal(0, 0.1, size=(n, (degree + 1) ** 2 - 1, 3)),
    )


@pytest.mark.parametrize("degree", range(5))
def test_round_trip_bit_exact_every_degree(tmp_path, degree):
    cloud = random_cloud(degree=degree, seed=degree)
    path = tmp_path / "scene.ply"
    write_ply(path, cloud)
    back = read_ply(path)
    assert back.sh_degree == degree
    # zero normals are added on write (Inria layout); everything else is bit-exact
    assert set(back.extra) == {"nx", "ny", "nz"}
    back.extra.clear()
    assert back.equals(cloud)
    # and a second write reproduces the file byte for byte
    write_ply(tmp_path / "again.ply", read_ply(path))
    assert (tmp_path / "again.ply").read_bytes() == path.read_bytes()


def test_synthetic_scene_round_trip(tmp_path, small_cloud):
    write_ply(tmp_path / "s.ply", small_cloud)
    back = read_ply(tmp_path / "s.ply")
    back.extra.clear()
    assert back.equals(small_cloud)


@pytest.mark.shared_data
def test_real_scene_round_trip_is_byte_identical(tmp_path):
    source = shared_scene("kacy_sh3_9k", "point_cloud.ply")
    cloud = read_ply(source)
    assert cloud.num_gaussians == 9080 and cloud.sh_degree == 3
    write_ply(tmp_path / "out.ply", cloud)
    assert (tmp_path / "out.ply").read_bytes() == source.read_bytes()


def test_f_rest_is_read_channel_major(tmp_path):
    """Writes a PLY by hand with plyfile: f_rest_j = j; checks where each value lands."""
    n = 3
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{j}" for j in range(45)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    table = np.zeros(n, dtype=[(name, "<f4") for name in names])
    for j in range(45):
        table[f"f_rest_{j}"] = j
    plyfile.PlyData([plyfile.PlyElement.describe(table, "vertex")]).write(str(tmp_path / "h.ply"))
    cloud = read_ply(tmp_path / "h.ply")
    # Inria: f_rest_{c*15 + (k-1)} is channel c of coefficient k
    for k in range(1, 16):
        for c in range(3):
            assert cloud.sh_rest[0, k - 1, c] == c * 15 + (k - 1)
    # paper order: the G value of (l=1, m=0) (k=2) sits in AC column 4
    assert cloud.ac_matrix()[0, sh_index.ac_column(1, 0, 1)] == 15 + 1


def test_extra_properties_are_kept(tmp_path):
    cloud = random_cloud(n=10)
    cloud.extra["label"] = np.arange(10, dtype=np.int32)
    write_ply(tmp_path / "e.ply", cloud)
    back = read_ply(tmp_path / "e.ply")
    np.testing.assert_array_equal(back.extra["label"], np.arange(10))
    assert back.extra["label"].dtype == np.int32


def test_ascii_ply_is_read(tmp_path):
    cloud = random_cloud(n=5, degree=1)
    binary = tmp_path / "b.ply"
    write_ply(binary, cloud)
    data = plyfile.PlyData.read(str(binary))
    data.text = True
    data.write(str(tmp_path / "a.ply"))
    back = read_ply(tmp_path / "a.ply")
    np.testing.assert_allclose(back.means, cloud.means, rtol=1e-6)
    assert back.sh_degree == 1


# --------------------------------------------------------------------------- bad input
def write_table(path: Path, names, n=2):
    table = np.zeros(n, dtype=[(name, "<f4") for name in names])
    plyfile.PlyData([plyfile.PlyElement.describe(table, "vertex")]).write(str(path))


BASE = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"scale_{i}" for i in range(3)] + [
    f"rot_{i}" for i in range(4)
]


def test_not_a_ply(tmp_path):
    (tmp_path / "x.ply").write_bytes(b"hello world")
    with pytest.raises(PlyFormatError, match="not a PLY file"):
        read_ply(tmp_path / "x.ply")


def test_missing_file(tmp_path):
    with pytest.raises(PlyFormatError, match="no such file"):
        read_ply(tmp_path / "nope.ply")


def test_missing_properties(tmp_path):
    write_table(tmp_path / "m.ply", [n for n in BASE if n not in ("opacity", "rot_3")])
    with pytest.raises(PlyFormatError, match="missing properties: opacity, rot_3"):
        read_ply(tmp_path / "m.ply")


def test_f_rest_count_fits_no_degree(tmp_path):
    write_table(tmp_path / "f.ply", BASE + [f"f_rest_{j}" for j in range(30)])
    with pytest.raises(PlyFormatError, match="30 f_rest properties fit no SH degree"):
        read_ply(tmp_path / "f.ply")


def test_zero_vertices(tmp_path):
    write_table(tmp_path / "z.ply", BASE, n=0)
    with pytest.raises(PlyFormatError, match="zero vertices"):
        read_ply(tmp_path / "z.ply")


def test_truncated_binary(tmp_path):
    cloud = random_cloud(n=100)
    write_ply(tmp_path / "t.ply", cloud)
    data = (tmp_path / "t.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(data[: len(data) - 1000])
    with pytest.raises(PlyFormatError, match="malformed or truncated"):
        read_ply(tmp_path / "t.ply")


def test_nan_in_file_is_reported(tmp_path):
    cloud = random_cloud(n=10)
    table = plyfile.PlyData.read(str(_written(tmp_path, cloud)))["vertex"].data.copy()
    table["opacity"][3] = np.nan
    plyfile.PlyData([plyfile.PlyElement.describe(table, "vertex")]).write(str(tmp_path / "n.ply"))
    with pytest.raises(PlyFormatError, match=r"1 non-finite value\(s\).*opacity: 1 \(vertex 3\)"):
        read_ply(tmp_path / "n.ply")


def test_failed_write_leaves_nothing(tmp_path):
    cloud = random_cloud(n=4)
    cloud.extra["bad"] = np.array(["a", "b", "c", "d"])
    with pytest.raises(PlyFormatError, match="dtype"):
        write_ply(tmp_path / "bad.ply", cloud)
    assert list(tmp_path.iterdir()) == []


def _written(tmp_path, cloud):
    path = tmp_path / "w.ply"
    write_ply(path, cloud)
    return path
