"""Spherical-harmonics index bookkeeping, in one place.

Conventions (used everywhere in the package):

* Coefficient index ``k = l*l + l + m`` for degree ``l`` and order ``-l <= m <= l``;
  ``k = 0`` is the DC term. A degree-``L`` model has ``(L+1)^2`` coefficients per
  colour channel.
* ``sh_rest`` arrays are *coefficient-major*: shape ``(N, (L+1)^2 - 1, 3)``,
  row ``k - 1`` holds the R, G, B values of coefficient ``k``.
* The paper's AC matrix ``A`` (Sec. IV-B, N x K', K' = 3((L+1)^2 - 1)) puts the R, G, B
  of each (l, m) in adjacent columns: column ``3*(k-1) + c``. It is a plain reshape of
  ``sh_rest``.
* The Inria PLY stores ``f_rest_*`` *channel-major*: all R coefficients, then all G,
  then all B, i.e. ``f_rest_{c*((L+1)^2-1) + (k-1)}``.
"""

from __future__ import annotations

import numpy as np

from gscodec_shac.errors import ValidationError

MAX_SH_DEGREE = 4
CHANNELS = ("R", "G", "B")


def num_coeffs(degree: int) -> int:
    """Number of SH coefficients per channel for degree ``degree``: (L+1)^2."""
    _check_degree(degree)
    return (degree + 1) ** 2


def num_rest_coeffs(degree: int) -> int:
    """Number of AC (l > 0) coefficients per channel: (L+1)^2 - 1."""
    return num_coeffs(degree) - 1


def num_ac_columns(degree: int) -> int:
    """Columns K' of the AC matrix: 3((L+1)^2 - 1) (45 for L = 3)."""
    return 3 * num_rest_coeffs(degree)


def degree_from_rest_count(n_rest: int) -> int:
    """SH degree whose AC part has ``n_rest`` coefficients per channel.

    Raises :class:`ValidationError` when no degree 0..4 fits.
    """
    for degree in range(MAX_SH_DEGREE + 1):
        if num_rest_coeffs(degree) == n_rest:
            return degree
    valid = ", ".join(str(num_rest_coeffs(d)) for d in range(MAX_SH_DEGREE + 1))
    raise ValidationError(
        f"{n_rest} AC coefficients per channel fit no SH degree 0-{MAX_SH_DEGREE} "
        f"(expected one of {valid})"
    )


def coeff_index(l: int, m: int) -> int:
    """Coefficient index k of (l, m)."""
    if l < 0 or abs(m) > l:
        raise ValueError(f"invalid SH index l={l}, m={m}")
    return l * l + l + m


def degree_order(k: int) -> tuple[int, int]:
    """(l, m) of coefficient index k (inverse of :func:`coeff_index`)."""
    if k < 0:
        raise ValueError(f"invalid SH coefficient index {k}")
    l = int(np.floor(np.sqrt(k)))
    return l, k - l * l - l


def ac_column(l: int, m: int, channel: int) -> int:
    """Column of (l, m, channel) in the paper-order AC matrix (l >= 1)."""
    if l < 1:
        raise ValueError("the AC matrix holds degrees l >= 1 only")
    if channel not in (0, 1, 2):
        raise ValueError(f"channel must be 0, 1 or 2, got {channel}")
    return 3 * (coeff_index(l, m) - 1) + channel


def ac_column_labels(degree: int) -> list[str]:
    """Human-readable labels of the AC columns, e.g. ``'l1m-1R'``."""
    labels = []
    for k in range(1, num_coeffs(degree)):
        l, m = degree_order(k)
        labels.extend(f"l{l}m{m}{c}" for c in CHANNELS)
    return labels


def ac_matrix(sh_rest: np.ndarray) -> np.ndarray:
    """AC matrix A (N, K') in paper column order from coefficient-major ``sh_rest``."""
    if sh_rest.ndim != 3 or sh_rest.shape[2] != 3:
        raise ValidationError(f"sh_rest must have shape (N, K-1, 3), got {sh_rest.shape}")
    return sh_rest.reshape(sh_rest.shape[0], -1)


def sh_rest_from_ac(ac: np.ndarray) -> np.ndarray:
    """Inverse of :func:`ac_matrix`: (N, K') -> (N, K'/3, 3)."""
    if ac.ndim != 2 or ac.shape[1] % 3:
        raise ValidationError(f"AC matrix must have shape (N, 3*m), got {ac.shape}")
    degree_from_rest_count(ac.shape[1] // 3)
    return ac.reshape(ac.shape[0], -1, 3)


def inria_rest_from_sh_rest(sh_rest: np.ndarray) -> np.ndarray:
    """Coefficient-major (N, K-1, 3) -> Inria channel-major f_rest (N, 3(K-1))."""
    return np.ascontiguousarray(sh_rest.transpose(0, 2, 1)).reshape(sh_rest.shape[0], -1)


def sh_rest_from_inria_rest(f_rest: np.ndarray) -> np.ndarray:
    """Inria channel-major f_rest (N, 3(K-1)) -> coefficient-major (N, K-1, 3)."""
    if f_rest.ndim != 2 or f_rest.shape[1] % 3:
        raise ValidationError(f"f_rest must have shape (N, 3*m), got {f_rest.shape}")
    n_rest = f_rest.shape[1] // 3
    return np.ascontiguousarray(f_rest.reshape(f_rest.shape[0], 3, n_rest).transpose(0, 2, 1))


def ac_columns_up_to_degree(degree: int) -> np.ndarray:
    """Indices of the AC columns of degrees 1..``degree`` (a prefix, in degree order)."""
    return np.arange(num_ac_columns(degree))


def _check_degree(degree: int) -> None:
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValidationError(f"SH degree must be 0-{MAX_SH_DEGREE}, got {degree}")
