"""EWA projection of 3D Gaussians to screen-space ellipses (the reference 3DGS preprocess).

Per Gaussian, for one pinhole :class:`~gscodec_shac.camera.Camera`:

* camera-space centre ``p = R x + t``; culled when ``p_z <= 0.2`` (the reference's near test);
* 2D covariance ``J R Sigma R^T J^T + 0.3 I`` where ``J`` is the Jacobian of the pinhole
  projection at ``p`` with ``p_x / p_z`` and ``p_y / p_z`` clamped to 1.3x the frustum
  half-angles (see :func:`camera_limits`);
* conic (inverse 2D covariance), culled when the determinant is 0 (or, which only rounding of
  absurdly large Gaussians can cause, negative);
* radius ``ceil(3 sqrt(lambda_max))`` with the reference's ``max(0.1, mid^2 - det)`` guard;
* tile rectangle on the 16x16 grid, culled when empty.

**Pixel convention.** Pixel ``(i, j)`` (column, row) is sampled at the *integer* coordinates
``(i, j)`` and a camera-space point projects to ``(fx x/z + cx - 0.5, fy y/z + cy - 0.5)``.
In :meth:`Camera.project` terms (pixel (0, 0) is the top-left corner of the first pixel) each
pixel is sampled at its centre; for ``cx = W/2`` this is the reference's ``((ndc + 1) W - 1) / 2``.

The kernel writes one float64 row per Gaussian (columns ``P_*``) that the binning and raster
stages read; everything is float64 and numba-compiled with ``cache=True``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from gscodec_shac.camera import Camera

#: Tile side in pixels (the reference's BLOCK_X = BLOCK_Y).
BLOCK = 16
#: Near plane of the reference's frustum test: Gaussians with camera z <= NEAR are culled.
NEAR = 0.2
#: Screen-space dilation added to the 2D covariance diagonal (pixels^2).
DILATION = 0.3
#: The projection Jacobian is evaluated with x/z, y/z clamped to this factor times the half-fov.
FOV_CLAMP = 1.3
#: Alpha threshold of the reference (contributions below it are skipped).
ALPHA_MIN = 1.0 / 255.0
#: Relative and absolute enlargement of ``tau`` so rounding never drops a contributing pixel.
TAU_MARGIN = 1e-6

#: Columns of the per-Gaussian parameter rows: mean (x, y); conic (a, b, c) with
#: ``power = -0.5 (a dx^2 + c dy^2) - b dx dy``; activated opacity; ``tau`` (the alpha test can
#: pass only where ``-2 power <= tau``); half extents of that ellipse; ``a c - b^2``;
#: ``exp(-a)``; colour (r, g, b); camera depth.
(P_X, P_Y, P_A, P_B, P_C, P_OPACITY, P_TAU, P_HX, P_HY, P_DETC, P_STEP,
 P_R, P_G, P_BLUE, P_DEPTH) = range(15)
PACK_WIDTH = 16
#: Sort key of Gaussians that cannot contribute (sorted last).
NO_KEY = np.uint64(0xFFFFFFFFFFFFFFFF)


@dataclass(frozen=True)
class CameraParams:
    """Plain numbers of a camera for the kernels (world-to-camera R, t; intrinsics; limits)."""

    R: np.ndarray
    t: np.ndarray
    center: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    limits: tuple[float, float, float, float]


def camera_limits(camera: Camera) -> tuple[float, float, float, float]:
    """``(x_neg, x_pos, y_neg, y_pos)``: clamp range of ``x/z`` and ``y/z`` for the Jacobian.

    The reference clamps to ``+-1.3 tan(fov/2)``, i.e. the frustum edge plus 30% of the
    half-angle tangent. With an off-centre principal point the frustum is asymmetric, so each
    side gets its own edge (``cx/fx`` to the left, ``(W - cx)/fx`` to the right) plus the same
    margin ``0.3 * W / (2 fx)``; for ``cx = W/2`` this is the reference's symmetric clamp.
    """
    margin_x = (FOV_CLAMP - 1.0) * 0.5 * camera.width / camera.fx
    margin_y = (FOV_CLAMP - 1.0) * 0.5 * camera.height / camera.fy
    return (
        camera.cx / camera.fx + margin_x,
        (camera.width - camera.cx) / camera.fx + margin_x,
        camera.cy / camera.fy + margin_y,
        (camera.height - camera.cy) / camera.fy + margin_y,
    )


def camera_params(camera: Camera) -> CameraParams:
    """The kernel-ready numbers of ``camera``."""
    return CameraParams(
        R=np.array(camera.R, dtype=np.float64),  # writable copies: one numba specialisation
        t=np.array(camera.t, dtype=np.float64),
        center=np.array(camera.center, dtype=np.float64),
        fx=float(camera.fx), fy=float(camera.fy), cx=float(camera.cx), cy=float(camera.cy),
        width=int(camera.width), height=int(camera.height),
        limits=camera_limits(camera),
    )


def alpha_extent(opacity: np.ndarray) -> np.ndarray:
    """``tau = 2 ln(255 opacity)`` (slightly enlarged); negative where the alpha test always fails."""
    with np.errstate(divide="ignore"):
        tau = 2.0 * np.log(255.0 * np.asarray(opacity, dtype=np.float64))
    return tau * (1.0 + TAU_MARGIN) + TAU_MARGIN


@dataclass
class Projection:
    """Screen-space Gaussians for one camera; arrays are indexed by Gaussian (length N).

    ``radii == 0`` marks culled Gaussians (their other entries are meaningless); ``rects``
    holds the reference's tile rectangle ``(x0, y0, x1, y1)``, end-exclusive.
    """

    means2d: np.ndarray  # (N, 2) pixel coordinates (x, y)
    conics: np.ndarray  # (N, 3) inverse 2D covariance (a, b, c)
    depths: np.ndarray  # (N,) camera-space z
    radii: np.ndarray  # (N,) int32, 0 = culled
    rects: np.ndarray  # (N, 4) int32

    @property
    def visible(self) -> np.ndarray:
        return self.radii > 0

    def copy(self) -> "Projection":
        return Projection(*(np.array(getattr(self, k)) for k in ("means2d", "conics", "depths", "radii", "rects")))


@numba.njit(cache=True, parallel=True)
def _project_kernel(
    means, cov3, opacity, tau, R, t, fx, fy, cx, cy, width, height, lx_neg, lx_pos, ly_neg, ly_pos,
    pack, rects, radii, keys,
):  # pragma: no cover - compiled
    n = means.shape[0]
    grid_x = (width + BLOCK - 1) // BLOCK
    grid_y = (height + BLOCK - 1) // BLOCK
    for i in numba.prange(n):
        radii[i] = 0
        keys[i] = NO_KEY
        mx = np.float64(means[i, 0])
        my = np.float64(means[i, 1])
        mz = np.float64(means[i, 2])
        px = R[0, 0] * mx + R[0, 1] * my + R[0, 2] * mz + t[0]
        py = R[1, 0] * mx + R[1, 1] * my + R[1, 2] * mz + t[1]
        pz = R[2, 0] * mx + R[2, 1] * my + R[2, 2] * mz + t[2]
        pack[i, P_DEPTH] = pz
        if pz <= NEAR:
            continue
        inv_z = 1.0 / pz
        txz = min(lx_pos, max(-lx_neg, px * inv_z)) * pz
        tyz = min(ly_pos, max(-ly_neg, py * inv_z)) * pz
        j00 = fx * inv_z
        j02 = -fx * txz * inv_z * inv_z
        j11 = fy * inv_z
        j12 = -fy * tyz * inv_z * inv_z
        # M = J R (2 x 3); cov2 = M Sigma M^T
        m00 = j00 * R[0, 0] + j02 * R[2, 0]
        m01 = j00 * R[0, 1] + j02 * R[2, 1]
        m02 = j00 * R[0, 2] + j02 * R[2, 2]
        m10 = j11 * R[1, 0] + j12 * R[2, 0]
        m11 = j11 * R[1, 1] + j12 * R[2, 1]
        m12 = j11 * R[1, 2] + j12 * R[2, 2]
        sxx = cov3[i, 0]
        sxy = cov3[i, 1]
        sxz = cov3[i, 2]
        syy = cov3[i, 3]
        syz = cov3[i, 4]
        szz = cov3[i, 5]
        u0 = m00 * sxx + m01 * sxy + m02 * sxz
        u1 = m00 * sxy + m01 * syy + m02 * syz
        u2 = m00 * sxz + m01 * syz + m02 * szz
        v0 = m10 * sxx + m11 * sxy + m12 * sxz
        v1 = m10 * sxy + m11 * syy + m12 * syz
        v2 = m10 * sxz + m11 * syz + m12 * szz
        c00 = u0 * m00 + u1 * m01 + u2 * m02 + DILATION
        c01 = u0 * m10 + u1 * m11 + u2 * m12
        c11 = v0 * m10 + v1 * m11 + v2 * m12 + DILATION
        det = c00 * c11 - c01 * c01
        if not det > 0.0:  # the reference tests det == 0; with the dilation det >= 0.09 unless rounding fails
            continue
        inv_det = 1.0 / det
        mid = 0.5 * (c00 + c11)
        root = math.sqrt(max(0.1, mid * mid - det))
        radius = math.ceil(3.0 * math.sqrt(max(mid + root, mid - root)))
        x = fx * px * inv_z + cx - 0.5
        y = fy * py * inv_z + cy - 0.5
        # C's (int) cast truncates towards zero; after clamping at 0 that equals floor.
        rx0 = min(grid_x, max(0, int(math.floor((x - radius) / BLOCK))))
        ry0 = min(grid_y, max(0, int(math.floor((y - radius) / BLOCK))))
        rx1 = min(grid_x, max(0, int(math.floor((x + radius + BLOCK - 1) / BLOCK))))
        ry1 = min(grid_y, max(0, int(math.floor((y + radius + BLOCK - 1) / BLOCK))))
        if (rx1 - rx0) * (ry1 - ry0) == 0:
            continue
        a = c11 * inv_det
        b = -c01 * inv_det
        c = c00 * inv_det
        tk = tau[i]
        pack[i, P_X] = x
        pack[i, P_Y] = y
        pack[i, P_A] = a
        pack[i, P_B] = b
        pack[i, P_C] = c
        pack[i, P_OPACITY] = opacity[i]
        pack[i, P_TAU] = tk
        # the ellipse q(d) <= tau spans +-sqrt(tau cov_xx) in x and +-sqrt(tau cov_yy) in y
        pack[i, P_HX] = math.sqrt(max(0.0, tk) * c00)
        pack[i, P_HY] = math.sqrt(max(0.0, tk) * c11)
        pack[i, P_DETC] = inv_det  # a c - b^2 of the conic
        pack[i, P_STEP] = math.exp(-a)
        rects[i, 0] = rx0
        rects[i, 1] = ry0
        rects[i, 2] = rx1
        rects[i, 3] = ry1
        radii[i] = radius
        if tk >= 0.0:
            keys[i] = (_float32_bits(pz) << np.uint64(32)) | np.uint64(i)


@numba.njit(cache=True, inline="always")
def _float32_bits(value):  # pragma: no cover - compiled
    """IEEE bits of ``float32(value)`` for a positive normal value (monotone in the value)."""
    mantissa, exponent = math.frexp(np.float64(np.float32(value)))
    return np.uint64(((exponent + 126) << 23) | int((mantissa * 2.0 - 1.0) * 8388608.0))


def project_into(
    means: np.ndarray, cov3: np.ndarray, opacity: np.ndarray, tau: np.ndarray, cam: CameraParams,
    pack: np.ndarray, rects: np.ndarray, radii: np.ndarray, keys: np.ndarray,
) -> None:
    """Fill the per-Gaussian rows ``pack``, ``rects``, ``radii`` and the depth sort ``keys``.

    ``keys`` are ``float32 depth bits << 32 | index`` for Gaussians that can contribute
    (visible and opacity >= 1/255), ``NO_KEY`` otherwise: sorting them gives the reference's
    order (float32 depth, ties by index).
    """
    lx_neg, lx_pos, ly_neg, ly_pos = cam.limits
    _project_kernel(
        means, cov3, opacity, tau, cam.R, cam.t, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height,
        lx_neg, lx_pos, ly_neg, ly_pos, pack, rects, radii, keys,
    )
