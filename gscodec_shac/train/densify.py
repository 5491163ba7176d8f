"""Adaptive density control of the reference 3DGS trainer (clone, split, prune, opacity reset).

Statistics (:class:`DensifyStats`): per Gaussian, the sum of the view-space gradient norms
(the NDC 2D-mean gradient, :mod:`gscodec_shac.render.backward`) over the views where it was
visible, the number of those views, and its largest screen radius.

:func:`densify_and_prune` with the reference's rules:

* candidates: mean view-space gradient ``>= grad_threshold`` (2e-4);
* **clone** the small ones (largest scale ``<= percent_dense * extent``, 1%): an exact copy;
* **split** the large ones into 2 samples drawn from the Gaussian itself (``N(0, diag(s^2))``
  rotated), scales divided by ``0.8 * 2``, other attributes copied; the original is removed;
* **prune** opacity ``< min_opacity`` (0.005) and, after the first opacity reset, Gaussians
  whose screen radius exceeded 20 px or whose largest scale exceeds 10% of the extent.

``max_gaussians`` (not in the reference) caps the count: when clones + splits would pass it,
only the candidates with the largest gradients are densified. New rows start with zero Adam
moments (as the reference's concatenated optimiser state); every per-Gaussian array — SH rest
or the LST subset ``S`` included — is cloned, split and pruned alike by
:class:`~gscodec_shac.train.model.GaussianModel`'s row operations. The statistics are reset
after each call, as in the reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gscodec_shac.geometry import quat_to_rotmat
from gscodec_shac.train.model import GaussianModel, inverse_sigmoid


@dataclass
class DensifyStats:
    """Accumulated densification statistics (one entry per Gaussian)."""

    grad_accum: np.ndarray
    denom: np.ndarray
    max_radii: np.ndarray

    @classmethod
    def zeros(cls, n: int) -> "DensifyStats":
        return cls(np.zeros(n), np.zeros(n), np.zeros(n, dtype=np.int32))

    def update(self, ndc_grad_norm: np.ndarray, radii: np.ndarray) -> None:
        visible = radii > 0
        self.grad_accum[visible] += ndc_grad_norm[visible]
        self.denom[visible] += 1
        self.max_radii[visible] = np.maximum(self.max_radii[visible], radii[visible])

    def mean_grad(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            g = self.grad_accum / self.denom
        return np.where(np.isfinite(g), g, 0.0)

    def select(self, index: np.ndarray) -> None:
        self.grad_accum = self.grad_accum[index]
        self.denom = self.denom[index]
        self.max_radii = self.max_radii[index]


@dataclass
class DensifyResult:
    cloned: int
    split: int
    pruned: int


def densify_and_prune(
    model: GaussianModel,
    stats: DensifyStats,
    *,
    grad_threshold: float,
    extent: float,
    percent_dense: float,
    min_opacity: float,
    max_screen_size: float | None,
    rng: np.random.Generator,
    max_gaussians: int | None = None,
) -> DensifyResult:
    """Clone, split and prune in place (see the module docstring); resets ``stats``."""
    n = model.num_gaussians
    grads = stats.mean_grad()
    max_scale = np.exp(model.params["scales"].astype(np.float64)).max(axis=1)
    candidates = grads >= grad_threshold
    if max_gaussians is not None:
        budget = max(0, max_gaussians - n)
        idx = np.flatnonzero(candidates)
        if idx.size > budget:
            keep = idx[np.argsort(-grads[idx], kind="stable")[:budget]]
            candidates = np.zeros(n, dtype=bool)
            candidates[keep] = True
    small = max_scale <= percent_dense * extent
    clone_idx = np.flatnonzero(candidates & small)
    split_idx = np.flatnonzero(candidates & ~small)

    # clone: exact copies
    new_rows = [model.rows(clone_idx)]
    # split: 2 samples per selected Gaussian
    if split_idx.size:
        rows = model.rows(split_idx)
        stds = np.exp(rows["scales"].astype(np.float64))
        rot = quat_to_rotmat(rows["quats"])
        samples = []
        for _ in range(2):
            local = rng.normal(size=stds.shape) * stds
            child = {k: v.copy() for k, v in rows.items()}
            child["means"] = rows["means"] + np.einsum("nij,nj->ni", rot, local)
            child["scales"] = np.log(stds / (0.8 * 2))
            samples.append(child)
        new_rows += samples
    new = {k: np.concatenate([r[k] for r in new_rows]) for k in model.names}
    model.append(new)
    added = new["means"].shape[0]
    stats.grad_accum = np.concatenate([stats.grad_accum, np.zeros(added)])
    stats.denom = np.concatenate([stats.denom, np.zeros(added)])
    stats.max_radii = np.concatenate([stats.max_radii, np.zeros(added, dtype=np.int32)])

    opacity = 1.0 / (1.0 + np.exp(-model.params["opacities"].astype(np.float64)))
    prune = opacity < min_opacity
    prune[split_idx] = True
    if max_screen_size is not None:
        big_screen = stats.max_radii > max_screen_size
        big_world = np.exp(model.params["scales"].astype(np.float64)).max(axis=1) > 0.1 * extent
        prune |= big_screen | big_world
    keep = ~prune
    pruned = int(np.count_nonzero(prune)) - split_idx.size
    model.select(keep)
    n_new = model.num_gaussians
    stats.grad_accum = np.zeros(n_new)
    stats.denom = np.zeros(n_new)
    stats.max_radii = np.zeros(n_new, dtype=np.int32)
    return DensifyResult(cloned=int(clone_idx.size), split=int(split_idx.size), pruned=pruned)


def reset_opacity(model: GaussianModel, value: float = 0.01) -> None:
    """Opacities ``min(o, value)`` and zero Adam moments for the opacities (the reference's reset)."""
    cap = np.float32(inverse_sigmoid(value))
    np.minimum(model.params["opacities"], cap, out=model.params["opacities"])
    model.reset_moments(None, ("opacities",))
