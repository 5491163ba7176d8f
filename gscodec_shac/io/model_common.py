"""Helpers shared by the Gaussian-model formats (SPZ, .splat, SOG, compressed.ply, checkpoints).

What a reader changes or loses is reported as a :class:`FormatNote` warning with a
count, never as an error: :func:`gscodec_shac.io.models.read_model` collects the notes
and the CLI prints each as one line. The most common one: a format that stores opacity
as an 8-bit alpha gives alpha 0 or 255 an infinite logit, which is clamped to
``+-OPACITY_LOGIT_LIMIT`` (renders the same: sigmoid(20) = 1 - 2e-9).
"""

from __future__ import annotations

import os
import warnings

import numpy as np

from gscodec_shac import sh, sh_index
from gscodec_shac.errors import ModelFormatError
from gscodec_shac.gaussians import GaussianCloud

#: Finite stand-in for an infinite opacity logit (alpha exactly 0 or 1).
OPACITY_LOGIT_LIMIT = 20.0
#: DC SH constant: colour = 0.5 + SH_C0 * f_dc.
SH_C0 = sh.C0


class FormatNote(UserWarning):
    """A counted remark about what reading or writing a format changed (not an error)."""


def note(message: str) -> None:
    """Emit ``message`` as a :class:`FormatNote` (collected by ``read_model``/``write_model``)."""
    warnings.warn(FormatNote(message), stacklevel=3)


def read_bytes(path: str | os.PathLike, what: str) -> bytes:
    """The bytes of ``path`` (at most the memory budget); a missing file or a folder raises naming
    ``what`` was expected (:func:`gscodec_shac.io.bounded.read_file`)."""
    from gscodec_shac.io.bounded import read_file
    from gscodec_shac.limits import memory_budget

    return read_file(path, memory_budget(), what)


def sigmoid(x: np.ndarray) -> np.ndarray:
    """Logistic function in float64."""
    return 1.0 / (1.0 + np.exp(-np.asarray(x, dtype=np.float64)))


def logits_from_alpha(alpha: np.ndarray, path: str | os.PathLike, what: str = "alpha") -> np.ndarray:
    """Opacity logits of alphas in [0, 1] (float32); infinite ones are clamped with a note."""
    a = np.clip(np.asarray(alpha, dtype=np.float64), 0.0, 1.0)
    with np.errstate(divide="ignore"):
        logits = np.log(a) - np.log1p(-a)
    return clamp_logits(logits, path, what)


def clamp_logits(logits: np.ndarray, path: str | os.PathLike, what: str = "alpha") -> np.ndarray:
    """``logits`` with +-inf set to +-:data:`OPACITY_LOGIT_LIMIT`, counted in a note."""
    logits = np.asarray(logits, dtype=np.float64)
    high, low = int(np.sum(logits == np.inf)), int(np.sum(logits == -np.inf))
    if high or low:
        note(
            f"{path}: {high + low:,} infinite opacity logit(s) clamped to +-{OPACITY_LOGIT_LIMIT:g} "
            f"({high:,} with {what} 1, {low:,} with {what} 0)"
        )
        logits = np.clip(logits, -OPACITY_LOGIT_LIMIT, OPACITY_LOGIT_LIMIT)
    return logits.astype(np.float32)


def unit_quats(quats: np.ndarray) -> np.ndarray:
    """Normalised wxyz quaternions (float64); zero ones become the identity."""
    q = np.asarray(quats, dtype=np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))


def round_half_away(values: np.ndarray) -> np.ndarray:
    """Round to the nearest integer, halves away from zero (C's ``round``)."""
    values = np.asarray(values)
    return np.sign(values) * np.floor(np.abs(values) + 0.5)


def to_uint8(values: np.ndarray) -> np.ndarray:
    """Round (halves away from zero) and clamp to 0..255."""
    return np.clip(round_half_away(np.asarray(values, dtype=np.float64)), 0, 255).astype(np.uint8)


def sh_axis_signs(flips: tuple[float, float, float], degree: int) -> np.ndarray:
    """Sign of each AC coefficient (K-1,) under the axis flip ``diag(flips)``.

    Every real SH basis function is odd or even in each coordinate, so flipping axes
    only changes signs: ``y_k(F d) = s_k y_k(d)``. Found by evaluating the basis of
    :mod:`gscodec_shac.sh` at one generic direction.
    """
    direction = np.array([0.26, 0.53, 0.81])
    plain = sh.sh_basis(direction, degree)[1:]
    flipped = sh.sh_basis(direction * np.asarray(flips, dtype=np.float64), degree)[1:]
    return np.sign(flipped / plain).astype(np.float32)


def flip_axes(cloud: GaussianCloud, flips: tuple[float, float, float]) -> GaussianCloud:
    """The same scene seen in a frame whose axes are flipped by ``diag(flips)`` (det +1).

    Positions flip; the rotation R becomes F R F (quaternion x, y, z scaled by the
    products of the other two flips); SH AC coefficients change sign so that every
    direction shows the colour it showed before.
    """
    fx, fy, fz = (float(f) for f in flips)
    if fx * fy * fz != 1.0:
        raise ValueError("flip_axes needs an even number of flipped axes (a rotation)")
    signs = sh_axis_signs((fx, fy, fz), cloud.sh_degree)
    quat_signs = np.array([1.0, fy * fz, fx * fz, fx * fy], dtype=np.float32)
    return cloud.replace(
        means=cloud.means * np.array([fx, fy, fz], dtype=np.float32),
        quats=cloud.quats * quat_signs,
        sh_rest=cloud.sh_rest * signs[None, :, None],
    )


def zero_sh_rest(n: int, degree: int = 0) -> np.ndarray:
    """An all-zero coefficient-major ``sh_rest`` of ``degree``."""
    return np.zeros((n, sh_index.num_rest_coeffs(degree), 3), dtype=np.float32)


def check_rows(path: str | os.PathLike, count: int, what: str) -> None:
    """A model with no Gaussians is an error naming the format."""
    if count <= 0:
        raise ModelFormatError(f"{path}: the {what} holds no Gaussians")
