"""The 3DGS render loss and its image gradient in numba: ``(1 - l) L1 + l (1 - SSIM)``, l = 0.2.

Numerically the same function as :func:`gscodec_shac.train.losses.render_loss` (the tests
compare value and gradient): SSIM with the 11x11 Gaussian window (sigma 1.5), zero padding,
C1 = 0.01^2, C2 = 0.03^2, mean over pixels and channels. The 2D window is the outer product of
the 1D one, so every blur is two 11-tap passes; the gradient is written out instead of taken
by autograd:

    S = A1 A2 / (B1 B2),  A1 = 2 mx my + C1,  A2 = 2 (Exy - mx my) + C2,
                          B1 = mx^2 + my^2 + C1,  B2 = (Exx - mx^2) + (Eyy - my^2) + C2
    dS/dmx  = S (2 my / A1 - 2 my / A2 - 2 mx / B1 + 2 mx / B2)
    dS/dExx = -S / B2,  dS/dExy = 2 S / A2
    dL/dx   = blur(dL/dmx) + 2 x blur(dL/dExx) + y blur(dL/dExy)

(``mx = blur(x)``, ``Exx = blur(x^2)``, ``Exy = blur(x y)``; the zero-padded blur with a
symmetric window is its own adjoint.) With torch's grouped 11x11 convolution this costs
0.1-0.3 CPU-seconds per 495x371 image here; the separable numba version a small fraction.
"""

from __future__ import annotations

import numba
import numpy as np

from gscodec_shac.metrics import SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW, gaussian_window
from gscodec_shac.train.losses import LAMBDA_DSSIM

_WINDOW = np.ascontiguousarray(gaussian_window(SSIM_WINDOW, SSIM_SIGMA), dtype=np.float64)


@numba.njit(cache=True, parallel=True)
def _blur(src, out, tmp, w):  # pragma: no cover - compiled
    """Zero-padded separable blur of (C, H, W) planes (rows, then columns); taps outer,
    pixels inner so that the inner loops run over contiguous memory."""
    n_planes, h, wd = src.shape
    r = w.shape[0] // 2
    for job in numba.prange(n_planes * h):
        c = job // h
        y = job - c * h
        for x in range(wd):
            tmp[c, y, x] = 0.0
        for k in range(-r, r + 1):
            wk = w[k + r]
            lo = max(0, -k)
            hi = min(wd, wd - k)
            for x in range(lo, hi):
                tmp[c, y, x] += wk * src[c, y, x + k]
    for job in numba.prange(n_planes * h):
        c = job // h
        y = job - c * h
        for x in range(wd):
            out[c, y, x] = 0.0
        for yy in range(max(0, y - r), min(h - 1, y + r) + 1):
            wy = w[yy - y + r]
            for x in range(wd):
                out[c, y, x] += wy * tmp[c, yy, x]


@numba.njit(cache=True, parallel=True)
def _ssim_terms(mx, my, exx, eyy, exy, c1, c2, scale, s_map, gmx, gexx, gexy):  # pragma: no cover - compiled
    n_planes, h, w = mx.shape
    for job in numba.prange(n_planes * h):
        c = job // h
        y = job - c * h
        for x in range(w):
            ux = mx[c, y, x]
            uy = my[c, y, x]
            a1 = 2.0 * ux * uy + c1
            a2 = 2.0 * (exy[c, y, x] - ux * uy) + c2
            b1 = ux * ux + uy * uy + c1
            b2 = (exx[c, y, x] - ux * ux) + (eyy[c, y, x] - uy * uy) + c2
            s = a1 * a2 / (b1 * b2)
            s_map[c, y, x] = s
            gs = scale * s  # d(-lambda mean(S))/dS = scale, times S
            gmx[c, y, x] = gs * (2.0 * uy / a1 - 2.0 * uy / a2 - 2.0 * ux / b1 + 2.0 * ux / b2)
            gexx[c, y, x] = -gs / b2
            gexy[c, y, x] = 2.0 * gs / a2


def render_loss_and_grad(
    image: np.ndarray, target: np.ndarray, lambda_dssim: float = LAMBDA_DSSIM, dtype: type = np.float64
) -> tuple[float, np.ndarray]:
    """``(loss, dL/dimage)`` for (H, W, 3) arrays; see the module docstring.

    ``dtype`` is the working precision (float64: equal to the torch loss to ~1e-15; float32,
    as the trainer uses, to ~1e-6 relative, about twice as fast)."""
    x = np.ascontiguousarray(np.moveaxis(np.asarray(image, dtype=dtype), -1, 0))
    y = np.ascontiguousarray(np.moveaxis(np.asarray(target, dtype=dtype), -1, 0))
    window = _WINDOW.astype(dtype)
    if x.shape != y.shape:
        raise ValueError(f"image and target shapes differ: {image.shape} vs {target.shape}")
    count = x.size
    diff = x - y
    l1 = float(np.abs(diff).mean(dtype=np.float64))
    planes = np.concatenate([x, y, x * x, y * y, x * y])
    blurred = np.empty_like(planes)
    _blur(planes, blurred, np.empty_like(planes), window)
    k = x.shape[0]
    mx, my, exx, eyy, exy = (blurred[i * k:(i + 1) * k] for i in range(5))
    s_map = np.empty_like(x)
    g = np.empty((3 * k,) + x.shape[1:], dtype=x.dtype)
    scale = -lambda_dssim / count
    _ssim_terms(mx, my, exx, eyy, exy, SSIM_C1, SSIM_C2, scale, s_map, g[:k], g[k:2 * k], g[2 * k:])
    gb = np.empty_like(g)
    _blur(g, gb, np.empty_like(g), window)
    grad = gb[:k] + 2.0 * x * gb[k:2 * k] + y * gb[2 * k:]
    grad += np.asarray((1.0 - lambda_dssim) / count, dtype=x.dtype) * np.sign(diff)
    loss = (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - float(s_map.mean(dtype=np.float64)))
    return loss, np.moveaxis(grad, 0, -1)
