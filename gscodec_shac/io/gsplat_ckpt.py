"""Read and write gsplat checkpoints (``ckpt_*.pt`` of gsplat's ``examples/simple_trainer.py``).

The trainer saves ``torch.save({"step": step, "splats": splats.state_dict(), ...})``;
``splats`` holds float tensors (pre-activation, as :class:`GaussianCloud`)::

    means (N, 3)   scales (N, 3) log   quats (N, 4) wxyz   opacities (N,) logits
    sh0 (N, 1, 3)  shN (N, K-1, 3) coefficient-major

Trained with appearance optimisation (``--app_opt``) it holds ``features`` (N, D) and
``colors`` (N, 3) logits instead of ``sh0``/``shN``: the reader then takes the DC colour
from sigmoid(colors) (view-independent; the appearance network is not in ``splats``)
with a note. Any other per-Gaussian tensor is kept in ``GaussianCloud.extra`` and
written back. A file holding a bare splats dict is read too.

What it loses: nothing for the standard keys (float32 kept; other float dtypes are
converted to float32); the trainer's other entries (``step`` aside, pose and appearance
modules, optimiser state) are not read. The writer's file loads with
``torch.load(path, weights_only=True)``, as the trainer's ``--ckpt`` does.
"""

from __future__ import annotations

import io
import os
import pickle
import re
from typing import Any, Mapping

import numpy as np

from gscodec_shac.atomic import write_atomic
from gscodec_shac.errors import ModelFormatError, ValidationError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.bounded import BoundedZip, read_file
from gscodec_shac.io.model_common import SH_C0, check_rows, note, sigmoid
from gscodec_shac.limits import memory_budget

SPLAT_KEYS = ("means", "scales", "quats", "opacities", "sh0", "shN")
#: The object PyTorch's safe unpickler refused, as its message names it.
_UNSUPPORTED = re.compile(r"Unsupported global: GLOBAL ([\w.]+)")


def read_gsplat_checkpoint(path: str | os.PathLike) -> GaussianCloud:
    """Read the ``splats`` of a gsplat checkpoint into a :class:`GaussianCloud`."""
    import torch

    raw = read_file(path, memory_budget() // 3, "gsplat checkpoint")
    if raw[:4] == b"PK\x03\x04":  # torch.save's zip stores its records: they inflate to no more than the file
        with BoundedZip(path, max_members=1 << 16, max_total=len(raw)):
            pass
    try:
        data = torch.load(io.BytesIO(raw), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:  # weights_only refused a Python object: it is never built
        found = _UNSUPPORTED.search(str(exc))
        what = f" ({found.group(1)})" if found else ""
        raise ModelFormatError(f"{path}: the checkpoint holds Python objects other than tensors{what}; "
                               "they are not loaded, since loading them could run code") from None
    except Exception as exc:  # torch raises many types for foreign or corrupt files
        first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
        raise ModelFormatError(f"{path}: not a readable torch checkpoint ({first})") from None
    splats = data.get("splats", data) if isinstance(data, Mapping) else None
    if not isinstance(splats, Mapping) or "means" not in splats:
        keys = ", ".join(map(str, data)) if isinstance(data, Mapping) else type(data).__name__
        raise ModelFormatError(f"{path}: not a gsplat checkpoint (no 'splats' dict with 'means'; holds {keys})")
    arrays = {str(k): _numpy(path, k, v) for k, v in splats.items()}
    try:
        return splats_arrays_to_cloud(arrays, path)
    except ValidationError as exc:
        raise ModelFormatError(f"{path}: {exc}") from None


def write_gsplat_checkpoint(path: str | os.PathLike, cloud: GaussianCloud, *, step: int = 0) -> None:
    """Write ``{"step": step, "splats": {...}}`` as gsplat's trainer does, atomically."""
    import torch

    splats = {key: torch.from_numpy(np.ascontiguousarray(value)) for key, value in cloud_to_splats_arrays(cloud).items()}
    buffer = io.BytesIO()
    torch.save({"step": int(step), "splats": splats}, buffer)
    write_atomic(path, buffer.getvalue(), error=ModelFormatError)


def splats_arrays_to_cloud(arrays: Mapping[str, np.ndarray], path: str | os.PathLike = "splats") -> GaussianCloud:
    """A dict of numpy arrays in gsplat's layout -> :class:`GaussianCloud` (other keys -> ``extra``)."""
    for key in ("means", "scales", "quats", "opacities"):
        if key not in arrays:
            raise ModelFormatError(f"{path}: the splats lack {key!r}")
    n = arrays["means"].shape[0] if arrays["means"].ndim else 0
    check_rows(path, n, "splats dict")
    extra = {k: v for k, v in arrays.items() if k not in SPLAT_KEYS}
    if "sh0" in arrays:
        sh0 = arrays["sh0"]
        if sh0.shape[1:] != (1, 3):
            raise ModelFormatError(f"{path}: sh0 must have shape (N, 1, 3), got {tuple(sh0.shape)}")
        sh_dc = sh0[:, 0, :]
        sh_rest = arrays.get("shN", np.zeros((n, 0, 3), dtype=np.float32))
    elif "colors" in arrays and arrays["colors"].shape == (n, 3):
        note(f"{path}: appearance-optimised splats (no sh0/shN): DC colour taken from sigmoid(colors), "
             "view-dependent appearance not applied")
        sh_dc = (sigmoid(arrays["colors"]) - 0.5) / SH_C0
        sh_rest = np.zeros((n, 0, 3), dtype=np.float32)
        extra.pop("colors")
    else:
        raise ModelFormatError(f"{path}: the splats hold neither sh0/shN nor colors")
    for key, value in extra.items():
        if value.ndim < 1 or value.shape[0] != n:
            raise ModelFormatError(f"{path}: splats entry {key!r} has shape {tuple(value.shape)}, not one row per Gaussian")
    return GaussianCloud(
        means=arrays["means"], scales=arrays["scales"], quats=arrays["quats"],
        opacities=arrays["opacities"].reshape(-1), sh_dc=sh_dc, sh_rest=sh_rest, extra=extra,
    )


def cloud_to_splats_arrays(cloud: GaussianCloud) -> dict[str, np.ndarray]:
    """:class:`GaussianCloud` -> gsplat's splats layout as numpy arrays (``extra`` appended)."""
    arrays = {
        "means": cloud.means, "scales": cloud.scales, "quats": cloud.quats, "opacities": cloud.opacities,
        "sh0": cloud.sh_dc[:, None, :], "shN": cloud.sh_rest,
    }
    for key, value in cloud.extra.items():
        if key not in arrays:
            arrays[key] = value
    return arrays


def _numpy(path: str | os.PathLike, key: Any, value: Any) -> np.ndarray:
    if not hasattr(value, "detach"):
        raise ModelFormatError(f"{path}: splats entry {key!r} is a {type(value).__name__}, not a tensor")
    array = value.detach().cpu()
    if array.is_floating_point():
        array = array.float()
    return array.numpy()
