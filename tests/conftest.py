"""Shared fixtures: synthetic scenes made in code and the optional real data in ../shared."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
#: Real scenes: $GSCODEC_SHARED_SCENES, else ../shared/data/scenes beside the checkout.
SHARED_SCENES = Path(os.environ.get("GSCODEC_SHARED_SCENES", REPO_ROOT.parent / "shared" / "data" / "scenes"))


def shared_scene(*parts: str) -> Path:
    """Path under ../shared/data/scenes, or skip the test (with the reason) when absent."""
    path = SHARED_SCENES.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data not available: {path} (set GSCODEC_SHARED_SCENES or check out ../shared)")
    return path


@pytest.fixture(scope="session")
def small_scene():
    """A 2,000-Gaussian SH-3 synthetic scene with orbit cameras (seed 0)."""
    from gscodec_shac.synthetic import make_synthetic_scene

    return make_synthetic_scene(2_000, seed=0, n_cameras=8, width=96, height=72)


@pytest.fixture(scope="session")
def small_cloud(small_scene):
    return small_scene.cloud
