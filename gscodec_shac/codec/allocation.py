"""Reverse water-filling of QPs over an SH stage's features (rate-point ``allocation: waterfill``).

For independent features under one error budget, the classic rate-distortion answer
(reverse water-filling) gives every feature the same error, ``theta``, and drops the
features whose variance is below it. Our features are min/max quantised to ``b`` bits
before the grid codec, so an HEVC step of ``Qstep(QP)`` sample units is an absolute step
``Qstep(QP) * range_i / (2^b - 1)`` on feature ``i``; a unit error on feature ``i`` costs
``weight_i`` squared AC units in the rendered colour (:meth:`ShStage.feature_weights`).
Equal weighted steps, ``sqrt(weight_i) * range_i * Qstep(QP_i)`` constant, give

    QP_i = QP_base + 6 log2( s_0 / s_i ),     s_i = sqrt(weight_i) * range_i,

(``Qstep`` doubles every 6 QP), with ``QP_base`` on the feature of largest ``s``. The
trailing features whose QP would exceed 51 (the last HEVC QP, where the step spans the
whole range) carry nothing worth their bits and are dropped: for SHAC-PCA this picks the
rank M jointly with the QPs, instead of one energy retention for the whole RD curve.
"""

from __future__ import annotations

import numpy as np

#: The largest HEVC QP.
MAX_QP = 51
#: The step of a fractional water-filling base QP (rate points and the rate controller's choices).
BASE_QP_STEP = 0.25


def waterfill_qps(ranges: np.ndarray, weights: np.ndarray | None, base_qp: float) -> list[int]:
    """Per-feature QPs for the kept features (a prefix: trailing features above :data:`MAX_QP` are dropped).

    ``base_qp`` may be fractional (a multiple of :data:`BASE_QP_STEP` in rate points): each feature's
    QP is still ``QP_base + offset`` rounded to an integer, so a base between two integers moves only
    the features whose offsets round up there, a finer step in bytes and error than a whole QP.

    ``ranges``: each feature's quantiser range (max - min); ``weights``: the rendered
    error per unit feature error (None: all equal). At least one feature is kept.
    """
    offsets = waterfill_offsets(ranges, weights)
    if offsets is None:
        return [int(round(base_qp))] * min(1, np.size(ranges))
    qps = np.rint(base_qp + offsets).astype(np.int64)
    keep = int(np.flatnonzero(qps <= MAX_QP).max()) + 1 if np.any(qps <= MAX_QP) else 1
    return [int(min(q, MAX_QP)) for q in qps[:keep]]


def waterfill_offsets(ranges: np.ndarray, weights: np.ndarray | None) -> np.ndarray | None:
    """Each feature's QP above the base, ``6 log2(s_0 / s_i)`` (unrounded); None when no feature has a range."""
    ranges = np.asarray(ranges, dtype=np.float64)
    weights = np.ones_like(ranges) if weights is None else np.asarray(weights, dtype=np.float64)
    strength = np.sqrt(np.maximum(weights, 0.0)) * np.maximum(ranges, 0.0)
    top = float(strength.max()) if strength.size else 0.0
    if top <= 0:
        return None
    with np.errstate(divide="ignore"):
        return 6.0 * np.log2(top / np.maximum(strength, top * 1e-12))


def whole_base_equivalent(ranges: np.ndarray, weights: np.ndarray | None, bases: np.ndarray) -> np.ndarray:
    """For each (possibly fractional) base QP, the base on the whole-QP scale at which the features' QPs
    would be as fine on average: a whole base is itself; between two, the base moves by the mean step
    of the features' QPs (those that can be coded, offset <= :data:`MAX_QP`), so a quarter step that
    moves most features' QPs counts as most of a whole one. The rate controller reads the SH error
    model there: its bytes move feature by feature, and an error model smooth in the base alone made a
    quarter step after many features' QPs rose look cheap."""
    bases = np.asarray(bases, dtype=np.float64)
    offsets = waterfill_offsets(ranges, weights)
    if offsets is None:
        return bases.copy()
    offsets = offsets[offsets <= MAX_QP]
    floor = np.floor(bases)
    moved = np.rint(bases[:, None] + offsets[None, :]) - np.rint(floor[:, None] + offsets[None, :])
    return np.where(bases == floor, bases, floor + moved.mean(axis=1))
