"""Read the output folder of Deformable 3D Gaussians (Yang et al., CVPR 2024; the model of SHAC's Table IV).

The reference trainer (github ingra14m/Deformable-3D-Gaussians) writes, per saved iteration ``N``::

    OUT/point_cloud/iteration_N/point_cloud.ply   canonical Gaussians (Inria 3DGS PLY, SH degree 3)
    OUT/deform/iteration_N/deform.pth             torch.save(DeformNetwork.state_dict())

Which iteration is read: ``OUT`` gives the newest ``N`` of ``point_cloud/`` (the reference's own
loader does the same); the folder ``OUT/point_cloud/iteration_N`` (or ``OUT/deform/iteration_N``)
names one. Both files of that ``N`` must exist.

The state dict (loaded with ``torch.load(weights_only=True)``) has these keys; the reference
builds an 8 x 256 network, but its class takes any depth ``D >= 3`` and width ``W``, and both are
read from the shapes:

==========================================  =====================================================
reference key                               ours (:class:`gscodec_shac.deform.DeformNetwork`)
==========================================  =====================================================
``timenet.0`` (13 -> 256), ``timenet.2``    ``time_layers.0``, ``time_layers.1`` (256 -> 30);
(D-NeRF, ``--is_blender``)                  without them: no time net, 10 time octaves
``linear.0`` .. ``linear.{D-1}``            ``layers.0`` .. ``layers.{D-1}`` (skip input at D/2 + 1)
``gaussian_warp`` / ``_rotation`` /         ``head_xyz`` / ``head_rot`` / ``head_scale``
``_scaling``
==========================================  =====================================================

The only difference is the order of the positional-encoding features: the reference
interleaves ``sin(2^k x), cos(2^k x)`` per octave, ours puts all sines before all cosines
(:func:`gscodec_shac.deform.positional_encoding`). The reader permutes the input columns of
the first layer, of the skip layer and of the time net's first layer accordingly, so our
network computes the reference's function (up to the order of float32 sums). The 6-DoF
variant (``branch_w``/``branch_v``) is refused. The renderer's use of the three outputs
(``x + dx``, ``normalize(q) + dq``, ``exp(s) + ds``) is what :func:`gscodec_shac.deform.deform_tensors`
does.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Mapping

import numpy as np

from gscodec_shac.deform_arch import DeformArch, weight_shapes
from gscodec_shac.errors import ModelFormatError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.deformable3dgs_files import iteration_files

PathLike = str | os.PathLike
#: Sizes the reference's DeformNetwork fixes (utils/time_utils.py).
XYZ_OCTAVES = 10
BLENDER_T_OCTAVES, OTHER_T_OCTAVES = 6, 10
TIME_WIDTH, TIME_OUT = 256, 30
MAX_PTH_BYTES = 128 << 20  # far above the 2 MB of the reference's network
#: Our parameter name -> the reference's.
_RENAME = {"time_layers.0": "timenet.0", "time_layers.1": "timenet.2", "head_xyz": "gaussian_warp",
           "head_rot": "gaussian_rotation", "head_scale": "gaussian_scaling"}


def load_state_dict(pth: PathLike) -> dict[str, np.ndarray]:
    """The tensors of a ``deform.pth`` as float32 arrays by key (``torch.load(weights_only=True)``)."""
    import torch

    from gscodec_shac.io.bounded import read_file

    pth = Path(pth)
    raw = read_file(pth, MAX_PTH_BYTES, "deform.pth (a deformation network)")
    if raw[:4] == b"PK\x03\x04":  # torch.save's zip stores its records: they inflate to no more than the file
        from gscodec_shac.io.bounded import BoundedZip

        with BoundedZip(pth, max_members=1 << 16, max_total=len(raw)):
            pass
    try:
        data = torch.load(io.BytesIO(raw), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for foreign or corrupt files
        first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
        raise ModelFormatError(f"{pth}: not a readable torch state dict ({first})") from None
    if not isinstance(data, Mapping) or not all(isinstance(k, str) and torch.is_tensor(v) for k, v in data.items()):
        raise ModelFormatError(f"{pth}: not a DeformNetwork state dict (expected a dict of named tensors)")
    out = {}
    for key, value in data.items():
        if not value.is_floating_point():
            raise ModelFormatError(f"{pth}: {key} has dtype {value.dtype}, expected floating point")
        out[key] = value.detach().to(torch.float32).numpy()
    return out


def reference_arch(state: Mapping[str, np.ndarray], where: str) -> DeformArch:
    """The :class:`~gscodec_shac.deform_arch.DeformArch` of a reference state dict (variant, depth, width)."""
    if any(k.startswith(("branch_w.", "branch_v.")) for k in state):
        raise ModelFormatError(f"{where}: a 6-DoF network (branch_w/branch_v, --is_6dof) is not supported")
    depth = sum(1 for i in range(len(state)) if f"linear.{i}.weight" in state)
    first = state.get("linear.0.weight")
    if depth < 3 or first is None or first.ndim != 2:
        raise ModelFormatError(f"{where}: not a Deformable-3DGS DeformNetwork (needs linear.0 .. linear.N, N >= 2; "
                               f"keys: {', '.join(sorted(state)[:6])})")
    blender = any(k.startswith("timenet.") for k in state)
    return DeformArch(depth=depth, width=int(first.shape[0]), xyz_freqs=XYZ_OCTAVES,
                      t_freqs=BLENDER_T_OCTAVES if blender else OTHER_T_OCTAVES, time_net=blender,
                      time_width=TIME_WIDTH, time_out=TIME_OUT).validate()


def reference_key(ours: str) -> str:
    """The reference's name of our parameter ``ours`` (e.g. ``layers.3.bias`` -> ``linear.3.bias``)."""
    module, _, kind = ours.rpartition(".")
    if module.startswith("layers."):
        return f"linear.{module.split('.', 1)[1]}.{kind}"
    return f"{_RENAME[module]}.{kind}"


def encoding_permutation(dims: int, octaves: int) -> np.ndarray:
    """``perm`` with ``ours[i] = reference[perm[i]]`` for the NeRF encoding of ``dims`` inputs.

    Reference order: ``x, sin(2^0 x), cos(2^0 x), sin(2^1 x), ...``; ours: ``x, sin(2^k x) for all k,
    cos(2^k x) for all k`` (each a block of ``dims``)."""
    ref = [("x", 0, j) for j in range(dims)]
    for k in range(octaves):
        ref += [("sin", k, j) for j in range(dims)] + [("cos", k, j) for j in range(dims)]
    ours = [("x", 0, j) for j in range(dims)]
    for fn in ("sin", "cos"):
        ours += [(fn, k, j) for k in range(octaves) for j in range(dims)]
    where = {label: i for i, label in enumerate(ref)}
    return np.array([where[label] for label in ours], dtype=np.int64)


def to_our_weights(state: Mapping[str, np.ndarray], where: str) -> tuple[DeformArch, dict[str, np.ndarray]]:
    """``(arch, weights)`` of our network computing the reference state dict's function.

    Unknown or missing keys and other shapes raise :class:`ModelFormatError` naming them."""
    arch = reference_arch(state, where)
    shapes = weight_shapes(arch)
    expected = {reference_key(name): shape for name, shape in shapes}
    variant = f"{arch.depth}x{arch.width} {'D-NeRF (is_blender)' if arch.time_net else 'real-scene'} network"
    unknown = sorted(set(state) - set(expected))
    missing = sorted(set(expected) - set(state))
    if unknown or missing:
        parts = ([f"unknown key(s) {', '.join(unknown[:4])}{' ...' if len(unknown) > 4 else ''}"] if unknown else []) \
            + ([f"missing key(s) {', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''}"] if missing else [])
        raise ModelFormatError(f"{where}: does not match the reference's {variant}: {'; '.join(parts)}")
    for key, shape in expected.items():
        if tuple(state[key].shape) != shape:
            raise ModelFormatError(f"{where}: {key} has shape {tuple(state[key].shape)}, the reference's {variant} "
                                   f"needs {shape}")
    x_perm = encoding_permutation(3, arch.xyz_freqs)
    t_perm = encoding_permutation(1, arch.t_freqs)
    # the network's input: [x code, time feature]; the time feature is permuted only without a time net
    in_perm = np.concatenate([x_perm, len(x_perm) + (np.arange(arch.time_out) if arch.time_net else t_perm)])
    skip = arch.depth // 2
    weights = {}
    for name, _ in shapes:
        value = np.array(state[reference_key(name)], dtype=np.float32)
        if name in ("layers.0.weight", f"layers.{skip + 1}.weight"):
            value[:, : len(in_perm)] = value[:, in_perm]
        elif name == "time_layers.0.weight":
            value = value[:, t_perm]
        weights[name] = np.ascontiguousarray(value)
    return arch, weights


def read_deformable3dgs(path: PathLike) -> tuple[GaussianCloud, DeformArch, dict[str, np.ndarray]]:
    """``(canonical Gaussians, arch, weights in our names)`` of a Deformable-3DGS output folder
    (:func:`gscodec_shac.deform.load_dynamic_model` builds the network from them)."""
    from gscodec_shac.io.ply import read_ply

    ply, pth, _ = iteration_files(path)
    arch, weights = to_our_weights(load_state_dict(pth), str(pth))
    return read_ply(ply), arch, weights


def read_deformable3dgs_canonical(path: PathLike) -> GaussianCloud:
    """The canonical Gaussians only (what a static tool such as ``rd`` codes), with a note."""
    from gscodec_shac.io.model_common import note
    from gscodec_shac.io.ply import read_ply

    ply, pth, number = iteration_files(path)
    note(f"{path}: Deformable-3DGS output, iteration {number}: the canonical Gaussians only "
         f"(the deformation network {pth.name} is not part of a static model)")
    return read_ply(ply)
