"""Post-training quantisation-aware tuning of a dynamic model's deformation network (issue 28).

A network trained in float (here, or on a GPU with Deformable-3DGS) loses 0.1-0.2 dB when
``encode --network-bits 4`` codes it (docs/dynamic.md). This stage keeps the canonical
Gaussians exactly as they are and trains only the network on the training views, in two phases:

1. ``float_iterations`` views in float: with the Gaussians fixed, the network still improves
   (on the shared D-NeRF models trained here, by 0.65-0.98 dB of test PSNR in 600 views);
2. ``iterations`` views through the per-row grid that ``encode --network-bits B`` codes each
   matrix on (:func:`gscodec_shac.codec.deformation.encoder_grid`; the forward pass sees the grid
   values, the gradient passes straight through, :func:`gscodec_shac.deform.fake_quantised_rows`),
   then the weights are snapped onto the grid.

``encode`` recognises the saved grid (:func:`~gscodec_shac.codec.deformation.trained_grid`) and
codes what was tuned by plain rounding. Unlike ``train-dynamic --network-bits`` (quantisation-aware
for the last 10% of a whole training) this needs only the finished model and its training views,
and with the Gaussians frozen every difference against the float network is the network's.

The loss is the training loss of the reference (L1 + D-SSIM against the training view,
:func:`gscodec_shac.train.fastloss.render_loss_and_grad`); each phase runs Adam with a learning rate
decaying log-linearly, as the deformation network's in training.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Any, Callable, NamedTuple

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
    """Settings of :func:`tune_network`: ``float_iterations`` views in float, then ``iterations``
    views through the grid (each phase with a fresh Adam and the same seeded view order)."""

    #: the coded grid: ``encode --network-bits bits`` (2-7; 8 is already within 0.01 dB); 16: no grid
    #: phase (the float network alone, the control that isolates the grid's cost).
    bits: int = 4
    #: training views seen in float first (the network improves before it is put on the grid).
    float_iterations: int = 600
    float_lr: float = 1e-4
    float_lr_final: float = 1e-5
    #: training views seen through the grid.
    iterations: int = 300
    lr: float = 3e-5
    lr_final: float = 1e-5
    lambda_dssim: float = LAMBDA_DSSIM
    seed: int = 0

    def validate(self) -> None:
        if not (2 <= self.bits <= 7 or self.bits == 16):
            raise NetworkTuneError(f"--network-bits must be 2-7 for tuning (8 bits already costs at most 0.01 dB) or "
                                   f"16 (float, no grid), got {self.bits}")
        if self.float_iterations < 0 or self.iterations < 0 or self.float_iterations + self.iterations < 1:
            raise NetworkTuneError(f"--float-iterations and --iterations must be >= 0, together at least 1, got "
                                   f"{self.float_iterations} and {self.iterations}")
        if not all(rate > 0 for rate in (self.lr, self.lr_final, self.float_lr, self.float_lr_final)):
            raise NetworkTuneError(f"learning rates must be positive, got {self.float_lr}, {self.float_lr_final}, "
                                   f"{self.lr} and {self.lr_final}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class TuneStep:
    """One tuning step: its phase (``float`` / ``grid``), training loss, the view's PSNR, wall seconds."""

    phase: str
    iteration: int
    loss: float
    psnr: float
    seconds: float


def tune_network(
    model: DynamicModel, capture: DynamicCapture, config: NetworkTuneConfig, *,
    callback: Callable[[TuneStep], None] | None = None,
) -> DynamicModel:
    """A copy of ``model`` whose network was trained with the Gaussians frozen, in float and then
    through its ``config.bits`` coded grid, and snapped onto that grid (bits 16: the float phase
    only); the input model is not changed."""
    from gscodec_shac.codec.deformation import encoder_grid

    config.validate()
    if not capture.train_cameras:
        raise NetworkTuneError(f"{capture.name}: no training views to tune the network on")
    net = DeformNetwork(model.arch)
    net.load_weights(model.net.weights())
    grid = encoder_grid(model.arch, config.bits) if config.bits != 16 else None
    cloud = model.cloud
    tensors = (torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)) for a in (cloud.means, cloud.scales,
                                                                                    cloud.quats))
    gaussians = FrozenGaussians(*tensors, *(np.ascontiguousarray(a, dtype=np.float32)
                                            for a in (cloud.opacities, cloud.sh_dc, cloud.sh_rest)))
    _train_phase(net, gaussians, capture, None, config.float_iterations, config.float_lr, config.float_lr_final,
                 config, "float", callback)
    if grid is not None:
        _train_phase(net, gaussians, capture, grid, config.iterations, config.lr, config.lr_final, config, "grid",
                     callback)
        net.snap_to_grid(grid)
    return DynamicModel(model.cloud, net)


class FrozenGaussians(NamedTuple):
    """The canonical Gaussians as both phases use them: the deformation's inputs as tensors, the rest
    as the rasteriser's float32 arrays."""

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    logits: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray


def _train_phase(
    net: DeformNetwork, gaussians: FrozenGaussians, capture: DynamicCapture, grid: dict[str, int] | None,
    iterations: int, lr: float, lr_final: float, config: NetworkTuneConfig, phase: str,
    callback: Callable[[TuneStep], None] | None,
) -> None:
    """``iterations`` Adam steps of ``net`` (through ``grid`` when given), one training view each in a
    seeded random order, the learning rate decaying log-linearly from ``lr`` to ``lr_final``."""
    if iterations == 0:
        return
    net.grid_bits = grid
    optimizer = torch.optim.Adam(net.parameters(), lr=lr, eps=1e-15)
    rng = np.random.default_rng(config.seed)
    renderer = DiffRenderer()
    g = gaussians
    order: list[int] = []
    for it in range(1, iterations + 1):
        start = time.perf_counter()
        if not order:
            order = list(rng.permutation(len(capture.train_cameras)))
        view = int(order.pop())
        outputs = deform_tensors(net, g.means, g.log_scales, g.quats, capture.train_times[view])
        arrays = [np.ascontiguousarray(x.detach().numpy()) for x in outputs]
        state = renderer.forward(*arrays, g.logits, g.sh_dc, g.sh_rest, capture.train_cameras[view], capture.background)
        truth = capture.train_images[view]
        loss, dl_dimage = render_loss_and_grad(state.image, truth, config.lambda_dssim, dtype=np.float32)
        grads = renderer.backward(state, dl_dimage, dtype=np.float32)
        optimizer.zero_grad(set_to_none=True)
        torch.autograd.backward(list(outputs), [torch.from_numpy(np.ascontiguousarray(g, dtype=np.float32))
                                                for g in (grads.means, grads.log_scales, grads.quats)])
        for group in optimizer.param_groups:
            group["lr"] = log_linear(lr, lr_final, (it - 1) / max(1, iterations - 1))
        optimizer.step()
        if callback is not None:
            mse = float(np.mean((np.clip(state.image, 0.0, 1.0) - truth) ** 2))
            callback(TuneStep(phase, it, float(loss), -10.0 * np.log10(max(mse, 1e-12)), time.perf_counter() - start))
    net.grid_bits = None
