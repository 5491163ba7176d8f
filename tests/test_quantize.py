"""Attribute transforms and the per-channel min/max quantiser."""

import json

import numpy as np
import pytest

from gscodec_shac.codec import quantize as qz
from gscodec_shac.errors import ValidationError


def test_log_transform_round_trip_and_sign():
    x = np.array([-1e4, -2.5, -1e-6, 0.0, 1e-6, 3.0, 1e4])
    y = qz.log_transform(x)
    assert np.all(np.sign(y) == np.sign(x))
    assert np.allclose(qz.inverse_log_transform(y), x, rtol=1e-14, atol=0)
    assert y[-1] == pytest.approx(np.log1p(1e4))


def test_canonical_quaternions_are_unit_with_nonnegative_w():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(500, 4)) * rng.uniform(0.1, 10, size=(500, 1))
    q[0] = 0.0
    c = qz.canonical_quaternions(q)
    assert np.allclose(np.linalg.norm(c, axis=1), 1.0)
    assert np.all(c[:, 0] >= 0)
    assert np.array_equal(c[0], [1.0, 0.0, 0.0, 0.0])
    # same rotation: c is +-q / |q|
    unit = q[1:] / np.linalg.norm(q[1:], axis=1, keepdims=True)
    assert np.allclose(np.abs(np.sum(c[1:] * unit, axis=1)), 1.0)


def test_ycbcr_bt709_values_and_round_trip():
    white = qz.rgb_to_ycbcr(np.array([1.0, 1.0, 1.0]))
    assert np.allclose(white, [1.0, 0.0, 0.0])
    red = qz.rgb_to_ycbcr(np.array([1.0, 0.0, 0.0]))
    assert red[0] == pytest.approx(0.2126) and red[2] == pytest.approx(0.5)
    rng = np.random.default_rng(1)
    triplets = rng.normal(size=(100, 45))
    assert np.allclose(qz.triplets_from_ycbcr(qz.triplets_to_ycbcr(triplets)), triplets, atol=1e-12)
    with pytest.raises(ValidationError):
        qz.triplets_to_ycbcr(rng.normal(size=(4, 5)))


@pytest.mark.parametrize("bits", [1, 8, 10, 16])
def test_quantiser_error_is_at_most_half_a_step(bits):
    rng = np.random.default_rng(bits)
    values = rng.normal(size=(1000, 3)) * np.array([1.0, 1e-3, 50.0]) + np.array([0.0, 5.0, -7.0])
    quantizer = qz.Quantizer.fit(values, bits)
    q = quantizer.quantize(values)
    assert q.dtype == np.uint16 and q.min() == 0 and int(q.max()) == 2**bits - 1
    error = np.abs(quantizer.dequantize(q).astype(np.float64) - values)
    bound = quantizer.step / 2 + np.abs(values) * 2**-23 + 1e-12
    assert np.all(error <= bound)


def test_quantiser_ranges_cover_the_data_and_survive_json_exactly():
    rng = np.random.default_rng(2)
    values = rng.normal(size=(300, 4)) * 1e3 + 0.1  # float64 extremes not representable in float32
    quantizer = qz.Quantizer.fit(values, 10)
    assert np.all(quantizer.lo <= values.min(axis=0)) and np.all(quantizer.hi >= values.max(axis=0))
    back = qz.Quantizer.from_json(json.loads(json.dumps(quantizer.to_json())))
    assert back.lo.tobytes() == quantizer.lo.tobytes() and back.hi.tobytes() == quantizer.hi.tobytes()
    assert np.array_equal(back.dequantize(quantizer.quantize(values)), quantizer.dequantize(quantizer.quantize(values)))


def test_constant_channel_and_bad_input():
    values = np.column_stack([np.full(10, 3.5), np.arange(10.0)])
    quantizer = qz.Quantizer.fit(values, 10)
    q = quantizer.quantize(values)
    assert np.all(q[:, 0] == 0)
    assert np.all(quantizer.dequantize(q)[:, 0] == np.float32(3.5))
    with pytest.raises(ValidationError):
        quantizer.quantize(np.zeros((3, 3)))
    with pytest.raises(ValidationError):
        qz.Quantizer(17, [0.0], [1.0])
    with pytest.raises(ValidationError):
        qz.Quantizer(8, [1.0], [0.0])


def test_float32_json_reads_back_exactly():
    rng = np.random.default_rng(3)
    x = (rng.normal(size=20000) * 10.0 ** rng.integers(-30, 30, size=20000)).astype(np.float32)
    back = np.array([json.loads(json.dumps(qz.float32_json(v))) for v in x], dtype=np.float32)
    assert back.tobytes() == x.tobytes()


def test_split_and_join_planes():
    values = np.array([0, 1, 255, 256, 40000, 65535], dtype=np.uint16)
    high, low = qz.split_planes(values, 16)
    assert high.max() <= 255 and low.max() <= 255
    assert np.array_equal(qz.join_planes(high, low), values)
    with pytest.raises(ValidationError):
        qz.split_planes(values, 8)


def test_prune_mask(small_cloud):
    mask = qz.prune_mask(small_cloud, 0.5)
    assert np.array_equal(mask, small_cloud.activated_opacities() >= 0.5)
    assert qz.prune_mask(small_cloud, 0.0).all()
    with pytest.raises(ValidationError):
        qz.prune_mask(small_cloud, 1.0)
