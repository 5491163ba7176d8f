"""A dense, slow, obviously-correct renderer for tests: every pixel against every Gaussian.

Plain numpy float64, written independently of the numba kernels but with the same math and
pixel convention (see :mod:`gscodec_shac.render.projection`): the reference's culling (near
plane 0.2, non-positive determinant, empty tile rectangle), EWA projection with the 1.3x clamped
Jacobian, 0.3 dilation, 3-sigma radius and tile rectangle (a Gaussian reaches a pixel only when
the pixel's 16x16 tile lies in its rectangle), colours from :func:`gscodec_shac.sh.eval_sh`, one
stable depth sort (float32 depths, ties by index, as the reference's keys), and per-pixel
front-to-back blending with the alpha cap 0.99, the 1/255 skip and the stop before
accumulating when ``T (1 - alpha) < 1e-4``. Cost O(H W N): keep scenes small.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from gscodec_shac import sh
from gscodec_shac.camera import Camera
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.geometry import covariances

_TILE = 16


@dataclass
class ReferenceResult:
    """``image`` (H, W, 3), ``alpha`` (H, W), ``trans`` (H*W,) final T, ``weights`` (H*W, N) or None."""

    image: np.ndarray
    alpha: np.ndarray
    trans: np.ndarray
    colors: np.ndarray
    weights: np.ndarray | None


def render_reference(
    cloud: GaussianCloud,
    camera: Camera,
    *,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    return_weights: bool = False,
) -> ReferenceResult:
    """Render densely; with ``return_weights`` also the (H*W, N) blending weights ``alpha * T``."""
    n = cloud.num_gaussians
    width, height = camera.width, camera.height
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    means = cloud.means.astype(np.float64)
    cam = means @ camera.R.T + camera.t
    z = cam[:, 2]
    keep = z > 0.2
    z_safe = np.where(keep, z, 1.0)

    # Jacobian of (fx x/z + cx, fy y/z + cy), with x/z and y/z clamped to 1.3x the frustum.
    x_lim = (cx / fx + 0.15 * width / fx, (width - cx) / fx + 0.15 * width / fx)
    y_lim = (cy / fy + 0.15 * height / fy, (height - cy) / fy + 0.15 * height / fy)
    tx = np.clip(cam[:, 0] / z_safe, -x_lim[0], x_lim[1]) * z_safe
    ty = np.clip(cam[:, 1] / z_safe, -y_lim[0], y_lim[1]) * z_safe
    jac = np.zeros((n, 2, 3))
    jac[:, 0, 0] = fx / z_safe
    jac[:, 0, 2] = -fx * tx / z_safe**2
    jac[:, 1, 1] = fy / z_safe
    jac[:, 1, 2] = -fy * ty / z_safe**2
    m = jac @ camera.R
    cov2 = m @ covariances(cloud.scales, cloud.quats) @ np.swapaxes(m, 1, 2)
    cov2[:, 0, 0] += 0.3
    cov2[:, 1, 1] += 0.3
    det = cov2[:, 0, 0] * cov2[:, 1, 1] - cov2[:, 0, 1] ** 2
    keep &= det > 0
    det_safe = np.where(det > 0, det, 1.0)
    con_a = cov2[:, 1, 1] / det_safe
    con_b = -cov2[:, 0, 1] / det_safe
    con_c = cov2[:, 0, 0] / det_safe
    mid = 0.5 * (cov2[:, 0, 0] + cov2[:, 1, 1])
    root = np.sqrt(np.maximum(0.1, mid * mid - det))
    radius = np.ceil(3.0 * np.sqrt(np.maximum(mid + root, mid - root)))
    px = fx * cam[:, 0] / z_safe + cx - 0.5
    py = fy * cam[:, 1] / z_safe + cy - 0.5

    grid_x = (width + _TILE - 1) // _TILE
    grid_y = (height + _TILE - 1) // _TILE

    def tile_bound(value: np.ndarray, grid: int) -> np.ndarray:  # C's (int) cast, then clamp
        return np.clip(np.trunc(value / _TILE), 0, grid).astype(np.int64)

    rx0, rx1 = tile_bound(px - radius, grid_x), tile_bound(px + radius + _TILE - 1, grid_x)
    ry0, ry1 = tile_bound(py - radius, grid_y), tile_bound(py + radius + _TILE - 1, grid_y)
    keep &= (rx1 - rx0) * (ry1 - ry0) != 0

    colors = np.zeros((n, 3))
    directions = means - camera.center
    colors[keep] = sh.eval_sh(cloud.sh_coefficients()[keep], directions[keep])
    opacity = cloud.activated_opacities()

    visible = np.flatnonzero(keep)
    order = visible[np.argsort(z[visible].astype(np.float32), kind="stable")]  # float32 keys, ties by index
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    xs, ys = xs.ravel(), ys.ravel()
    tile_x, tile_y = xs.astype(np.int64) // _TILE, ys.astype(np.int64) // _TILE
    trans = np.ones(width * height)
    color = np.zeros((width * height, 3))
    done = np.zeros(width * height, dtype=bool)
    weights = np.zeros((width * height, n)) if return_weights else None
    for g in order:
        in_rect = (tile_x >= rx0[g]) & (tile_x < rx1[g]) & (tile_y >= ry0[g]) & (tile_y < ry1[g])
        dx = px[g] - xs
        dy = py[g] - ys
        power = -0.5 * (con_a[g] * dx * dx + con_c[g] * dy * dy) - con_b[g] * dx * dy
        alpha = np.minimum(0.99, opacity[g] * np.exp(np.minimum(power, 0.0)))
        passes = in_rect & ~done & (power <= 0.0) & (alpha >= 1.0 / 255.0)
        t_next = trans * (1.0 - alpha)
        stop = passes & (t_next < 1e-4)
        done |= stop
        accumulate = passes & ~stop
        w = np.where(accumulate, alpha * trans, 0.0)
        color += w[:, None] * colors[g]
        trans = np.where(accumulate, t_next, trans)
        if weights is not None:
            weights[:, g] = w
    bg = np.asarray(background, dtype=np.float64)
    image = (color + trans[:, None] * bg).reshape(height, width, 3)
    return ReferenceResult(image, (1.0 - trans).reshape(height, width), trans, colors, weights)
