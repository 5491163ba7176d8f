"""The rate controller's PCHIP against scipy's PchipInterpolator: the same values, bit for bit."""

import numpy as np
import pytest
from scipy.interpolate import PchipInterpolator

from gscodec_shac.codec.pchip import pchip


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return np.array_equal(np.asarray(a, np.float64).view(np.int64), np.asarray(b, np.float64).view(np.int64))


def _cases(rng: np.random.Generator):
    qps = np.array([6.0, 18.0, 30.0, 42.0])
    yield qps, np.log(np.array([9.1e5, 3.3e5, 8.7e4, 1.9e4]))  # a rate curve: bytes falling with the QP
    yield qps, np.log(np.array([2e-7, 5e-6, 1.1e-4, 2.4e-3]))  # an error curve: rising
    yield np.array([0.0, 1.0, 2.0, 3.0, 4.0]), np.array([0.0, 1.0, 1.0, 0.5, 2.0])  # flat piece, extrema
    yield np.array([0.0, 1.0, 3.0]), np.array([0.0, 5.0, 4.9])  # an end derivative clipped to 3 m0
    yield np.array([0.0, 1.0, 2.0]), np.array([1.0, 1.0, 1.0])  # constant
    for _ in range(300):
        n = int(rng.integers(3, 9))
        x = np.cumsum(rng.uniform(0.1, 12.0, n)) + rng.uniform(-5, 5)
        kind = rng.integers(3)
        y = (np.cumsum(rng.normal(0, 2, n)) if kind == 0 else
             np.sort(rng.normal(0, 3, n))[:: 1 if kind == 1 else -1])
        yield x, y


def test_pchip_equals_scipy_bit_for_bit():
    rng = np.random.default_rng(7)
    for x, y in _cases(rng):
        at = np.concatenate([np.linspace(x[0], x[-1], 205), x, rng.uniform(x[0], x[-1], 50)])
        assert _same_bits(pchip(x, y, at), PchipInterpolator(x, y)(at)), (x, y)


def test_pchip_refuses_what_it_does_not_cover():
    x, y = np.array([0.0, 1.0, 2.0]), np.array([0.0, 1.0, 0.0])
    with pytest.raises(ValueError, match="inside"):
        pchip(x, y, np.array([2.5]))
    with pytest.raises(ValueError, match="three points"):
        pchip(x[:2], y[:2], np.array([0.5]))
    with pytest.raises(ValueError, match="increasing"):
        pchip(x[::-1], y, np.array([0.5]))
