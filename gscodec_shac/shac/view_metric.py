"""How much each SH AC coefficient shows in the views a scene is seen from (rate controller version 18).

A Gaussian's view-dependent colour from direction ``d`` is ``sum_k c_k Y_k(d)``, so an error ``e``
in its AC coefficients shows as ``(sum_k e_k Y_k(d))^2`` in that view. Averaged over the Gaussians
and the cameras it is ``e^T G e`` with

    G = mean over Gaussians g and cameras v of  Y(d_gv) Y(d_gv)^T,   d_gv = (mu_g - c_v) / |mu_g - c_v|.

Over directions spread evenly on the sphere the real SH basis is orthonormal and ``G`` is a multiple
of the identity: every coefficient counts alike, which is what the paper's SHAC-PCA (eq. 23-29)
assumes. A capture seen from a ring of cameras is not: on Mip-NeRF 360 bonsai the eigenvalues of
``G`` (degree 3, normalised to a mean of 1) span 0.22-2.07, the same from the training and the
held-out cameras. SHAC-PCA fitted in this metric (:meth:`ShacPCA.set_metric`) orders and water-fills its
components by what the cameras see.

``G`` is normalised to a mean eigenvalue of 1 and mixed with the identity (:data:`IDENTITY_SHARE`),
so directions no camera saw keep some weight: a view between the cameras still gets its colours.
"""

from __future__ import annotations

import numpy as np

from gscodec_shac.errors import ValidationError
from gscodec_shac.sh import sh_basis

#: The identity's share in the metric: directions the cameras do not see keep this much weight.
IDENTITY_SHARE = 0.1
#: Gaussians sampled for the average (seeded; the metric is a 15 x 15 mean, steady at this size).
SAMPLE = 20_000


def view_metric(means: np.ndarray, centres: np.ndarray, degree: int, *, identity_share: float = IDENTITY_SHARE,
                sample: int = SAMPLE, seed: int = 0) -> np.ndarray:
    """The (3K', 3K') metric of the AC matrix's columns (coefficient-major, R, G, B interleaved, as
    :meth:`GaussianCloud.ac_matrix` lays them out) for Gaussians at ``means`` seen from cameras at
    ``centres``: ``kron(G, I_3)`` with ``G`` as in the module docstring."""
    means = np.asarray(means, dtype=np.float64)
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    if degree < 1:
        raise ValidationError("a view metric needs SH degree >= 1")
    if centres.shape[0] == 0:
        raise ValidationError("a view metric needs at least one camera")
    if not 0.0 <= identity_share <= 1.0:
        raise ValidationError(f"identity_share must be in [0, 1], got {identity_share}")
    rng = np.random.default_rng(seed)
    rows = rng.choice(means.shape[0], sample, replace=False) if means.shape[0] > sample else np.arange(means.shape[0])
    k = (degree + 1) ** 2 - 1
    gram = np.zeros((k, k))
    count = 0
    for centre in centres:  # one camera at a time: (sample, K') at most
        d = means[rows] - centre
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        d = d[norm[:, 0] > 0] / norm[norm[:, 0] > 0]
        basis = sh_basis(d, degree)[:, 1:]
        gram += basis.T @ basis
        count += d.shape[0]
    if count == 0:
        raise ValidationError("a view metric needs Gaussians away from the cameras")
    gram /= count
    gram *= k / np.trace(gram)
    gram = (1.0 - identity_share) * gram + identity_share * np.eye(k)
    return np.kron(gram, np.eye(3))
