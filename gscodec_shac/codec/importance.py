"""Render-based importance of each Gaussian, and pruning by it (rate point ``prune.keep_share``).

A Gaussian's importance is its share of the rendered images: its blending weights
``w_i = alpha_i T_i`` (the factor that multiplies its colour in the blend, paper Eq. 3)
summed over every pixel of every view, each view's sum divided by the view's pixel count,
averaged over the views. It is the global significance of LightGaussian without the volume
factor: exactly what the Gaussian adds to the images, so a Gaussian hidden behind opaque
ones or outside every view scores 0. The sums come from the CPU renderer's blend kernel in
one pass per view (:meth:`gscodec_shac.render.Renderer.contributions`).

Views: the scene's cameras (all of them up to :data:`MAX_VIEWS`, evenly spread by name: a
Gaussian seen by few cameras scores 0 when those are left out, and pruning it shows in exactly
those views) at their own
resolution up to :data:`MAX_WIDTH` pixels wide, else :data:`ORBIT_VIEWS` orbit views around the
model (:func:`gscodec_shac.camera.orbit_views`) :data:`ORBIT_WIDTH` wide. The ranking depends on
the resolution, in both directions: the renderer's 0.3-pixel dilation makes sub-pixel Gaussians
cover more of a coarse image, so a ranking from renders coarser or finer than the views the model
is seen in prunes worse (docs/rate_control.md, "Importance pruning").
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

from gscodec_shac.camera import Camera, orbit_views, spread_views
from gscodec_shac.errors import ValidationError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.progress import optional_bar

if TYPE_CHECKING:
    from gscodec_shac.render import Renderer

#: Orbit views used when the scene has no cameras, and their width (that of ``info --compare``).
ORBIT_VIEWS = 24
ORBIT_WIDTH = 320
#: At most this many of the scene's cameras are rendered, at most this wide.
MAX_VIEWS = 512
MAX_WIDTH = 1024


def importance_views(cloud: GaussianCloud, cameras: Sequence[Camera] | None = None, *,
                     up: Sequence[float] | None = (0.0, 0.0, 1.0), width: int = MAX_WIDTH) -> list[Camera]:
    """The views importance is measured from: ``cameras`` (at most :data:`MAX_VIEWS`, spread evenly
    in name order, at most ``width`` pixels wide) or :data:`ORBIT_VIEWS` orbit views around ``cloud``."""
    if cameras:
        return spread_views(cameras, MAX_VIEWS, width)
    return orbit_views(cloud.means, ORBIT_VIEWS, min(width, ORBIT_WIDTH), up=up, opacities=cloud.activated_opacities())


def gaussian_importance(cloud: GaussianCloud, views: Sequence[Camera], *,
                        renderer: "Renderer | None" = None, progress: bool = False) -> np.ndarray:
    """(N,) float64 mean over ``views`` of each Gaussian's summed blending weight per pixel (``renderer``:
    one of ``cloud`` to use, else a new one; ``progress``: a bar over the views, which a scene's cameras
    make long: about 0.2-0.3 s per view at 1M Gaussians on 2 cores, so 300 cameras take a minute or more)."""
    from gscodec_shac.render import Renderer

    if not views:
        raise ValidationError("importance needs at least one view")
    if renderer is not None and renderer.cloud is not cloud:
        raise ValidationError("importance: the renderer given renders another cloud")
    renderer = renderer or Renderer(cloud)
    total = np.zeros(cloud.num_gaussians)
    for view in optional_bar(views, progress, desc="importance", unit="view", leave=False):
        total += renderer.contributions(view) / (view.width * view.height)
    return total / len(views)


def most_important(importance: np.ndarray, rows: np.ndarray, count: int) -> np.ndarray:
    """The ``count`` of ``rows`` with the highest importance, in increasing row order (ties: lower row first)."""
    if count >= rows.size:
        return rows
    ranked = rows[np.argsort(-importance[rows], kind="stable")]
    return np.sort(ranked[:count])


def most_important_counts(importance: np.ndarray, counts: list[int]) -> list[np.ndarray]:
    """``most_important(importance, all rows, count)`` for each of ``counts``, the rows ranked once."""
    ranked = np.argsort(-importance, kind="stable") if counts else None
    return [np.arange(importance.size) if count >= importance.size else np.sort(ranked[:count]) for count in counts]


def keep_count(n: int, keep_share: float) -> int:
    """Gaussians kept of ``n`` at ``keep_share`` (at least one)."""
    return max(1, int(round(keep_share * n)))
