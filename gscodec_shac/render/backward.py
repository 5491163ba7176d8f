"""Differentiable rendering on the CPU: a forward pass that keeps what the backward needs, and
the full backward pass (pixels -> 2D Gaussians -> 3D parameters), all numba.

:class:`DiffRenderer` renders raw (pre-activation) parameter arrays with exactly the math of
:mod:`gscodec_shac.render` (it reuses the projection, binning and blending kernels) and returns
a :class:`ForwardState`; :meth:`DiffRenderer.backward` turns ``dL/dimage`` into gradients for
every parameter group (:class:`ParamGrads`): means, log-scales, quaternions (unnormalised,
w first), opacity logits, SH DC and SH rest.

**Raster backward** (per 16x16 tile, Gaussian-outer like the forward): each pixel starts from
its final transmittance ``T`` and its ``last`` contributor and walks its list back to front,
recovering ``T_i = T_{i+1} / (1 - alpha_i)`` and the colour behind entry ``i``,
``B_i = alpha_{i+1} c_{i+1} + (1 - alpha_{i+1}) B_{i+1}`` (``B = background`` behind the last
contributor), so that ``dC/dalpha_i = T_i (c_i - B_i)`` and ``dC/dc_i = alpha_i T_i``. Through
``alpha = o exp(power)`` this gives the 2D mean, conic and opacity gradients. Tiles are split
into :data:`LANES` fixed interleaved lanes (tile ``t`` belongs to lane ``t % LANES``) that run in
parallel, each with its own gradient buffer; the lanes are summed in a fixed order afterwards,
so results are bit-identical from run to run whatever the thread scheduling.

**Preprocess backward** (per Gaussian): conic -> 2D covariance (``dS = -S^-1 dS^-1 S^-1``),
``cov2 = (J W) Sigma (J W)^T`` -> ``Sigma`` and the Jacobian ``J`` (which depends on the camera-
space mean), ``Sigma = R S S^T R^T`` (eq. 2) -> log-scales and the normalised quaternion ->
the raw quaternion; the 2D mean -> camera-space mean -> world mean; SH colour (clamped at 0:
no gradient through a clamped channel) -> coefficients and the viewing direction -> mean.

**Where these are the exact derivatives rather than the reference CUDA's.** Two places where
the reference 3DGS backward deviates from the derivative of its own forward are done exactly
here (finite differences agree): (1) ``alpha = min(0.99, o G)``: a clamped alpha passes no
gradient to ``o`` or ``G`` (gsplat does the same; the original CUDA ignores the clamp);
(2) the Jacobian clamp: where ``x/z`` is clamped, ``J_02 = -fx * limit / z`` and its derivative
is ``fx * limit / z^2`` (the original treats the clamped ``t_x`` as a constant and gets twice
that). Both only touch rare or boundary cases.

**View-space gradient** (densification): :attr:`ParamGrads.means2d_ndc_norm` is
``|(dL/dx * W/2, dL/dy * H/2)|`` with ``(x, y)`` the pixel-space mean, i.e. the norm of the
gradient w.r.t. the NDC mean, which is what the reference accumulates (its screen-space point
is in NDC; ``pixel = ((ndc + 1) W - 1) / 2``) and what its threshold 0.0002 refers to.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numba
import numpy as np

from gscodec_shac.camera import Camera
from gscodec_shac.render.binning import TileBins, bin_gaussians
from gscodec_shac.render.projection import (
    ALPHA_MIN,
    BLOCK,
    DILATION,
    P_A,
    P_B,
    P_BLUE,
    P_C,
    P_DETC,
    P_G,
    P_HY,
    P_OPACITY,
    P_R,
    P_STEP,
    P_TAU,
    P_X,
    P_Y,
    CameraParams,
    alpha_extent,
    camera_params,
    project_into,
)
from gscodec_shac.render.raster import ALPHA_MAX, rasterize, tile_pixels
from gscodec_shac.render.renderer import _Workspace
from gscodec_shac.render.shading import view_colors
from gscodec_shac.sh import C0, C1, C2, C3

#: Fixed number of tile lanes of the raster backward (see the module docstring).
LANES = 4
#: Columns of the per-entry 2D gradient rows: mean x, y; conic a, b, c; opacity; colour r, g, b.
G_X, G_Y, G_A, G_B, G_C, G_O, G_R, G_G, G_BL = range(9)
GRAD_WIDTH = 9
#: Highest SH degree the backward supports (training uses 0-3).
MAX_DEGREE = 3
_CHUNK = 512

_C2 = np.array(C2)
_C3 = np.array(C3)


# --------------------------------------------------------------------------- forward helpers
@numba.njit(cache=True, parallel=True)
def _cov3_kernel(log_scales, quats, out):  # pragma: no cover - compiled
    """(N, 6) upper covariances (xx, xy, xz, yy, yz, zz) of ``R S S^T R^T`` (eq. 2)."""
    for i in numba.prange(log_scales.shape[0]):
        w = np.float64(quats[i, 0])
        x = np.float64(quats[i, 1])
        y = np.float64(quats[i, 2])
        z = np.float64(quats[i, 3])
        norm = math.sqrt(w * w + x * x + y * y + z * z)
        if norm > 0.0:
            w /= norm
            x /= norm
            y /= norm
            z /= norm
        else:
            w, x, y, z = 1.0, 0.0, 0.0, 0.0
        s0 = math.exp(np.float64(log_scales[i, 0]))
        s1 = math.exp(np.float64(log_scales[i, 1]))
        s2 = math.exp(np.float64(log_scales[i, 2]))
        m00 = (1.0 - 2.0 * (y * y + z * z)) * s0
        m01 = 2.0 * (x * y - w * z) * s1
        m02 = 2.0 * (x * z + w * y) * s2
        m10 = 2.0 * (x * y + w * z) * s0
        m11 = (1.0 - 2.0 * (x * x + z * z)) * s1
        m12 = 2.0 * (y * z - w * x) * s2
        m20 = 2.0 * (x * z - w * y) * s0
        m21 = 2.0 * (y * z + w * x) * s1
        m22 = (1.0 - 2.0 * (x * x + y * y)) * s2
        out[i, 0] = m00 * m00 + m01 * m01 + m02 * m02
        out[i, 1] = m00 * m10 + m01 * m11 + m02 * m12
        out[i, 2] = m00 * m20 + m01 * m21 + m02 * m22
        out[i, 3] = m10 * m10 + m11 * m11 + m12 * m12
        out[i, 4] = m10 * m20 + m11 * m21 + m12 * m22
        out[i, 5] = m20 * m20 + m21 * m21 + m22 * m22


def covariances_upper(log_scales: np.ndarray, quats: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(N, 6) float64 upper triangles of the 3D covariances (same math as :func:`geometry.covariances`)."""
    if out is None:
        out = np.empty((log_scales.shape[0], 6))
    _cov3_kernel(log_scales, quats, out)
    return out


def sigmoid(x: np.ndarray) -> np.ndarray:
    """float64 logistic function."""
    return 1.0 / (1.0 + np.exp(-np.asarray(x, dtype=np.float64)))


# --------------------------------------------------------------------------- raster backward
@numba.njit(cache=True, parallel=True)
def _raster_backward_kernel(
    tile_start, ids, pack, width, height, tiles_x, t_final, last, dl_dpix, bg, lanes,
):  # pragma: no cover - compiled
    n_lanes = lanes.shape[0]
    n_tiles = tile_start.shape[0] - 1
    npix = BLOCK * BLOCK
    for lane in numba.prange(n_lanes):
        out = lanes[lane]
        trans = np.empty(npix)
        back_r = np.empty(npix)
        back_g = np.empty(npix)
        back_b = np.empty(npix)
        gr = np.empty(npix)
        gg = np.empty(npix)
        gb = np.empty(npix)
        count = np.zeros(npix, dtype=np.int64)
        for tile in range(lane, n_tiles, n_lanes):
            x0, y0, x1, y1 = tile_pixels(tile, tiles_x, width, height)
            max_last = 0
            for yy in range(y0, y1 + 1):
                for xx in range(x0, x1 + 1):
                    p = (yy - y0) * BLOCK + xx - x0
                    pix = yy * width + xx
                    trans[p] = t_final[pix]
                    back_r[p] = bg[0]
                    back_g[p] = bg[1]
                    back_b[p] = bg[2]
                    gr[p] = dl_dpix[pix, 0]
                    gg[p] = dl_dpix[pix, 1]
                    gb[p] = dl_dpix[pix, 2]
                    count[p] = last[pix]
                    if last[pix] > max_last:
                        max_last = last[pix]
            start = tile_start[tile]
            for j in range(max_last - 1, -1, -1):
                s = ids[start + j]
                mx = pack[s, P_X]
                my = pack[s, P_Y]
                a = pack[s, P_A]
                b = pack[s, P_B]
                c = pack[s, P_C]
                opacity = pack[s, P_OPACITY]
                tau = pack[s, P_TAU]
                hy = pack[s, P_HY]
                detc = pack[s, P_DETC]
                step = pack[s, P_STEP]
                cr = pack[s, P_R]
                cg = pack[s, P_G]
                cb = pack[s, P_BLUE]
                inv_a = 1.0 / a
                acc_x = 0.0
                acc_y = 0.0
                acc_a = 0.0
                acc_b = 0.0
                acc_c = 0.0
                acc_o = 0.0
                acc_r = 0.0
                acc_g = 0.0
                acc_bl = 0.0
                touched = False
                row_lo = max(y0, math.ceil(my - hy))
                row_hi = min(y1, math.floor(my + hy))
                for py in range(row_lo, row_hi + 1):
                    v = py - my
                    disc = a * tau - detc * v * v
                    if disc < 0.0:
                        continue
                    root = math.sqrt(disc)
                    x_lo = max(x0, math.ceil(mx - (b * v + root) * inv_a))
                    x_hi = min(x1, math.floor(mx - (b * v - root) * inv_a))
                    if x_lo > x_hi:
                        continue
                    dy = my - py
                    dx = mx - x_lo
                    g = opacity * math.exp(-0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy)
                    ratio = math.exp(a * dx - 0.5 * a + b * dy)
                    p = (py - y0) * BLOCK + (x_lo - x0)
                    for px in range(x_lo, x_hi + 1):
                        if j < count[p]:
                            alpha = min(ALPHA_MAX, g)
                            if alpha >= ALPHA_MIN:
                                touched = True
                                t_i = trans[p] / (1.0 - alpha)
                                w = alpha * t_i
                                acc_r += w * gr[p]
                                acc_g += w * gg[p]
                                acc_bl += w * gb[p]
                                dl_dalpha = t_i * (
                                    (cr - back_r[p]) * gr[p] + (cg - back_g[p]) * gg[p] + (cb - back_b[p]) * gb[p]
                                )
                                back_r[p] = alpha * cr + (1.0 - alpha) * back_r[p]
                                back_g[p] = alpha * cg + (1.0 - alpha) * back_g[p]
                                back_b[p] = alpha * cb + (1.0 - alpha) * back_b[p]
                                trans[p] = t_i
                                if g < ALPHA_MAX:  # a clamped alpha has no gradient w.r.t. o or G
                                    acc_o += (g / opacity) * dl_dalpha
                                    dpow = g * dl_dalpha
                                    ex = mx - px
                                    acc_x -= dpow * (a * ex + b * dy)
                                    acc_y -= dpow * (c * dy + b * ex)
                                    acc_a -= 0.5 * dpow * ex * ex
                                    acc_b -= dpow * ex * dy
                                    acc_c -= 0.5 * dpow * dy * dy
                        g *= ratio
                        ratio *= step
                        p += 1
                if touched:
                    out[s, G_X] += acc_x
                    out[s, G_Y] += acc_y
                    out[s, G_A] += acc_a
                    out[s, G_B] += acc_b
                    out[s, G_C] += acc_c
                    out[s, G_O] += acc_o
                    out[s, G_R] += acc_r
                    out[s, G_G] += acc_g
                    out[s, G_BL] += acc_bl


# --------------------------------------------------------------------------- SH helpers
@numba.njit(cache=True, inline="always")
def _sh_basis_grad(x, y, z, degree, c2, c3, val, dx, dy, dz):  # pragma: no cover - compiled
    """Basis values and their partial derivatives w.r.t. the (unnormalised-treated) x, y, z."""
    val[0] = C0
    dx[0] = 0.0
    dy[0] = 0.0
    dz[0] = 0.0
    if degree >= 1:
        val[1] = -C1 * y
        dx[1] = 0.0
        dy[1] = -C1
        dz[1] = 0.0
        val[2] = C1 * z
        dx[2] = 0.0
        dy[2] = 0.0
        dz[2] = C1
        val[3] = -C1 * x
        dx[3] = -C1
        dy[3] = 0.0
        dz[3] = 0.0
    if degree >= 2:
        xx = x * x
        yy = y * y
        zz = z * z
        val[4] = c2[0] * x * y
        dx[4] = c2[0] * y
        dy[4] = c2[0] * x
        dz[4] = 0.0
        val[5] = c2[1] * y * z
        dx[5] = 0.0
        dy[5] = c2[1] * z
        dz[5] = c2[1] * y
        val[6] = c2[2] * (2.0 * zz - xx - yy)
        dx[6] = -2.0 * c2[2] * x
        dy[6] = -2.0 * c2[2] * y
        dz[6] = 4.0 * c2[2] * z
        val[7] = c2[3] * x * z
        dx[7] = c2[3] * z
        dy[7] = 0.0
        dz[7] = c2[3] * x
        val[8] = c2[4] * (xx - yy)
        dx[8] = 2.0 * c2[4] * x
        dy[8] = -2.0 * c2[4] * y
        dz[8] = 0.0
        if degree >= 3:
            val[9] = c3[0] * y * (3.0 * xx - yy)
            dx[9] = c3[0] * 6.0 * x * y
            dy[9] = c3[0] * 3.0 * (xx - yy)
            dz[9] = 0.0
            val[10] = c3[1] * x * y * z
            dx[10] = c3[1] * y * z
            dy[10] = c3[1] * x * z
            dz[10] = c3[1] * x * y
            val[11] = c3[2] * y * (4.0 * zz - xx - yy)
            dx[11] = -2.0 * c3[2] * x * y
            dy[11] = c3[2] * (4.0 * zz - xx - 3.0 * yy)
            dz[11] = 8.0 * c3[2] * y * z
            val[12] = c3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            dx[12] = -6.0 * c3[3] * x * z
            dy[12] = -6.0 * c3[3] * y * z
            dz[12] = c3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy)
            val[13] = c3[4] * x * (4.0 * zz - xx - yy)
            dx[13] = c3[4] * (4.0 * zz - 3.0 * xx - yy)
            dy[13] = -2.0 * c3[4] * x * y
            dz[13] = 8.0 * c3[4] * x * z
            val[14] = c3[5] * z * (xx - yy)
            dx[14] = 2.0 * c3[5] * x * z
            dy[14] = -2.0 * c3[5] * y * z
            dz[14] = c3[5] * (xx - yy)
            val[15] = c3[6] * x * (xx - 3.0 * yy)
            dx[15] = c3[6] * 3.0 * (xx - yy)
            dy[15] = -6.0 * c3[6] * x * y
            dz[15] = 0.0


# --------------------------------------------------------------------------- preprocess backward
@numba.njit(cache=True, parallel=True)
def _preprocess_backward_kernel(
    order, lanes, means, log_scales, quats, logits, sh_dc, sh_rest,
    R, t, center, fx, fy, width, height, lx_neg, lx_pos, ly_neg, ly_pos, c2, c3,
    g_means, g_scales, g_quats, g_logits, g_dc, g_rest, g_ndc,
):  # pragma: no cover - compiled
    n_lanes = lanes.shape[0]
    n_rest = sh_rest.shape[1]
    degree = 0
    while (degree + 1) * (degree + 1) - 1 < n_rest:
        degree += 1
    n_entries = order.shape[0]
    n_chunks = (n_entries + _CHUNK - 1) // _CHUNK
    for chunk in numba.prange(n_chunks):
        val = np.empty(16)
        bdx = np.empty(16)
        bdy = np.empty(16)
        bdz = np.empty(16)
        rot = np.empty((3, 3))
        sc = np.empty(3)
        mm = np.empty((3, 3))
        sig = np.empty((3, 3))
        tm = np.empty((2, 3))
        u = np.empty((2, 3))
        gtm = np.empty((2, 3))
        gsig = np.empty((3, 3))
        grot = np.empty((3, 3))
        for k in range(chunk * _CHUNK, min(n_entries, (chunk + 1) * _CHUNK)):
            i = order[k]
            gx = 0.0
            gy = 0.0
            ga = 0.0
            gb = 0.0
            gc = 0.0
            go = 0.0
            gcol0 = 0.0
            gcol1 = 0.0
            gcol2 = 0.0
            for lane in range(n_lanes):
                gx += lanes[lane, k, G_X]
                gy += lanes[lane, k, G_Y]
                ga += lanes[lane, k, G_A]
                gb += lanes[lane, k, G_B]
                gc += lanes[lane, k, G_C]
                go += lanes[lane, k, G_O]
                gcol0 += lanes[lane, k, G_R]
                gcol1 += lanes[lane, k, G_G]
                gcol2 += lanes[lane, k, G_BL]
            g_ndc[i] = math.sqrt((gx * 0.5 * width) ** 2 + (gy * 0.5 * height) ** 2)

            # ---- opacity: o = sigmoid(logit)
            o = 1.0 / (1.0 + math.exp(-np.float64(logits[i])))
            g_logits[i] = go * o * (1.0 - o)

            mx = np.float64(means[i, 0])
            my = np.float64(means[i, 1])
            mz = np.float64(means[i, 2])
            gmx = 0.0
            gmy = 0.0
            gmz = 0.0

            # ---- SH colour: c = max(0, 0.5 + sum h y(d)), d = (m - centre) / |m - centre|
            ddx = mx - center[0]
            ddy = my - center[1]
            ddz = mz - center[2]
            dist = math.sqrt(ddx * ddx + ddy * ddy + ddz * ddz)
            if dist > 0.0:
                ux = ddx / dist
                uy = ddy / dist
                uz = ddz / dist
            else:
                ux, uy, uz = 0.0, 0.0, 1.0
            _sh_basis_grad(ux, uy, uz, degree, c2, c3, val, bdx, bdy, bdz)
            gdx = 0.0
            gdy = 0.0
            gdz = 0.0
            for ch in range(3):
                gch = gcol0 if ch == 0 else (gcol1 if ch == 1 else gcol2)
                raw = val[0] * np.float64(sh_dc[i, ch])
                for q in range(n_rest):
                    raw += val[q + 1] * np.float64(sh_rest[i, q, ch])
                if raw + 0.5 < 0.0:
                    gch = 0.0
                g_dc[i, ch] = gch * val[0]
                for q in range(n_rest):
                    h = np.float64(sh_rest[i, q, ch])
                    g_rest[i, q, ch] = gch * val[q + 1]
                    gdx += gch * h * bdx[q + 1]
                    gdy += gch * h * bdy[q + 1]
                    gdz += gch * h * bdz[q + 1]
            if dist > 0.0:
                dot = gdx * ux + gdy * uy + gdz * uz
                gmx += (gdx - dot * ux) / dist
                gmy += (gdy - dot * uy) / dist
                gmz += (gdz - dot * uz) / dist

            # ---- 3D covariance Sigma = M M^T, M = R(q) diag(s)
            qw = np.float64(quats[i, 0])
            qx = np.float64(quats[i, 1])
            qy = np.float64(quats[i, 2])
            qz = np.float64(quats[i, 3])
            qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            if qn > 0.0:
                w = qw / qn
                x = qx / qn
                y = qy / qn
                z = qz / qn
            else:
                w, x, y, z = 1.0, 0.0, 0.0, 0.0
            rot[0, 0] = 1.0 - 2.0 * (y * y + z * z)
            rot[0, 1] = 2.0 * (x * y - w * z)
            rot[0, 2] = 2.0 * (x * z + w * y)
            rot[1, 0] = 2.0 * (x * y + w * z)
            rot[1, 1] = 1.0 - 2.0 * (x * x + z * z)
            rot[1, 2] = 2.0 * (y * z - w * x)
            rot[2, 0] = 2.0 * (x * z - w * y)
            rot[2, 1] = 2.0 * (y * z + w * x)
            rot[2, 2] = 1.0 - 2.0 * (x * x + y * y)
            for cc in range(3):
                sc[cc] = math.exp(np.float64(log_scales[i, cc]))
            for r in range(3):
                for cc in range(3):
                    mm[r, cc] = rot[r, cc] * sc[cc]
            for r in range(3):
                for cc in range(3):
                    sig[r, cc] = mm[r, 0] * mm[cc, 0] + mm[r, 1] * mm[cc, 1] + mm[r, 2] * mm[cc, 2]

            # ---- camera space and the projection Jacobian (clamped as the forward)
            px = R[0, 0] * mx + R[0, 1] * my + R[0, 2] * mz + t[0]
            py = R[1, 0] * mx + R[1, 1] * my + R[1, 2] * mz + t[1]
            pz = R[2, 0] * mx + R[2, 1] * my + R[2, 2] * mz + t[2]
            inv_z = 1.0 / pz
            rx_raw = px * inv_z
            ry_raw = py * inv_z
            rx = min(lx_pos, max(-lx_neg, rx_raw))
            ry = min(ly_pos, max(-ly_neg, ry_raw))
            clamp_x = rx != rx_raw
            clamp_y = ry != ry_raw
            j00 = fx * inv_z
            j02 = -fx * rx * inv_z
            j11 = fy * inv_z
            j12 = -fy * ry * inv_z
            for cc in range(3):
                tm[0, cc] = j00 * R[0, cc] + j02 * R[2, cc]
                tm[1, cc] = j11 * R[1, cc] + j12 * R[2, cc]
            # cov2 = tm sig tm^T + 0.3 I
            for r in range(2):
                for cc in range(3):
                    u[r, cc] = tm[r, 0] * sig[0, cc] + tm[r, 1] * sig[1, cc] + tm[r, 2] * sig[2, cc]
            c00 = u[0, 0] * tm[0, 0] + u[0, 1] * tm[0, 1] + u[0, 2] * tm[0, 2] + DILATION
            c01 = u[0, 0] * tm[1, 0] + u[0, 1] * tm[1, 1] + u[0, 2] * tm[1, 2]
            c11 = u[1, 0] * tm[1, 0] + u[1, 1] * tm[1, 1] + u[1, 2] * tm[1, 2] + DILATION
            det = c00 * c11 - c01 * c01
            inv_det = 1.0 / det
            ca = c11 * inv_det
            cb = -c01 * inv_det
            ccn = c00 * inv_det
            # dL/dcov2 (symmetric matrix gradient) = -Con G Con, G = [[ga, gb/2], [gb/2, gc]]
            h = 0.5 * gb
            t00 = ca * ga + cb * h
            t01 = ca * h + cb * gc
            t10 = cb * ga + ccn * h
            t11 = cb * h + ccn * gc
            gs00 = -(t00 * ca + t01 * cb)
            gs01 = -(t00 * cb + t01 * ccn)
            gs11 = -(t10 * cb + t11 * ccn)
            # dL/dSigma = tm^T G tm, dL/dtm = 2 G tm Sigma = 2 G u
            for cc in range(3):
                gtm[0, cc] = 2.0 * (gs00 * u[0, cc] + gs01 * u[1, cc])
                gtm[1, cc] = 2.0 * (gs01 * u[0, cc] + gs11 * u[1, cc])
            for r in range(3):
                for cc in range(3):
                    gsig[r, cc] = (
                        tm[0, r] * (gs00 * tm[0, cc] + gs01 * tm[1, cc])
                        + tm[1, r] * (gs01 * tm[0, cc] + gs11 * tm[1, cc])
                    )
            # tm = J W: dL/dJ = dL/dtm W^T (only J00, J02, J11, J12 exist)
            gj00 = gtm[0, 0] * R[0, 0] + gtm[0, 1] * R[0, 1] + gtm[0, 2] * R[0, 2]
            gj02 = gtm[0, 0] * R[2, 0] + gtm[0, 1] * R[2, 1] + gtm[0, 2] * R[2, 2]
            gj11 = gtm[1, 0] * R[1, 0] + gtm[1, 1] * R[1, 1] + gtm[1, 2] * R[1, 2]
            gj12 = gtm[1, 0] * R[2, 0] + gtm[1, 1] * R[2, 1] + gtm[1, 2] * R[2, 2]
            inv_z2 = inv_z * inv_z
            gpx = 0.0
            gpy = 0.0
            gpz = -gj00 * fx * inv_z2 - gj11 * fy * inv_z2
            if clamp_x:
                gpz += gj02 * fx * rx * inv_z2
            else:
                gpx += -gj02 * fx * inv_z2
                gpz += gj02 * 2.0 * fx * px * inv_z2 * inv_z
            if clamp_y:
                gpz += gj12 * fy * ry * inv_z2
            else:
                gpy += -gj12 * fy * inv_z2
                gpz += gj12 * 2.0 * fy * py * inv_z2 * inv_z
            # 2D mean (x = fx px / pz + cx - 0.5)
            gpx += gx * fx * inv_z
            gpy += gy * fy * inv_z
            gpz -= (gx * fx * px + gy * fy * py) * inv_z2
            gmx += R[0, 0] * gpx + R[1, 0] * gpy + R[2, 0] * gpz
            gmy += R[0, 1] * gpx + R[1, 1] * gpy + R[2, 1] * gpz
            gmz += R[0, 2] * gpx + R[1, 2] * gpy + R[2, 2] * gpz
            g_means[i, 0] = gmx
            g_means[i, 1] = gmy
            g_means[i, 2] = gmz

            # ---- Sigma = M M^T: dL/dM = 2 dL/dSigma M; M = R diag(s)
            for cc in range(3):
                gscale = 0.0
                for r in range(3):
                    gm = 2.0 * (gsig[r, 0] * mm[0, cc] + gsig[r, 1] * mm[1, cc] + gsig[r, 2] * mm[2, cc])
                    grot[r, cc] = gm * sc[cc]
                    gscale += gm * rot[r, cc]
                g_scales[i, cc] = gscale * sc[cc]
            if qn > 0.0:
                gw = 2.0 * (-z * grot[0, 1] + y * grot[0, 2] + z * grot[1, 0] - x * grot[1, 2] - y * grot[2, 0] + x * grot[2, 1])
                gxq = 2.0 * (y * grot[0, 1] + z * grot[0, 2] + y * grot[1, 0] - 2.0 * x * grot[1, 1] - w * grot[1, 2]
                             + z * grot[2, 0] + w * grot[2, 1] - 2.0 * x * grot[2, 2])
                gyq = 2.0 * (-2.0 * y * grot[0, 0] + x * grot[0, 1] + w * grot[0, 2] + x * grot[1, 0] + z * grot[1, 2]
                             - w * grot[2, 0] + z * grot[2, 1] - 2.0 * y * grot[2, 2])
                gzq = 2.0 * (-2.0 * z * grot[0, 0] - w * grot[0, 1] + x * grot[0, 2] + w * grot[1, 0] - 2.0 * z * grot[1, 1]
                             + y * grot[1, 2] + x * grot[2, 0] + y * grot[2, 1])
                dot = gw * w + gxq * x + gyq * y + gzq * z
                g_quats[i, 0] = (gw - dot * w) / qn
                g_quats[i, 1] = (gxq - dot * x) / qn
                g_quats[i, 2] = (gyq - dot * y) / qn
                g_quats[i, 3] = (gzq - dot * z) / qn




# --------------------------------------------------------------------------- API
@dataclass
class ForwardState:
    """One differentiable render: the image and what :meth:`DiffRenderer.backward` reuses.

    Arrays (bins, transmittance, last contributor) are views into the renderer's workspace,
    valid until its next :meth:`~DiffRenderer.forward`.
    """

    image: np.ndarray  # (H, W, 3) float64, background included, not clipped
    camera: Camera
    params: CameraParams
    bins: TileBins
    trans: np.ndarray  # (H*W,) final transmittance
    last: np.ndarray  # (H*W,) int32 list entries up to the last contributor
    radii: np.ndarray  # (N,) int32 copy; 0 = culled
    background: np.ndarray
    arrays: tuple  # the parameter arrays rendered (means, log_scales, quats, logits, sh_dc, sh_rest)

    @property
    def visible(self) -> np.ndarray:
        return self.radii > 0


@dataclass
class ParamGrads:
    """Gradients of the loss w.r.t. every parameter array (float64, shapes as the inputs).

    ``means2d_ndc_norm`` (N,) is the view-space gradient norm used by densification (see the
    module docstring); ``visible`` (N,) marks Gaussians with ``radii > 0`` in this view.
    """

    means: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray
    logits: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray
    means2d_ndc_norm: np.ndarray
    visible: np.ndarray
    radii: np.ndarray


class _Buffers(_Workspace):
    """The forward renderer's reused buffers plus those of the backward pass."""

    def __init__(self, n: int) -> None:
        super().__init__(n)
        self.n = n
        self.cov3 = np.empty((n, 6))
        self.lanes = np.empty((LANES, n, GRAD_WIDTH))


class DiffRenderer:
    """Forward + backward rendering of raw parameter arrays (float32 or float64).

    Parameters are passed per call (they change every optimiser step):
    ``means (N, 3)``, ``log_scales (N, 3)``, ``quats (N, 4)`` (w first, any norm),
    ``logits (N,)`` (opacity logits), ``sh_dc (N, 3)``, ``sh_rest (N, K-1, 3)`` (the active SH
    degree: pass only its coefficients; degrees 0-3). Not thread-safe.
    """

    def __init__(self) -> None:
        self._buf: _Buffers | None = None
        #: Seconds of the stages of the last forward / backward (project, colours, binning,
        #: raster; raster_backward, preprocess_backward), filled when set to a dict.
        self.timings: dict[str, float] | None = None

    def _tick(self, name: str, start: float) -> float:
        now = time.perf_counter()
        if self.timings is not None:
            self.timings[name] = now - start
        return now

    def _buffers(self, n: int) -> _Buffers:
        if self._buf is None or self._buf.n != n:
            self._buf = _Buffers(n)
        return self._buf

    def forward(
        self,
        means: np.ndarray,
        log_scales: np.ndarray,
        quats: np.ndarray,
        logits: np.ndarray,
        sh_dc: np.ndarray,
        sh_rest: np.ndarray,
        camera: Camera,
        background: np.ndarray | tuple = (0.0, 0.0, 0.0),
    ) -> ForwardState:
        """Render; the image equals :func:`gscodec_shac.render.render` of the same cloud."""
        n = means.shape[0]
        if sh_rest.ndim != 3 or sh_rest.shape[1] > 15:
            raise ValueError("sh_rest must be (N, K-1, 3) with SH degree <= 3")
        if not sh_rest.flags.c_contiguous:
            sh_rest = np.ascontiguousarray(sh_rest)
        t = time.perf_counter()
        buf = self._buffers(n)
        bg = np.asarray(background, dtype=np.float64).reshape(3)
        cam = camera_params(camera)
        covariances_upper(log_scales, quats, buf.cov3)
        opacity = sigmoid(logits)
        tau = alpha_extent(opacity)
        project_into(means, buf.cov3, opacity, tau, cam, buf.pack_n, buf.rects_n, buf.radii, buf.keys)
        t = self._tick("project", t)
        view_colors(means, sh_dc, sh_rest, cam.center, buf.radii > 0, buf.pack_n, P_R)
        t = self._tick("colours", t)
        bins = bin_gaussians(buf.keys, buf.pack_n, buf.rects_n, cam.width, cam.height, buf.order, buf.pack, buf.rects)
        t = self._tick("binning", t)
        color, trans, _, last = rasterize(bins, cam.width, cam.height, buf.pixels)
        self._tick("raster", t)
        buf.pixels = {"color": color, "trans": trans, "depth": _, "last": last}
        image = (color + trans[:, None] * bg).reshape(cam.height, cam.width, 3)
        return ForwardState(
            image=image, camera=camera, params=cam, bins=bins, trans=trans, last=last,
            radii=buf.radii.copy(), background=bg, arrays=(means, log_scales, quats, logits, sh_dc, sh_rest),
        )

    def backward(self, state: ForwardState, dl_dimage: np.ndarray, dtype: type = np.float64) -> ParamGrads:
        """Gradients of a scalar loss given ``dL/dimage`` (H, W, 3) for the state's render.

        Everything is computed in float64; ``dtype`` is the type of the returned arrays
        (float32 halves the memory traffic of a training step)."""
        cam = state.params
        means, log_scales, quats, logits, sh_dc, sh_rest = state.arrays
        n = means.shape[0]
        buf = self._buffers(n)
        grad = np.ascontiguousarray(np.asarray(dl_dimage, dtype=np.float64).reshape(cam.height * cam.width, 3))
        bins = state.bins
        v = bins.order.shape[0]
        t = time.perf_counter()
        lanes = buf.lanes[:, :v]
        lanes[...] = 0.0
        if v:
            _raster_backward_kernel(
                bins.tile_start, bins.ids, bins.pack, cam.width, cam.height, bins.tiles_x,
                state.trans, state.last, grad, state.background, lanes,
            )
        t = self._tick("raster_backward", t)
        out = ParamGrads(
            means=np.zeros((n, 3), dtype), log_scales=np.zeros((n, 3), dtype), quats=np.zeros((n, 4), dtype),
            logits=np.zeros(n, dtype), sh_dc=np.zeros((n, 3), dtype), sh_rest=np.zeros(sh_rest.shape, dtype),
            means2d_ndc_norm=np.zeros(n),
            visible=state.radii > 0, radii=state.radii,
        )
        if v:
            lx_neg, lx_pos, ly_neg, ly_pos = cam.limits
            _preprocess_backward_kernel(
                bins.order, lanes, means, log_scales, quats, logits, sh_dc, sh_rest,
                cam.R, cam.t, cam.center, cam.fx, cam.fy, cam.width, cam.height, lx_neg, lx_pos, ly_neg, ly_pos,
                _C2, _C3, out.means, out.log_scales, out.quats, out.logits, out.sh_dc, out.sh_rest, out.means2d_ndc_norm,
            )
        self._tick("preprocess_backward", t)
        return out

    def screen_gradients(self, state: ForwardState, dl_dimage: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(order, grads (V, 9))``: the raster backward alone, per depth-sorted entry (for tests)."""
        cam = state.params
        buf = self._buffers(state.arrays[0].shape[0])
        grad = np.ascontiguousarray(np.asarray(dl_dimage, dtype=np.float64).reshape(cam.height * cam.width, 3))
        v = state.bins.order.shape[0]
        lanes = buf.lanes[:, :v]
        lanes[...] = 0.0
        if v:
            _raster_backward_kernel(
                state.bins.tile_start, state.bins.ids, state.bins.pack, cam.width, cam.height, state.bins.tiles_x,
                state.trans, state.last, grad, state.background, lanes,
            )
        return state.bins.order.copy(), lanes.sum(axis=0)
