"""The codec: a :class:`~gscodec_shac.gaussians.GaussianCloud` <-> one ``.gsc`` file.

=============== ================================================================
module          what
=============== ================================================================
rate_points     rate points: YAML schema, loader, overrides
attributes      the coded attributes and their value transforms
quantize        value transforms and per-channel n-bit quantisers
layout          grid placement (pruning, sorting, padding) and values <-> planes
encoder         :class:`Encoder`: cloud -> :class:`Bitstream`
decoder         :class:`Decoder`: bytes -> cloud
container       the ``.gsc`` container (:class:`Bitstream`)
files           :func:`encode_file` / :func:`decode_file` / :func:`encode_file_to_target`
rate_control    SHAC-auto: settings chosen for a size or PSNR target
positions       positions coded as a Morton-sorted set
allocation      water-filled QPs over SH features
summary         what is in a model (``info`` of a PLY)
grid/           grid codecs by name (hevc, png, jpegls, raw, hm)
=============== ================================================================

See docs/architecture.md for the data flow.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.decoder import Decoder
    from gscodec_shac.codec.encoder import Encoder
    from gscodec_shac.codec.files import decode_file, encode_file, encode_file_to_target
    from gscodec_shac.codec.layout import GridOrder
    from gscodec_shac.codec.rate_points import RatePoint, load_rate_point

#: Where each public name lives; imported on first use (PEP 562), so a decode does not load
#: the encoder, the rate controller and the YAML loader (about 0.1 s of start-up).
_PUBLIC = {"Bitstream": "container", "Decoder": "decoder", "Encoder": "encoder", "GridOrder": "layout",
           "RatePoint": "rate_points", "load_rate_point": "rate_points", "decode_file": "files",
           "encode_file": "files", "encode_file_to_target": "files"}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_PUBLIC[name]}"), name)
    globals()[name] = value
    return value
