"""The coded attributes: how each one's (N, C) values come out of a cloud and go back.

======== ===================================== =========================================
name     values coded                          transform recorded in the header
======== ===================================== =========================================
positions ``sign(x) log1p(|x|)`` of the means   ``sign_log1p``
rotation unit quaternion, ``w >= 0``            ``unit_w_nonnegative`` (chunks: w | xyz)
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
    """One coded attribute: its values from a cloud (``forward``) and back (``inverse``).

    Both take a ``ycbcr`` flag (only the colour uses it). ``groups`` fixes the channel
    runs that form chunks; without it, channels sharing a QP form one chunk.
    """

    name: str
    forward: Callable[[GaussianCloud, bool], np.ndarray]
    inverse: Callable[[np.ndarray, bool], np.ndarray]
    transform: str
    groups: tuple[tuple[int, int], ...] | None = None


def _dc_forward(cloud: GaussianCloud, ycbcr: bool) -> np.ndarray:
    return qz.triplets_to_ycbcr(cloud.sh_dc) if ycbcr else cloud.sh_dc


def _dc_inverse(values: np.ndarray, ycbcr: bool) -> np.ndarray:
    return qz.triplets_from_ycbcr(values) if ycbcr else values


ATTRIBUTES: dict[str, Attribute] = {
    a.name: a
    for a in (
        Attribute("positions", lambda c, _: qz.log_transform(c.means), lambda v, _: qz.inverse_log_transform(v),
                  "sign_log1p"),
        Attribute("rotation", lambda c, _: qz.canonical_quaternions(c.quats), lambda v, _: v, "unit_w_nonnegative",
                  groups=((0, 1), (1, 4))),
        Attribute("scale", lambda c, _: c.scales, lambda v, _: v, "log_scale"),
        Attribute("opacity", lambda c, _: c.opacities[:, None], lambda v, _: v, "logit"),
        Attribute("sh_dc", _dc_forward, _dc_inverse, "color"),
    )
}
#: The transform name recorded for the SH stage's features.
SH_FEATURES_TRANSFORM = "sh_stage_features"
