"""scripts/position_octree_estimate.py: the ideal adaptive code lengths it sums."""

import pytest

from tests.conftest import load_script

estimate = load_script("position_octree_estimate")


def test_the_octree_estimate_counts_adaptive_code_lengths():
    import math

    import numpy as np

    # n zeros in one context: the adaptive probabilities telescope to 1 / (n + 1)
    assert estimate.adaptive_code_length(np.zeros(7, int), np.zeros(7, int), 1) == pytest.approx(math.log2(8))
    # a single point: eight occupancy bits per level, each the first of its context (1 bit each)
    one = estimate.octree_bits(np.array([[5, 2, 7]]), 3)
    assert one == pytest.approx(3 * 8)
    two = estimate.octree_bits(np.array([[5, 2, 7], [0, 0, 0]]), 3)
    assert two > one
