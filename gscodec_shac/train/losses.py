"""The 3DGS render loss in torch: (1 - lambda) L1 + lambda (1 - SSIM), lambda = 0.2.

SSIM is the differentiable twin of :func:`gscodec_shac.metrics.ssim`: the same
11x11 Gaussian window (sigma 1.5), zero padding of 5, constants C1 = 0.01^2 and
C2 = 0.03^2, mean over pixels and channels. Images are (H, W, 3) or (B, H, W, 3)
float tensors in [0, 1].
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from gscodec_shac.metrics import SSIM_SIGMA, SSIM_WINDOW, gaussian_window

#: Weight of the D-SSIM term in the reference 3DGS loss.
LAMBDA_DSSIM = 0.2
_C1 = 0.01**2
_C2 = 0.03**2


def _as_nchw(image: torch.Tensor) -> torch.Tensor:
    if image.dim() == 3:
        image = image.unsqueeze(0)
    return image.permute(0, 3, 1, 2)


def _window(channels: int, dtype: torch.dtype) -> torch.Tensor:
    w1 = torch.as_tensor(gaussian_window(SSIM_WINDOW, SSIM_SIGMA), dtype=dtype)
    w2 = torch.outer(w1, w1)
    return w2.expand(channels, 1, SSIM_WINDOW, SSIM_WINDOW).contiguous()


def ssim(image: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Differentiable SSIM (scalar tensor), as 3DGS computes it."""
    x, y = _as_nchw(image), _as_nchw(reference)
    channels = x.shape[1]
    window = _window(channels, x.dtype)
    pad = SSIM_WINDOW // 2

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, window, padding=pad, groups=channels)

    mu_x, mu_y = blur(x), blur(y)
    sigma_x = blur(x * x) - mu_x * mu_x
    sigma_y = blur(y * y) - mu_y * mu_y
    sigma_xy = blur(x * y) - mu_x * mu_y
    numerator = (2 * mu_x * mu_y + _C1) * (2 * sigma_xy + _C2)
    denominator = (mu_x * mu_x + mu_y * mu_y + _C1) * (sigma_x + sigma_y + _C2)
    return (numerator / denominator).mean()


def l1(image: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    return (image - reference).abs().mean()


def render_loss(image: torch.Tensor, reference: torch.Tensor, lambda_dssim: float = LAMBDA_DSSIM) -> torch.Tensor:
    """(1 - lambda) L1 + lambda (1 - SSIM): the reference 3DGS photometric loss."""
    return (1.0 - lambda_dssim) * l1(image, reference) + lambda_dssim * (1.0 - ssim(image, reference))
