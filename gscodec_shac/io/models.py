"""One entry point for Gaussian model files: :func:`read_model` and :func:`write_model`.

The reader is chosen by content where the format has a signature, else by extension:

=================  ==========================================================  =========
format             recognised by                                               write
=================  ==========================================================  =========
``ply``            ``ply`` magic, no ``chunk`` element (Inria 3DGS PLY)        ``.ply``
``compressed-ply`` ``ply`` magic with ``chunk`` + ``packed_*`` properties      ``.compressed.ply``
``spz``            gzip magic or ``NGSP`` (version 4)                          ``.spz``
``sog``            a zip holding ``meta.json``; a SOG ``meta.json``; a folder  ``.sog``
                   holding one
``gsplat``         a zip holding ``data.pkl`` (torch), or ``.pt``/``.pth``     ``.pt``
``splat``          the ``.splat`` extension (no signature; size a multiple     ``.splat``
                   of 32)
``gsc``            the ``.gsc`` magic (decoded; a dynamic stream gives its      no (encode)
                   canonical Gaussians)
``deformable3dgs`` a folder holding ``point_cloud/`` and ``deform/`` (or one    no
                   of their ``iteration_N``): the canonical Gaussians only
=================  ==========================================================  =========

A file without any of these signatures is handed to the reader its extension names,
which then says what is wrong with it (e.g. "not a PLY file").

What each format loses is in its module's docstring and in ``docs/formats.md``.
Readers report what they changed (clamped opacity logits, dropped data) as
:class:`~gscodec_shac.io.model_common.FormatNote` warnings; here they are returned as
one-line notes, for the CLI to print.
"""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path
from typing import Any, Callable, TextIO

from gscodec_shac.errors import ModelFormatError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.model_common import FormatNote

READ_FORMATS = ("ply", "compressed-ply", "spz", "splat", "sog", "gsplat", "gsc", "deformable3dgs")
#: Output extension -> format.
WRITE_EXTENSIONS = {".ply": "ply", ".spz": "spz", ".splat": "splat", ".sog": "sog", ".pt": "gsplat", ".pth": "gsplat"}
#: A name ending like this is written as PlayCanvas's compressed PLY (its suffix alone is ``.ply``).
COMPRESSED_PLY_SUFFIX = ".compressed.ply"
_SUPPORTED = (
    "Inria .ply, PlayCanvas .compressed.ply, .spz (versions 1-4), .splat, "
    "SOG (.sog, meta.json or its folder), gsplat checkpoint .pt, .gsc"
)


def detect_format(path: str | os.PathLike) -> str:
    """The format name of ``path`` (see the module table); unknown -> :class:`ModelFormatError`."""
    from gscodec_shac.io.bounded import BoundedZip
    from gscodec_shac.io.compressed_ply import is_compressed_ply_header
    from gscodec_shac.io.deformable3dgs_files import is_deformable_output
    from gscodec_shac.io.sog import find_sog_meta

    path = Path(path)
    if not path.exists():
        raise ModelFormatError(f"{path}: no such file or folder")
    if path.is_dir():
        if find_sog_meta(path) is not None:
            return "sog"
        if is_deformable_output(path):
            return "deformable3dgs"
        raise ModelFormatError(f"{path}: is a directory without a SOG meta.json; supported: {_SUPPORTED}")
    from gscodec_shac.codec.container import MAGIC

    with open(path, "rb") as handle:
        head = handle.read(4096)
    if head.startswith(MAGIC):
        return "gsc"
    if head.startswith(b"ply"):
        text = head.decode("latin-1")
        return "compressed-ply" if is_compressed_ply_header(text.split("end_header")[0]) else "ply"
    if head[:2] == b"\x1f\x8b" or head[:4] == b"NGSP":
        return "spz"
    if head[:4] == b"PK\x03\x04":
        with BoundedZip(path, max_members=1 << 16) as bundle:
            names = [Path(n).name for n in bundle.names()]
        if "meta.json" in names:
            return "sog"
        if "data.pkl" in names:
            return "gsplat"
        raise ModelFormatError(f"{path}: a zip that is neither a .sog bundle nor a torch checkpoint")
    if find_sog_meta(path) is not None:
        return "sog"
    # no signature: the extension decides, and that reader names what is wrong with the file
    by_extension = {".ply": "ply", ".spz": "spz", ".splat": "splat", ".sog": "sog", ".json": "sog",
                    ".pt": "gsplat", ".pth": "gsplat"}
    if path.suffix.lower() in by_extension:
        return by_extension[path.suffix.lower()]
    raise ModelFormatError(f"{path}: unknown Gaussian model format; supported: {_SUPPORTED}")


def read_model(path: str | os.PathLike) -> tuple[GaussianCloud, list[str]]:
    """Read any supported model file: ``(cloud, notes)``, notes being one-line remarks."""
    return _collecting(lambda: _readers()[detect_format(path)](path))


def write_model(path: str | os.PathLike, cloud: GaussianCloud, *, progress: bool = False, **options: Any) -> list[str]:
    """Write ``cloud`` in the format of ``path``'s extension, atomically; returns the notes.

    ``options`` go to the format's writer (e.g. ``version=2`` for SPZ); ``progress`` to a writer
    with a long step that shows a progress bar (SOG's SH palette).
    """
    import inspect

    path = Path(path)
    check_model_extension(path)
    writer = _writers()[output_format(path)]
    if progress and "progress" in inspect.signature(writer).parameters:
        options["progress"] = True
    _, notes = _collecting(lambda: writer(path, cloud, **options))
    return notes


def report_notes(notes: list[str], stream: TextIO | None = None) -> None:
    """Print each note as one ``note: ...`` line (stderr by default)."""
    for text in notes:
        print(f"note: {text}", file=stream or sys.stderr)


def model_bytes(path: str | os.PathLike) -> int:
    """Bytes a model occupies: the file, or for a SOG ``meta.json`` or folder, it and its images;
    for a dynamic model directory, its canonical PLY and network files."""
    path = Path(path)
    from gscodec_shac.deform_arch import dynamic_model_files
    from gscodec_shac.io.sog import find_sog_meta, sog_files

    if path.is_dir() and dynamic_model_files(path):
        return sum(f.stat().st_size for f in dynamic_model_files(path))

    meta = find_sog_meta(path)
    if meta is None:
        return path.stat().st_size
    files = {meta, *sog_files(meta)}
    return sum(f.stat().st_size for f in files if f.is_file())


def _collecting(call: Callable[[], Any]) -> tuple[Any, list[str]]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", FormatNote)
        result = call()
    notes = []
    for item in caught:
        if issubclass(item.category, FormatNote):
            notes.append(str(item.message))
        else:
            warnings.warn_explicit(item.message, item.category, item.filename, item.lineno)
    return result, notes


def _readers() -> dict[str, Callable[[Any], GaussianCloud]]:
    from gscodec_shac.io.compressed_ply import read_compressed_ply
    from gscodec_shac.io.deformable3dgs import read_deformable3dgs_canonical
    from gscodec_shac.io.gsplat_ckpt import read_gsplat_checkpoint
    from gscodec_shac.io.sog import read_sog
    from gscodec_shac.io.splat import read_splat
    from gscodec_shac.io.spz import read_spz

    return {"ply": _read_ply_clamped, "compressed-ply": read_compressed_ply, "spz": read_spz, "splat": read_splat,
            "sog": read_sog, "gsplat": read_gsplat_checkpoint, "gsc": _read_gsc,
            "deformable3dgs": read_deformable3dgs_canonical}


def _read_ply_clamped(path: str | os.PathLike) -> GaussianCloud:
    """An Inria PLY; infinite opacity logits (alpha 0/255, as splat-transform writes) clamped with a note."""
    from gscodec_shac.io.ply import read_ply

    return read_ply(path, clamp_opacity=True)


def _read_gsc(path: str | os.PathLike) -> GaussianCloud:
    """A ``.gsc`` stream, decoded (a dynamic model's canonical Gaussians, with a note)."""
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.decoder import Decoder
    from gscodec_shac.io.model_common import note

    stream = Bitstream.read(path)
    if "deformation" in stream.features:
        note(f"{path}: a dynamic model; its canonical Gaussians are read (the deformation network is not)")
    return Decoder().decode(stream)


def _writers() -> dict[str, Callable[..., None]]:
    from gscodec_shac.io.compressed_ply_writer import write_compressed_ply
    from gscodec_shac.io.gsplat_ckpt import write_gsplat_checkpoint
    from gscodec_shac.io.ply import write_ply
    from gscodec_shac.io.sog import write_sog
    from gscodec_shac.io.splat import write_splat
    from gscodec_shac.io.spz import write_spz

    return {"ply": write_ply, "spz": write_spz, "splat": write_splat, "sog": write_sog, "gsplat": write_gsplat_checkpoint,
            "compressed-ply": write_compressed_ply}


def output_format(path: str | os.PathLike) -> str | None:
    """The format a model output path names: by extension (``x.compressed.ply`` -> ``compressed-ply``),
    or ``sog`` for a ``meta.json`` (an unbundled SOG: the file and its images beside it); None when
    it names none."""
    path = Path(path)
    if path.name == "meta.json":
        return "sog"
    if path.name.lower().endswith(COMPRESSED_PLY_SUFFIX):
        return "compressed-ply"
    return WRITE_EXTENSIONS.get(path.suffix.lower())


def output_files(path: str | os.PathLike) -> list[Path]:
    """Every file writing a model to ``path`` creates (an unbundled SOG: its images and ``meta.json``)."""
    from gscodec_shac.io.sog import SOG_IMAGES

    path = Path(path)
    if path.name == "meta.json":
        return [path.parent / name for name in SOG_IMAGES] + [path]
    return [path]


def check_model_extension(path: str | os.PathLike) -> None:
    """Raise before any work when ``path``'s extension names no writable model format."""
    if output_format(path) is None:
        suffix = Path(path).suffix.lower()
        raise ModelFormatError(
            f"{path}: cannot write a Gaussian model with extension {suffix or '(none)'!r}; "
            f"writable: {', '.join([*WRITE_EXTENSIONS, COMPRESSED_PLY_SUFFIX])} or a SOG meta.json"
        )
