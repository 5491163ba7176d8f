"""HEVC parameter sets stored once per file (codec/parameter_sets.py, format 2.4, feature
``hevc_parameter_sets``): where a stream's sets end, the table the encoder writes, the decoder's
restoring them byte for byte, and the header's checks."""

from __future__ import annotations

import dataclasses
import zlib

import pytest

from gscodec_shac.codec import Decoder, Encoder, load_rate_point
from gscodec_shac.codec import parameter_sets as ps
from gscodec_shac.codec.container import Bitstream
from gscodec_shac.errors import BitstreamError
from gscodec_shac.synthetic import make_synthetic_scene

ARRAYS = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")


def _nal(nal_type: int, payload: bytes, zero_byte: bool = True) -> bytes:
    return (b"\x00" if zero_byte else b"") + b"\x00\x00\x01" + bytes([nal_type << 1, 1]) + payload


def test_the_parameter_sets_end_at_the_first_other_nal_unit():
    sets = _nal(32, b"vps") + _nal(33, b"sps-long") + _nal(34, b"pps", zero_byte=False)
    stream = sets + _nal(20, b"idr slice") + _nal(1, b"p slice")
    assert ps.parameter_sets_end(stream) == len(sets)
    assert ps.parameter_sets_end(sets) == len(sets)  # nothing but parameter sets
    assert ps.parameter_sets_end(_nal(20, b"idr") + sets) == 0  # they do not lead
    assert ps.parameter_sets_end(b"\x07" + stream) == 0  # no start code first
    assert ps.parameter_sets_end(b"") == 0


@pytest.fixture(scope="module")
def cloud():
    return make_synthetic_scene(500, seed=4, n_cameras=1, width=32, height=24).cloud


def _encode(cloud, point: str | None = None, share: bool = True, monkeypatch=None) -> bytes:
    """``point`` (default: the SHAC-auto template, one stream: its tiers off) encoded fast."""
    point = point or dataclasses.replace(load_rate_point("shac_auto:template"), tiers=None)
    if not share:
        monkeypatch.setattr(ps, "share", lambda stream, codecs: None)
    data = Encoder(point, codec_options={"preset": "ultrafast"}).encode(cloud).to_bytes()
    if not share:
        monkeypatch.undo()
    return data


def test_a_shared_table_decodes_to_the_same_cloud_in_fewer_bytes(cloud, monkeypatch):
    shared, whole = _encode(cloud), _encode(cloud, share=False, monkeypatch=monkeypatch)
    stream = Bitstream.from_bytes(shared)
    assert ps.FEATURE in stream.features and ps.FEATURE not in Bitstream.from_bytes(whole).features
    hevc = [c for c in stream.chunks if ps.META_KEY in c.meta]
    streams = sum(len(c.meta[ps.META_KEY]) for c in hevc)
    sets = stream.chunk(ps.CHUNK).meta["sets"]
    assert streams >= 10 and sets <= 4  # the template's 12-bit planes: a few distinct sets
    assert len(whole) - len(shared) >= 60 * (streams - sets)  # ~80 bytes per stream saved, less the table
    a, b = Decoder().decode(shared), Decoder().decode(whole)
    for key in ARRAYS:
        assert getattr(a, key).tobytes() == getattr(b, key).tobytes(), key


def test_a_stream_without_features_stays_format_1_0(cloud):
    data = Encoder("paper_table3:rp2", sh_stage="pca", sh_params={"n_components": 8},
                   codec_options={"preset": "ultrafast"}).encode(cloud).to_bytes()
    assert data[8:12] == b"\x01\x00\x00\x00"
    assert all(ps.META_KEY not in c.meta for c in Bitstream.from_bytes(data).chunks)


def test_the_restored_chunks_are_the_codecs_bytes(cloud, monkeypatch):
    shared = Bitstream.from_bytes(_encode(cloud))
    whole = Bitstream.from_bytes(_encode(cloud, share=False, monkeypatch=monkeypatch))
    table = ps.read_table(zlib.decompress(shared.chunk(ps.CHUNK).data), shared.chunk(ps.CHUNK).meta["sets"])
    for chunk in shared.chunks:
        if ps.META_KEY in chunk.meta:
            assert ps.restore(chunk.data, tuple(chunk.meta[ps.META_KEY]), table) == whole.chunk(chunk.name).data


def _first_hevc(stream: Bitstream):
    return next(c for c in stream.chunks if ps.META_KEY in c.meta)


@pytest.mark.parametrize("edit, message", [
    (lambda s: _first_hevc(s).meta.update(parameter_sets=[99]), "must list indices below"),
    (lambda s: _first_hevc(s).meta.update(parameter_sets="0"), "must be a non-empty list"),
    (lambda s: _first_hevc(s).meta.update(parameter_sets=[0, 0, 0, 0, 0, 0]), "hevc streams but lists parameter"),
    (lambda s: _first_hevc(s).meta.pop(ps.META_KEY), "is listed exactly for the hevc chunks"),
    (lambda s: s.chunk(ps.CHUNK).meta.update(sets=0), "key 'chunks.hevc_parameter_sets.sets'"),
    (lambda s: s.chunks.remove(s.chunk(ps.CHUNK)), "chunk 'hevc_parameter_sets' is missing"),
    (lambda s: s.features.discard(ps.FEATURE), "needs the hevc_parameter_sets feature"),
    (lambda s: s.chunk(ps.CHUNK).meta.update(raw_size=10**9), "key 'chunks.hevc_parameter_sets.raw_size'"),
])
def test_a_broken_table_or_reference_is_one_clear_error(cloud, edit, message):
    stream = Bitstream.from_bytes(_encode(cloud))
    edit(stream)
    with pytest.raises(BitstreamError, match=message) as error:
        Decoder().decode(stream.to_bytes())
    assert str(error.value).startswith("corrupt .gsc file")
