"""gscodec-shac: low-rank SH compression (SHAC) for 2D-mapped 3D Gaussian Splatting codecs.

The package is organised as small modules with one job each; see README.md
and ``../shared/DESIGN.md`` for the data flow
(PLY -> GaussianCloud -> sort -> SH stage -> quantise -> grid codec -> container).
"""

from gscodec_shac.errors import GscodecError
from gscodec_shac.gaussians import GaussianCloud

__version__ = "0.1.0"

__all__ = ["GaussianCloud", "GscodecError", "__version__"]
