"""Degree truncation stage "trunc" (the paper's Trunc.-L3-D24 baseline)."""

import numpy as np
import pytest

from gscodec_shac import sh_index
from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.shac.analysis import truncation_energy_curve
from gscodec_shac.shac.base import StageState, make_stage, stage_from_state
from gscodec_shac.shac.truncation import TruncationStage


def test_degree_two_keeps_the_first_24_columns_and_zero_pads(small_cloud):
    ac = small_cloud.ac_matrix()
    stage = make_stage("trunc", degree=2).fit(ac)
    features = stage.transform(ac)
    assert features.shape == (len(ac), 24) and stage.n_features == 24
    assert np.array_equal(features, small_cloud.sh_rest[:, :8].reshape(len(ac), 24))
    rec = stage.inverse_transform(features)
    assert rec.shape == ac.shape and rec.dtype == ac.dtype
    assert np.array_equal(rec[:, :24], ac[:, :24]) and not rec[:, 24:].any()
    # Same as the cloud's own truncation, padded back.
    assert np.array_equal(rec[:, :24], small_cloud.truncate_sh(2).ac_matrix())


def test_error_is_the_raw_energy_of_the_dropped_degree(small_cloud):
    ac = small_cloud.ac_matrix().astype(np.float64)
    stage = TruncationStage(2).fit(ac)
    err = ((ac - stage.inverse_transform(stage.transform(ac))) ** 2).sum()
    kept = truncation_energy_curve(ac, "raw")[23]
    assert err / (ac**2).sum() == pytest.approx(1 - kept, rel=1e-9)


@pytest.mark.parametrize("degree,width", [(0, 0), (1, 9), (3, 45)])
def test_other_degrees(small_cloud, degree, width):
    ac = small_cloud.ac_matrix()
    stage = TruncationStage(degree).fit(ac)
    features = stage.transform(ac)
    assert features.shape == (len(ac), width)
    rec = stage.inverse_transform(features)
    assert np.array_equal(rec[:, :width], ac[:, :width]) and not rec[:, width:].any()


def test_state_round_trip_and_ratio(small_cloud):
    ac = small_cloud.ac_matrix()
    stage = TruncationStage(2).fit(ac)
    state = stage.state()
    assert state.nbytes() == 0
    rebuilt = stage_from_state(StageState.from_bytes(state.to_bytes()))
    assert isinstance(rebuilt, TruncationStage)
    features = stage.transform(ac)
    assert np.array_equal(rebuilt.inverse_transform(features), stage.inverse_transform(features))
    assert stage.compression_ratio(len(ac)) == pytest.approx(27 / 48)
    assert stage.compression_ratio_bytes(len(ac)) == pytest.approx(
        (len(ac) * 27 * 4 + len(state.to_bytes())) / (len(ac) * 48 * 4)
    )


def test_user_mistakes(small_cloud):
    ac = small_cloud.ac_matrix()
    with pytest.raises(ValidationError, match="higher degree"):
        TruncationStage(3).fit(ac[:, :24])
    with pytest.raises(ValidationError, match="integer 0-4"):
        TruncationStage(7)
    with pytest.raises(ValidationError, match="not fitted"):
        TruncationStage(2).transform(ac)
    stage = TruncationStage(1).fit(ac)
    with pytest.raises(ValidationError, match="9 columns"):
        stage.inverse_transform(ac)
    with pytest.raises(GscodecError, match="inconsistent"):
        stage_from_state(StageState("trunc", {"degree": 3, "n_columns": sh_index.num_ac_columns(2)}))
