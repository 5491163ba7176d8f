"""Debug record of every x265 stream: ``GSCODEC_X265_DUMP=DIR`` (off by default).

For each stream :func:`.hevc.encode_frames` codes, one JSON line is appended to
``DIR/x265-<pid>.jsonl``: the sha256 of the input frames (their shapes, dtypes and
samples), the pixel format, the codec options, and the sha256 and length of the
stream x265 wrote. The frames themselves are kept once per distinct input as
``DIR/frames-<input sha256 prefix>.npz`` so a piece can be fed to x265 again. Two runs of
one encode then tell whether a differing stream had a differing input (ours) or the
same input (x265): ``scripts/x265_repeat.py`` compares the records and re-codes pieces.
"""

from __future__ import annotations

import hashlib
import json
import os

import numpy as np

#: Environment variable naming the directory the records go to (unset or empty: no record).
ENV = "GSCODEC_X265_DUMP"


def input_digest(frames: list[np.ndarray]) -> str:
    """sha256 of the frames' shapes, dtypes and samples (C order)."""
    digest = hashlib.sha256()
    for frame in frames:
        frame = np.ascontiguousarray(frame)
        digest.update(f"{frame.shape}{frame.dtype.str};".encode())
        digest.update(memoryview(frame).cast("B"))
    return digest.hexdigest()


def record(frames: list[np.ndarray], pix_fmt: str, options: dict[str, str], stream: bytes) -> None:
    """Append one stream's record to ``$GSCODEC_X265_DUMP`` (nothing when it is unset)."""
    folder = os.environ.get(ENV, "")
    if not folder:
        return
    os.makedirs(folder, exist_ok=True)
    source = input_digest(frames)
    kept = os.path.join(folder, f"frames-{source[:16]}.npz")
    if not os.path.exists(kept):
        temporary = f"{kept}.{os.getpid()}.tmp.npz"
        np.savez(temporary, *frames)
        os.replace(temporary, kept)
    line = json.dumps({
        "input": source, "shape": [list(f.shape) for f in frames], "dtype": str(frames[0].dtype),
        "pix_fmt": pix_fmt, "options": options,
        "output": hashlib.sha256(stream).hexdigest(), "bytes": len(stream),
    }, sort_keys=True)
    with open(os.path.join(folder, f"x265-{os.getpid()}.jsonl"), "a", encoding="utf-8") as out:
        out.write(line + "\n")


def load_frames(path: str) -> list[np.ndarray]:
    """The frames a record kept (``frames-*.npz``), in their order."""
    with np.load(path) as kept:
        return [kept[f"arr_{i}"] for i in range(len(kept.files))]
