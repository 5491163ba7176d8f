"""The coded attributes: how each one's (N, C) values come out of a cloud and go back.

======== ===================================== =========================================
name     values coded                          transform recorded in the header
======== ===================================== =========================================
positions ``sign(x) log1p(|x|)`` of the means   ``sign_log1p``
rotation unit quaternion, ``w >= 0``            ``unit_w_nonnegative`` (chunks: w | xyz)
rotation or its rotation vector (``form: vector``) ``rotation_vector`` (format 2.4)
scale    log-scales                             ``log_scale``
opacity  logits                                 ``logit``
sh_dc    DC colour (YCbCr when the point says)  ``color``
sh       the SH stage's features                ``sh_stage_features``
======== ===================================== =========================================
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from gscodec_shac.codec import quantize as qz
from gscodec_shac.gaussians import GaussianCloud


@dataclass(frozen=True)
class Attribute:
    """One coded attribute: its values from a cloud and back (``inverse``).

    The values coded are ``column(cloud)`` (the cloud's array, no copy) put through the
    row-wise transform ``rows(ycbcr)`` (``None``: coded as stored), which the encoder
    applies a block of rows at a time; :meth:`forward` is the whole array at once.
    ``rows`` and ``inverse`` take the ``ycbcr`` flag (only the colour uses it).
    ``groups`` fixes the channel runs that form chunks; without it, channels sharing a
    QP form one chunk.
    """

    name: str
    column: Callable[[GaussianCloud], np.ndarray]
    rows: Callable[[bool], qz.RowTransform | None]
    inverse: Callable[[np.ndarray, bool], np.ndarray]
    transform: str
    channels: int
    groups: tuple[tuple[int, int], ...] | None = None

    def forward(self, cloud: GaussianCloud, ycbcr: bool) -> np.ndarray:
        """The (N, C) values coded, whole."""
        values, rows = self.column(cloud), self.rows(ycbcr)
        return values if rows is None else rows(values)


def _dc_inverse(values: np.ndarray, ycbcr: bool) -> np.ndarray:
    return qz.triplets_from_ycbcr(values) if ycbcr else values


ATTRIBUTES: dict[str, Attribute] = {
    a.name: a
    for a in (
        Attribute("positions", lambda c: c.means, lambda _: qz.log_transform,
                  lambda v, _: qz.inverse_log_transform(v), "sign_log1p", 3),
        Attribute("rotation", lambda c: c.quats, lambda _: qz.canonical_quaternions, lambda v, _: v,
                  "unit_w_nonnegative", 4, groups=((0, 1), (1, 4))),
        Attribute("scale", lambda c: c.scales, lambda _: None, lambda v, _: v, "log_scale", 3),
        Attribute("opacity", lambda c: c.opacities[:, None], lambda _: None, lambda v, _: v, "logit", 1),
        Attribute("sh_dc", lambda c: c.sh_dc, lambda ycbcr: qz.triplets_to_ycbcr if ycbcr else None, _dc_inverse,
                  "color", 3),
    )
}
#: The forms a rate point may code the rotation in (``attributes.rotation.form``). A rotation vector
#: (``angle * axis``) is three numbers where the quaternion takes four: 13-15% fewer rotation bytes at
#: the same rendered PSNR on bonsai and the chair (docs/rate_control.md, "Controller version 19").
ROTATION_FORMS: dict[str, Attribute] = {
    "quaternion": ATTRIBUTES["rotation"],
    "vector": Attribute("rotation", lambda c: c.quats, lambda _: qz.rotation_vectors,
                        lambda v, _: qz.quaternions_from_rotation_vectors(v), "rotation_vector", 3),
}
#: The container feature a stream with rotation vectors needs (format 2.4).
ROTATION_VECTOR_FEATURE = "rotation_vector"


def coded_attributes(rotation_form: str = "quaternion") -> dict[str, Attribute]:
    """The attributes an encode codes, in :data:`ATTRIBUTES`' order, the rotation in ``rotation_form``."""
    return {**ATTRIBUTES, "rotation": ROTATION_FORMS[rotation_form]}


def transforms(name: str) -> dict[str, Attribute]:
    """The forms attribute ``name`` may be coded in, by the transform a header records."""
    forms = ROTATION_FORMS.values() if name == "rotation" else (ATTRIBUTES[name],)
    return {form.transform: form for form in forms}


#: The transform name recorded for the SH stage's features.
SH_FEATURES_TRANSFORM = "sh_stage_features"
