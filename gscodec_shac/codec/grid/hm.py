"""``hm``: the HEVC reference software (HM) as external encoder and decoder binaries.

For users who must match the MPEG anchor bit for bit. HM is never a dependency:
it is found through ``GSCODEC_HM_DIR`` (a folder holding the binaries, or an HM
checkout whose ``bin/`` does) or on ``PATH``, under its usual names
(``TAppEncoder``/``TAppDecoder``, their ``Static`` builds, or ``EncoderApp``/
``DecoderApp``). Each stream is one picture written as a planar YUV file into a
temporary folder (8-bit samples, or 16-bit little-endian above 8 bits) and coded
with ``--FramesToBeEncoded=1 --ConformanceWindowMode=1 --Profile=main-RExt``.

The bytes have exactly the layout of the ``hevc`` codec (layout byte, shift byte,
length-prefixed Annex-B streams; layouts ``gray`` and ``yuv444``), so the
in-process ``hevc`` decoder reads HM streams too; this codec decodes with HM's
own decoder. Lossless mode uses ``--CostMode=lossless --TransquantBypassEnable=1
--CUTransquantBypassFlagForce=1`` (the HM 16.20/18 option names).
"""

from __future__ import annotations

import functools
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from gscodec_shac.codec.grid.base import GridCodec, join_chunks, register_codec, split_chunks
from gscodec_shac.codec.grid.hevc import (
    LAYOUTS,
    check_depth,
    check_qp,
    check_sps,
    codable_size,
    coding_depth,
    pad_to_codable,
    restore_samples,
    stream_plan,
)
from gscodec_shac.errors import BitstreamError, CodecUnavailableError, ValidationError

ENV_VAR = "GSCODEC_HM_DIR"
ENCODER_NAMES = ("TAppEncoderStatic", "TAppEncoder", "EncoderAppStatic", "EncoderApp")
DECODER_NAMES = ("TAppDecoderStatic", "TAppDecoder", "DecoderAppStatic", "DecoderApp")
HOW_TO_GET = (
    "build HM 18.0, the HEVC reference software (public source: the jvet/HM project on Fraunhofer HHI's GitLab), "
    "with `cmake -B build -DCMAKE_BUILD_TYPE=Release && cmake --build build -j` (about 4 minutes), "
    f"then set {ENV_VAR} to the folder holding TAppEncoder and TAppDecoder (HM's bin/ folder) or put them on PATH"
)


def find_hm() -> tuple[Path, Path]:
    """Paths of the HM encoder and decoder; CodecUnavailableError saying how to get them."""
    folders = []
    if os.environ.get(ENV_VAR):
        root = Path(os.environ[ENV_VAR]).expanduser()
        folders = [root, root / "bin"] + sorted(p.parent for p in (root / "bin").glob("**/TAppEncoder*"))
    found = []
    for names in (ENCODER_NAMES, DECODER_NAMES):
        path = None
        for name in names:
            for folder in folders:
                if (folder / name).is_file() and os.access(folder / name, os.X_OK):
                    path = folder / name
                    break
            if path is None and not folders and shutil.which(name):
                path = Path(shutil.which(name))  # type: ignore[arg-type]
            if path is not None:
                break
        if path is None:
            where = f"in {ENV_VAR}={os.environ[ENV_VAR]}" if folders else f"on PATH ({ENV_VAR} is not set)"
            raise CodecUnavailableError(
                f"codec 'hm' needs the HM binary {names[1]} and found none {where}: {HOW_TO_GET}"
            )
        found.append(path)
    return found[0], found[1]


@register_codec
class HmCodec(GridCodec):
    """HM reference encoder/decoder run as subprocesses.

    Options: ``layout`` (``"gray"`` or ``"yuv444"``, as in ``hevc``), ``cfg`` (an HM
    .cfg file passed with ``-c`` before our options, e.g. HM's
    ``cfg/encoder_intra_main_rext.cfg``; ``None`` = HM's defaults with
    ``--IntraPeriod=1``), ``depth`` (8, 10, 12 or ``None``) and ``timeout`` (seconds
    per HM run, default 3600).
    """

    name = "hm"

    def __init__(
        self, layout: str = "gray", cfg: str | None = None, depth: int | None = None, timeout: float = 3600.0
    ) -> None:
        if layout not in ("gray", "yuv444"):
            raise ValidationError(f"hm: layout must be 'gray' or 'yuv444', got {layout!r}")
        if cfg is not None and not Path(cfg).is_file():
            raise ValidationError(f"hm: cfg file {cfg!r} does not exist")
        if depth is not None and depth not in (8, 10, 12):
            raise ValidationError(f"hm: depth must be 8, 10, 12 or None, got {depth!r}")
        super().__init__(layout=layout, cfg=cfg, depth=depth, timeout=timeout)
        self.layout, self.cfg, self.depth, self.timeout = layout, cfg, depth, timeout

    @classmethod
    def check_available(cls) -> None:
        find_hm()

    def version(self) -> str:
        return hm_version(*find_hm())

    def encode(self, planes: np.ndarray, bit_depth: int, qp: int | None) -> bytes:
        planes = self._check_planes(planes, bit_depth, qp)
        check_qp(self.name, qp)
        depth = coding_depth(self.name, bit_depth, self.depth)
        shift = 0 if qp is None else depth - bit_depth
        grid = pad_to_codable(planes << shift if shift else planes)
        encoder, _ = find_hm()
        streams = []
        with tempfile.TemporaryDirectory(prefix="gscodec_hm_") as tmp:
            source, bitstream = Path(tmp) / "in.yuv", Path(tmp) / "out.hevc"
            for first, _, chroma in stream_plan(self.layout, len(grid)):
                picture = grid[first : first + (3 if chroma else 1)]
                _write_yuv(source, picture, depth)
                self._run([str(encoder), *self.encoder_args(source, bitstream, picture.shape[1:], chroma, depth, qp)])
                streams.append(bitstream.read_bytes())
        return bytes([LAYOUTS.index(self.layout), shift]) + join_chunks(streams)

    def encoder_args(
        self, source: Path, bitstream: Path, size: tuple[int, int], chroma: int, depth: int, qp: int | None
    ) -> list[str]:
        """HM encoder arguments for one picture (public so the command can be inspected)."""
        fmt = "444" if chroma else "400"
        args = ["-c", str(self.cfg)] if self.cfg else ["--IntraPeriod=1"]
        args += [
            f"--InputFile={source}", f"--BitstreamFile={bitstream}",
            f"--SourceWidth={size[1]}", f"--SourceHeight={size[0]}",
            "--FramesToBeEncoded=1", "--FrameRate=1", "--ConformanceWindowMode=1",
            f"--InputChromaFormat={fmt}", f"--ChromaFormatIDC={fmt}", "--Profile=main-RExt",
            f"--InputBitDepth={depth}", f"--InternalBitDepth={depth}", f"--OutputBitDepth={depth}",
        ]  # fmt: skip
        if qp is None:
            args += ["--CostMode=lossless", "--TransquantBypassEnable=1", "--CUTransquantBypassFlagForce=1"]
        else:
            args += [f"--QP={int(qp)}"]
        return args

    def decode(self, data: bytes, shape: tuple[int, int, int], bit_depth: int) -> np.ndarray:
        channels, height, width = self._check_shape(shape, bit_depth)
        if len(data) < 2 or data[0] >= len(LAYOUTS) or LAYOUTS[data[0]] == "frames":
            raise BitstreamError("hm stream is corrupt (unknown layout byte)")
        layout, shift = LAYOUTS[data[0]], data[1]
        coded_h, coded_w = codable_size(height, width)
        plan = stream_plan(layout, channels)
        _, decoder = find_hm()
        out = np.empty((channels, coded_h, coded_w), dtype=np.uint16)
        depths = set()
        with tempfile.TemporaryDirectory(prefix="gscodec_hm_") as tmp:
            bitstream, recon = Path(tmp) / "in.hevc", Path(tmp) / "out.yuv"
            streams = split_chunks(data[2:], len(plan), self.name)
            for index, (stream, (first, _, chroma)) in enumerate(zip(streams, plan)):
                depth = check_sps(stream, coded_w, coded_h, chroma, index)
                depths.add(depth)
                bitstream.write_bytes(stream)
                recon.unlink(missing_ok=True)
                self._run([str(decoder), "-b", str(bitstream), "-o", str(recon), "-d", str(depth)], decoding=True)
                count = 3 if chroma else 1
                out[first : first + count] = _read_yuv(recon, count, coded_h, coded_w, depth, index)
        planes = restore_samples(out[:, :height, :width], check_depth(depths, shift, bit_depth), shift, bit_depth)
        return self._check_decoded(self.name, planes, shape)

    def _run(self, command: list[str], decoding: bool = False) -> None:
        """Run an HM binary; its failure becomes one clear error with the tail of its output."""
        try:
            result = subprocess.run(command, capture_output=True, text=True, timeout=self.timeout, check=False)
        except subprocess.TimeoutExpired:
            raise CodecUnavailableError(f"hm: {Path(command[0]).name} ran past {self.timeout:.0f} s") from None
        except OSError as exc:
            raise CodecUnavailableError(f"hm: cannot run {command[0]} ({exc}); {HOW_TO_GET}") from None
        if result.returncode != 0:
            tail = " | ".join((result.stdout + result.stderr).strip().splitlines()[-3:])
            error = BitstreamError if decoding else ValidationError
            raise error(f"hm: {Path(command[0]).name} failed with status {result.returncode}: {tail}")


@functools.lru_cache(maxsize=4)
def hm_version(encoder: Path, decoder: Path) -> str:
    """'HM <version>' as the encoder prints it in its banner (run once with --help)."""
    try:
        result = subprocess.run([str(encoder), "--help"], capture_output=True, text=True, timeout=60, check=False)
        match = re.search(r"Version \[([^\]]+)\]", result.stdout + result.stderr)
    except (OSError, subprocess.TimeoutExpired):
        match = None
    return f"HM {match.group(1)} ({encoder.name})" if match else f"HM (version unknown, {encoder.name})"


def _write_yuv(path: Path, picture: np.ndarray, depth: int) -> None:
    """One planar picture (1 or 3 planes): 8-bit samples, or 16-bit little-endian above 8 bits."""
    picture.astype("<u2" if depth > 8 else np.uint8).tofile(path)


def _read_yuv(path: Path, planes: int, height: int, width: int, depth: int, index: int) -> np.ndarray:
    """The first ``planes`` planes of HM's reconstruction (a 4:0:0 file may carry filler chroma)."""
    itemsize = 2 if depth > 8 else 1
    needed = planes * height * width * itemsize
    if not path.is_file() or path.stat().st_size < needed:
        raise BitstreamError(f"hm stream {index} decoded to less than one {width}x{height} picture")
    with path.open("rb") as handle:
        raw = handle.read(needed)
    samples = np.frombuffer(raw, dtype="<u2" if itemsize == 2 else np.uint8)
    return samples.reshape(planes, height, width).astype(np.uint16)
