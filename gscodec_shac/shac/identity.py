"""The no-op SH stage (the baseline: every AC coefficient is coded)."""

from __future__ import annotations

import numpy as np

from gscodec_shac.shac.base import ShStage, StageState, check_ac_matrix, register_stage


@register_stage
class IdentityStage(ShStage):
    """Features are the AC matrix itself; no side information."""

    name = "none"
    summary = "no SH stage: every AC coefficient is coded (the baseline)"
    feature_kind = "coefficients"
    rate_attribute = "sh_ac"
    inverts_row_blocks = True  # each row's inverse is a copy of its own features

    def __init__(self) -> None:
        self.n_columns_: int | None = None

    def feature_columns(self) -> np.ndarray | None:
        return np.arange(self.n_features)

    def fit(self, ac: np.ndarray) -> "IdentityStage":
        self.n_columns_ = check_ac_matrix(ac).shape[1]
        return self

    def transform(self, ac: np.ndarray) -> np.ndarray:
        return check_ac_matrix(ac, self.n_columns_)

    def inverse_transform(self, features: np.ndarray) -> np.ndarray:
        return check_ac_matrix(features, self.n_columns_)

    @property
    def n_features(self) -> int:
        return int(self.n_columns_ or 0)

    def state(self) -> StageState:
        return StageState(self.name, {"n_columns": self.n_columns_})

    @classmethod
    def from_state(cls, state: StageState) -> "IdentityStage":
        stage = cls()
        stage.n_columns_ = int(state.params["n_columns"])
        return stage
