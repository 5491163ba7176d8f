"""The trainable model: per-Gaussian parameter rows, their Adam state, and (for SHAC-LST) ``T``.

:class:`GaussianModel` keeps every per-Gaussian parameter as one float32 numpy array with one
row per Gaussian (``means``, ``scales`` (log), ``quats`` (w first), ``opacities`` (logits),
``sh_dc``, and either ``sh_rest`` (N, K-1, 3) for full SH or ``sh_subset`` (N, d) for SHAC-LST,
eq. 32) and, per array, Adam's first and second moments. Row operations
(:meth:`~GaussianModel.select`, :meth:`~GaussianModel.append`,
:meth:`~GaussianModel.reset_moments`) act on every array and its moments together, so cloning,
splitting, pruning and relocation keep parameters, LST ``S`` rows and optimiser state
consistent by construction. ``T`` (:class:`~gscodec_shac.shac.lst_torch.LSTModule`, zero
initialised, blocks of eq. 34) is shared and never touched by row operations.

:class:`Adam` is torch's Adam update (``m / (sqrt(v) / sqrt(1 - b2^t) + eps)`` scaled by
``lr / (1 - b1^t)``) in a numba kernel with the reference's ``eps = 1e-15``; as with the
reference (one torch tensor per attribute), each array has one step counter, and rows added by
densification start with zero moments.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

import gscodec_shac.render  # noqa: F401  (sets OMP_WAIT_POLICY before torch loads OpenMP)
import torch  # noqa: E402

from gscodec_shac import sh_index
from gscodec_shac.errors import ValidationError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.sh import C0
from gscodec_shac.shac.lst import ShacLST
from gscodec_shac.shac.lst_torch import LAMBDA_T, LSTConfig, LSTModule

ADAM_EPS = 1e-15
BETA1 = 0.9
BETA2 = 0.999
ROW_PARAMS_FULL = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")
ROW_PARAMS_LST = ("means", "scales", "quats", "opacities", "sh_dc", "sh_subset")


@numba.njit(cache=True, parallel=True)
def _adam_kernel(p, g, m, v, lr, b1, b2, eps, bc1, bc2):  # pragma: no cover - compiled
    step_size = lr / bc1
    root_bc2 = math.sqrt(bc2)
    for i in numba.prange(p.shape[0]):
        for j in range(p.shape[1]):
            gi = g[i, j]
            m[i, j] = b1 * m[i, j] + (1.0 - b1) * gi
            v[i, j] = b2 * v[i, j] + (1.0 - b2) * gi * gi
            p[i, j] -= step_size * m[i, j] / (math.sqrt(v[i, j]) / root_bc2 + eps)


def _rows2d(a: np.ndarray) -> np.ndarray:
    return a.reshape(a.shape[0], -1)


def adam_update(
    param: np.ndarray, grad: np.ndarray, m: np.ndarray, v: np.ndarray, lr: float, step: int,
    beta1: float = BETA1, beta2: float = BETA2, eps: float = ADAM_EPS, columns: int | None = None,
) -> None:
    """One in-place Adam step at 1-based ``step`` on C-contiguous row arrays.

    With ``columns``, only the first ``columns`` values of each (flattened) row are updated and
    ``grad`` holds just those (e.g. the SH rest of the active degree: the other coefficients
    have zero gradient and zero moments, so Adam would leave them unchanged anyway).
    """
    p2, m2, v2 = _rows2d(param), _rows2d(m), _rows2d(v)
    if columns is not None:
        p2, m2, v2 = p2[:, :columns], m2[:, :columns], v2[:, :columns]
    g2 = grad.reshape(p2.shape)
    _adam_kernel(p2, g2, m2, v2, float(lr), beta1, beta2, eps, 1.0 - beta1**step, 1.0 - beta2**step)


def inverse_sigmoid(x: np.ndarray | float) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return np.log(x / (1.0 - x))


def init_scales(points: np.ndarray) -> np.ndarray:
    """log of the RMS distance to the 3 nearest neighbours (the reference's ``distCUDA2`` init)."""
    from scipy.spatial import cKDTree

    n = points.shape[0]
    if n < 2:
        return np.full((n, 3), math.log(0.01))
    k = min(4, n)
    dist, _ = cKDTree(points).query(points, k=k)
    mean_sq = np.maximum(np.mean(dist[:, 1:] ** 2, axis=1), 1e-7)
    return np.repeat(np.log(np.sqrt(mean_sq))[:, None], 3, axis=1)


class GaussianModel:
    """Parameters + Adam moments of a 3DGS model under training (see the module docstring)."""

    def __init__(
        self, params: dict[str, np.ndarray], sh_degree: int, sh_mode: str = "full", lambda_t: float = LAMBDA_T,
        lst_config: LSTConfig | None = None,
    ) -> None:
        if sh_mode not in ("full", "lst"):
            raise ValidationError(f"sh must be 'full' or 'lst', got {sh_mode!r}")
        if not 0 <= sh_degree <= 3:
            raise ValidationError(f"--sh-degree must be 0-3 for training, got {sh_degree}")
        if sh_mode == "lst" and sh_degree < 2:
            raise ValidationError("SHAC-LST needs SH degree 2 or 3")
        self.sh_mode = sh_mode
        self.sh_degree = sh_degree
        self.names = ROW_PARAMS_LST if sh_mode == "lst" else ROW_PARAMS_FULL
        self.params = {k: np.ascontiguousarray(params[k], dtype=np.float32) for k in self.names}
        self.exp_avg = {k: np.zeros_like(v) for k, v in self.params.items()}
        self.exp_avg_sq = {k: np.zeros_like(v) for k, v in self.params.items()}
        self.step = 0
        self.lst: LSTModule | None = None
        self.lst_exp_avg: dict[str, np.ndarray] = {}
        self.lst_exp_avg_sq: dict[str, np.ndarray] = {}
        if sh_mode == "lst":
            if lst_config is None:
                lst_config = LSTConfig(degree=sh_degree, lambda_t=lambda_t)
            elif lst_config.degree != sh_degree:
                raise ValidationError(f"the LST variant is for SH degree {lst_config.degree}, the model has {sh_degree}")
            self.lst = LSTModule(lst_config)
            for key, w in self.lst_parameters().items():
                self.lst_exp_avg[key] = np.zeros(tuple(w.shape), dtype=np.float32)
                self.lst_exp_avg_sq[key] = np.zeros(tuple(w.shape), dtype=np.float32)

    # ------------------------------------------------------------------ construction
    def lst_parameters(self) -> dict[str, torch.nn.Parameter]:
        """Learnable tensors of the LST operator by a stable name: the matrix/vector weights
        under their block keys (``t2``, ``t3``, ``w``), linear/MLP layers as ``net.<name>``."""
        if self.lst is None:
            return {}
        out = dict(self.lst.weights.items())
        if self.lst.net is not None:
            out.update({f"net.{name}": p for name, p in self.lst.net.named_parameters()})
        return out

    @classmethod
    def from_points(
        cls, points: np.ndarray, colors: np.ndarray, sh_degree: int = 3, sh_mode: str = "full",
        opacity: float = 0.1, lambda_t: float = LAMBDA_T, lst_config: LSTConfig | None = None,
    ) -> "GaussianModel":
        """The reference initialisation: DC from the colours, higher SH 0, identity rotations,
        isotropic scales from :func:`init_scales`, opacity ``opacity``."""
        n = points.shape[0]
        if n == 0:
            raise ValidationError("cannot initialise a model from zero points")
        params: dict[str, np.ndarray] = {
            "means": points,
            "scales": init_scales(points),
            "quats": np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
            "opacities": np.full(n, float(inverse_sigmoid(opacity))),
            "sh_dc": (np.asarray(colors, dtype=np.float64) - 0.5) / C0,
        }
        if sh_mode == "lst":
            params["sh_subset"] = np.zeros((n, 3 * (2 * sh_degree + 1)))
        else:
            params["sh_rest"] = np.zeros((n, sh_index.num_rest_coeffs(sh_degree), 3))
        return cls(params, sh_degree, sh_mode, lambda_t, lst_config)

    # ------------------------------------------------------------------ views
    @property
    def num_gaussians(self) -> int:
        return int(self.params["means"].shape[0])

    def __len__(self) -> int:
        return self.num_gaussians

    def sh_rest(self) -> np.ndarray:
        """(N, K-1, 3) float32 SH rest: the parameters (full) or ``S T`` (LST, eq. 33)."""
        if self.sh_mode == "full":
            return self.params["sh_rest"]
        with torch.no_grad():
            ac = self.lst(torch.from_numpy(self.params["sh_subset"])).numpy()
        return sh_index.sh_rest_from_ac(np.ascontiguousarray(ac, dtype=np.float32))

    def lst_stage(self) -> ShacLST:
        """The learned ``T`` as the numpy SH stage (for coding / export)."""
        if self.lst is None:
            raise ValidationError("this model is not SHAC-LST")
        return self.lst.to_stage()

    def to_cloud(self) -> GaussianCloud:
        """A :class:`GaussianCloud` (full SH; LST reconstructed as ``S T``)."""
        p = self.params
        return GaussianCloud(
            means=p["means"], scales=p["scales"], quats=p["quats"], opacities=p["opacities"],
            sh_dc=p["sh_dc"], sh_rest=self.sh_rest().copy(),
        )

    def sh_floats_per_gaussian(self) -> int:
        """SH floats stored per Gaussian: 3 (L+1)^2 (full) or 3 + d (LST, eq. 38 without P_T)."""
        if self.sh_mode == "lst":
            return 3 + self.params["sh_subset"].shape[1]
        return 3 * sh_index.num_coeffs(self.sh_degree)

    def stored_floats(self) -> int:
        """Floats of the stored model: 11 geometry/opacity + SH per Gaussian, plus P_T for LST."""
        extra = self.lst.n_params if self.lst is not None else 0
        return self.num_gaussians * (11 + self.sh_floats_per_gaussian()) + extra

    # ------------------------------------------------------------------ row operations
    def select(self, index: np.ndarray) -> None:
        """Keep (and reorder) rows by an integer index or boolean mask: parameters and moments."""
        index = np.asarray(index)
        for store in (self.params, self.exp_avg, self.exp_avg_sq):
            for k in self.names:
                store[k] = np.ascontiguousarray(store[k][index])

    def append(self, new: dict[str, np.ndarray]) -> None:
        """Add rows (every row parameter must be given); their moments start at zero."""
        missing = set(self.names) - set(new)
        if missing:
            raise ValidationError(f"append needs every row parameter, missing {sorted(missing)}")
        count = {np.asarray(new[k]).shape[0] for k in self.names}
        if len(count) != 1:
            raise ValidationError("append: the new rows must have the same count for every parameter")
        for k in self.names:
            value = np.asarray(new[k], dtype=np.float32).reshape((-1,) + self.params[k].shape[1:])
            self.params[k] = np.concatenate([self.params[k], value])
            zeros = np.zeros_like(value)
            self.exp_avg[k] = np.concatenate([self.exp_avg[k], zeros])
            self.exp_avg_sq[k] = np.concatenate([self.exp_avg_sq[k], zeros])

    def rows(self, index: np.ndarray) -> dict[str, np.ndarray]:
        """Copies of the parameter rows at ``index``."""
        return {k: self.params[k][index].copy() for k in self.names}

    def reset_moments(self, index: np.ndarray | None = None, names: tuple[str, ...] | None = None) -> None:
        """Zero Adam's moments for some rows (all when ``index`` is None) of some parameters."""
        for k in names or self.names:
            if index is None:
                self.exp_avg[k][...] = 0.0
                self.exp_avg_sq[k][...] = 0.0
            else:
                self.exp_avg[k][index] = 0.0
                self.exp_avg_sq[k][index] = 0.0

    # ------------------------------------------------------------------ optimisation
    def adam_step(
        self, grads: dict[str, np.ndarray], lrs: dict[str, float], lst_lr: float | None = None,
        columns: dict[str, int] | None = None,
    ) -> None:
        """One Adam step for every row parameter (and T when ``lst_lr`` is given); ``columns``
        limits a parameter to its first values per row (see :func:`adam_update`)."""
        self.step += 1
        columns = columns or {}
        for k in self.names:
            adam_update(self.params[k], grads[k], self.exp_avg[k], self.exp_avg_sq[k], lrs[k], self.step,
                        columns=columns.get(k))
        if self.lst is not None and lst_lr is not None:
            for key, w in self.lst_parameters().items():
                g = w.grad.numpy() if w.grad is not None else np.zeros(tuple(w.shape), dtype=np.float32)
                adam_update(w.data.numpy(), np.ascontiguousarray(g), self.lst_exp_avg[key], self.lst_exp_avg_sq[key],
                            lst_lr, self.step)
                w.grad = None

    # ------------------------------------------------------------------ state
    def state_arrays(self) -> dict[str, np.ndarray]:
        """Every array (parameters, moments, T and its moments) by a flat name, for checkpoints."""
        out: dict[str, np.ndarray] = {}
        for k in self.names:
            out[f"param/{k}"] = self.params[k]
            out[f"m/{k}"] = self.exp_avg[k]
            out[f"v/{k}"] = self.exp_avg_sq[k]
        if self.lst is not None:
            for key, w in self.lst_parameters().items():
                out[f"lst/{key}"] = w.detach().numpy().copy()
                out[f"lst_m/{key}"] = self.lst_exp_avg[key]
                out[f"lst_v/{key}"] = self.lst_exp_avg_sq[key]
        return out

    def meta(self) -> dict[str, Any]:
        return {
            "sh_mode": self.sh_mode, "sh_degree": self.sh_degree, "step": self.step,
            "lambda_t": self.lst.config.lambda_t if self.lst is not None else LAMBDA_T,
            "lst": self.lst.config.as_dict() if self.lst is not None else None,
        }

    @classmethod
    def from_state(cls, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> "GaussianModel":
        """Inverse of :meth:`state_arrays` + :meth:`meta`."""
        names = ROW_PARAMS_LST if meta["sh_mode"] == "lst" else ROW_PARAMS_FULL
        lst_config = LSTConfig(**meta["lst"]) if meta.get("lst") else None
        model = cls({k: arrays[f"param/{k}"] for k in names}, int(meta["sh_degree"]), meta["sh_mode"],
                    float(meta.get("lambda_t", LAMBDA_T)), lst_config)
        for k in names:
            model.exp_avg[k] = np.ascontiguousarray(arrays[f"m/{k}"], dtype=np.float32)
            model.exp_avg_sq[k] = np.ascontiguousarray(arrays[f"v/{k}"], dtype=np.float32)
        model.step = int(meta["step"])
        if model.lst is not None:
            with torch.no_grad():
                for key, w in model.lst_parameters().items():
                    w.copy_(torch.from_numpy(np.asarray(arrays[f"lst/{key}"], dtype=np.float32)))
                    model.lst_exp_avg[key] = np.ascontiguousarray(arrays[f"lst_m/{key}"], dtype=np.float32)
                    model.lst_exp_avg_sq[key] = np.ascontiguousarray(arrays[f"lst_v/{key}"], dtype=np.float32)
        return model
