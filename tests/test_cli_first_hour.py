"""The first hour of a new user (issue 26): ``convert`` between every pair of formats, the
compressed.ply writer, .gsc read by every command, name checks, bits per input Gaussian, notes."""

from __future__ import annotations

import numpy as np
import pytest

from gscodec_shac.cli import main
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.models import detect_format, read_model, write_model

#: extension -> (format name detect_format gives, keeps SH, position tolerance relative to the extent)
FORMATS = {
    ".ply": ("ply", True, 1e-6),
    ".compressed.ply": ("compressed-ply", True, 2e-3),
    ".spz": ("spz", True, 2e-3),
    ".splat": ("splat", False, 1e-6),
    ".sog": ("sog", True, 2e-3),
    ".pt": ("gsplat", True, 1e-6),
}


def _cloud(n: int = 300, seed: int = 5) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    return GaussianCloud(
        means=rng.uniform(-2, 2, (n, 3)), scales=rng.uniform(-5, -2, (n, 3)), quats=rng.normal(size=(n, 4)),
        opacities=rng.uniform(-4, 4, n), sh_dc=rng.uniform(-1, 1, (n, 3)), sh_rest=rng.uniform(-0.5, 0.5, (n, 3, 3)),
    )


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    """The same small model in every writable format, and as a .gsc."""
    folder = tmp_path_factory.mktemp("convert_sources")
    cloud = _cloud()
    paths = {}
    for ext in FORMATS:
        paths[ext] = folder / f"source{ext}"
        write_model(paths[ext], cloud)
    paths[".gsc"] = folder / "source.gsc"
    assert main(["encode", str(paths[".ply"]), str(paths[".gsc"]), "-q"]) == 0
    return cloud, paths


def _nearest(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each point of ``a``: (distance to, index of) its nearest point of ``b``."""
    from scipy.spatial import cKDTree

    return cKDTree(b).query(a)


@pytest.mark.parametrize("source", [*FORMATS, ".gsc"])
@pytest.mark.parametrize("target", list(FORMATS))
def test_convert_every_pair(tmp_path, sources, source, target, capsys):
    cloud, paths = sources
    out = tmp_path / f"out{target}"
    assert main(["convert", str(paths[source]), str(out)]) == 0
    assert detect_format(out) == FORMATS[target][0]
    converted, _ = read_model(out)
    original, _ = read_model(paths[source])
    assert converted.num_gaussians == original.num_gaussians
    keeps_sh = FORMATS[target][1] and (source == ".gsc" or FORMATS[source][1])
    assert converted.sh_degree == (1 if keeps_sh else 0)
    # positions survive within the coarser format's precision (orders may differ: compare point sets)
    tolerance = 4.0 * max(FORMATS[target][2], FORMATS.get(source, ("", True, 1e-2))[2])
    distance, _ = _nearest(original.means, converted.means)
    assert distance.max() <= 2.0 * tolerance + 1e-5, (source, target, distance.max())
    assert "wrote" in capsys.readouterr().out


def test_compressed_ply_round_trip_values(tmp_path):
    """Our writer's file read back: each attribute within its packed precision (Morton order, so
    compare Gaussian by Gaussian after matching positions)."""
    cloud = _cloud(n=1000, seed=9)
    path = tmp_path / "x.compressed.ply"
    write_model(path, cloud)
    text = path.read_bytes()[:4000].decode("latin-1")
    assert "element chunk 4" in text and "packed_position" in text and "element sh 1000" in text
    back, _ = read_model(path)
    distance, match = _nearest(cloud.means, back.means)
    assert len(set(match.tolist())) == 1000  # a one-to-one match
    assert distance.max() < 2e-3 * np.ptp(cloud.means, axis=0).max()
    assert np.abs(back.sh_dc[match] - cloud.sh_dc).max() < 0.02
    assert np.abs(back.sh_rest[match] - cloud.sh_rest).max() < 0.02
    a, b = cloud.normalized_quats(), back.normalized_quats()[match]
    assert np.minimum(np.abs(a - b).max(axis=1), np.abs(a + b).max(axis=1)).max() < 3e-3


def test_encode_refuses_non_gsc_output(tmp_path, capsys):
    source = tmp_path / "in.ply"
    write_model(source, _cloud(n=50))
    assert main(["encode", str(source), str(tmp_path / "out.ply")]) == 2
    assert "encode writes a .gsc" in capsys.readouterr().err
    assert not (tmp_path / "out.ply").exists()


def test_missing_input_reported_before_existing_output(tmp_path, capsys):
    out = tmp_path / "out.gsc"
    out.write_bytes(b"x")
    assert main(["encode", str(tmp_path / "missing.ply"), str(out)]) == 2
    assert "no such file" in capsys.readouterr().err


def test_decode_to_compressed_ply_writes_the_chunked_format(tmp_path, sources):
    _, paths = sources
    out = tmp_path / "d.compressed.ply"
    assert main(["decode", str(paths[".gsc"]), str(out), "-q"]) == 0
    assert detect_format(out) == "compressed-ply"


def test_render_and_info_compare_read_gsc(tmp_path, sources, capsys):
    _, paths = sources
    assert main(["render", str(paths[".gsc"]), str(tmp_path / "views"), "--orbit-views", "2", "--width", "32",
                 "-q"]) == 0
    assert len(list((tmp_path / "views").glob("*.png"))) == 2
    capsys.readouterr()
    assert main(["info", "--compare", str(paths[".ply"]), str(paths[".gsc"]), "--width", "48", "--views", "2",
                 "--json"]) == 0
    import json

    result = json.loads(capsys.readouterr().out)
    assert 15.0 < result["psnr"] < 99.0 and result["views"] == 2


def test_ply_with_infinite_opacity_is_clamped_with_a_note(tmp_path, capsys):
    import plyfile

    finite, source = tmp_path / "finite.ply", tmp_path / "in.ply"
    write_model(finite, _cloud(n=20))
    data = plyfile.PlyData.read(str(finite), mmap=False)
    data["vertex"].data["opacity"][:3] = [np.inf, -np.inf, np.inf]
    data.write(str(source))
    assert main(["convert", str(source), str(tmp_path / "out.spz")]) == 0
    assert "3 infinite opacity logit(s)" in capsys.readouterr().err


def test_spz_version_4_written_and_read(tmp_path, sources):
    _, paths = sources
    out = tmp_path / "v4.spz"
    assert main(["convert", str(paths[".ply"]), str(out), "--spz-version", "4"]) == 0
    assert out.read_bytes()[:4] == b"NGSP"  # version 4: zstd streams behind a plain header, not gzip
    back, _ = read_model(out)
    assert back.num_gaussians == 300 and back.sh_degree == 1


def test_info_bits_per_input_gaussian_and_older_streams_labelled(tmp_path, sources, capsys):
    """info divides by the input count the header records (as encode does); a stream without it
    (older writers) falls back to the decoded count and says so."""
    import json

    from gscodec_shac.codec.container import Bitstream

    _, paths = sources
    assert main(["info", str(paths[".gsc"]), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["bits_per_gaussian_of"] == "input"
    assert summary["bits_per_gaussian"] == pytest.approx(8.0 * paths[".gsc"].stat().st_size / 300)
    stream = Bitstream.read(paths[".gsc"])
    del stream.header["input_gaussians"]
    old = tmp_path / "old.gsc"
    stream.write(old)
    assert main(["info", str(old)]) == 0
    assert "bits per decoded (no input count in this older stream) Gaussian" in capsys.readouterr().out


def test_sh_stage_on_sh0_model_is_a_noted_no_op(tmp_path, capsys):
    source = tmp_path / "in.ply"
    write_model(source, _cloud(n=60).replace(sh_rest=np.zeros((60, 0, 3), np.float32)))
    assert main(["encode", str(source), str(tmp_path / "o.gsc"), "--sh", "pca", "-q"]) == 0
    assert "has nothing to do (a no-op)" in capsys.readouterr().err
    assert main(["info", str(tmp_path / "o.gsc")]) == 0
    assert "stage None" not in capsys.readouterr().out


def test_target_size_above_the_largest_file_says_so(tmp_path, sources, capsys):
    _, paths = sources
    out = tmp_path / "t.gsc"
    assert main(["encode", str(paths[".ply"]), str(out), "--target-size", "1GB", "-q"]) == 0
    err = capsys.readouterr().err
    assert "--target-size 1GB is above the largest file" in err and f"{out.stat().st_size:,} bytes" in err
