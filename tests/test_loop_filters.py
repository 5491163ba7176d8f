"""x265 without its in-loop filters (hevc option ``loop_filters=False``): SAO and deblocking off on lossy
streams, recorded in the header only when off, decoded by any decoder from the stream itself."""

from __future__ import annotations

import numpy as np
import pytest

from gscodec_shac.codec.grid import get_codec
from gscodec_shac.codec.grid.hevc import NO_LOOP_FILTER_PARAMS
from gscodec_shac.errors import ValidationError
from tests.test_codecs import smooth_planes
from tests.test_effort import _x265_params


def test_without_loop_filters_lossy_streams_differ_and_decode_with_a_default_decoder(tmp_path, monkeypatch):
    monkeypatch.setenv("GSCODEC_X265_PROCESSES", "0")  # coded here, so this process writes the records
    monkeypatch.setenv("GSCODEC_X265_DUMP", str(tmp_path))
    rng = np.random.default_rng(0)
    planes = np.clip(smooth_planes((3, 64, 96), 10).astype(int) + rng.integers(-60, 60, (3, 64, 96)), 0, 1023)
    planes = planes.astype(np.uint16)  # block edges for the filters to act on at a coarse QP
    unfiltered = get_codec("hevc", layout="frames", loop_filters=False)
    lossy = unfiltered.encode(planes, 10, 36)
    lossless = unfiltered.encode(planes[:1], 10, None)
    filtered = get_codec("hevc", layout="frames").encode(planes, 10, 36)
    params = _x265_params(tmp_path)
    assert sorted(p.endswith(NO_LOOP_FILTER_PARAMS) for p in params) == [False, False, True]
    assert [p for p in params if p.endswith(NO_LOOP_FILTER_PARAMS)][0].startswith("qp=36")
    assert lossy != filtered
    default = get_codec("hevc", layout="frames")  # the decoder needs no option: the stream says it
    for stream, source in ((lossy, planes), (filtered, planes)):
        assert np.abs(default.decode(stream, planes.shape, 10).astype(int) - source).mean() < 40
    np.testing.assert_array_equal(default.decode(lossless, (1, 64, 96), 10), planes[:1])


def test_loop_filters_are_recorded_only_when_off_and_checked():
    assert "loop_filters" not in get_codec("hevc").describe()["options"]  # files of earlier versions: same options
    assert get_codec("hevc", loop_filters=False).describe()["options"]["loop_filters"] is False
    with pytest.raises(ValidationError, match="loop_filters must be true or false"):
        get_codec("hevc", loop_filters="off")
