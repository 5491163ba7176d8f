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

from gscodec_shac.codec.container import Bitstream
from gscodec_shac.codec.decoder import Decoder
from gscodec_shac.codec.encoder import Encoder
from gscodec_shac.codec.files import decode_file, encode_file, encode_file_to_target
from gscodec_shac.codec.layout import GridOrder
from gscodec_shac.codec.rate_points import RatePoint, load_rate_point

__all__ = ["Bitstream", "Decoder", "Encoder", "GridOrder", "RatePoint", "decode_file", "encode_file",
           "encode_file_to_target", "load_rate_point"]
