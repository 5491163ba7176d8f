"""Exception types.

Every user mistake (bad file, bad option, missing codec) raises a subclass of
:class:`GscodecError` carrying one sentence that names the problem. The CLI
prints that sentence and exits with status 2 instead of showing a traceback.
"""


class GscodecError(Exception):
    """Base class of all errors caused by user input or the environment."""


class ValidationError(GscodecError, ValueError):
    """Arrays handed to a data type have the wrong shape, dtype or values."""


class PlyFormatError(GscodecError):
    """A file is not a usable 3DGS PLY."""


class CameraFormatError(GscodecError):
    """A camera file (cameras.json, COLMAP model, transforms.json) is unusable."""


class BitstreamError(GscodecError):
    """A .gsc container is truncated, corrupt, foreign or of an unknown version."""


class RatePointError(GscodecError):
    """A rate point (YAML) is missing, malformed or names unknown settings."""


class CodecUnavailableError(GscodecError):
    """A grid codec or external tool needed for the job is not installed."""


class ModelFormatError(GscodecError):
    """A Gaussian model file (SPZ, .splat, SOG, compressed.ply, gsplat checkpoint) is unusable or unknown."""
