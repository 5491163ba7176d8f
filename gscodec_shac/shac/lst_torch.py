"""Torch parameterisation of SHAC-LST for training (paper Sec. V-B2-3, VI-B2, VII-E).

:class:`LSTModule` maps the per-Gaussian subset ``S`` (N x d, a trainable tensor
owned by the trainer) to ``A~`` (N x K', eq. 33). The subset columns always pass
through unchanged; only the prediction of the remaining K'-d columns depends on
the variant chosen by one :class:`LSTConfig`:

``operator="matrix"`` (ours, Table VIII)
    linear maps from subset rows to remaining columns laid out by
    :func:`~gscodec_shac.shac.lst.lst_layout`, with the sub-options
    ``structure``: ``"block"`` (blocks ``t_l``, eq. 34) or ``"dense"`` (one d x (K'-d) map);
    ``rgb``: ``"joint"`` (every entry learnable, 3(2l-1) x 3(2l-1) blocks) or
    ``"separate"`` (one (2l-1) x (2l-1) matrix per channel, channels never mix);
    ``init``: ``"zero"`` (ours: A~ starts as truncation to the subset) or
    ``"identity"`` (1 where input and output share order ``m`` and channel, 0 elsewhere:
    each remaining coefficient starts as a copy of the same-order subset member;
    for the square blocks this is the identity matrix, for the non-square dense map
    one 1 per output column).
``operator="vector"``
    one scalar weight per remaining AC column: ``A~[l, m, c] = w[l, m, c] * S[m, c]``,
    where ``S[m, c]`` is the subset member of the same order ``m`` and channel ``c``.
    Each coefficient is predicted from a single subset element, with no sharing
    across orders, degrees or channels (the "strict independence" of Sec. VII-E4).
    K'-d parameters (24 for L = 3). ``init`` as for the matrix.
``operator="linear"``
    one ``nn.Linear(d, K'-d)`` with bias from the whole subset to the remaining
    columns (AC order); ``init="zero"`` zeroes weight and bias, ``"identity"`` sets the
    same-order diagonal of the weight and a zero bias.
``operator="mlp"``
    ``d -> 2(K'-d) -> 2(K'-d) -> K'-d`` with ReLU (two hidden layers, width twice the
    output dimension, as Sec. VI-B2 / VII-E4); hidden layers keep torch's default
    initialisation (seed torch yourself), the output layer is zeroed so the start is
    truncation to the subset; ``init="identity"`` has no meaning here and is refused.

``structure`` and ``rgb`` apply to the matrix operator only; other operators
require their defaults. Every variant exposes :meth:`LSTModule.regularization`
(the eq. (36) scale term generalised: ``sum_W ||W||_F^2 / numel(W)`` over its weight
tensors, biases excluded: they shift, they do not amplify quantisation noise) and
:attr:`LSTModule.n_params`.

Optimisation (Sec. VI-B2): Adam; S at the reference trainer's SH-rest rate
(0.0025 / 20), DC at 0.0025, ``T`` with :func:`t_learning_rate` (linear warm-up to
2.5e-3 over the first 5 % of steps, cosine decay to 2.5e-5). See
:func:`lst_param_groups` and :func:`make_lst_optimizer`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Iterable, Mapping

import numpy as np
import torch
from torch import nn

from gscodec_shac.errors import ValidationError
from gscodec_shac.shac.lst import STRUCTURES, SUBSET_STRATEGIES, LstLayout, ShacLST, lst_layout

OPERATORS = ("matrix", "vector", "linear", "mlp")
INITS = ("zero", "identity")
RGB_MODES = ("joint", "separate")

#: lambda_t of eq. (37).
LAMBDA_T = 5e-3
#: Peak and final learning rate of T (Sec. VI-B2) and the warm-up share of the steps.
T_LR_PEAK = 2.5e-3
T_LR_FINAL = 2.5e-5
T_WARMUP_FRACTION = 0.05
#: Reference 3DGS trainer: feature_lr = 0.0025 for DC, divided by 20 for the SH rest.
DC_LR = 2.5e-3
SH_REST_LR = 2.5e-3 / 20.0
#: Adam epsilon of the reference 3DGS trainer.
ADAM_EPS = 1e-15


@dataclass(frozen=True)
class LSTConfig:
    """One switch for every SHAC-LST variant of Tables VII-IX (defaults = the paper's model)."""

    degree: int = 3
    subset: str = "lowest"
    operator: str = "matrix"
    structure: str = "block"
    rgb: str = "joint"
    init: str = "zero"
    lambda_t: float = LAMBDA_T

    def __post_init__(self) -> None:
        for what, value, choices in (
            ("subset", self.subset, SUBSET_STRATEGIES),
            ("operator", self.operator, OPERATORS),
            ("structure", self.structure, STRUCTURES),
            ("rgb", self.rgb, RGB_MODES),
            ("init", self.init, INITS),
        ):
            if value not in choices:
                raise ValidationError(f"{what} must be one of {', '.join(map(repr, choices))}, got {value!r}")
        if self.operator != "matrix" and (self.structure != "block" or self.rgb != "joint"):
            raise ValidationError(f"structure and rgb apply to the matrix operator only, not to {self.operator!r}")
        if self.operator == "mlp" and self.init == "identity":
            raise ValidationError("the mlp operator has no identity initialisation; use init='zero'")
        if not (math.isfinite(self.lambda_t) and self.lambda_t >= 0):
            raise ValidationError(f"lambda_t must be a finite number >= 0, got {self.lambda_t!r}")
        lst_layout(self.degree, self.subset, self.structure)  # validates the degree
        if self.degree < 2:
            raise ValidationError(f"SHAC-LST training needs SH degree 2-4 (degree {self.degree} has nothing to predict)")

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class LSTModule(nn.Module):
    """``S -> A~`` for SHAC-LST training (eq. 33), variant chosen by :class:`LSTConfig`."""

    def __init__(self, config: LSTConfig | None = None, **overrides: Any) -> None:
        super().__init__()
        if config is None:
            config = LSTConfig(**overrides)
        elif overrides:
            config = LSTConfig(**{**config.as_dict(), **overrides})
        self.config = config
        structure = config.structure if config.operator == "matrix" else "dense"
        self.layout: LstLayout = lst_layout(config.degree, config.subset, structure)
        layout = self.layout
        self.d = layout.d
        self.n_ac = layout.n_ac_columns
        n_rest = self.n_ac - self.d
        # Column order of cat([S, predictions...]) and its inverse (back to AC order).
        order = np.concatenate([layout.subset_columns] + [b.output_columns for b in layout.blocks])
        if config.operator != "matrix":
            order = np.concatenate([layout.subset_columns, layout.remaining_columns])
        self.register_buffer("_to_ac", torch.as_tensor(np.argsort(order), dtype=torch.long), persistent=False)
        #: AC columns of S and of the predicted coefficients, as index tensors (paper order).
        self.register_buffer("subset_index", torch.tensor(np.array(layout.subset_columns)), persistent=False)
        self.register_buffer("remaining_index", torch.tensor(np.array(layout.remaining_columns)), persistent=False)
        for i, b in enumerate(layout.blocks):
            self.register_buffer(f"_rows{i}", torch.tensor(np.array(b.input_rows)), persistent=False)

        self.weights = nn.ParameterDict()
        self.net: nn.Module | None = None
        if config.operator == "matrix":
            for b in layout.blocks:
                mask = torch.as_tensor(b.same_order_mask(), dtype=torch.float32)
                if config.rgb == "joint":
                    value = mask.clone() if config.init == "identity" else torch.zeros(b.shape)
                else:  # (3, in/3, out/3): channel c uses rows c::3 and columns c::3
                    value = torch.stack([mask[c::3, c::3] for c in range(3)])
                    if config.init == "zero":
                        value = torch.zeros_like(value)
                self.weights[b.key] = nn.Parameter(value)
        elif config.operator == "vector":
            self.register_buffer("_source", torch.as_tensor(_same_order_sources(layout)), persistent=False)
            init = torch.ones(n_rest) if config.init == "identity" else torch.zeros(n_rest)
            self.weights["w"] = nn.Parameter(init)
        elif config.operator == "linear":
            linear = nn.Linear(self.d, n_rest, bias=True)
            with torch.no_grad():
                linear.bias.zero_()
                if config.init == "identity":
                    linear.weight.copy_(torch.as_tensor(layout.blocks[0].same_order_mask().T, dtype=torch.float32))
                else:
                    linear.weight.zero_()
            self.net = linear
        else:  # mlp
            width = 2 * n_rest
            self.net = nn.Sequential(
                nn.Linear(self.d, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU(), nn.Linear(width, n_rest)
            )
            with torch.no_grad():
                self.net[-1].weight.zero_()
                self.net[-1].bias.zero_()

    # ------------------------------------------------------------------ forward
    def forward(self, subset: torch.Tensor) -> torch.Tensor:
        """S (N, d) -> A~ (N, K') in paper AC order (eq. 33)."""
        if subset.ndim != 2 or subset.shape[1] != self.d:
            raise ValidationError(f"expected the subset as an (N, {self.d}) tensor, got shape {tuple(subset.shape)}")
        op = self.config.operator
        if op == "matrix":
            parts = [subset] + [
                subset[:, getattr(self, f"_rows{i}")] @ self.block_matrix(b.key) for i, b in enumerate(self.layout.blocks)
            ]
        elif op == "vector":
            parts = [subset, subset[:, self._source] * self.weights["w"]]
        else:
            parts = [subset, self.net(subset)]
        return torch.cat(parts, dim=1)[:, self._to_ac]

    def block_matrix(self, key: str) -> torch.Tensor:
        """Full (in, out) matrix of a matrix-operator block (per-channel blocks expanded)."""
        w = self.weights[key]
        if self.config.rgb == "joint":
            return w
        n_in, n_out = w.shape[1] * 3, w.shape[2] * 3
        eye = torch.eye(3, dtype=w.dtype, device=w.device)
        # [a, c, b, c'] = w[c, a, b] * delta(c, c') -> row 3a + c, column 3b + c'
        return (w.permute(1, 0, 2)[:, :, :, None] * eye[None, :, None, :]).reshape(n_in, n_out)

    # ------------------------------------------------------------------ regularisation
    def weight_tensors(self) -> list[torch.Tensor]:
        """The tensors the scale regulariser acts on (weights, not biases)."""
        if self.net is None:
            return list(self.weights.values())
        return [m.weight for m in self.net.modules() if isinstance(m, nn.Linear)]

    def regularization(self) -> torch.Tensor:
        """L_T = sum_W ||W||_F^2 / P_W (eq. 36; W = the blocks t_l for the paper's model)."""
        terms = [w.pow(2).sum() / w.numel() for w in self.weight_tensors()]
        if not terms:
            return torch.zeros(())
        return torch.stack(terms).sum()

    def penalty(self) -> torch.Tensor:
        """lambda_t * L_T, the second term of eq. (37)."""
        return self.config.lambda_t * self.regularization()

    @property
    def n_params(self) -> int:
        """Learnable parameters of this variant (eq. 34 for the paper's model)."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad)

    # ------------------------------------------------------------------ numpy stage bridge
    def export_blocks(self) -> dict[str, np.ndarray]:
        """Matrix-operator blocks as float32 arrays for :meth:`ShacLST.from_blocks`
        (per-channel blocks are expanded to the joint block-diagonal form)."""
        if self.config.operator != "matrix":
            raise ValidationError(f"only the matrix operator exports to the SHAC-LST stage, not {self.config.operator!r}")
        with torch.no_grad():
            return {b.key: self.block_matrix(b.key).detach().cpu().numpy().astype(np.float32) for b in self.layout.blocks}

    def to_stage(self) -> ShacLST:
        """The numpy SH stage with these blocks (for coding)."""
        blocks = self.export_blocks()
        c = self.config
        return ShacLST.from_blocks(blocks, degree=c.degree, subset=c.subset, structure=c.structure)

    def load_blocks(self, blocks: Mapping[str, Any]) -> "LSTModule":
        """Set joint matrix blocks (e.g. a post-hoc :class:`ShacLST` fit as a warm start)."""
        if self.config.operator != "matrix" or self.config.rgb != "joint":
            raise ValidationError("load_blocks needs the matrix operator with rgb='joint'")
        with torch.no_grad():
            for b in self.layout.blocks:
                value = torch.as_tensor(np.asarray(blocks[b.key]), dtype=self.weights[b.key].dtype)
                if tuple(value.shape) != b.shape:
                    raise ValidationError(f"block {b.key} must have shape {b.shape}, got {tuple(value.shape)}")
                self.weights[b.key].copy_(value)
        return self

    @classmethod
    def from_stage(cls, stage: ShacLST, **overrides: Any) -> "LSTModule":
        """A matrix-operator module initialised from a fitted stage's blocks."""
        layout = stage._fitted_layout()
        config = LSTConfig(degree=layout.degree, subset=layout.subset, structure=layout.structure, **overrides)
        return cls(config).load_blocks(stage.blocks_)

    def extra_repr(self) -> str:
        c = self.config
        return f"degree={c.degree}, subset={c.subset}, operator={c.operator}, structure={c.structure}, rgb={c.rgb}, init={c.init}, n_params={self.n_params}"


def _same_order_sources(layout: LstLayout) -> np.ndarray:
    """For each remaining AC column, the S column of the same order and channel."""
    mask = layout.blocks[0].same_order_mask()  # dense layout: all subset rows x all remaining columns
    if not (mask.sum(axis=0) == 1).all():
        raise AssertionError("every remaining coefficient must have exactly one same-order subset member")
    return np.argmax(mask, axis=0)


# ------------------------------------------------------------------------------ schedule
def t_learning_rate(
    step: int,
    total_steps: int,
    *,
    peak: float = T_LR_PEAK,
    final: float = T_LR_FINAL,
    warmup_fraction: float = T_WARMUP_FRACTION,
    start: float = 0.0,
) -> float:
    """Learning rate of T at optimiser step ``step`` (0-based) of ``total_steps`` (Sec. VI-B2).

    Linear from ``start`` (0 by default: the paper names no start value; the first
    step then leaves T unchanged) at step 0 to ``peak`` at step ``W = round(warmup_fraction
    * total_steps)``, then a half cosine from ``peak`` to ``final`` at the last step
    ``total_steps - 1``; steps beyond stay at ``final``. With ``W = 0`` there is no
    warm-up; when no step is left after the warm-up the rate stays at ``peak``.
    """
    if total_steps < 1:
        raise ValidationError(f"total_steps must be positive, got {total_steps}")
    if step < 0:
        raise ValidationError(f"step must be >= 0, got {step}")
    warmup = int(round(warmup_fraction * total_steps))
    last = total_steps - 1
    if step < warmup:
        return start + (peak - start) * step / warmup
    if last <= warmup:  # too few steps to decay
        return peak
    progress = min(1.0, (step - warmup) / (last - warmup))
    return final + 0.5 * (peak - final) * (1.0 + math.cos(math.pi * progress))


def lst_param_groups(
    module: LSTModule,
    subset_params: Iterable[torch.Tensor],
    dc_params: Iterable[torch.Tensor] = (),
    *,
    sh_rest_lr: float = SH_REST_LR,
    dc_lr: float = DC_LR,
    t_lr: float = T_LR_PEAK,
) -> list[dict[str, Any]]:
    """Adam parameter groups of Sec. VI-B2: ``S`` (SH-rest rate), DC, and ``T`` (named ``"lst_T"``).

    ``t_lr`` is the peak rate; :func:`make_lst_optimizer` scales it by the schedule.
    Other 3DGS parameters (means, scales, ...) can be appended by the trainer.
    """
    groups = [{"params": list(subset_params), "lr": sh_rest_lr, "name": "sh_subset"}]
    dc = list(dc_params)
    if dc:
        groups.append({"params": dc, "lr": dc_lr, "name": "sh_dc"})
    groups.append({"params": list(module.parameters()), "lr": t_lr, "name": "lst_T"})
    return groups


def make_lst_optimizer(
    groups: list[dict[str, Any]], total_steps: int, *, eps: float = ADAM_EPS, warmup_start: float = 0.0
) -> tuple[torch.optim.Adam, torch.optim.lr_scheduler.LambdaLR]:
    """Adam over ``groups`` and a LambdaLR that drives the ``"lst_T"`` group by
    :func:`t_learning_rate` (its ``lr`` is the peak; final = peak * 2.5e-5 / 2.5e-3,
    start = peak * ``warmup_start``) and keeps every other group constant.
    Call ``scheduler.step()`` once after each ``optimizer.step()``."""
    if not any(g.get("name") == "lst_T" for g in groups):
        raise ValidationError("no parameter group named 'lst_T'; build the groups with lst_param_groups()")
    optimizer = torch.optim.Adam(groups, eps=eps)

    def t_factor(step: int) -> float:
        return t_learning_rate(step, total_steps, peak=1.0, final=T_LR_FINAL / T_LR_PEAK, start=warmup_start)

    lambdas = [t_factor if g.get("name") == "lst_T" else (lambda step: 1.0) for g in groups]
    return optimizer, torch.optim.lr_scheduler.LambdaLR(optimizer, lambdas)
