"""Post-training quantisation-aware tuning of a dynamic model's deformation network (issue 28).

A network trained in float (here, or on a GPU with Deformable-3DGS) loses 0.1-0.2 dB when
``encode --network-bits 4`` codes it (docs/dynamic.md). This stage keeps the canonical
Gaussians exactly as they are and trains only the network, for a few hundred views, through
the per-row grid that ``encode --network-bits B`` codes each matrix on
(:func:`gscodec_shac.codec.deformation.encoder_grid`; the forward pass sees the grid values,
the gradient passes straight through, :func:`gscodec_shac.deform.fake_quantised_rows`).
The saved network lies on that grid, so ``encode`` recognises it
(:func:`~gscodec_shac.codec.deformation.trained_grid`) and codes what was tuned by plain rounding.

Unlike ``train-dynamic --network-bits`` (quantisation-aware for the last 10% of a whole
training) this needs only the finished model and its training views, and the Gaussians being
frozen, the difference against the float network is the network's alone.

The loss is the training loss of the reference (L1 + D-SSIM against the training view,
:func:`gscodec_shac.train.fastloss.render_loss_and_grad`); the learning rate decays
log-linearly from ``lr`` to ``lr_final`` (Adam, as the deformation network's in training).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Any, Callable

import numpy as np

import gscodec_shac.render  # noqa: F401  (sets OMP_WAIT_POLICY before torch loads OpenMP)
import torch  # noqa: E402

from gscodec_shac.deform import DeformNetwork, DynamicModel, deform_tensors
from gscodec_shac.errors import GscodecError
from gscodec_shac.render.backward import DiffRenderer
from gscodec_shac.train.dynamic import DynamicCapture, log_linear
from gscodec_shac.train.fastloss import render_loss_and_grad
from gscodec_shac.train.losses import LAMBDA_DSSIM


class NetworkTuneError(GscodecError):
    """A tuning setting or model that cannot be used."""


@dataclass
class NetworkTuneConfig:
    """Settings of :func:`tune_network`."""

    #: the coded grid: ``encode --network-bits bits`` (2-7; 8 is already within 0.01 dB); 16: no grid (the
    #: float network trained the same way, the control that isolates the grid's cost).
    bits: int = 4
    #: training views seen (one view per step).
    iterations: int = 600
    lr: float = 1e-4
    lr_final: float = 1e-5
    lambda_dssim: float = LAMBDA_DSSIM
    seed: int = 0

    def validate(self) -> None:
        if not (2 <= self.bits <= 7 or self.bits == 16):
            raise NetworkTuneError(f"--network-bits must be 2-7 for tuning (8 bits already costs at most 0.01 dB) or "
                                   f"16 (float, no grid), got {self.bits}")
        if self.iterations < 1:
            raise NetworkTuneError(f"--iterations must be at least 1, got {self.iterations}")
        if not (self.lr > 0 and self.lr_final > 0):
            raise NetworkTuneError(f"learning rates must be positive, got {self.lr} and {self.lr_final}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class TuneStep:
    """One tuning step: its training loss, the view's PSNR and wall seconds."""

    iteration: int
    loss: float
    psnr: float
    seconds: float


def tune_network(
    model: DynamicModel, capture: DynamicCapture, config: NetworkTuneConfig, *,
    callback: Callable[[TuneStep], None] | None = None,
) -> DynamicModel:
    """A copy of ``model`` whose network was trained through its ``config.bits`` coded grid with the
    Gaussians frozen, then snapped onto that grid (bits 16: trained in float, no grid); the input
    model is not changed."""
    from gscodec_shac.codec.deformation import encoder_grid

    config.validate()
    if not capture.train_cameras:
        raise NetworkTuneError(f"{capture.name}: no training views to tune the network on")
    cloud = model.cloud
    grid = encoder_grid(model.arch, config.bits) if config.bits != 16 else None
    net = DeformNetwork(model.arch)
    net.load_weights(model.net.weights())
    net.grid_bits = grid
    optimizer = torch.optim.Adam(net.parameters(), lr=config.lr, eps=1e-15)
    rng = np.random.default_rng(config.seed)
    renderer = DiffRenderer()
    means = torch.from_numpy(np.ascontiguousarray(cloud.means, dtype=np.float32))
    log_scales = torch.from_numpy(np.ascontiguousarray(cloud.scales, dtype=np.float32))
    quats = torch.from_numpy(np.ascontiguousarray(cloud.quats, dtype=np.float32))
    logits = np.ascontiguousarray(cloud.opacities, dtype=np.float32)
    sh_dc = np.ascontiguousarray(cloud.sh_dc, dtype=np.float32)
    sh_rest = np.ascontiguousarray(cloud.sh_rest, dtype=np.float32)
    order: list[int] = []
    for it in range(1, config.iterations + 1):
        start = time.perf_counter()
        if not order:
            order = list(rng.permutation(len(capture.train_cameras)))
        view = int(order.pop())
        outputs = deform_tensors(net, means, log_scales, quats, capture.train_times[view])
        arrays = [np.ascontiguousarray(x.detach().numpy()) for x in outputs]
        state = renderer.forward(*arrays, logits, sh_dc, sh_rest, capture.train_cameras[view], capture.background)
        truth = capture.train_images[view]
        loss, dl_dimage = render_loss_and_grad(state.image, truth, config.lambda_dssim, dtype=np.float32)
        grads = renderer.backward(state, dl_dimage, dtype=np.float32)
        optimizer.zero_grad(set_to_none=True)
        torch.autograd.backward(list(outputs), [torch.from_numpy(np.ascontiguousarray(g, dtype=np.float32))
                                                for g in (grads.means, grads.log_scales, grads.quats)])
        for group in optimizer.param_groups:
            group["lr"] = log_linear(config.lr, config.lr_final, (it - 1) / max(1, config.iterations - 1))
        optimizer.step()
        if callback is not None:
            mse = float(np.mean((np.clip(state.image, 0.0, 1.0) - truth) ** 2))
            callback(TuneStep(it, float(loss), -10.0 * np.log10(max(mse, 1e-12)), time.perf_counter() - start))
    net.grid_bits = None
    if grid is not None:
        net.snap_to_grid(grid)
    return DynamicModel(cloud, net)
