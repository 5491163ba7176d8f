"""Fixed-budget density control in the spirit of "3D Gaussian Splatting as MCMC" (Kheradmand et
al. 2024), the strategy the paper's gsplat runs use to set the number of Gaussians N.

What is implemented (a compact, CPU version of the published method):

* **Relocation** (:func:`relocate`): "dead" Gaussians (opacity ``<= min_opacity``, 0.005) are
  moved onto live ones drawn with probability proportional to opacity (with replacement). A
  source drawn ``k`` times ends up as ``n = k + 1`` identical Gaussians whose opacity is
  ``1 - (1 - o)^(1/n)`` and whose scales are multiplied by
  ``o / sum_{i=1..n} sum_{j=0..i-1} C(i-1, j) (-1)^j o_n^(j+1) / sqrt(j+1)`` (the paper's
  moment-preserving rule, ``o_n`` the new opacity), so that the rendered sum is approximately
  unchanged. Sources and the moved rows get zero Adam moments.
* **Growth** (:func:`grow`): new Gaussians are added the same way (sources drawn by opacity,
  the copies appended) until ``cap`` is reached; ``growth`` sets the fraction added per step.
* **Noise** (:func:`inject_noise`): after every optimiser step each mean moves by
  ``Sigma @ eps * sigmoid(100 (1 - o - 0.995)) * noise_lr * lr_means`` with ``eps ~ N(0, I)``
  and ``Sigma`` its 3D covariance: transparent Gaussians explore, opaque ones barely move
  (gates below 1e-6 are skipped, a negligible move, to save the covariances).
* **Regularisers** (:func:`regularizer_grads`): ``opacity_reg * mean(o) + scale_reg *
  mean(exp(s))`` added to the loss (0.01 each) so that unused Gaussians fade and get relocated.

Simplifications (documented, not in the paper): the copy count per source is capped at 51 (as
gsplat does); no other heuristics (no opacity reset, no gradient-based cloning).
"""

from __future__ import annotations

import math

import numpy as np

from gscodec_shac.geometry import covariances
from gscodec_shac.train.model import GaussianModel, inverse_sigmoid

#: Largest number of copies one source is split into per relocation step.
MAX_COPIES = 51
#: Gaussians whose noise gate is below this (opacity above ~0.14) are not moved: their noise
#: would be below ~1e-8 scene units.
NOISE_GATE_MIN = 1e-6


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(x, dtype=np.float64)))


def relocation_update(opacity: np.ndarray, copies: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(new opacity, scale factor)`` for sources of opacity ``o`` turned into ``copies`` Gaussians."""
    o = np.clip(np.asarray(opacity, dtype=np.float64), 1e-12, 1.0 - 1e-12)
    n = np.clip(np.asarray(copies, dtype=np.int64), 1, MAX_COPIES)
    new_o = 1.0 - np.power(1.0 - o, 1.0 / n)
    total = np.zeros_like(o)
    for i in range(1, int(n.max()) + 1):
        active = n >= i
        for j in range(i):
            coeff = math.comb(i - 1, j) * (-1.0) ** j / math.sqrt(j + 1.0)
            total += np.where(active, coeff * np.power(new_o, j + 1), 0.0)
    factor = o / np.maximum(total, 1e-12)
    return new_o, factor


def _sample_sources(opacity: np.ndarray, candidates: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    weights = opacity[candidates]
    total = weights.sum()
    if count <= 0 or candidates.size == 0 or not total > 0:
        return np.zeros(0, dtype=np.int64)
    return candidates[rng.choice(candidates.size, size=count, replace=True, p=weights / total)]


def _apply_copies(model: GaussianModel, sources: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Update opacity and scales of each distinct source for its copy count; returns
    ``(unique sources, their counts, the source of every drawn copy)``."""
    unique, counts = np.unique(sources, return_counts=True)
    opacity = _sigmoid(model.params["opacities"][unique])
    new_o, factor = relocation_update(opacity, counts + 1)
    new_o = np.clip(new_o, 1e-6, 1.0 - 1e-6)
    model.params["opacities"][unique] = inverse_sigmoid(new_o).astype(np.float32)
    scales = np.exp(model.params["scales"][unique].astype(np.float64)) * factor[:, None]
    model.params["scales"][unique] = np.log(np.maximum(scales, 1e-12)).astype(np.float32)
    return unique, counts, sources


def relocate(model: GaussianModel, rng: np.random.Generator, min_opacity: float = 0.005) -> int:
    """Move dead Gaussians onto live ones (in place); returns how many moved."""
    opacity = _sigmoid(model.params["opacities"])
    dead = np.flatnonzero(opacity <= min_opacity)
    alive = np.flatnonzero(opacity > min_opacity)
    if dead.size == 0 or alive.size == 0:
        return 0
    sources = _sample_sources(opacity, alive, dead.size, rng)
    unique, _, _ = _apply_copies(model, sources)
    for k in model.names:
        model.params[k][dead] = model.params[k][sources]
    model.reset_moments(np.concatenate([unique, dead]))
    return int(dead.size)


def grow(model: GaussianModel, rng: np.random.Generator, cap: int, growth: float) -> int:
    """Append ``min(cap, (1 + growth) N) - N`` Gaussians drawn by opacity; returns how many."""
    n = model.num_gaussians
    target = min(int(cap), int(math.floor((1.0 + growth) * n)))
    count = max(0, target - n)
    if count == 0:
        return 0
    opacity = _sigmoid(model.params["opacities"])
    sources = _sample_sources(opacity, np.arange(n), count, rng)
    if sources.size == 0:
        return 0
    unique, _, _ = _apply_copies(model, sources)
    model.append(model.rows(sources))
    model.reset_moments(unique)
    return int(sources.size)


def inject_noise(model: GaussianModel, lr_means: float, rng: np.random.Generator, noise_lr: float = 5e5) -> None:
    """Covariance-shaped position noise, large for transparent Gaussians (in place)."""
    p = model.params
    opacity = _sigmoid(p["opacities"])
    gate = 1.0 / (1.0 + np.exp(-100.0 * ((1.0 - opacity) - 0.995)))
    eps = rng.normal(size=p["means"].shape) * (gate * noise_lr * lr_means)[:, None]
    moving = np.flatnonzero(gate > NOISE_GATE_MIN)
    if moving.size == 0:
        return
    cov = covariances(p["scales"][moving], p["quats"][moving])
    p["means"][moving] += np.einsum("nij,nj->ni", cov, eps[moving]).astype(np.float32)


def regularizer_grads(
    model: GaussianModel, opacity_reg: float, scale_reg: float
) -> tuple[float, np.ndarray, np.ndarray]:
    """``(loss, d/d logits, d/d log-scales)`` of ``opacity_reg mean(o) + scale_reg mean(exp(s))``."""
    n = model.num_gaussians
    o = _sigmoid(model.params["opacities"])
    s = np.exp(model.params["scales"].astype(np.float64))
    loss = opacity_reg * float(o.mean()) + scale_reg * float(s.mean())
    return loss, opacity_reg * o * (1.0 - o) / n, scale_reg * s / s.size
