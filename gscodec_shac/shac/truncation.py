"""Degree truncation, the SH baseline SHAC is compared with (paper Sec. VI-B, "Trunc.").

Keep the AC coefficients of degrees 1..``degree`` (a prefix of the paper-order AC
matrix, 3((degree+1)^2 - 1) columns) and drop the rest; the inverse zero-pads
the dropped columns. Trunc.-L3-D24 of Table II is ``degree=2`` on an SH-3 model.
"""

from __future__ import annotations

import numpy as np

from gscodec_shac import sh_index
from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.shac.base import ShStage, StageParam, StageState, check_ac_matrix, register_stage

FLOAT32_BYTES = 4


@register_stage
class TruncationStage(ShStage):
    """SH stage "trunc": keep degrees <= ``degree``; no side information."""

    name = "trunc"
    summary = "truncation to a lower SH degree (higher degrees dropped)"
    feature_kind = "coefficients"
    rate_attribute = "sh_ac"
    inverts_row_blocks = True  # each row's inverse is a copy of its own features
    params = (StageParam("degree", "int", 2, "SH degree L' kept", flag="degree", lo=0, hi=3),)

    def __init__(self, degree: int = 2) -> None:
        if isinstance(degree, bool) or int(degree) != degree or not 0 <= degree <= sh_index.MAX_SH_DEGREE:
            raise ValidationError(f"truncation degree must be an integer 0-{sh_index.MAX_SH_DEGREE}, got {degree!r}")
        self.degree = int(degree)
        self.n_columns_: int | None = None
        self.input_degree_: int | None = None

    def fit(self, ac: np.ndarray) -> "TruncationStage":
        """Record the input width K' (and so the input degree L >= ``degree``)."""
        ac = check_ac_matrix(ac)
        if ac.shape[1] % 3:
            raise ValidationError(f"expected R, G, B AC columns (a multiple of 3), got {ac.shape[1]}")
        input_degree = sh_index.degree_from_rest_count(ac.shape[1] // 3)
        if self.degree > input_degree:
            raise ValidationError(
                f"cannot truncate SH degree {input_degree} to the higher degree {self.degree}"
            )
        self.n_columns_, self.input_degree_ = ac.shape[1], input_degree
        return self

    def transform(self, ac: np.ndarray) -> np.ndarray:
        """(N, K') -> (N, 3((degree+1)^2 - 1)): the low-degree prefix."""
        self._check_fitted()
        ac = check_ac_matrix(ac, self.n_columns_)
        return ac[:, : self.n_features].copy()

    def inverse_transform(self, features: np.ndarray) -> np.ndarray:
        """Zero-pad the dropped higher-degree columns back to (N, K')."""
        self._check_fitted()
        features = check_ac_matrix(features, self.n_features)
        out = np.zeros((features.shape[0], self.n_columns_), dtype=features.dtype)
        out[:, : self.n_features] = features
        return out

    def feature_columns(self) -> np.ndarray | None:
        return np.arange(self.n_features)

    @property
    def n_features(self) -> int:
        self._check_fitted()
        return sh_index.num_ac_columns(self.degree)

    def compression_ratio(self, n_gaussians: int) -> float:
        """(N (3 + K'_kept)) / (N K): the truncation counterpart of eq. 30 (no side information)."""
        if int(n_gaussians) < 1:
            raise ValidationError(f"the number of Gaussians must be positive, got {n_gaussians}")
        return (3 + self.n_features) / (self.n_columns_ + 3)

    def compression_ratio_bytes(self, n_gaussians: int, feature_bytes: float = FLOAT32_BYTES) -> float:
        """The same from bytes: float32 DC, kept features of ``feature_bytes``, serialised state."""
        n = int(n_gaussians)
        if n < 1:
            raise ValidationError(f"the number of Gaussians must be positive, got {n_gaussians}")
        side = len(self.state().to_bytes())
        return (n * (3 * FLOAT32_BYTES + self.n_features * feature_bytes) + side) / (
            n * (self.n_columns_ + 3) * FLOAT32_BYTES
        )

    def state(self) -> StageState:
        self._check_fitted()
        return StageState(self.name, {"degree": self.degree, "n_columns": self.n_columns_})

    @classmethod
    def from_state(cls, state: StageState) -> "TruncationStage":
        try:
            stage = cls(int(state.params["degree"]))
            n_columns = int(state.params["n_columns"])
            stage.input_degree_ = sh_index.degree_from_rest_count(n_columns // 3)
            if n_columns % 3 or stage.degree > stage.input_degree_:
                raise ValueError("degree")
        except (KeyError, TypeError, ValueError) as exc:
            raise GscodecError(f"truncation state is inconsistent ({exc})") from None
        stage.n_columns_ = n_columns
        return stage

    def _check_fitted(self) -> None:
        if self.n_columns_ is None:
            raise ValidationError("this truncation stage is not fitted yet; call fit() first")

    def __repr__(self) -> str:
        return f"TruncationStage(degree={self.degree})"
