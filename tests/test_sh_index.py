"""SH index bookkeeping: (l, m) <-> k, paper AC order and the Inria channel-major order."""

import numpy as np
import pytest

from gscodec_shac import sh_index
from gscodec_shac.errors import ValidationError


def test_index_round_trip_all_degrees():
    for k in range(sh_index.num_coeffs(4)):
        l, m = sh_index.degree_order(k)
        assert -l <= m <= l
        assert sh_index.coeff_index(l, m) == k


def test_counts_per_degree():
    assert [sh_index.num_ac_columns(d) for d in range(5)] == [0, 9, 24, 45, 72]
    assert [sh_index.degree_from_rest_count(n) for n in (0, 3, 8, 15, 24)] == [0, 1, 2, 3, 4]
    with pytest.raises(ValidationError, match="fit no SH degree"):
        sh_index.degree_from_rest_count(14)


def test_ac_matrix_puts_rgb_of_one_coefficient_side_by_side():
    n = 4
    rest = np.zeros((n, 15, 3), dtype=np.float32)
    # value encodes (k, channel) so we can read back where it landed
    for k in range(1, 16):
        for c in range(3):
            rest[:, k - 1, c] = 10 * k + c
    ac = sh_index.ac_matrix(rest)
    l, m = 2, -1
    for c in range(3):
        col = sh_index.ac_column(l, m, c)
        assert ac[0, col] == 10 * sh_index.coeff_index(l, m) + c
    # columns 0..2 are the R, G, B of (l=1, m=-1)
    np.testing.assert_array_equal(ac[0, :3], [10, 11, 12])


def test_inria_order_is_channel_major_and_differs_from_paper_order():
    rng = np.random.default_rng(0)
    rest = rng.normal(size=(5, 15, 3)).astype(np.float32)
    f_rest = sh_index.inria_rest_from_sh_rest(rest)
    # f_rest_j for j < 15 is the red channel of coefficient j + 1
    np.testing.assert_array_equal(f_rest[:, :15], rest[:, :, 0])
    np.testing.assert_array_equal(f_rest[:, 15:30], rest[:, :, 1])
    np.testing.assert_array_equal(f_rest[:, 30:], rest[:, :, 2])
    # confusing the two orders would give a different matrix
    assert not np.array_equal(f_rest, sh_index.ac_matrix(rest))
    np.testing.assert_array_equal(sh_index.sh_rest_from_inria_rest(f_rest), rest)


def test_column_labels():
    labels = sh_index.ac_column_labels(3)
    assert len(labels) == 45
    assert labels[:4] == ["l1m-1R", "l1m-1G", "l1m-1B", "l1m0R"]
    assert labels[-1] == "l3m3B"
