"""The codec: a :class:`~gscodec_shac.gaussians.GaussianCloud` <-> one ``.gsc`` file.

See docs/architecture.md for the data flow and where each step lives.
"""

from gscodec_shac.codec.container import Bitstream
from gscodec_shac.codec.pipeline import Decoder, Encoder, decode_file, encode_file
from gscodec_shac.codec.rate_points import RatePoint, load_rate_point

__all__ = ["Bitstream", "Decoder", "Encoder", "RatePoint", "decode_file", "encode_file", "load_rate_point"]
