"""Grid codecs found by name: see :mod:`gscodec_shac.codec.grid.base`."""

from gscodec_shac.codec.grid.base import CODECS, GridCodec, available_codecs, get_codec, register_codec

__all__ = ["CODECS", "GridCodec", "available_codecs", "get_codec", "register_codec"]
