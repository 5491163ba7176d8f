"""What the plan experiments share (scripts/sh_view_metric.py, scripts/rotation_form.py): a model and its
cameras, split into the rate controller's views and the held-out ones, and the mean PSNR of renders."""

from __future__ import annotations

import argparse
import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gscodec_shac.camera import Camera, test_split
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.cameras import load_cameras
from gscodec_shac.io.models import read_model
from gscodec_shac.metrics import psnr
from gscodec_shac.render import Renderer


def add_scene_arguments(parser: argparse.ArgumentParser, *, bpg: float, model: str = "a 3DGS model (PLY)",
                        cameras: str = "the scene's cameras") -> None:
    """The model, its cameras and held-out split, the background, the plan's bits per Gaussian, a CSV."""
    parser.add_argument("model", help=model)
    parser.add_argument("--cameras", required=True, help=cameras)
    parser.add_argument("--test-every", type=int, default=8, help="every N-th camera is held out (1: all are)")
    parser.add_argument("--background", default="0,0,0", help="R,G,B in [0, 1]")
    parser.add_argument("--bpg", type=float, default=bpg, help="the plan whose other settings stay fixed")
    parser.add_argument("--csv", type=Path, help="one row per encode")


@dataclass
class HeldOutScene:
    """A model with the controller's views (``train``; the held-out ones when there are no others)
    and the held-out views (``test``)."""

    cloud: GaussianCloud
    train: list[Camera]
    test: list[Camera]
    background: tuple[float, ...]

    @classmethod
    def from_arguments(cls, args: argparse.Namespace) -> "HeldOutScene":
        background = tuple(float(v) for v in args.background.split(","))
        cloud, _ = read_model(args.model)
        train, test = test_split(load_cameras(args.cameras), args.test_every)
        return cls(cloud, train or test, test, background)

    def references(self) -> list[np.ndarray]:
        """The uncompressed model's renders of the held-out views."""
        renderer = Renderer(self.cloud)
        return [np.clip(renderer.render(v, background=self.background).image, 0, 1) for v in self.test]

    def mean_psnr(self, cloud: GaussianCloud, references: list[np.ndarray]) -> float:
        """Mean PSNR of ``cloud``'s renders of the held-out views against ``references``."""
        renderer = Renderer(cloud)
        return float(np.mean([psnr(np.clip(renderer.render(v, background=self.background).image, 0, 1), ref)
                              for v, ref in zip(self.test, references)]))


def write_rows(path: Path | None, rows: list[dict]) -> None:
    """The encodes' rows as CSV (nothing without a path)."""
    if path is None or not rows:
        return
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
