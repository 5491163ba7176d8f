"""The deformation network of a dynamic model as one more chunk of a ``.gsc`` stream.

A dynamic model (:mod:`gscodec_shac.deform`) is coded as its canonical Gaussians (the ordinary
pipeline) plus the chunk ``deformation``: every weight tensor in ``state_dict`` order
(:func:`gscodec_shac.deform_arch.weight_shapes`), cast to little-endian float16, concatenated
and deflated (zlib). The header entry ``deformation`` = ``{"arch": {...}, "dtype": "float16"}``
says how to rebuild the network; the chunk records ``encoding: zlib`` and ``raw_size`` (= 2 x
the weight count, checked by :mod:`gscodec_shac.codec.header`). The stream needs the container
feature ``deformation`` (format 2.0), so a decoder that does not know dynamic models refuses it
by name instead of decoding only the canonical Gaussians.
"""

from __future__ import annotations

import zlib
from typing import Any

import numpy as np

from gscodec_shac.codec.container import Bitstream
from gscodec_shac.deform_arch import DeformArch, weight_shapes

CHUNK = "deformation"
FEATURE = "deformation"
DTYPE = "float16"


def add_deformation(stream: Bitstream, arch: DeformArch, weights: dict[str, np.ndarray]) -> int:
    """Append the network chunk + header entry to ``stream``; returns the chunk's size in bytes."""
    parts = []
    for name, shape in weight_shapes(arch):
        value = np.asarray(weights[name], dtype=np.float32)
        if value.shape != shape:
            raise ValueError(f"deformation weight {name} has shape {value.shape}, expected {shape}")
        parts.append(value.astype("<f2").tobytes())
    raw = b"".join(parts)
    data = zlib.compress(raw, 9)
    stream.add_chunk(CHUNK, data, attribute=CHUNK, encoding="zlib", raw_size=len(raw))
    stream.header[CHUNK] = {"arch": arch.to_dict(), "dtype": DTYPE}
    stream.require(FEATURE)
    return len(data)


def decode_weights(raw: bytes, arch: DeformArch) -> dict[str, np.ndarray]:
    """The float32 weights from the inflated chunk (its size is checked by the header validator)."""
    out: dict[str, np.ndarray] = {}
    offset = 0
    values = np.frombuffer(raw, dtype="<f2")
    for name, shape in weight_shapes(arch):
        size = int(np.prod(shape))
        out[name] = values[offset : offset + size].astype(np.float32).reshape(shape)
        offset += size
    return out


def summary(arch: DeformArch, chunk_bytes: int) -> dict[str, Any]:
    from gscodec_shac.deform_arch import weight_count

    n = weight_count(arch)
    return {"arch": arch.to_dict(), "weights": n, "dtype": DTYPE, "bytes": chunk_bytes,
            "float32_bytes": 4 * n}
