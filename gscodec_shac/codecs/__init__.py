"""Grid codecs found by name: see :mod:`gscodec_shac.codecs.base`."""

from gscodec_shac.codecs.base import CODECS, GridCodec, available_codecs, get_codec, register_codec

__all__ = ["CODECS", "GridCodec", "available_codecs", "get_codec", "register_codec"]
