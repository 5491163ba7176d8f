"""View-dependent Gaussian colours: the SH of :mod:`gscodec_shac.sh` evaluated per camera.

``colour = max(0, 0.5 + sum_k h_k y_k(d))`` with ``d`` the unit vector from the camera centre
to the Gaussian mean (the reference rasteriser's ``computeColorFromSH``). The numba kernel uses
the basis constants of :mod:`gscodec_shac.sh` (degrees 0-4) and is tested against
:func:`gscodec_shac.sh.eval_sh`.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from gscodec_shac.sh import C0, C1, C2, C3, C4

_C2 = np.array(C2)
_C3 = np.array(C3)
_C4 = np.array(C4)


@numba.njit(cache=True, inline="always")
def _basis(x, y, z, degree, c2, c3, c4, out):  # pragma: no cover - compiled
    out[0] = C0
    if degree >= 1:
        out[1] = -C1 * y
        out[2] = C1 * z
        out[3] = -C1 * x
    if degree >= 2:
        xx = x * x
        yy = y * y
        zz = z * z
        xy = x * y
        yz = y * z
        xz = x * z
        out[4] = c2[0] * xy
        out[5] = c2[1] * yz
        out[6] = c2[2] * (2.0 * zz - xx - yy)
        out[7] = c2[3] * xz
        out[8] = c2[4] * (xx - yy)
        if degree >= 3:
            out[9] = c3[0] * y * (3.0 * xx - yy)
            out[10] = c3[1] * xy * z
            out[11] = c3[2] * y * (4.0 * zz - xx - yy)
            out[12] = c3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            out[13] = c3[4] * x * (4.0 * zz - xx - yy)
            out[14] = c3[5] * z * (xx - yy)
            out[15] = c3[6] * x * (xx - 3.0 * yy)
        if degree >= 4:
            out[16] = c4[0] * xy * (xx - yy)
            out[17] = c4[1] * yz * (3.0 * xx - yy)
            out[18] = c4[2] * xy * (7.0 * zz - 1.0)
            out[19] = c4[3] * yz * (7.0 * zz - 3.0)
            out[20] = c4[4] * (zz * (35.0 * zz - 30.0) + 3.0)
            out[21] = c4[5] * xz * (7.0 * zz - 3.0)
            out[22] = c4[6] * (xx - yy) * (7.0 * zz - 1.0)
            out[23] = c4[7] * xz * (xx - 3.0 * yy)
            out[24] = c4[8] * (xx * (xx - 3.0 * yy) - yy * (3.0 * xx - yy))


_CHUNK = 1024


@numba.njit(cache=True, parallel=True)
def _colors_kernel(means, sh_dc, sh_rest, center, mask, c2, c3, c4, out, col0):  # pragma: no cover - compiled
    n = means.shape[0]
    n_rest = sh_rest.shape[1]
    degree = 0
    while (degree + 1) * (degree + 1) - 1 < n_rest:
        degree += 1
    n_chunks = (n + _CHUNK - 1) // _CHUNK
    for chunk in numba.prange(n_chunks):
        basis = np.empty(25)
        for i in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            if not mask[i]:
                continue
            dx = np.float64(means[i, 0]) - center[0]
            dy = np.float64(means[i, 1]) - center[1]
            dz = np.float64(means[i, 2]) - center[2]
            norm = math.sqrt(dx * dx + dy * dy + dz * dz)
            if norm > 0.0:
                dx /= norm
                dy /= norm
                dz /= norm
            else:
                dx, dy, dz = 0.0, 0.0, 1.0
            _basis(dx, dy, dz, degree, c2, c3, c4, basis)
            for ch in range(3):
                acc = basis[0] * np.float64(sh_dc[i, ch])
                for k in range(n_rest):
                    acc += basis[k + 1] * np.float64(sh_rest[i, k, ch])
                out[i, col0 + ch] = max(0.0, acc + 0.5)


def view_colors(
    means: np.ndarray, sh_dc: np.ndarray, sh_rest: np.ndarray, center: np.ndarray,
    mask: np.ndarray | None = None, out: np.ndarray | None = None, column: int = 0,
) -> np.ndarray:
    """Clamped SH colours seen from ``center`` for the rows in ``mask`` (others untouched).

    Written to ``out[:, column:column + 3]`` when ``out`` (a C-contiguous float64 (N, K) array)
    is given, else into a new (N, 3) zero array, which is returned.
    """
    n = means.shape[0]
    if mask is None:
        mask = np.ones(n, dtype=np.bool_)
    if out is None:
        out = np.zeros((n, 3))
    if out.ndim != 2 or out.shape[0] != n or not 0 <= column <= out.shape[1] - 3 or not out.flags.c_contiguous:
        raise ValueError("view_colors: out must be a C-contiguous (N, K) array with room for 3 columns")
    _colors_kernel(
        means, sh_dc, sh_rest, np.asarray(center, dtype=np.float64), mask.astype(np.bool_, copy=False),
        _C2, _C3, _C4, out, column,
    )
    return out
