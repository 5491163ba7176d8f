"""Sizes of the deformation network of a dynamic model (no torch: stream validators use it).

:class:`DeformArch` holds the layer sizes (:mod:`gscodec_shac.deform` builds the network
from it) and :func:`weight_shapes` lists every weight tensor's name and shape in
``state_dict`` order, computed from the sizes alone, so a ``.gsc`` header can be checked
before anything is allocated.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from gscodec_shac.errors import ModelFormatError

#: The files of a dynamic model directory.
MODEL_PLY = "point_cloud.ply"
WEIGHTS_FILE = "deformation.npz"
ARCH_FILE = "deformation.json"
#: Bounds of an architecture read from a file or stream (about 17 M weights at most).
MAX_WIDTH = 1024
MAX_DEPTH = 16


@dataclass(frozen=True)
class DeformArch:
    """Sizes of the deformation MLP (defaults: the reference's D-NeRF network)."""

    depth: int = 8
    width: int = 256
    xyz_freqs: int = 10
    t_freqs: int = 6
    time_net: bool = True
    time_width: int = 256
    time_out: int = 30

    def validate(self) -> "DeformArch":
        for key in ("depth", "width", "xyz_freqs", "t_freqs", "time_width", "time_out"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < (0 if "freqs" in key else 1):
                raise ModelFormatError(f"deformation architecture: {key} must be a positive integer, got {value!r}")
        if self.depth > MAX_DEPTH or self.width > MAX_WIDTH or self.time_width > MAX_WIDTH or self.time_out > MAX_WIDTH:
            raise ModelFormatError(f"deformation architecture too large: {asdict(self)}")
        if self.xyz_freqs > 20 or self.t_freqs > 20:
            raise ModelFormatError("deformation architecture: at most 20 encoding octaves")
        if not isinstance(self.time_net, bool):
            raise ModelFormatError("deformation architecture: time_net must be true or false")
        return self

    @property
    def xyz_dims(self) -> int:
        return 3 + 6 * self.xyz_freqs

    @property
    def t_dims(self) -> int:
        return 1 + 2 * self.t_freqs

    @property
    def input_dims(self) -> int:
        return self.xyz_dims + (self.time_out if self.time_net else self.t_dims)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Any) -> "DeformArch":
        if not isinstance(data, dict):
            raise ModelFormatError("deformation architecture must be a JSON object")
        names = {f.name for f in fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ModelFormatError(f"deformation architecture: unknown key(s) {sorted(unknown)}")
        return cls(**data).validate()



def weight_shapes(arch: DeformArch) -> list[tuple[str, tuple[int, ...]]]:
    """``[(name, shape)]`` of every weight in ``DeformNetwork(arch).state_dict()`` order."""
    out: list[tuple[str, tuple[int, ...]]] = []

    def linear(name: str, fan_in: int, fan_out: int) -> None:
        out.append((f"{name}.weight", (fan_out, fan_in)))
        out.append((f"{name}.bias", (fan_out,)))

    if arch.time_net:
        linear("time_layers.0", arch.t_dims, arch.time_width)
        linear("time_layers.1", arch.time_width, arch.time_out)
    skip = skip_index(arch)
    linear("layers.0", arch.input_dims, arch.width)
    for i in range(arch.depth - 1):
        linear(f"layers.{i + 1}", arch.width + (arch.input_dims if i == skip else 0), arch.width)
    linear("head_xyz", arch.width, 3)
    linear("head_rot", arch.width, 4)
    linear("head_scale", arch.width, 3)
    return out


def skip_index(arch: DeformArch) -> int:
    """The hidden layer whose output is joined by the encoded input again (the reference's skip at
    ``depth // 2``), -1 when that would be the last layer; ``layers.{skip + 1}`` takes both."""
    return arch.depth // 2 if arch.depth // 2 < arch.depth - 1 else -1


def skip_input_layer(arch: DeformArch) -> str | None:
    """Name of the weight matrix that takes the skip's concatenated input, if there is a skip."""
    skip = skip_index(arch)
    return None if skip < 0 else f"layers.{skip + 1}.weight"


def weight_count(arch: DeformArch) -> int:
    total = 0
    for _, shape in weight_shapes(arch):
        size = 1
        for d in shape:
            size *= d
        total += size
    return total


def is_own_dynamic_model(path: str | os.PathLike) -> bool:
    """True for a directory holding ``deformation.json`` (our dynamic model, :mod:`gscodec_shac.deform`)."""
    path = Path(path)
    return path.is_dir() and (path / ARCH_FILE).is_file()


def is_dynamic_model(path: str | os.PathLike) -> bool:
    """True for a dynamic model directory: ours, or a Deformable-3DGS output folder
    (:mod:`gscodec_shac.io.deformable3dgs`); :func:`gscodec_shac.deform.load_dynamic_model` reads both."""
    from gscodec_shac.io.deformable3dgs_files import is_deformable_output

    return is_own_dynamic_model(path) or is_deformable_output(path)


def dynamic_model_files(path: str | os.PathLike) -> list[Path]:
    """The files a dynamic model directory is made of (empty for anything else): what its size counts."""
    from gscodec_shac.io.deformable3dgs_files import is_deformable_output, iteration_files

    path = Path(path)
    if is_own_dynamic_model(path):
        return [f for f in (path / MODEL_PLY, path / WEIGHTS_FILE, path / ARCH_FILE) if f.is_file()]
    if is_deformable_output(path):
        return list(iteration_files(path)[:2])
    return []
