"""Ship the repository's top-level ``rate_points/`` inside the wheel as ``gscodec_shac/rate_points/``.

The YAML rate points live at the repository root (data, not code; one source). A wheel
(``pip install .``) gets a copy next to the package, where
:func:`gscodec_shac.codec.rate_points.rate_point_folder` finds it; a checkout or an
editable install reads the root folder directly. Everything else is in pyproject.toml.
"""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent


class BuildPyWithRatePoints(build_py):
    """``build_py`` that also copies ``rate_points/*.yaml`` into the built package."""

    def run(self) -> None:
        super().run()
        target = Path(self.build_lib) / "gscodec_shac" / "rate_points"
        target.mkdir(parents=True, exist_ok=True)
        for source in sorted((ROOT / "rate_points").glob("*.yaml")):
            shutil.copy2(source, target / source.name)


setup(cmdclass={"build_py": BuildPyWithRatePoints})
