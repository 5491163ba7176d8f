"""The memory-bounded paths (issue 25) give exactly what the whole-array paths give.

Each blocked or streamed path is run with tiny blocks (1 row, a few rows, a block size
that does not divide N) and compared bit for bit with the whole array computed at once.
"""

from pathlib import Path

import numpy as np
import plyfile
import pytest

from gscodec_shac.codec import Decoder, Encoder
from gscodec_shac.codec import decoder as decoder_module
from gscodec_shac.codec import quantize as qz
from gscodec_shac.codec.attributes import ATTRIBUTES
from gscodec_shac.codec.layout import placement_view, planes
from gscodec_shac.codec.rate_points import builtin_rate_point_files, load_rate_point_file, parse_rate_points
from gscodec_shac.errors import ValidationError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.ply import read_ply, write_ply
from gscodec_shac.row_blocks import GatheredRows
from gscodec_shac.shac.base import check_ac_matrix
from gscodec_shac.shac.identity import IdentityStage
from gscodec_shac.shac.lst import ShacLST
from gscodec_shac.shac.pca import ShacPCA
from gscodec_shac.shac.truncation import TruncationStage

BLOCKS = (1, 3, 7, 1000)
STREAMS = Path(__file__).parent / "fixtures" / "streams"
ROW_BLOCK_STAGES = (ShacPCA, ShacLST, IdentityStage, TruncationStage)


def _cloud(n: int = 53, degree: int = 3, seed: int = 0) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    rest = (degree + 1) ** 2 - 1
    return GaussianCloud(
        means=rng.normal(0, 30, (n, 3)), scales=rng.normal(-4, 1, (n, 3)), quats=rng.normal(0, 1, (n, 4)),
        opacities=rng.normal(0, 2, n), sh_dc=rng.normal(0, 1, (n, 3)),
        sh_rest=rng.normal(0, 0.2, (n, rest, 3)) * np.linspace(1, 3, rest * 3).reshape(rest, 3),
        extra={**{k: rng.normal(size=n).astype(np.float32) for k in ("nx", "ny", "nz")}, "label": rng.integers(-5, 5, n).astype(np.int16),
               "weight": rng.normal(size=n)},
    )


# ----------------------------------------------------------------------- PLY
@pytest.mark.parametrize("split", [False, True])
@pytest.mark.parametrize("degree", [0, 3])
def test_a_binary_ply_read_in_row_blocks_is_the_cloud_written(tmp_path, monkeypatch, degree, split):
    """Also read in two threads (each half of the rows), as files of SPLIT_READ_ROWS vertices or more are."""
    from gscodec_shac.io import ply

    monkeypatch.setattr(ply, "SPLIT_READ_ROWS", 2 if split else 1 << 62)
    cloud = _cloud(degree=degree)
    path = tmp_path / "c.ply"
    write_ply(path, cloud)
    for block in BLOCKS:
        read = read_ply(path, block_rows=block)
        assert read.equals(cloud), block
        assert read.extra["label"].dtype == np.int16 and read.extra["weight"].dtype == np.float64


def test_a_ply_read_in_two_threads_reports_a_truncated_second_half(tmp_path, monkeypatch):
    from gscodec_shac.errors import PlyFormatError
    from gscodec_shac.io import ply

    monkeypatch.setattr(ply, "SPLIT_READ_ROWS", 2)
    path = tmp_path / "c.ply"
    write_ply(path, _cloud())
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(PlyFormatError, match="truncated"):
        read_ply(path)


def test_row_blocks_of_a_big_endian_double_ply_after_another_element(tmp_path):
    """Doubles rounded to float32 as numpy does, the vertex rows found after a fixed-size element."""
    cloud = _cloud(n=20, degree=1)
    path = tmp_path / "c.ply"
    write_ply(path, cloud)
    table = plyfile.PlyData.read(str(path))["vertex"].data
    doubles = table.astype([(name, ">f8" if table.dtype[name] == np.float32 else table.dtype[name].newbyteorder(">"))
                            for name in table.dtype.names])
    doubles["x"] += 1e-9  # not a float32: the read rounds it
    before = np.array([(1.0, 2), (3.0, 4)], dtype=[("a", ">f4"), ("b", ">i4")])
    big = tmp_path / "big.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(before, "camera"), plyfile.PlyElement.describe(doubles, "vertex")],
                    byte_order=">").write(str(big))
    ascii_path = tmp_path / "ascii.ply"  # the whole-file plyfile path
    plyfile.PlyData([plyfile.PlyElement.describe(doubles, "vertex")], text=True).write(str(ascii_path))
    with pytest.warns(UserWarning, match="camera"):
        reads = [read_ply(big, block_rows=block) for block in BLOCKS]
    whole = read_ply(ascii_path)
    assert np.array_equal(whole.means[:, 0], doubles["x"].astype(np.float32))
    for read in reads:
        assert read.equals(whole)


# ----------------------------------------------------------------- quantiser
ROW_TRANSFORMS = {"log": qz.log_transform, "quaternions": qz.canonical_quaternions, "ycbcr": qz.triplets_to_ycbcr}


@pytest.mark.parametrize("name", list(ROW_TRANSFORMS))
def test_quantising_a_row_transform_block_by_block_is_quantising_the_whole_transform(name):
    rng = np.random.default_rng(1)
    columns = 4 if name == "quaternions" else 6
    values = (rng.normal(0, 5, (41, columns))).astype(np.float32)
    rows = ROW_TRANSFORMS[name]
    whole = rows(values)
    expected = qz.Quantizer.fit(whole, 11)
    codes = expected.quantize(whole)
    for block in BLOCKS:
        lo, hi = qz.column_extrema(values, rows, block)
        assert lo.tobytes() == whole.min(axis=0).tobytes() and hi.tobytes() == whole.max(axis=0).tobytes()
        quantizer = qz.Quantizer.fit(values, 11, rows, block)
        assert quantizer.to_json() == expected.to_json()
        assert np.array_equal(quantizer.quantize(values, rows, block), codes)
        assert np.array_equal(expected.quantize(whole, block_rows=block), codes)


def test_each_attribute_is_its_row_transform_of_its_column():
    cloud = _cloud()
    for ycbcr in (False, True):
        for attribute in ATTRIBUTES.values():
            rows = attribute.rows(ycbcr)
            values = attribute.column(cloud)
            got = attribute.forward(cloud, ycbcr)
            assert np.array_equal(got, values if rows is None else rows(values))
    assert ATTRIBUTES["sh_dc"].rows(False) is None and ATTRIBUTES["scale"].rows(True) is None


def test_planes_gathered_per_channel_are_the_gathered_rows_transposed():
    rng = np.random.default_rng(2)
    q = rng.integers(0, 1024, (30, 5)).astype(np.uint16)
    cell_rows = np.minimum(np.arange(36), 29)  # 6 empty cells repeat the last row
    got = planes(q[:, 1:4], cell_rows, (6, 6))
    assert got.flags.c_contiguous and got.dtype == np.uint16
    assert np.array_equal(got, q[:, 1:4][cell_rows].T.reshape(3, 6, 6))


# ------------------------------------------------------------ gathered rows
def test_shac_pca_on_gathered_rows_is_shac_pca_on_the_gathered_copy():
    cloud = _cloud(n=61)
    index = np.random.default_rng(3).permutation(61)[:57]
    copy = cloud.ac_matrix()[index]
    for chunk in (1, 4, 57, 1000):
        gathered = GatheredRows(cloud.ac_matrix(), index)
        lazy = ShacPCA(energy_retention=0.9, chunk_size=chunk).fit(gathered)
        whole = ShacPCA(energy_retention=0.9, chunk_size=chunk).fit(copy)
        for name in ("components_", "mean_", "scale_", "singular_values_"):
            assert getattr(lazy, name).tobytes() == getattr(whole, name).tobytes(), (chunk, name)
        assert lazy.transform(gathered).tobytes() == whole.transform(copy).tobytes()


def test_gathered_rows_slice_and_convert_like_the_copy():
    base = np.arange(40, dtype=np.float32).reshape(10, 4)
    gathered = GatheredRows(base, [9, 2, 2, 5])
    assert gathered.shape == (4, 4) and len(gathered) == 4 and gathered.dtype == np.float32
    assert np.array_equal(gathered[1:3], base[[2, 2]])
    assert np.array_equal(np.asarray(gathered), base[[9, 2, 2, 5]])
    assert check_ac_matrix(gathered) is gathered
    base[0, 0] = np.nan
    with pytest.raises(ValidationError, match="non-finite"):
        check_ac_matrix(GatheredRows(base, [1]))
    with pytest.raises(TypeError):
        gathered[0]


# ------------------------------------------------------------------- encoder
def test_an_encode_that_releases_the_model_writes_the_same_bytes(small_cloud):
    point = parse_rate_points({"points": {"p": {"codec": "png", "bits": 10, "prune": {"min_opacity": 0.3},
                                                 "sort": {"method": "morton"}}}}, "test")["p"]
    kept = small_cloud.copy()
    expected = Encoder(point, sh_stage="pca", sh_params={"energy_retention": 0.95}).encode(kept)
    assert kept.equals(small_cloud)  # not released: the caller's cloud is untouched
    given = small_cloud.copy()
    encoder = Encoder(point, sh_stage="pca", sh_params={"energy_retention": 0.95})
    stream = encoder.encode(given, release_input=True)
    assert stream.to_bytes() == expected.to_bytes()
    assert stream.header["prune"]["pruned"] > 0 and stream.header["input_gaussians"] == small_cloud.num_gaussians
    assert given.num_gaussians == 0 and given.sh_degree == small_cloud.sh_degree


def test_take_moves_the_arrays_and_leaves_an_empty_cloud():
    cloud = _cloud(n=7)
    copy = cloud.copy()
    means = cloud.means
    taken = cloud.take()
    assert taken.equals(copy) and taken.means is means
    assert cloud.num_gaussians == 0 and cloud.sh_degree == 3 and set(cloud.extra) == set(copy.extra)


def test_the_placement_view_shares_all_rows_and_copies_a_subset():
    cloud = _cloud(n=9)
    whole = placement_view(cloud, np.arange(9))
    assert whole.means is cloud.means and whole.sh_degree == 0 and not whole.extra
    part = placement_view(cloud, np.array([1, 4]))
    assert np.array_equal(part.quats, cloud.quats[[1, 4]]) and part.num_gaussians == 2


# ------------------------------------------------------------------- decoder
@pytest.fixture(scope="module")
def row_block_streams() -> list[bytes]:
    """Streams of the stages that invert row blocks: 3,000 Gaussians (blocks of thousands of rows) with
    SHAC-PCA, SHAC-LST, no stage (the AC coefficients in YCbCr) and truncated to degree 2; the DC in
    the PCA and DC-only Gaussians (fixtures)."""
    point = load_rate_point_file(builtin_rate_point_files()["shac_ladder"])["rp6"]
    cloud = _cloud(n=3000, seed=4)
    streams = [Encoder(point, sh_stage=stage, sh_params=params).encode(cloud).to_bytes()
               for stage, params in (("pca", {"energy_retention": 0.97}), ("lst", {}), ("none", {}),
                                     ("trunc", {"degree": 2}))]
    return streams + [(STREAMS / f"{name}.gsc").read_bytes() for name in ("v1.0/table3_rp3_pca_dc",
                                                                          "v2.3/ladder_rp4_pca_dc_only")]


@pytest.mark.parametrize("block", [1000, 1024, 2999, 1 << 16])
def test_sh_features_inverted_in_row_blocks_decode_to_the_whole_inverse(monkeypatch, row_block_streams, block):
    """The SH features dequantised and inverted block by block (as they are decoded) are the
    whole-matrix inverse bit for bit, whether the blocks divide N or not (a last block of 1 row)."""
    calls = []
    inverse = decoder_module._FeatureCodes.inverse
    monkeypatch.setattr(decoder_module._FeatureCodes, "inverse", lambda self, *a: calls.append(1) or inverse(self, *a))
    monkeypatch.setattr(decoder_module._FeatureCodes, "block_rows", block)
    for data in row_block_streams:
        for stage in ROW_BLOCK_STAGES:
            monkeypatch.setattr(stage, "inverts_row_blocks", False)
        whole = Decoder(workers=2).decode(data)
        for stage in ROW_BLOCK_STAGES:
            monkeypatch.setattr(stage, "inverts_row_blocks", True)
        assert Decoder(workers=2).decode(data).equals(whole)
    assert len(calls) == len(row_block_streams)


@pytest.mark.parametrize("name", ["v1.0/custom_lossless_drop", "v2.3/custom_lossless_drop_dc_only"])
def test_tail_padded_planes_read_as_a_slice_decode_as_gathered(monkeypatch, name):
    """On a tail-padded grid the occupied cells are read as a view of each plane; the same values as
    gathering them by index (a full grid, and a DC-only stream's partly filled SH grid)."""
    data = (STREAMS / f"{name}.gsc").read_bytes()
    sliced = Decoder().decode(data)
    monkeypatch.setattr(decoder_module, "_cell_selector", lambda padding, n, cells: cells)
    assert Decoder().decode(data).equals(sliced)
