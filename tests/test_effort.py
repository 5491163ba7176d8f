"""x265's full analysis (RD level 6) for small scenes, the preset's for big ones (codec/effort.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gscodec_shac.codec import effort
from gscodec_shac.codec.decoder import Decoder
from gscodec_shac.codec.encoder import Encoder
from gscodec_shac.codec.grid import get_codec
from gscodec_shac.codec.grid.hevc import FULL_ANALYSIS_PARAMS
from gscodec_shac.codec.rate_points import load_rate_point
from gscodec_shac.errors import ValidationError
from tests.test_codecs import smooth_planes


def _x265_params(folder) -> list[str]:
    return [json.loads(line)["options"]["x265-params"]
            for path in folder.glob("x265-*.jsonl") for line in path.read_text().splitlines()]


def test_full_analysis_adds_rd_6_to_lossy_streams_only_and_decodes_without_it(tmp_path, monkeypatch):
    monkeypatch.setenv("GSCODEC_X265_PROCESSES", "0")  # coded here, so this process writes the records
    monkeypatch.setenv("GSCODEC_X265_DUMP", str(tmp_path))
    planes = smooth_planes((6, 40, 80), 10)
    full = get_codec("hevc", layout="frames", analysis="full")
    lossy = full.encode(planes, 10, 20)
    full.encode(planes[:1], 10, None)  # lossless: nothing to decide by rate and distortion
    preset = get_codec("hevc", layout="frames").encode(planes, 10, 20)
    params = _x265_params(tmp_path)
    assert sorted(p.endswith(FULL_ANALYSIS_PARAMS) for p in params) == [False, False, True]
    assert [p for p in params if p.endswith(FULL_ANALYSIS_PARAMS)][0].startswith("qp=20")
    assert lossy != preset
    decoded = get_codec("hevc", layout="frames").decode(lossy, planes.shape, 10)  # the decoder needs no option
    assert np.abs(decoded.astype(int) - planes).max() < 40


def test_analysis_is_recorded_only_when_full_and_checked():
    assert "analysis" not in get_codec("hevc").describe()["options"]  # files of earlier versions: same options
    assert get_codec("hevc", analysis="full").describe()["options"]["analysis"] == "full"
    with pytest.raises(ValidationError, match="analysis must be one of preset, full"):
        get_codec("hevc", analysis="max")


def test_scene_analysis_follows_the_number_of_gaussians():
    limit = effort.FULL_ANALYSIS_MAX_GAUSSIANS
    assert effort.scene_analysis(limit) == "full"
    assert effort.scene_analysis(limit + 1) == "preset"


def test_with_scene_analysis_sets_lossy_hevc_attributes_that_have_none():
    point = load_rate_point("paper_table3:rp2")  # positions lossless (hevc), the others lossy hevc
    big = effort.with_scene_analysis(point, effort.FULL_ANALYSIS_MAX_GAUSSIANS + 1)
    small = effort.with_scene_analysis(point.with_overrides(codec_options={"analysis": "preset"}), 10)
    for name, spec in point.attributes.items():
        if spec.lossless:
            assert "analysis" not in big.attributes[name].options
        else:
            assert big.attributes[name].options["analysis"] == "preset"
            assert small.attributes[name].options["analysis"] == "preset"  # a caller's choice stays
    assert effort.with_scene_analysis(point, 10).attributes["scale"].options["analysis"] == "full"


def _header_analyses(stream) -> set:
    return {codec.get("options", {}).get("analysis", "preset") for codec in stream.header["codecs"]
            if codec["name"] == "hevc"}


def _chunks(stream) -> dict[str, bytes]:
    return {name: stream.chunk(name).data for name in stream.sizes() if name != "header"}


def test_an_encode_chooses_by_its_scene_unless_told(small_cloud, monkeypatch):
    small = Encoder("shac_ladder:rp4", "pca").encode(small_cloud)
    assert _header_analyses(small) == {"full"}
    told = Encoder("shac_ladder:rp4", "pca", codec_options={"analysis": "preset"}).encode(small_cloud)
    assert _header_analyses(told) == {"preset"}
    assert _chunks(told) != _chunks(small)
    monkeypatch.setattr("gscodec_shac.codec.encoder.scene_analysis",
                        lambda n: "full" if n <= small_cloud.num_gaussians - 1 else "preset")
    big = Encoder("shac_ladder:rp4", "pca").encode(small_cloud)
    assert _chunks(big) == _chunks(told)  # over the limit: the preset's analysis, bit for bit
    for stream in (small, told):
        cloud = Decoder().decode(stream.to_bytes())
        assert cloud.num_gaussians == small.header["num_gaussians"]


def test_the_rate_controllers_probes_take_the_whole_scenes_analysis(small_cloud, monkeypatch):
    """A probe is a subset of the scene: it is analysed as the scene's encodes are, not by its own size."""
    from gscodec_shac.codec.rate_control import RateController

    monkeypatch.setattr(effort, "FULL_ANALYSIS_MAX_GAUSSIANS", small_cloud.num_gaussians - 1)
    controller = RateController(small_cloud)
    lossy = [spec for spec in controller.template.attributes.values() if spec.codec == "hevc" and not spec.lossless]
    assert lossy and all(spec.options["analysis"] == "preset" for spec in lossy)
    rows = np.arange(small_cloud.num_gaussians // 4)  # a probe far under the limit
    stream = Encoder(controller._rate_point({"opacity": 20}), "pca").encode(small_cloud.select(rows))
    assert _header_analyses(stream) == {"preset"}


def test_the_cli_analysis_flag_overrides_the_scenes_choice(tmp_path, small_cloud):
    from gscodec_shac.cli import main
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.io.ply import write_ply

    ply = tmp_path / "small.ply"
    write_ply(ply, small_cloud)
    chosen = {}
    for flag in ([], ["--analysis", "preset"], ["--analysis", "full"]):
        out = tmp_path / f"out{len(chosen)}.gsc"
        assert main(["encode", str(ply), str(out), "-r", "shac_ladder:rp4", "-q", *flag]) == 0
        chosen[" ".join(flag) or "default"] = _header_analyses(Bitstream.read(out))
    assert chosen == {"default": {"full"}, "--analysis preset": {"preset"}, "--analysis full": {"full"}}
