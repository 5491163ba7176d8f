"""Decoded renders an RD sweep keeps for looking at (the HTML report's image comparison).

Each run saves its render of the scene's first test view as an 8-bit PNG, and the scene's
uncompressed render and ground truth of the same view once, under ``OUT/renders/``:

    renders/<scene>/uncompressed.png, renders/<scene>/ground_truth.png (when the scene has it),
    renders/<scene>/<method>/<rate point>.png

Paths follow from the names alone, so a report finds them without extra result columns.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

FOLDER = "renders"


def _part(name: str) -> str:
    """A name made safe as one path component (rate points can be ``ladder:rp3`` or paths)."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_") or "_"


def scene_dir(out_dir: str | Path, scene: str) -> Path:
    return Path(out_dir) / FOLDER / _part(scene)


def run_render_path(out_dir: str | Path, scene: str, method: str, rate_point: str) -> Path:
    return scene_dir(out_dir, scene) / _part(method) / f"{_part(rate_point)}.png"


def reference_paths(out_dir: str | Path, scene: str) -> tuple[Path, Path]:
    """(uncompressed render, ground truth) of the scene's first test view."""
    folder = scene_dir(out_dir, scene)
    return folder / "uncompressed.png", folder / "ground_truth.png"


def save_run_view(out_dir: str | Path, scene: str, method: str, rate_point: str, decoded: np.ndarray,
                  reference: np.ndarray, ground_truth: np.ndarray | None) -> Path:
    """Save one run's first test view (and, once per scene, the uncompressed one and ground truth)."""
    from gscodec_shac.render.output import save_png

    uncompressed, truth = reference_paths(out_dir, scene)
    path = run_render_path(out_dir, scene, method, rate_point)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not uncompressed.is_file():
        save_png(uncompressed, reference)
    if ground_truth is not None and not truth.is_file():
        save_png(truth, ground_truth)
    save_png(path, decoded)
    return path
