"""The torch render loss: SSIM equals the numpy metric; gradients exist; the loss is 0 at the target."""

import numpy as np
import torch

from gscodec_shac import metrics
from gscodec_shac.train import losses


def test_torch_ssim_equals_metric():
    rng = np.random.default_rng(0)
    a = rng.random((23, 31, 3))
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    value = losses.ssim(torch.tensor(a), torch.tensor(b)).item()
    assert abs(value - metrics.ssim(a, b)) < 1e-10
    assert abs(losses.ssim(torch.tensor(a), torch.tensor(a)).item() - 1.0) < 1e-12


def test_loss_is_zero_at_target_and_has_gradients():
    rng = np.random.default_rng(1)
    target = torch.tensor(rng.random((16, 16, 3)))
    image = (target + 0.05 * torch.randn_like(target)).requires_grad_(True)
    loss = losses.render_loss(image, target)
    loss.backward()
    assert loss.item() > 0 and image.grad is not None and image.grad.abs().sum() > 0
    assert losses.render_loss(target, target).item() < 1e-12
