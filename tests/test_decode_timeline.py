"""scripts/decode_timeline.py: each task of a decode with its start, end and thread."""

from gscodec_shac.codec import Bitstream, decoder
from gscodec_shac.codec.files import encode_file
from gscodec_shac.io.ply import write_ply
from tests.conftest import load_script


def test_every_chunk_and_the_position_set_are_on_the_timeline(tmp_path, small_scene):
    script = load_script("decode_timeline")
    ply, gsc = tmp_path / "in.ply", tmp_path / "out.gsc"
    write_ply(ply, small_scene.cloud)
    encode_file(ply, gsc, "shac_ladder:rp4", "pca", energy_retention=0.97)  # positions coded as a set
    before = (decoder._ChunkTask.decode, decoder._position_set, decoder._FeatureCodes.inverse)
    rows = script.main([str(gsc), "--repeat", "2", "--out", str(tmp_path / "t")])
    assert (decoder._ChunkTask.decode, decoder._position_set, decoder._FeatureCodes.inverse) == before  # restored
    hevc = {chunk.name for chunk in Bitstream.read(gsc).chunks if "codec" in chunk.meta}  # the grid chunks
    for run in (1, 2):
        mine = [row for row in rows if row["decode"] == run]
        assert {row["chunk"] for row in mine if row["task"] == "chunk"} == hevc
        assert [row["chunk"] for row in mine if row["task"] == "position set"] == ["positions"]
        whole = [row for row in mine if row["task"] == "whole decode"]
        assert len(whole) == 1 and all(0 <= row["start_s"] <= row["end_s"] <= whole[0]["end_s"] for row in mine)
    assert len(hevc) >= 5 and (tmp_path / "t.csv").read_text().count("\n") == len(rows) + 1
