"""Dynamic (deformable) 3DGS models: canonical Gaussians + a deformation network.

The model of Deformable 3D Gaussians (Yang et al., CVPR 2024), as SHAC's Table IV codes it:
one set of canonical Gaussians (ordinary SH-3 3DGS) and one MLP, queried per Gaussian and
frame, that maps the canonical centre ``x`` and the frame time ``t`` to offsets
``(dx, dq, ds)``. At time ``t`` a Gaussian is rendered with

* centre ``x + dx``;
* rotation ``q / |q| + dq`` (the rasteriser normalises it again);
* scale ``exp(s) + ds`` (the offset is added to the activated scale, as the reference;
  the rasteriser takes log-scales, so we pass ``log |exp(s) + ds|``: the covariance depends
  on the scale's square only, so this is the same Gaussian).

Network (:class:`DeformNetwork`, sizes in :class:`DeformArch`): NeRF positional encoding
of ``x`` (``L_x = 10`` octaves, input included: 63 values) and of ``t`` (``L_t = 6``: 13
values); for D-NeRF the time code first passes a small time net (13 -> 256 -> 30, ReLU).
``depth`` fully connected ReLU layers of ``width`` with the encoded input concatenated again
after layer ``depth // 2`` (0-based; none when that is the last layer), then three linear heads (3, 4, 3). The reference is ``depth=8,
width=256`` (about 0.52 M weights); ``depth=4, width=128`` is our CPU option. The heads start
at zero (the reference uses PyTorch's default initialisation), so deformation starts as the
identity when it is switched on after the static warm-up.

A dynamic model on disk is a directory (:func:`save_dynamic_model`): ``point_cloud.ply``
(canonical Gaussians, ordinary Inria PLY), ``deformation.npz`` (the weights by name) and
``deformation.json`` (``{"format": "gscodec-shac-deformation", "version": 1, "arch": ...}``).
:func:`load_dynamic_model` also reads the output folder of the reference implementation
(:mod:`gscodec_shac.io.deformable3dgs`), whose network this one expresses exactly.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import gscodec_shac.openmp  # noqa: F401  (sets OMP_WAIT_POLICY before torch loads OpenMP)
import torch  # noqa: E402

from gscodec_shac.deform_arch import (
    ARCH_FILE, MODEL_PLY, WEIGHTS_FILE, DeformArch, is_dynamic_model, is_own_dynamic_model, skip_index,
)
from gscodec_shac.errors import ModelFormatError
from gscodec_shac.gaussians import GaussianCloud

PathLike = str | os.PathLike
ARCH_FORMAT = "gscodec-shac-deformation"
ARCH_VERSION = 1
__all__ = ["DeformArch", "DeformNetwork", "DynamicModel", "deform_tensors", "deformed_cloud", "load_dynamic_model",
           "save_dynamic_model", "is_dynamic_model", "positional_encoding"]
def positional_encoding(x: torch.Tensor, octaves: int) -> torch.Tensor:
    """``[x, sin(2^k x), cos(2^k x)]`` for ``k = 0 .. octaves-1`` (NeRF's encoding), on the last axis."""
    if octaves == 0:
        return x
    freqs = 2.0 ** torch.arange(octaves, dtype=x.dtype)
    scaled = (x[..., None, :] * freqs[:, None]).reshape(*x.shape[:-1], -1)
    return torch.cat([x, torch.sin(scaled), torch.cos(scaled)], dim=-1)


def fake_quantised_rows(weight: torch.Tensor, bits: int) -> torch.Tensor:
    """``weight`` (out, in) on the per-row grid ``lo + code * step`` that ``encode --network-bits``
    codes (``lo``/``step``: each row's minimum and (max - min) / (2^bits - 1), as
    :func:`gscodec_shac.codec.deformation_fit.quantise_rows` before its float16 rounding), rounded
    to the nearest grid point; the gradient passes straight through (quantisation-aware training)."""
    return weight + (grid_values(weight, bits) - weight).detach()


def grid_values(weight: torch.Tensor, bits: int) -> torch.Tensor:
    """The nearest points of :func:`fake_quantised_rows`' per-row grid (no gradient)."""
    with torch.no_grad():
        top = (1 << bits) - 1
        lo = weight.min(dim=1, keepdim=True).values
        step = (weight.max(dim=1, keepdim=True).values - lo) / top
        safe = torch.where(step > 0, step, torch.ones_like(step))
        return lo + torch.round((weight - lo) / safe) * step


class DeformNetwork(torch.nn.Module):
    """The deformation MLP (see the module docstring); ``forward(x (N, 3), t float) -> (dx, dq, ds)``."""

    def __init__(self, arch: DeformArch = DeformArch()) -> None:
        super().__init__()
        self.arch = arch.validate()
        a = arch
        if a.time_net:
            self.time_layers = torch.nn.ModuleList([torch.nn.Linear(a.t_dims, a.time_width),
                                                    torch.nn.Linear(a.time_width, a.time_out)])
        else:
            self.time_layers = torch.nn.ModuleList()
        self.skip = skip_index(a)  # no skip after the last layer
        layers = [torch.nn.Linear(a.input_dims, a.width)]
        for i in range(a.depth - 1):
            layers.append(torch.nn.Linear(a.width + (a.input_dims if i == self.skip else 0), a.width))
        self.layers = torch.nn.ModuleList(layers)
        self.head_xyz = torch.nn.Linear(a.width, 3)
        self.head_rot = torch.nn.Linear(a.width, 4)
        self.head_scale = torch.nn.Linear(a.width, 3)
        with torch.no_grad():
            for head in (self.head_xyz, self.head_rot, self.head_scale):
                head.weight.zero_()
                head.bias.zero_()

    @property
    def n_params(self) -> int:
        return int(sum(p.numel() for p in self.parameters()))

    def time_code(self, t: float, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """(1, C) time feature: encoded ``t``, through the time net for D-NeRF."""
        code = positional_encoding(torch.tensor([[float(t)]], dtype=dtype), self.arch.t_freqs)
        if self.arch.time_net:
            first, second = self.time_layers
            code = self._linear(second, "time_layers.1", torch.relu(self._linear(first, "time_layers.0", code)))
        return code

    def forward(self, x: torch.Tensor, t: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        code = self.time_code(t, x.dtype)
        inputs = torch.cat([positional_encoding(x, self.arch.xyz_freqs), code.expand(x.shape[0], -1)], dim=1)
        h = inputs
        for i, layer in enumerate(self.layers):
            h = torch.relu(self._linear(layer, f"layers.{i}", h))
            if i == self.skip:
                h = torch.cat([inputs, h], dim=1)
        return (self._linear(self.head_xyz, "head_xyz", h), self._linear(self.head_rot, "head_rot", h),
                self._linear(self.head_scale, "head_scale", h))

    # ------------------------------------------------------------------ quantisation-aware training
    #: ``{"layers.0.weight": bits, ...}`` while the forward pass sees the weight matrices on their
    #: coded per-row grids (:func:`fake_quantised_rows`); ``None``: the float weights.
    grid_bits: dict[str, int] | None = None

    def _linear(self, layer: torch.nn.Linear, name: str, h: torch.Tensor) -> torch.Tensor:
        bits = None if self.grid_bits is None else self.grid_bits.get(name + ".weight")
        if bits is None:
            return layer(h)
        return torch.nn.functional.linear(h, fake_quantised_rows(layer.weight, bits), layer.bias)

    def snap_to_grid(self, grid_bits: dict[str, int]) -> None:
        """Replace each named weight matrix by its values on its ``bits``-bit per-row grid (in place)."""
        params = dict(self.named_parameters())
        with torch.no_grad():
            for name, bits in grid_bits.items():
                params[name].copy_(grid_values(params[name], bits))

    # ------------------------------------------------------------------ weights as numpy
    def weights(self) -> dict[str, np.ndarray]:
        """float32 copies of every weight by its parameter name (the order of ``state_dict``)."""
        return {k: v.detach().cpu().numpy().astype(np.float32).copy() for k, v in self.state_dict().items()}

    def load_weights(self, weights: dict[str, np.ndarray], where: str = "deformation weights") -> None:
        expected = self.state_dict()
        if set(weights) != set(expected):
            missing = sorted(set(expected) - set(weights))
            extra = sorted(set(weights) - set(expected))
            raise ModelFormatError(f"{where}: weights do not match the architecture (missing {missing[:4]}, "
                                   f"unexpected {extra[:4]})")
        state = {}
        for key, ref in expected.items():
            value = np.asarray(weights[key])
            if tuple(value.shape) != tuple(ref.shape):
                raise ModelFormatError(f"{where}: {key} has shape {value.shape}, the architecture needs "
                                       f"{tuple(ref.shape)}")
            if not np.all(np.isfinite(value)):
                raise ModelFormatError(f"{where}: {key} holds NaN or infinite values")
            state[key] = torch.from_numpy(np.ascontiguousarray(value, dtype=np.float32))
        self.load_state_dict(state)


def deform_tensors(
    net: DeformNetwork, means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor, t: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Deformed ``(means, log-scales, quats)`` at time ``t`` (differentiable; see the module docstring).

    The network sees the canonical centres with the gradient stopped, as the reference."""
    dx, dq, ds = net(means.detach(), t)
    qn = quats / torch.linalg.norm(quats, dim=1, keepdim=True).clamp_min(1e-12)
    scale = torch.exp(log_scales) + ds
    return means + dx, torch.log(scale.abs().clamp_min(1e-12)), qn + dq


def deformed_cloud(cloud: GaussianCloud, net: DeformNetwork, t: float) -> GaussianCloud:
    """The static :class:`GaussianCloud` the dynamic model shows at time ``t``."""
    with torch.no_grad():
        m, s, q = deform_tensors(
            net, torch.from_numpy(np.ascontiguousarray(cloud.means, dtype=np.float32)),
            torch.from_numpy(np.ascontiguousarray(cloud.scales, dtype=np.float32)),
            torch.from_numpy(np.ascontiguousarray(cloud.quats, dtype=np.float32)), t,
        )
    return GaussianCloud(means=m.numpy(), scales=s.numpy(), quats=q.numpy(), opacities=cloud.opacities,
                         sh_dc=cloud.sh_dc, sh_rest=cloud.sh_rest)


@dataclass
class DynamicModel:
    """Canonical Gaussians + deformation network."""

    cloud: GaussianCloud
    net: DeformNetwork

    def at(self, t: float) -> GaussianCloud:
        return deformed_cloud(self.cloud, self.net, t)

    @property
    def arch(self) -> DeformArch:
        return self.net.arch


def arch_json(arch: DeformArch, extra: dict[str, Any] | None = None) -> str:
    data = {"format": ARCH_FORMAT, "version": ARCH_VERSION, "arch": arch.to_dict(), "weights": WEIGHTS_FILE,
            "canonical": MODEL_PLY}
    data.update(extra or {})
    return json.dumps(data, indent=1)


def read_arch(path: PathLike) -> DeformArch:
    """The architecture recorded in ``deformation.json``."""
    from gscodec_shac.io.bounded import MAX_MODEL_JSON_BYTES, load_json, read_file

    path = Path(path)
    data = load_json(read_file(path, MAX_MODEL_JSON_BYTES, "deformation.json"), str(path))
    if not isinstance(data, dict) or data.get("format") != ARCH_FORMAT:
        raise ModelFormatError(f"{path}: not a gscodec-shac deformation description (format {ARCH_FORMAT!r})")
    if data.get("version") != ARCH_VERSION:
        raise ModelFormatError(f"{path}: deformation description version {data.get('version')!r} is not supported")
    return DeformArch.from_dict(data.get("arch"))


def load_weights_npz(path: PathLike, max_bytes: int | None = None) -> dict[str, np.ndarray]:
    """The arrays of a weights ``.npz`` (numeric, no pickles), at most ``max_bytes`` inflated
    (:func:`gscodec_shac.io.bounded.read_npz` checks every member before allocating it)."""
    from gscodec_shac.io.bounded import read_npz

    return read_npz(path, max_total=max_bytes)


def load_dynamic_model(path: PathLike) -> DynamicModel:
    """Read a dynamic model directory (see the module docstring) or a Deformable-3DGS output folder
    (:mod:`gscodec_shac.io.deformable3dgs`)."""
    from gscodec_shac.io.deformable3dgs import read_deformable3dgs
    from gscodec_shac.io.deformable3dgs_files import is_deformable_output
    from gscodec_shac.io.ply import read_ply

    path = Path(path)
    if not is_own_dynamic_model(path):
        if is_deformable_output(path):
            cloud, arch, weights = read_deformable3dgs(path)
            net = DeformNetwork(arch)
            net.load_weights(weights, f"{path}: deform.pth")
            return DynamicModel(cloud, net)
        raise ModelFormatError(f"{path}: not a dynamic model directory (no {ARCH_FILE}, and not a "
                               "Deformable-3DGS output folder)")
    from gscodec_shac.deform_arch import weight_count
    from gscodec_shac.io.bounded import member_path

    arch_file, weights_file, model_ply = (member_path(path, name, str(path))
                                          for name in (ARCH_FILE, WEIGHTS_FILE, MODEL_PLY))
    arch = read_arch(arch_file)
    net = DeformNetwork(arch)
    if not weights_file.is_file():
        raise ModelFormatError(f"{path}: the dynamic model has no {WEIGHTS_FILE}")
    # float64 weights at most, and each member's .npy header
    net.load_weights(load_weights_npz(weights_file, 8 * weight_count(arch) + (1 << 16)), str(weights_file))
    if not model_ply.is_file():
        raise ModelFormatError(f"{path}: the dynamic model has no {MODEL_PLY}")
    return DynamicModel(read_ply(model_ply), net)


def save_dynamic_model(path: PathLike, model: DynamicModel, extra: dict[str, Any] | None = None) -> Path:
    """Write ``point_cloud.ply``, ``deformation.npz`` and ``deformation.json`` into ``path`` (atomically)."""
    from gscodec_shac.atomic import write_atomic, write_npz
    from gscodec_shac.io.ply import write_ply

    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    write_ply(path / MODEL_PLY, model.cloud)
    write_npz(path / WEIGHTS_FILE, model.net.weights())
    write_atomic(path / ARCH_FILE, arch_json(model.arch, extra))
    return path


def weights_size_bytes(net: DeformNetwork, bytes_per_weight: int = 4) -> int:
    return net.n_params * bytes_per_weight

