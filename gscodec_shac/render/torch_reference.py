"""A dense, differentiable torch twin of :mod:`gscodec_shac.render.reference` (tests only).

Every pixel against every Gaussian in float64 with autograd, from the raw parameters
(means, log-scales, quaternions, opacity logits, SH DC and rest), with the same math and
discrete decisions as the numba renderer: near-plane / determinant / tile-rectangle culling,
the clamped projection Jacobian, 0.3 dilation, float32 depth sort, alpha cap 0.99, the 1/255
skip and the stop before accumulating when ``T (1 - alpha) < 1e-4``. The decisions are taken on
detached values; everything else is differentiated by torch, so its gradients are an
independent check of :mod:`gscodec_shac.render.backward`. Cost O(H W N): keep scenes tiny.
"""

from __future__ import annotations

import numpy as np
import torch

from gscodec_shac import sh
from gscodec_shac.camera import Camera
from gscodec_shac.render.projection import camera_limits

_TILE = 16


def _basis(d: torch.Tensor, degree: int) -> torch.Tensor:
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    out = [torch.full_like(x, sh.C0)]
    if degree >= 1:
        out += [-sh.C1 * y, sh.C1 * z, -sh.C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        c2 = sh.C2
        out += [c2[0] * x * y, c2[1] * y * z, c2[2] * (2 * zz - xx - yy), c2[3] * x * z, c2[4] * (xx - yy)]
    if degree >= 3:
        c3 = sh.C3
        out += [
            c3[0] * y * (3 * xx - yy), c3[1] * x * y * z, c3[2] * y * (4 * zz - xx - yy),
            c3[3] * z * (2 * zz - 3 * xx - 3 * yy), c3[4] * x * (4 * zz - xx - yy), c3[5] * z * (xx - yy),
            c3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=1)


def _rotations(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm(dim=1, keepdim=True)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=1).reshape(-1, 3, 3)


def render_torch(
    means: torch.Tensor,
    log_scales: torch.Tensor,
    quats: torch.Tensor,
    logits: torch.Tensor,
    sh_dc: torch.Tensor,
    sh_rest: torch.Tensor,
    camera: Camera,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    intermediates: dict[str, torch.Tensor] | None = None,
) -> torch.Tensor:
    """(H, W, 3) float64 image, differentiable w.r.t. every parameter tensor.

    With ``intermediates`` (a dict), the pixel-space 2D means (N, 2) are stored under
    ``"means2d"`` with ``retain_grad()`` so that their gradient can be read after ``backward``.
    """
    width, height = camera.width, camera.height
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    rw = torch.tensor(np.array(camera.R), dtype=torch.float64)
    tw = torch.tensor(np.array(camera.t), dtype=torch.float64)
    cam = means @ rw.T + tw
    z = cam[:, 2]
    keep = (z > 0.2).detach()
    z_safe = torch.where(keep, z, torch.ones_like(z))
    lx_neg, lx_pos, ly_neg, ly_pos = camera_limits(camera)
    rx = torch.clamp(cam[:, 0] / z_safe, -lx_neg, lx_pos)
    ry = torch.clamp(cam[:, 1] / z_safe, -ly_neg, ly_pos)
    zeros = torch.zeros_like(z)
    jac = torch.stack([
        torch.stack([fx / z_safe, zeros, -fx * rx / z_safe], dim=1),
        torch.stack([zeros, fy / z_safe, -fy * ry / z_safe], dim=1),
    ], dim=1)
    m = jac @ rw
    rot = _rotations(quats)
    scaled = rot * torch.exp(log_scales)[:, None, :]
    sigma = scaled @ scaled.transpose(1, 2)
    cov2 = m @ sigma @ m.transpose(1, 2)
    c00 = cov2[:, 0, 0] + 0.3
    c01 = cov2[:, 0, 1]
    c11 = cov2[:, 1, 1] + 0.3
    det = c00 * c11 - c01 * c01
    keep = keep & (det > 0).detach()
    det_safe = torch.where(keep, det, torch.ones_like(det))
    con_a, con_b, con_c = c11 / det_safe, -c01 / det_safe, c00 / det_safe
    px = fx * cam[:, 0] / z_safe + cx - 0.5
    py = fy * cam[:, 1] / z_safe + cy - 0.5
    if intermediates is not None:
        means2d = torch.stack([px, py], dim=1)
        means2d.retain_grad()
        intermediates["means2d"] = means2d
        px, py = means2d[:, 0], means2d[:, 1]

    with torch.no_grad():
        mid = 0.5 * (c00 + c11)
        root = torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
        radius = torch.ceil(3.0 * torch.sqrt(torch.maximum(mid + root, mid - root)))
        grid_x, grid_y = (width + _TILE - 1) // _TILE, (height + _TILE - 1) // _TILE

        def bound(v: torch.Tensor, grid: int) -> torch.Tensor:
            return torch.clamp(torch.trunc(v / _TILE), 0, grid).long()

        rx0, rx1 = bound(px - radius, grid_x), bound(px + radius + _TILE - 1, grid_x)
        ry0, ry1 = bound(py - radius, grid_y), bound(py + radius + _TILE - 1, grid_y)
        keep = keep & ((rx1 - rx0) * (ry1 - ry0) != 0)

    degree = int(round((sh_rest.shape[1] + 1) ** 0.5)) - 1
    dirs = means - torch.tensor(np.array(camera.center), dtype=torch.float64)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    coeffs = torch.cat([sh_dc[:, None, :], sh_rest], dim=1)
    colors = torch.clamp_min((_basis(dirs, degree)[:, :, None] * coeffs).sum(dim=1) + 0.5, 0.0)
    opacity = torch.sigmoid(logits)

    visible = np.flatnonzero(keep.numpy())
    order = visible[np.argsort(z.detach().numpy()[visible].astype(np.float32), kind="stable")]
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                            indexing="ij")
    xs, ys = xs.reshape(-1), ys.reshape(-1)
    tile_x, tile_y = xs.long() // _TILE, ys.long() // _TILE
    trans = torch.ones(width * height, dtype=torch.float64)
    color = torch.zeros(width * height, 3, dtype=torch.float64)
    done = torch.zeros(width * height, dtype=torch.bool)
    for g in order:
        in_rect = (tile_x >= rx0[g]) & (tile_x < rx1[g]) & (tile_y >= ry0[g]) & (tile_y < ry1[g])
        dx = px[g] - xs
        dy = py[g] - ys
        power = -0.5 * (con_a[g] * dx * dx + con_c[g] * dy * dy) - con_b[g] * dx * dy
        alpha = torch.clamp(opacity[g] * torch.exp(power), max=0.99)
        with torch.no_grad():
            passes = in_rect & ~done & (power <= 0.0) & (alpha >= 1.0 / 255.0)
            stop = passes & (trans * (1.0 - alpha) < 1e-4)
            done = done | stop
            accumulate = passes & ~stop
        w = torch.where(accumulate, alpha * trans, torch.zeros_like(trans))
        color = color + w[:, None] * colors[g]
        trans = torch.where(accumulate, trans * (1.0 - alpha), trans)
    bg = torch.as_tensor(background, dtype=torch.float64)
    return (color + trans[:, None] * bg).reshape(height, width, 3)
