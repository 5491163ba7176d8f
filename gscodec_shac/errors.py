"""Exception types, one per kind of failure, and the CLI exit status of each.

Every user mistake (bad file, bad option, missing codec) raises a subclass of
:class:`GscodecError` carrying one sentence that names the problem (the file, key or
byte offset). The CLI prints that sentence as ``error: ...`` and exits with the
class's :attr:`~GscodecError.exit_code` instead of showing a traceback
(docs/reliability.md, "Exit codes").
"""

#: Exit statuses of ``gscodec-shac`` (also in ``gscodec-shac --help``).
EXIT_OK = 0
EXIT_FAILED_RUNS = 1  # a sweep finished, but some of its runs failed
EXIT_USAGE = 2  # bad option, bad input file (PLY, YAML, cameras), output exists
EXIT_CORRUPT_STREAM = 3  # a .gsc file is corrupt, truncated, foreign or of an unknown version
EXIT_MISSING_TOOL = 4  # a grid codec library or external tool is not installed
EXIT_LIMIT = 5  # the input exceeds the memory budget or a documented limit
EXIT_INTERNAL = 70  # a bug: an unexpected exception (traceback with --debug)
EXIT_INTERRUPTED = 130  # Ctrl-C (SIGINT)
EXIT_BROKEN_PIPE = 141  # the reader of our output went away (e.g. `| head`)
EXIT_TERMINATED = 143  # SIGTERM


class GscodecError(Exception):
    """Base class of all errors caused by user input or the environment."""

    exit_code = EXIT_USAGE


class ValidationError(GscodecError, ValueError):
    """Arrays handed to a data type have the wrong shape, dtype or values."""


class PlyFormatError(GscodecError):
    """A file is not a usable 3DGS PLY."""


class CameraFormatError(GscodecError):
    """A camera file (cameras.json, COLMAP model, transforms.json) is unusable."""


class BitstreamError(GscodecError):
    """A .gsc container is truncated, corrupt, foreign or of an unknown version."""

    exit_code = EXIT_CORRUPT_STREAM


class StreamFileError(BitstreamError):
    """The .gsc input does not exist, is a directory or cannot be read (a usage error, not a corrupt file)."""

    exit_code = EXIT_USAGE


class RatePointError(GscodecError):
    """A rate point (YAML) is missing, malformed or names unknown settings."""


class CodecUnavailableError(GscodecError):
    """A grid codec or external tool needed for the job is not installed."""

    exit_code = EXIT_MISSING_TOOL


class MemoryLimitError(GscodecError):
    """The input would need more memory than this process may use (checked before allocating)."""

    exit_code = EXIT_LIMIT


class OutputError(GscodecError):
    """An output path is unusable: it exists (without ``--force``), is an input, or is a directory."""


class ModelFormatError(GscodecError):
    """A Gaussian model file (SPZ, .splat, SOG, compressed.ply, gsplat checkpoint) is unusable or unknown."""
