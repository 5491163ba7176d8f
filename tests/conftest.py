"""Shared fixtures: synthetic scenes made in code and the optional real data in ../shared."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path
from types import ModuleType

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
#: Real scenes: $GSCODEC_SHARED_SCENES, else ../shared/data/scenes beside the checkout.
SHARED_SCENES = Path(os.environ.get("GSCODEC_SHARED_SCENES", REPO_ROOT.parent / "shared" / "data" / "scenes"))


def load_script(name: str) -> ModuleType:
    """The module of ``scripts/<name>.py`` (the scripts are not a package)."""
    spec = importlib.util.spec_from_file_location(name, REPO_ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


#: Tests `make test-fast` leaves out: measured-slow node ids and modules (scripts/slow_tests.py).
SLOW_LIST = Path(__file__).with_name("slow_tests.txt")


def slow_entries(path: Path = SLOW_LIST) -> list[str]:
    """Node ids (``tests/test_x.py::name[param]``) and modules (``tests/test_x.py``) in the slow list."""
    if not path.is_file():
        return []
    lines = (line.split("#", 1)[0].strip() for line in path.read_text().splitlines())
    return [line for line in lines if line]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark ``slow`` every test named in tests/slow_tests.txt (``-m "not slow"`` is the fast tier)."""
    entries = slow_entries()
    modules = {e for e in entries if "::" not in e}
    nodes = {e for e in entries if "::" in e}
    for item in items:
        module = item.nodeid.split("::", 1)[0]
        if module in modules or item.nodeid in nodes:
            item.add_marker(pytest.mark.slow)


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
