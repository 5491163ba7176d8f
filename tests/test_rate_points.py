"""Rate points: the shipped YAML files, their numbers, references and validation errors."""

import pytest
import yaml

from gscodec_shac.errors import RatePointError
from gscodec_shac.codec import Decoder, Encoder
from gscodec_shac.codec.rate_points import (
    builtin_rate_point_files,
    list_rate_points,
    load_rate_point,
    load_rate_point_file,
)

EXPECTED = {
    "mpeg_ctc_video": ["rp01", "rp02", "rp03", "rp04"],
    "paper_table3": ["rp1", "rp2", "rp3", "rp4"],
    "gscodec_studio": ["rp0", "rp1", "rp2", "rp3"],
    "gsplat_png": ["default"],
    "shac_recommended": ["rp1", "rp2", "rp3", "rp4"],
    "shac_auto": ["template"],
    "shac_ladder": [f"rp{i}" for i in range(1, 10)],
}
# opacity, rotation, scale, SH DC, SH AC (one QP or one per degree)
MPEG = {"rp01": (22, 17, 12, 7, (32, 37, 42)), "rp02": (17, 7, 12, 7, (22, 27, 32)),
        "rp03": (17, 2, 7, 7, (12, 22, 27)), "rp04": (7, 2, 7, 7, (7, 12, 17))}
TABLE3 = {"rp1": (22, 17, 12, 7, 22), "rp2": (17, 7, 12, 7, 17), "rp3": (17, 2, 7, 7, 12), "rp4": (7, 2, 7, 7, 7)}


def _qps(point):
    return tuple(point.attributes[a].qp for a in ("opacity", "rotation", "scale", "sh_dc", "sh_ac"))


def test_shipped_files_and_points():
    assert sorted(builtin_rate_point_files()) == sorted(EXPECTED)
    assert set(list_rate_points()) == {f"{stem}:{p}" for stem, points in EXPECTED.items() for p in points}


def test_recommended_points_keep_the_paper_qps_and_change_only_layouts():
    for name, qps in TABLE3.items():
        point = load_rate_point(f"shac_recommended:{name}")
        assert _qps(point) == qps
        assert point.attributes["positions"].codec == "jpegls" and point.attributes["positions"].lossless
        assert point.attributes["sh_ac"].options["layout"] == "frames"


def test_mpeg_and_paper_numbers():
    for name, qps in MPEG.items():
        point = load_rate_point(f"mpeg_ctc_video:{name}")
        assert _qps(point) == qps
        assert point.attributes["positions"].bits == 16 and point.attributes["positions"].lossless
        assert point.attributes["positions"].layout == "split8"
        assert all(point.attributes[a].bits == 10 for a in ("opacity", "rotation", "scale", "sh_dc", "sh_ac"))
        assert point.color == "ycbcr"
    for name, qps in TABLE3.items():
        point = load_rate_point(f"paper_table3:{name}")
        assert _qps(point) == qps
        assert point.attributes["sh_features"].qp == qps[-1]  # the SH AC QP codes any stage output
        assert point.attributes["positions"].bits == 16 and point.attributes["positions"].lossless


def test_studio_and_gsplat_numbers():
    for name, qp in zip(EXPECTED["gscodec_studio"], (4, 10, 16, 22)):
        point = load_rate_point(f"gscodec_studio:{name}")
        assert _qps(point) == (qp,) * 5
        assert point.attributes["sh_dc"].bits == 8
        assert point.attributes["positions"].codec == "png" and point.attributes["positions"].bits == 16
    gsplat = load_rate_point("gsplat_png")
    assert gsplat.name == "gsplat_png:default"
    assert all(spec.codec == "png" and spec.lossless for spec in gsplat.attributes.values())
    assert gsplat.attributes["scale"].bits == 8 and gsplat.attributes["positions"].bits == 16
    assert gsplat.sh_stage == "vq" and gsplat.sh_params == {"n_clusters": 65536, "centroid_bits": 6}


def test_ladder_lookup():
    spec = load_rate_point("mpeg_ctc_video:rp01").attributes["sh_ac"]
    assert [spec.qp_for_degree(d) for d in (1, 2, 3, 4)] == [32, 37, 42, 42]
    assert load_rate_point("paper_table3:rp1").attributes["sh_ac"].qp_for_degree(3) == 22


@pytest.mark.parametrize("ref", [f"{s}:{p}" for s, points in EXPECTED.items() for p in points])
def test_every_rate_point_round_trips_a_small_scene(small_cloud, ref):
    fast_sort = None if load_rate_point(ref).positions_as_set else "none"  # set-coded: the order is the positions'
    encoder = Encoder(ref, sort=fast_sort)
    stream = encoder.encode(small_cloud)
    decoded = Decoder().decode(stream.to_bytes())
    assert decoded.num_gaussians == small_cloud.num_gaussians
    assert decoded.sh_degree == small_cloud.sh_degree
    assert stream.header["rate_point"]["name"] == ref


def test_references_to_user_files(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text(yaml.safe_dump({"points": {"fast": {"codec": "raw", "bits": 8}}}))
    assert load_rate_point(str(path)).name == "mine:fast"
    assert load_rate_point(f"{path}:fast").attributes["scale"].codec == "raw"
    two = tmp_path / "two.yaml"
    two.write_text(yaml.safe_dump({"points": {"a": {"codec": "raw"}, "b": {"codec": "png"}}}))
    with pytest.raises(RatePointError, match="holds 2 rate points"):
        load_rate_point(str(two))
    with pytest.raises(RatePointError, match="no rate point 'c'"):
        load_rate_point(f"{two}:c")


@pytest.mark.parametrize(
    "ref, message",
    [
        ("paper_table3:rp9", "no rate point 'rp9'"),
        ("nonexistent:rp1", "unknown rate-point file 'nonexistent'"),
        ("rp1", "unknown rate point 'rp1'"),
        ("missing.yaml", "not found"),
    ],
)
def test_unknown_references(ref, message):
    with pytest.raises(RatePointError, match=message):
        load_rate_point(ref)


@pytest.mark.parametrize(
    "document, key, problem",
    [
        ({"points": {"a": {"qp": {"opacity": 60}}}}, "qp.opacity", "0-51"),
        ({"points": {"a": {"qp": {"opacity": "high"}}}}, "qp.opacity", "QP must be"),
        ({"points": {"a": {"qp": {"sh_ac": [10, 99]}}}}, "qp.sh_ac[1]", "0-51"),
        ({"points": {"a": {"qp": {"colour": 10}}}}, "qp.colour", "unknown attribute"),
        ({"points": {"a": {"qp": {"rotation": [10, 12, 14]}}}}, "qp.rotation", "one QP or two"),
        ({"points": {"a": {"qp": {"positions": 10}}}}, "qp.positions", "losslessly"),
        ({"points": {"a": {"codec": "webp2"}}}, "attributes.positions.codec", "unknown codec 'webp2'"),
        ({"points": {"a": {"codec": "png", "qp": {"scale": 10}}}}, "attributes.scale.codec", "lossless only"),
        ({"points": {"a": {"bits": 20}}}, "bits", "1..16"),
        ({"points": {"a": {"bits": "ten"}}}, "bits", "integer"),
        ({"points": {"a": {"colour": "rgb"}}}, "colour", "unknown key"),
        ({"points": {"a": {"color": "hsv"}}}, "color", "must be one of"),
        ({"points": {"a": {"sh": {"stage": "wavelet"}}}}, "sh.stage", "unknown SH stage 'wavelet'"),
        ({"points": {"a": {"sort": {"method": "hilbert"}}}}, "sort.method", "must be one of"),
        ({"points": {"a": {"sort": {"weights": {"xyz": -1}}}}}, "sort.weights.xyz", ">= 0"),
        ({"points": {"a": {"prune": {"min_opacity": 1.5}}}}, "prune.min_opacity", "[0, 1)"),
        ({"points": {"a": {"attributes": {"scale": {"layout": "zigzag"}}}}}, "attributes.scale.layout", "must be one of"),
        ({"points": {"a": {"attributes": {"scale": {"quality": 3}}}}}, "attributes.scale.quality", "unknown key"),
        ({"defaults": {"codec": "hevc"}, "pointz": {}}, "pointz", "unknown key"),
        ({"points": {}}, "points", "non-empty"),
        ([1, 2, 3], "", "must be a mapping"),
    ],
)
def test_bad_yaml_is_one_clear_error(tmp_path, document, key, problem):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(document))
    with pytest.raises(RatePointError) as info:
        load_rate_point_file(path)
    message = str(info.value)
    assert str(path) in message and problem in message
    if key:
        assert f"key {key!r}" in message
    if "points" in document and isinstance(document, dict) and document["points"]:
        assert "point 'a'" in message


def test_invalid_yaml_syntax_names_the_line(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("points:\n  a: {codec: png\n")
    with pytest.raises(RatePointError, match=r"broken.yaml: not valid YAML at line \d+"):
        load_rate_point_file(path)


def test_overrides():
    point = load_rate_point("gsplat_png")
    pca = point.with_overrides(sh_stage="pca", sh_params={"energy_retention": 0.95})
    assert pca.sh_stage == "pca" and pca.sh_params == {"energy_retention": 0.95}
    more = point.with_overrides(sh_params={"centroid_bits": 8})
    assert more.sh_params == {"n_clusters": 65536, "centroid_bits": 8}
    fast = load_rate_point("paper_table3:rp1").with_overrides(codec_options={"preset": "ultrafast"}, sort_method="morton", seed=3)
    assert fast.attributes["scale"].options["preset"] == "ultrafast"
    assert "preset" not in fast.attributes["positions"].options or fast.attributes["positions"].options["preset"] == "slow"
    assert fast.sort.method == "morton" and fast.sort.seed == 3
    with pytest.raises(RatePointError, match="unknown SH stage"):
        point.with_overrides(sh_stage="wavelet")


def test_the_ladder_spans_the_rates_monotonically():
    """Nine points, every QP non-increasing and the position bits non-decreasing along the ladder."""
    points = [load_rate_point(f"shac_ladder:rp{i}") for i in range(1, 10)]
    for name in ("opacity", "rotation", "scale", "sh_dc", "sh_features"):
        qps = [p.attributes[name].qp for p in points]
        assert qps == sorted(qps, reverse=True), name
    pruning = [p.min_opacity for p in points]
    assert pruning == sorted(pruning, reverse=True) and pruning[-1] == 0.0
    bits = [p.attributes["positions"].bits for p in points]
    assert bits == sorted(bits) and bits[0] == 10 and bits[-1] == 16 and all(p.positions_as_set for p in points)


def test_rotation_takes_a_qp_for_x_y_z_and_one_for_w(tmp_path, small_cloud):
    path = tmp_path / "rot.yaml"
    path.write_text(yaml.safe_dump({"points": {"a": {"codec": "hevc", "qp": {
        "opacity": 22, "rotation": [17, 29], "scale": 12, "sh_dc": 7, "sh_ac": 22}}}}))
    point = load_rate_point_file(path)["a"]
    assert point.attributes["rotation"].qp == (17, 29)
    stream = Encoder(point).encode(small_cloud)
    assert {c.name: c.meta["qp"] for c in stream.chunks if c.name.startswith("rotation")} == \
        {"rotation_0": 29, "rotation_1": 17}  # chunk 0 holds w
    assert Decoder().decode(stream.to_bytes()).num_gaussians == small_cloud.num_gaussians
