"""Encoder/Decoder: exactness, QP-bounded error, determinism, side information, files and CLI."""

import subprocess
import sys
import zlib

import numpy as np
import plyfile
import pytest

from gscodec_shac.codec import quantize as qz
from gscodec_shac.codec.container import Bitstream
from gscodec_shac.cli import main
from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.io.ply import read_ply, write_ply
from gscodec_shac.codec import Decoder, Encoder, decode_file, encode_file
from gscodec_shac.codec.attributes import ATTRIBUTES
from gscodec_shac.codec.rate_points import parse_rate_points
from gscodec_shac.shac.base import StageState, make_stage
from gscodec_shac.synthetic import make_synthetic_scene


def _point(**settings):
    return parse_rate_points({"points": {"p": settings}}, "test")["p"]


def _roundtrip(point, cloud, **encoder_args):
    encoder = Encoder(point, **encoder_args)
    stream = encoder.encode(cloud)
    decoded = Decoder().decode(stream.to_bytes())
    return encoder, stream, decoded


def _quantizer(stream, name):
    return qz.Quantizer.from_json(stream.header["attributes"][name]["quantizer"])


# ----------------------------------------------------------------- exactness
@pytest.mark.parametrize(
    "codec, layout, color, sort",
    [("png", "single", "ycbcr", "none"), ("raw", "split8", "rgb", "morton"), ("png", "split8", "rgb", "random")],
)
def test_lossless_settings_reproduce_the_quantised_input_bit_exactly(small_cloud, codec, layout, color, sort):
    point = _point(codec=codec, bits=12, color=color, sort={"method": sort},
                   attributes={"positions": {"bits": 16, "layout": layout}})
    encoder, stream, decoded = _roundtrip(point, small_cloud)
    source = small_cloud.select(encoder.order_)
    ycbcr = color == "ycbcr"
    for name in ("positions", "rotation", "scale", "opacity", "sh_dc"):
        values = ATTRIBUTES[name].forward(source, ycbcr)
        quantizer = qz.Quantizer.fit(values, 16 if name == "positions" else 12)
        assert quantizer.to_json() == stream.header["attributes"][name]["quantizer"]
        expected = ATTRIBUTES[name].inverse(quantizer.dequantize(quantizer.quantize(values)), ycbcr)
        got = {"positions": decoded.means, "rotation": decoded.quats, "scale": decoded.scales,
               "opacity": decoded.opacities[:, None], "sh_dc": decoded.sh_dc}[name]
        assert got.tobytes() == expected.astype(np.float32).tobytes(), name
    ac = qz.triplets_to_ycbcr(source.ac_matrix()) if ycbcr else source.ac_matrix()
    quantizer = qz.Quantizer.fit(ac, 12)
    features = quantizer.dequantize(quantizer.quantize(ac))
    expected = qz.triplets_from_ycbcr(features) if ycbcr else features
    assert decoded.ac_matrix().tobytes() == expected.astype(np.float32).tobytes()
    assert stream.header["grid"]["padding"] == ("tail" if sort == "none" else "mask")


def test_decoded_order_matches_input_rows(small_cloud):
    encoder, _, decoded = _roundtrip(_point(codec="raw", bits=16, sort={"method": "morton"}), small_cloud)
    assert sorted(encoder.order_) == list(range(small_cloud.num_gaussians))
    assert np.allclose(decoded.scales, small_cloud.scales[encoder.order_], atol=1e-3)


# -------------------------------------------------------------------- lossy
def _qstep(qp: int, bits: int) -> float:
    """HEVC quantiser step in units of a ``bits``-bit sample (2^((QP-4)/6) at 8 bit)."""
    return 2.0 ** ((qp - 4) / 6 + bits - 8)


@pytest.mark.parametrize("ref", ["paper_table3:rp1", "mpeg_ctc_video:rp01", "gscodec_studio:rp2"])
def test_lossy_error_stays_within_what_the_qp_allows(small_cloud, ref):
    encoder, stream, decoded = _roundtrip(ref, small_cloud, sh_stage="none", sort="morton")
    source = small_cloud.select(encoder.order_)
    ycbcr = stream.header["color"] == "ycbcr"
    pairs = {
        "rotation": (qz.canonical_quaternions(source.quats), decoded.quats),
        "scale": (source.scales, decoded.scales),
        "opacity": (source.opacities[:, None], decoded.opacities[:, None]),
        "sh_dc": (ATTRIBUTES["sh_dc"].forward(source, ycbcr), ATTRIBUTES["sh_dc"].forward(decoded, ycbcr)),
        "sh": tuple(qz.triplets_to_ycbcr(c.ac_matrix()) if ycbcr else c.ac_matrix() for c in (source, decoded)),
    }
    checked = 0
    for name, (original, got) in pairs.items():
        quantizer = _quantizer(stream, name)
        codes = quantizer.quantize(original).astype(np.float64)
        decoded_codes = (got - quantizer.lo) / np.where(quantizer.step > 0, quantizer.step, 1.0)
        for chunk_name in stream.header["attributes"][name]["chunks"]:
            meta = stream.chunk(chunk_name).meta
            start, stop = meta["channels"]
            error = decoded_codes[:, start:stop] - codes[:, start:stop]
            rms = float(np.sqrt(np.mean(error**2)))
            assert rms <= 0.6 * _qstep(meta["qp"], meta["bits"]) + 1.0, (name, chunk_name, meta["qp"], rms)
            checked += 1
    assert checked >= 6
    assert np.array_equal(decoded.means, qz.inverse_log_transform(
        _quantizer(stream, "positions").dequantize(_quantizer(stream, "positions").quantize(qz.log_transform(source.means)))
    ).astype(np.float32))


def test_qp_ladder_follows_sh_degrees(small_cloud):
    _, stream, _ = _roundtrip("mpeg_ctc_video:rp01", small_cloud, sh_stage="none", sort="none")
    sh = stream.header["attributes"]["sh"]
    spans = [(stream.chunk(c).meta["channels"], stream.chunk(c).meta["qp"]) for c in sh["chunks"]]
    assert spans == [([0, 9], 32), ([9, 24], 37), ([24, 45], 42)]
    _, stream, _ = _roundtrip("mpeg_ctc_video:rp01", small_cloud, sh_stage="pca", sh_params={"n_components": 12}, sort="none")
    spans = [(stream.chunk(c).meta["channels"], stream.chunk(c).meta["qp"]) for c in stream.header["attributes"]["sh"]["chunks"]]
    assert spans == [([0, 9], 32), ([9, 12], 37)]


def test_feature_degrees_per_stage(small_cloud):
    ac = small_cloud.ac_matrix()
    assert make_stage("none").fit(ac).feature_degrees(45) == [1] * 9 + [2] * 15 + [3] * 21
    assert make_stage("trunc", degree=2).fit(ac).feature_degrees(24) == [1] * 9 + [2] * 15
    assert make_stage("pca", n_components=21).fit(ac).feature_degrees(21) == [1] * 9 + [2] * 12
    assert make_stage("lst").fit(ac).feature_degrees(21) == [1] * 9 + [2] * 6 + [3] * 6


# ------------------------------------------------------ determinism, side info
def test_encoding_is_deterministic(small_cloud):
    first = Encoder("paper_table3:rp2", sh_stage="pca").encode(small_cloud).to_bytes()
    second = Encoder("paper_table3:rp2", sh_stage="pca").encode(small_cloud.copy()).to_bytes()
    assert first == second
    vq = _point(codec="png", bits=8, sh={"stage": "vq", "n_clusters": 300}, sort={"method": "morton"})
    assert Encoder(vq).encode(small_cloud).to_bytes() == Encoder(vq).encode(small_cloud).to_bytes()


def test_stage_side_information_is_counted_in_the_size(small_cloud):
    point = _point(codec="png", bits=10, sort={"method": "none"})
    with_pca = Encoder(point, sh_stage="pca", sh_params={"n_components": 8}).encode(small_cloud)
    data = with_pca.to_bytes()
    sizes = with_pca.sizes()
    assert sum(sizes.values()) == len(data)
    chunk = with_pca.chunk("sh_state")
    state = StageState.from_bytes(zlib.decompress(chunk.data))
    assert state.name == "pca" and state.arrays["components"].shape == (45, 8)
    assert sizes["sh_state"] == len(chunk.data) >= 0.5 * state.nbytes()
    assert with_pca.header["sh"] == {"stage": "pca", "features": 8, "lossless": False, "uses_dc": False, "ycbcr": False}


def test_vq_labels_are_coded_losslessly(small_cloud):
    for clusters in (200, 1000):  # 8-bit labels in one plane, 10-bit labels in two 8-bit planes
        point = _point(codec="png", bits=8, sh={"stage": "vq", "n_clusters": clusters}, sort={"method": "morton"})
        _, stream, decoded = _roundtrip(point, small_cloud)
        codebook = make_stage("vq").from_state(StageState.from_bytes(zlib.decompress(stream.chunk("sh_state").data))).codebook_
        rows = {row.tobytes() for row in codebook}
        assert all(row.tobytes() in rows for row in decoded.ac_matrix())
        assert len({r.tobytes() for r in decoded.ac_matrix()}) > clusters // 2
        names = set(stream.header["attributes"]["sh"]["chunks"])
        assert names == ({"sh"} if clusters <= 256 else {"sh_hi", "sh_lo"})


def test_side_stages_round_trip(small_cloud):
    point = _point(codec="raw", bits=12, sort={"method": "none"})
    _, _, truncated = _roundtrip(point, small_cloud, sh_stage="trunc", sh_params={"degree": 1})
    assert truncated.sh_degree == 3 and np.all(truncated.sh_rest[:, 3:] == 0) and np.any(truncated.sh_rest[:, :3] != 0)
    from gscodec_shac.shac.lst import ShacLST

    _, stream, lst = _roundtrip(point, small_cloud, sh_stage=ShacLST.zeros(3), fit_stage=False)
    assert stream.header["sh"]["features"] == 21
    assert np.all(lst.sh_rest[:, 3:8][:, [1, 2]] == 0)  # (2,-1), (2,0)... predicted from a zero T
    _, stream, with_dc = _roundtrip(point, small_cloud, sh_stage="pca", sh_params={"include_dc": True, "n_components": 30})
    assert "sh_dc" not in stream.header["attributes"] and stream.header["sh"]["uses_dc"]
    stage = make_stage("pca", include_dc=True, n_components=30)
    joint = np.concatenate([small_cloud.sh_dc, small_cloud.ac_matrix()], axis=1)
    expected = stage.inverse_transform(stage.fit_transform(joint))  # DC comes back through the PCA
    assert np.abs(with_dc.sh_dc - expected[:, :3]).max() < 0.02


@pytest.mark.parametrize("degree", [0, 1])
def test_low_sh_degrees(degree):
    cloud = make_synthetic_scene(700, sh_degree=degree, seed=1).cloud
    _, stream, decoded = _roundtrip(_point(codec="png", bits=10, sort={"method": "morton"}), cloud, sh_stage="pca" if degree else None)
    assert decoded.sh_degree == degree and decoded.num_gaussians == 700
    assert ("sh" in stream.header["attributes"]) == (degree > 0)


def test_pruning_and_drop_policy(small_cloud):
    point = _point(codec="png", bits=10, prune={"min_opacity": 0.5}, sort={"method": "none"})
    encoder, stream, decoded = _roundtrip(point, small_cloud)
    kept = int((small_cloud.activated_opacities() >= 0.5).sum())
    assert decoded.num_gaussians == kept < small_cloud.num_gaussians
    assert stream.header["prune"] == {"min_opacity": 0.5, "pruned": small_cloud.num_gaussians - kept}
    assert np.all(small_cloud.activated_opacities()[encoder.order_] >= 0.5)
    point = _point(codec="png", bits=10, sort={"method": "morton", "policy": "drop"})
    _, stream, decoded = _roundtrip(point, small_cloud)
    grid = stream.header["grid"]
    assert decoded.num_gaussians == grid["height"] * grid["width"] < small_cloud.num_gaussians
    assert grid["dropped"] == small_cloud.num_gaussians - decoded.num_gaussians and grid["padding"] == "tail"


def test_stage_mistakes_are_clear_errors(small_cloud):
    with pytest.raises(GscodecError, match="^unknown SH stage 'wavelet'"):
        Encoder("paper_table3:rp1", sh_stage="wavelet")
    with pytest.raises(ValidationError, match="n_components"):
        Encoder(_point(codec="png"), sh_stage="pca", sh_params={"n_components": 99}).encode(small_cloud)
    with pytest.raises(ValidationError, match="removes every Gaussian"):
        Encoder(_point(codec="png", prune={"min_opacity": 0.9999})).encode(small_cloud)


# ------------------------------------------------------------------ files, CLI
def test_files_round_trip_and_decoded_ply_rereads(tmp_path, small_cloud):
    ply = tmp_path / "in.ply"
    write_ply(ply, small_cloud)
    summary = encode_file(ply, tmp_path / "out.gsc", "paper_table3:rp2", sh="pca", sort="morton", energy_retention=0.95)
    assert summary["bytes"] == (tmp_path / "out.gsc").stat().st_size
    assert summary["bits_per_gaussian"] == pytest.approx(8 * summary["bytes"] / 2000)
    assert summary["sizes"]["sh_state"] > 0
    result = decode_file(tmp_path / "out.gsc", tmp_path / "dec.ply")
    assert result["num_gaussians"] == 2000 and result["sh_degree"] == 3
    table = plyfile.PlyData.read(str(tmp_path / "dec.ply"))["vertex"].data
    assert len(table) == 2000 and "f_rest_44" in table.dtype.names
    cloud = read_ply(tmp_path / "dec.ply")
    assert cloud.num_gaussians == 2000 and cloud.sh_degree == 3


def test_cli_encode_decode_info(tmp_path, small_cloud, capsys):
    ply = tmp_path / "in.ply"
    write_ply(ply, small_cloud)
    gsc, out = tmp_path / "x.gsc", tmp_path / "x.ply"
    assert main(["encode", str(ply), str(gsc), "--rate-point", "paper_table3:rp2", "--sh", "pca", "--er", "0.99",
                 "--sort", "morton", "--preset", "ultrafast", "--seed", "1"]) == 0
    line = capsys.readouterr().out.strip()
    assert "\n" not in line and "bits per input Gaussian" in line and "pca" in line and "2,000 in" in line
    assert Bitstream.read(gsc).header["rate_point"]["attributes"]["scale"]["options"]["preset"] == "ultrafast"
    assert main(["decode", str(gsc), str(out)]) == 0
    assert "2,000 Gaussians" in capsys.readouterr().out
    assert main(["info", str(gsc)]) == 0
    text = capsys.readouterr().out
    assert "bits per input Gaussian" in text and "sh_state" in text and "paper_table3:rp2" in text
    assert main(["encode", str(ply), str(gsc), "-r", "gsplat_png", "--sort", "none", "--clusters", "128", "--json",
                 "--force"]) == 0
    assert '"sh_stage": "vq"' in capsys.readouterr().out
    # the default: SHAC-PCA on shac_ladder:rp5, said so in the summary line
    assert main(["encode", str(ply), str(gsc), "--force"]) == 0
    line = capsys.readouterr().out
    assert "default: shac_ladder:rp5 + SHAC-PCA" in line and "bits per input Gaussian" in line
    assert Bitstream.read(gsc).header["rate_point"]["name"] == "shac_ladder:rp5"


@pytest.mark.parametrize(
    "args, message, status",
    [
        (["encode", "{ply}", "{gsc}", "-r", "paper_table3:rp7"], "no rate point 'rp7'", 2),
        (["encode", "{ply}", "{gsc}", "--sh", "none", "--er", "0.9"], "--er applies to --sh pca", 2),
        (["encode", "{ply}", "{gsc}", "-r", "paper_table3:rp2", "--sh", "pca", "--components", "99", "--sort", "none"],
         "n_components=99", 2),
        (["encode", "{missing}", "{gsc}"], "no such file", 2),
        (["decode", "{ply}", "{gsc}"], "not a .gsc file", 3),
        (["encode", "{ply}", "{nodir}"], "does not exist", 2),
    ],
)
def test_cli_errors_are_one_line_and_leave_no_file(tmp_path, small_cloud, capsys, args, message, status):
    ply = tmp_path / "in.ply"
    write_ply(ply, small_cloud)
    names = {"ply": ply, "gsc": tmp_path / "out.gsc", "missing": tmp_path / "missing.ply", "nodir": tmp_path / "no" / "x.gsc"}
    assert main([a.format(**names) for a in args]) == status
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.ply"]


def test_cli_error_in_a_fresh_process_has_no_traceback(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "gscodec_shac", "decode", str(tmp_path / "none.gsc"), str(tmp_path / "x.ply")],
        capture_output=True, text=True,
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip() == f"error: {tmp_path / 'none.gsc'}: no such file"
    assert not (tmp_path / "x.ply").exists()


def test_precomputed_grid_order_gives_the_same_bytes(small_cloud):
    point = _point(codec="png", bits=10, prune={"min_opacity": 0.3}, sort={"method": "morton"})
    encoder = Encoder(point, sh_stage="pca")
    grid = encoder.grid_order(small_cloud)
    assert grid.shape[0] * grid.shape[1] == grid.order.size
    assert encoder.encode(small_cloud, grid=grid).to_bytes() == Encoder(point, sh_stage="pca").encode(small_cloud).to_bytes()
    with pytest.raises(ValidationError, match="does not fit"):
        encoder.encode(small_cloud, grid=grid._replace(order=np.arange(grid.order.size)))
