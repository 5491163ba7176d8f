"""Positions coded as a set: Morton codes, gap coding, the derived grid order, streams."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gscodec_shac.codec import Decoder, Encoder, load_rate_point
from gscodec_shac.codec import quantize as qz
from gscodec_shac.codec.container import Bitstream
from gscodec_shac.codec.positions import (
    decode_sorted_codes,
    encode_sorted_codes,
    morton_decode,
    morton_encode,
    set_order,
)
from gscodec_shac.errors import BitstreamError, RatePointError


def _set_point(ref: str = "paper_table3:rp2", bits: int = 16):
    point = load_rate_point(ref)
    attributes = dict(point.attributes)
    attributes["positions"] = dataclasses.replace(attributes["positions"], layout="set", bits=bits)
    return dataclasses.replace(point, attributes=attributes)


@pytest.mark.parametrize("bits", [1, 7, 16, 21])
def test_morton_codes_round_trip_and_interleave(bits):
    rng = np.random.default_rng(bits)
    q = rng.integers(0, 1 << bits, size=(5000, 3))
    assert np.array_equal(morton_decode(morton_encode(q)), q)
    # x takes bit 0, y bit 1, z bit 2 of each triple
    assert morton_encode(np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [2, 0, 0]])).tolist() == [1, 2, 4, 8]


@pytest.mark.parametrize("bits, n", [(16, 20_000), (10, 20_000), (3, 500), (16, 1)])
def test_sorted_codes_round_trip(bits, n):
    rng = np.random.default_rng(n)
    codes = np.sort(morton_encode(rng.integers(0, 1 << bits, size=(n, 3))))
    data = encode_sorted_codes(codes)
    assert np.array_equal(decode_sorted_codes(data, n, bits), codes)


def test_clustered_points_cost_less_than_raw():
    rng = np.random.default_rng(0)
    centres = rng.integers(0, 1 << 16, size=(50, 3))
    q = np.clip(centres[rng.integers(0, 50, 20_000)] + rng.integers(-200, 200, size=(20_000, 3)), 0, (1 << 16) - 1)
    bits_per_point = 8 * len(encode_sorted_codes(np.sort(morton_encode(q)))) / len(q)
    assert bits_per_point < 0.7 * 48  # raw 3 x 16 bits


def test_corrupt_or_inconsistent_sets_are_one_clear_error():
    codes = np.sort(morton_encode(np.random.default_rng(1).integers(0, 1 << 12, size=(1000, 3))))
    data = encode_sorted_codes(codes)
    with pytest.raises(BitstreamError, match="header says"):
        decode_sorted_codes(data, 999, 12)
    with pytest.raises(BitstreamError):
        decode_sorted_codes(data[:-3], 1000, 12)
    with pytest.raises(BitstreamError, match="outside the grid|gap lengths"):
        decode_sorted_codes(data, 1000, 8)
    with pytest.raises(BitstreamError):
        decode_sorted_codes(data[:5], 1000, 12)


def test_set_order_sorts_by_morton_code_and_keeps_ties_in_input_order():
    q = np.array([[3, 0, 0], [0, 0, 0], [3, 0, 0], [1, 0, 0]])
    assert set_order(q).tolist() == [1, 3, 0, 2]


def test_set_coded_stream_decodes_to_the_quantised_positions_in_morton_order(small_cloud):
    point = _set_point(bits=14)
    encoder = Encoder(point, sh_stage="none")
    stream = encoder.encode(small_cloud)
    data = stream.to_bytes()
    # format 2.0 for the set; 2.4 because a format-2 stream's HEVC chunks share their parameter sets
    assert Bitstream.from_bytes(data).version == (2, 4)
    assert stream.features == {"positions_set", "hevc_parameter_sets"}
    decoded = Decoder().decode(data)
    source = small_cloud.select(encoder.order_)
    values = qz.log_transform(source.means)
    quantizer = qz.Quantizer.fit(values, 14)
    expected = qz.inverse_log_transform(quantizer.dequantize(quantizer.quantize(values)))
    assert np.array_equal(decoded.means, expected.astype(np.float32))
    codes = morton_encode(quantizer.quantize(values))
    assert np.all(np.diff(codes.astype(np.float64)) >= 0)  # grid order = Morton order
    # every other attribute travels in the same order
    spread = np.ptp(source.opacities)
    assert np.abs(decoded.opacities - source.opacities).max() < 0.03 * spread
    assert stream.header["grid"]["padding"] == "zorder" and "grid_mask" not in stream.sizes()


def test_set_coding_is_smaller_than_16_bit_planes(small_cloud):
    planes = Encoder("paper_table3:rp2", sh_stage="none").encode(small_cloud).attribute_sizes()["positions"]
    as_set = Encoder(_set_point(bits=16), sh_stage="none").encode(small_cloud).attribute_sizes()["positions"]
    assert as_set < 0.8 * planes


def test_set_coding_is_deterministic_and_reuses_its_grid(small_cloud):
    encoder = Encoder(_set_point(bits=12), sh_stage="pca", workers=1)
    first = encoder.encode(small_cloud).to_bytes()
    grid = encoder.grid_order(small_cloud)
    again = Encoder(_set_point(bits=12), sh_stage="pca", workers=2).encode(small_cloud, grid=grid).to_bytes()
    assert first == again


def test_a_sort_method_does_not_apply_to_set_coded_positions():
    with pytest.raises(RatePointError, match="codes positions as a set"):
        Encoder(_set_point(), sort="plas")


def test_set_layout_is_for_positions_only():
    from gscodec_shac.codec.rate_points import parse_rate_points

    with pytest.raises(RatePointError, match="only positions can be coded as a set"):
        parse_rate_points({"points": {"a": {"attributes": {"scale": {"layout": "set"}}}}}, "t")
    point = parse_rate_points({"points": {"a": {"attributes": {"positions": {"layout": "set", "bits": 12}}}}}, "t")["a"]
    assert point.positions_as_set and point.attributes["sh_labels"].layout == "split8"
