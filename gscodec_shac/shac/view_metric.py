"""How much each SH AC coefficient shows in the views a scene is seen from (rate controller version 18).

A Gaussian's view-dependent colour from direction ``d`` is ``sum_k c_k Y_k(d)``, so an error ``e``
in its AC coefficients shows as ``(sum_k e_k Y_k(d))^2`` in the pixels it covers in that view.
Summed over the pixels of the cameras, occlusion aside, the error is ``e^T G e`` with

    G = sum over Gaussians g and cameras v that see g of  w_gv Y(d_gv) Y(d_gv)^T,
    d_gv = (mu_g - c_v) / |mu_g - c_v|,   w_gv = opacity_g * (area of g's two largest axes) / |mu_g - c_v|^2

(``w_gv``: the Gaussian's share of the picture; :func:`footprints`). Over directions spread evenly
on the sphere the real SH basis is orthonormal and ``G`` is a multiple of the identity: every
coefficient counts alike, as the paper's SHAC-PCA (eq. 23-29) assumes. Real captures are not seen
from everywhere: on Mip-NeRF 360 bonsai the eigenvalues of the unweighted ``G`` (degree 3, mean 1)
span 0.22-2.07, on the snowmiku phone capture 0.04-1.6. SHAC-PCA fitted in this metric
(:meth:`ShacPCA.set_metric`) orders and water-fills its components by what the cameras see.

The footprint weights matter: unweighted, the far background of a phone capture (seen from one
direction by every camera) made up most of ``G`` and the SH curve of snowmiku was 7% worse on its
held-out views than the paper's (docs/rate_control.md, "Controller version 18").

``G`` is normalised to a mean eigenvalue of 1 and mixed with the identity (:data:`IDENTITY_SHARE`),
so directions no camera saw keep some weight: a view between the cameras still gets its colours.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from gscodec_shac.camera import Camera
from gscodec_shac.errors import ValidationError
from gscodec_shac.sh import sh_basis

if TYPE_CHECKING:
    from gscodec_shac.gaussians import GaussianCloud

#: The identity's share in the metric: directions the cameras do not see keep this much weight. Set at 0.1
#: a priori and kept: 0.3 did better for the SH stage alone at one plan on bonsai and snowmiku, worse for
#: the rate controller's curves on both (docs/rate_control.md, "Controller version 18").
IDENTITY_SHARE = 0.1
#: (Gaussian, camera) pairs sampled for the sum: the Gaussians are a seeded sample of this many over the
#: number of cameras (at least :data:`MIN_SAMPLE`); the metric is a 15 x 15 mean, steady at this size.
PAIRS = 1_000_000
MIN_SAMPLE = 2_000


def view_metric(means: np.ndarray, cameras: Sequence[Camera] | np.ndarray, degree: int, *,
                footprints: np.ndarray | None = None, identity_share: float = IDENTITY_SHARE, pairs: int = PAIRS,
                seed: int = 0) -> np.ndarray:
    """The (3K', 3K') metric of the AC matrix's columns (coefficient-major, R, G, B interleaved, as
    :meth:`GaussianCloud.ac_matrix` lays them out) for Gaussians at ``means`` seen from ``cameras``:
    ``kron(G, I_3)`` with ``G`` as in the module docstring. A :class:`Camera` counts the Gaussians
    inside its picture only; a row of an (M, 3) array is a camera centre that sees every Gaussian."""
    means = np.asarray(means, dtype=np.float64)
    if not isinstance(cameras, np.ndarray) and any(isinstance(c, Camera) for c in cameras):
        views = list(cameras)
    else:
        views = list(np.asarray(cameras, dtype=np.float64).reshape(-1, 3))
    if degree < 1:
        raise ValidationError("a view metric needs SH degree >= 1")
    if not views:
        raise ValidationError("a view metric needs at least one camera")
    if not 0.0 <= identity_share <= 1.0:
        raise ValidationError(f"identity_share must be in [0, 1], got {identity_share}")
    sample = max(MIN_SAMPLE, pairs // len(views))
    rng = np.random.default_rng(seed)
    area = None if footprints is None else np.asarray(footprints, dtype=np.float64).reshape(-1)
    if means.shape[0] <= sample:
        rows = np.arange(means.shape[0])
    elif area is None:
        rows = np.sort(rng.choice(means.shape[0], sample, replace=False))
    else:  # drawn by footprint (a few large Gaussians carry much of the sum), each then counts alike
        rows = np.sort(rng.choice(means.shape[0], sample, replace=True, p=area / area.sum()))
        area = np.ones(means.shape[0])
    k = (degree + 1) ** 2 - 1
    gram = np.zeros((k, k))
    count = 0
    points = means[rows]
    area = None if area is None else area[rows]
    for view in views:  # one camera at a time: (sample, K') at most
        seen = _in_picture(view, points)
        d = points[seen] - (view.center if isinstance(view, Camera) else view)
        norm = np.linalg.norm(d, axis=1)
        near = norm > 0
        d, norm = d[near] / norm[near, None], norm[near]
        weight = np.ones(d.shape[0]) if area is None else area[seen][near] / norm ** 2
        basis = sh_basis(d, degree)[:, 1:]
        gram += (basis * weight[:, None]).T @ basis
        count += weight.sum()
    if count == 0:
        raise ValidationError(f"none of the {len(views)} cameras frames a visible Gaussian of the model, so they "
                              "cannot weigh its SH (a camera file of another scene, or another axis convention?)")
    gram /= count
    gram *= k / np.trace(gram)
    gram = (1.0 - identity_share) * gram + identity_share * np.eye(k)
    return np.kron(gram, np.eye(3))


def cloud_view_metric(cloud: GaussianCloud, cameras: Sequence[Camera]) -> np.ndarray:
    """:func:`view_metric` of ``cloud``'s Gaussians weighed by their :func:`footprints`, as the rate
    controller and ``encode --cameras`` fit SHAC-PCA in it."""
    return view_metric(cloud.means, cameras, cloud.sh_degree,
                       footprints=footprints(cloud.scales, cloud.activated_opacities()))


def metric_applies(stage: str, params: dict) -> bool:
    """Whether an SH stage (rate-point ``sh_stage`` and ``sh_params``) takes a view metric: SHAC-PCA
    over R, G and B together, without the DC (:meth:`ShacPCA.set_metric`), with one basis or one per
    spatial region (``pca-spatial``)."""
    if stage == "pca-spatial":
        return True
    return stage == "pca" and bool(params.get("joint_rgb", True)) and not params.get("include_dc", False)


def footprints(log_scales: np.ndarray, opacities: np.ndarray) -> np.ndarray:
    """Each Gaussian's weight in the picture at unit distance: its opacity times the area of its two
    largest axes (``exp`` of their log scales; the picture's area falls with the squared distance)."""
    axes = np.sort(np.asarray(log_scales, dtype=np.float64), axis=1)
    return np.asarray(opacities, dtype=np.float64).reshape(-1) * np.exp(axes[:, -1] + axes[:, -2])


def _in_picture(view: Camera | np.ndarray, points: np.ndarray) -> np.ndarray:
    """Which ``points`` a camera sees in its picture (in front of it, inside the image); all for a bare centre."""
    if not isinstance(view, Camera):
        return np.ones(points.shape[0], dtype=np.bool_)
    uv, depth = view.project(points)
    with np.errstate(invalid="ignore"):
        return (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < view.width) & (uv[:, 1] >= 0) & (uv[:, 1] < view.height)
