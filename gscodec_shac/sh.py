"""Real spherical-harmonics basis of 3DGS, degrees 0-4 (paper eq. 8).

The constants and signs are those of the reference 3DGS rasteriser (``C0 .. C4``
in its ``forward.cu``; degree 4 as in gsplat). In terms of the complex basis
``Y_l^m`` *with* the Condon-Shortley phase (scipy's convention) the basis is::

    y_l^m = sqrt(2) * Im(Y_l^|m|)   for m < 0
    y_l^0 = Y_l^0
    y_l^m = sqrt(2) * Re(Y_l^m)     for m > 0

which the tests check against ``scipy.special``. The colour of a Gaussian seen
along the unit direction ``d`` (from the camera centre towards the Gaussian) is
``max(0, 0.5 + sum_lm h_lm * y_l^m(d))``, clamped at 0 as the reference
rasteriser does (it clamps only from below).
"""

from __future__ import annotations

import numpy as np

from gscodec_shac import sh_index

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
C4 = (
    2.5033429417967046,
    -1.7701307697799304,
    0.9461746957575601,
    -0.6690465435572892,
    0.10578554691520431,
    -0.6690465435572892,
    0.47308734787878004,
    -1.7701307697799304,
    0.6258357354491761,
)


def sh_basis(directions: np.ndarray, degree: int) -> np.ndarray:
    """Basis values y_k(d) for unit directions (..., 3) -> (..., (degree+1)^2).

    Directions are normalised here; zero vectors give NaN-free output (they are
    treated as +z).
    """
    d = np.asarray(directions, dtype=np.float64)
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    d = np.where(norm > 0, d / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 1.0]))
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = np.empty(d.shape[:-1] + (sh_index.num_coeffs(degree),), dtype=np.float64)
    out[..., 0] = C0
    if degree >= 1:
        out[..., 1] = -C1 * y
        out[..., 2] = C1 * z
        out[..., 3] = -C1 * x
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out[..., 4] = C2[0] * xy
        out[..., 5] = C2[1] * yz
        out[..., 6] = C2[2] * (2.0 * zz - xx - yy)
        out[..., 7] = C2[3] * xz
        out[..., 8] = C2[4] * (xx - yy)
    if degree >= 3:
        out[..., 9] = C3[0] * y * (3.0 * xx - yy)
        out[..., 10] = C3[1] * xy * z
        out[..., 11] = C3[2] * y * (4.0 * zz - xx - yy)
        out[..., 12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
        out[..., 13] = C3[4] * x * (4.0 * zz - xx - yy)
        out[..., 14] = C3[5] * z * (xx - yy)
        out[..., 15] = C3[6] * x * (xx - 3.0 * yy)
    if degree >= 4:
        out[..., 16] = C4[0] * xy * (xx - yy)
        out[..., 17] = C4[1] * yz * (3.0 * xx - yy)
        out[..., 18] = C4[2] * xy * (7.0 * zz - 1.0)
        out[..., 19] = C4[3] * yz * (7.0 * zz - 3.0)
        out[..., 20] = C4[4] * (zz * (35.0 * zz - 30.0) + 3.0)
        out[..., 21] = C4[5] * xz * (7.0 * zz - 3.0)
        out[..., 22] = C4[6] * (xx - yy) * (7.0 * zz - 1.0)
        out[..., 23] = C4[7] * xz * (xx - 3.0 * yy)
        out[..., 24] = C4[8] * (xx * (xx - 3.0 * yy) - yy * (3.0 * xx - yy))
    return out


def eval_sh(coefficients: np.ndarray, directions: np.ndarray, *, clamp: bool = True) -> np.ndarray:
    """Colour of each Gaussian for its viewing direction (paper eq. 8, 3DGS offset and clamp).

    Parameters
    ----------
    coefficients
        (N, (L+1)^2, 3) SH coefficients, DC first (``GaussianCloud.sh_coefficients()``).
    directions
        (N, 3) viewing directions from the camera centre towards each Gaussian.
    clamp
        Clamp the result at 0 from below, as the reference rasteriser does.
    """
    coefficients = np.asarray(coefficients)
    degree = sh_index.degree_from_rest_count(coefficients.shape[1] - 1)
    basis = sh_basis(directions, degree)
    colour = np.einsum("nk,nkc->nc", basis, coefficients.astype(np.float64)) + 0.5
    return np.maximum(colour, 0.0) if clamp else colour


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """DC coefficient that gives colour ``rgb`` (in [0, 1]) with no AC terms."""
    return (np.asarray(rgb, dtype=np.float64) - 0.5) / C0


def sh_dc_to_rgb(dc: np.ndarray) -> np.ndarray:
    """Colour of a DC-only Gaussian: 0.5 + C0 * dc."""
    return np.asarray(dc, dtype=np.float64) * C0 + 0.5


def fit_sh(directions: np.ndarray, values: np.ndarray, degree: int, *, ridge: float = 0.0) -> np.ndarray:
    """Least-squares SH coefficients reproducing ``values`` (..., S, C) sampled at directions (S, 3).

    Solves ``min_h sum_s ||0.5 + y(d_s)^T h - v_s||^2 + ridge ||h||^2`` for each leading
    index with one shared pseudo-inverse; returns (..., (L+1)^2, C).
    """
    basis = sh_basis(directions, degree)  # (S, K)
    gram = basis.T @ basis + ridge * np.eye(basis.shape[1])
    projector = np.linalg.solve(gram, basis.T)  # (K, S)
    return np.einsum("ks,...sc->...kc", projector, np.asarray(values, dtype=np.float64) - 0.5)
