"""SH stages (paper Sec. V): identity, truncation, SHAC-PCA, SHAC-LST, vector quantisation.

All share the contract of :mod:`gscodec_shac.shac.base`; build one by name with
:func:`~gscodec_shac.shac.base.make_stage`.
"""

from gscodec_shac.shac.base import STAGES, ShStage, StageState, make_stage, stage_from_state

__all__ = ["STAGES", "ShStage", "StageState", "make_stage", "stage_from_state"]
