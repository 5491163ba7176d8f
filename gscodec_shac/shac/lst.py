"""SHAC-LST: the learned subset transformation (paper Sec. V-B, eq. 32-39).

The AC matrix ``A`` (N x K', paper column order, see :mod:`gscodec_shac.sh_index`)
is represented by a per-Gaussian *subset* ``S`` (N x d, d = 3(2L+1)) and one shared
transformation ``T`` (d x K'): ``A~ = S T`` (eq. 33). This module holds the numpy
side: the index bookkeeping (:func:`lst_layout`), the SH stage :class:`ShacLST`
(registered as ``"lst"``) with a closed-form post-hoc fit of ``T``, and the
compression ratio of eq. (38)-(39). The torch parameterisation used for
training lives in :mod:`gscodec_shac.shac.lst_torch`.

Subset (eq. 32, ``subset="lowest"``): for every order ``m`` the coefficient of the
lowest degree, ``l = max(1, |m|)``. The ablation of Sec. VII-E1 (``"highest"``)
takes ``l = L`` for every ``m``. Both give one subset member per order, so
``d = 3(2L+1)`` (21 for L = 3); the subset columns of ``S`` keep the AC order.

Structure of ``T`` (eq. 33-34, ``structure="block"``) for L = 3, lowest subset;
``[S]`` = subset member, ``t_l`` = predicted by block ``t_l``::

    order m :   -3    -2    -1     0    +1    +2    +3
    degree 1:               [S]   [S]   [S]
    degree 2:         [S]   t_2   t_2   t_2   [S]
    degree 3:   [S]   t_3   t_3   t_3   t_3   t_3   [S]

    t_2 (9 x 9):   S(1,-1) S(1,0) S(1,1)                 -> (2,-1) (2,0) (2,1)
    t_3 (15 x 15): S(2,-2) S(1,-1) S(1,0) S(1,1) S(2,2)  -> (3,-2) ... (3,2)

Block ``t_l`` predicts the *remaining* coefficients of degree ``l`` (the 2l-1 orders
``|m| < l``) from the subset member of each of those orders, RGB jointly: it is
square, 3(2l-1) x 3(2l-1), rows and columns ordered by ``m`` with the channel
fastest, so its diagonal pairs each output with the same-order, same-channel input.
The subset columns pass through ``T`` unchanged (the identity part) and every
other entry of ``T`` is zero. Parameters: ``P_T = sum_{l=2}^{L} [3(2l-1)]^2``
(eq. 34): 81 (L = 2), 306 (L = 3), 747 (L = 4). A degree-1 coefficient feeds
several blocks (for L = 3 both ``t_2`` and ``t_3``), so "block-diagonal" refers to
the output side: each predicted coefficient belongs to exactly one block.

For the ``"highest"`` subset the same rule applies with the roles of the degrees
swapped: the remaining coefficients are those of degrees ``1 .. L-1`` and block
``t_l`` (l = 1 .. L-1, square, 3(2l+1)) predicts degree ``l`` from ``S(L, m)``,
``|m| <= l``; its parameter count equals the lowest-subset one.

``structure="dense"`` (ablation of Table IX) replaces the blocks by one full
d x (K'-d) matrix from the whole subset to all remaining coefficients.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Mapping, Sequence

import numpy as np

from gscodec_shac import sh_index
from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.shac.base import ShStage, StageParam, StageState, check_ac_matrix, register_stage

SUBSET_STRATEGIES = ("lowest", "highest")
STRUCTURES = ("block", "dense")
#: Default strength of the post-hoc scale penalty (eq. 36 units, see :meth:`ShacLST.fit`);
#: far weaker than the training value ``lambda_t = 5e-3`` of Sec. V-B3.
DEFAULT_RIDGE = 1e-6
DENSE_KEY = "t_dense"

Coeff = tuple[int, int]


# ----------------------------------------------------------------------------- layout
@dataclass(frozen=True)
class LstBlock:
    """One learnable block of ``T``: which subset rows feed which AC columns.

    ``input_rows`` index columns of ``S`` and ``output_columns`` columns of ``A``; both
    hold three entries (R, G, B) per coefficient, channel fastest, in the order of
    ``input_coeffs`` / ``output_coeffs``.
    """

    key: str
    degree: int | None
    input_coeffs: tuple[Coeff, ...]
    output_coeffs: tuple[Coeff, ...]
    input_rows: np.ndarray
    output_columns: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return (len(self.input_rows), len(self.output_columns))

    @property
    def n_params(self) -> int:
        """P_{t_l}: entries of the block (eq. 34)."""
        return self.shape[0] * self.shape[1]

    def same_order_mask(self) -> np.ndarray:
        """(in, out) bool: input and output share order ``m`` and channel ("identity" init)."""
        m_in = np.repeat([m for _, m in self.input_coeffs], 3)
        m_out = np.repeat([m for _, m in self.output_coeffs], 3)
        c_in = np.tile(np.arange(3), len(self.input_coeffs))
        c_out = np.tile(np.arange(3), len(self.output_coeffs))
        return (m_in[:, None] == m_out[None, :]) & (c_in[:, None] == c_out[None, :])


@dataclass(frozen=True)
class LstLayout:
    """Index bookkeeping of SHAC-LST for one SH degree, subset strategy and structure."""

    degree: int
    subset: str
    structure: str
    subset_coeffs: tuple[Coeff, ...]
    subset_columns: np.ndarray
    remaining_coeffs: tuple[Coeff, ...]
    remaining_columns: np.ndarray
    blocks: tuple[LstBlock, ...]

    @property
    def d(self) -> int:
        """Subset dimension d = 3(2L+1) (eq. 32)."""
        return len(self.subset_columns)

    @property
    def n_ac_columns(self) -> int:
        """K' = 3((L+1)^2 - 1)."""
        return sh_index.num_ac_columns(self.degree)

    @property
    def n_params(self) -> int:
        """P_T, the learnable entries of ``T`` (eq. 34 for the block structure)."""
        return sum(b.n_params for b in self.blocks)

    @property
    def block_keys(self) -> tuple[str, ...]:
        return tuple(b.key for b in self.blocks)

    def block(self, key: str) -> LstBlock:
        for b in self.blocks:
            if b.key == key:
                return b
        raise ValidationError(f"no block {key!r} in this layout; blocks: {', '.join(self.block_keys) or 'none'}")

    def transform_matrix(self, blocks: Mapping[str, np.ndarray]) -> np.ndarray:
        """Dense ``T`` (d x K', float64) of eq. (33) from the block values."""
        t = np.zeros((self.d, self.n_ac_columns))
        t[np.arange(self.d), self.subset_columns] = 1.0
        for b in self.blocks:
            t[np.ix_(b.input_rows, b.output_columns)] = blocks[b.key]
        return t


def subset_coefficients(degree: int, subset: str = "lowest") -> tuple[Coeff, ...]:
    """The (l, m) of the subset of eq. (32) (``"lowest"``) or its ablation (``"highest"``), AC order."""
    _check_lst_degree(degree)
    _check_choice("subset", subset, SUBSET_STRATEGIES)
    if subset == "lowest":
        members = {(max(1, abs(m)), m) for m in range(-degree, degree + 1)}
    else:
        members = {(degree, m) for m in range(-degree, degree + 1)}
    return tuple(sorted(members, key=lambda lm: sh_index.coeff_index(*lm)))


@lru_cache(maxsize=None)
def lst_layout(degree: int, subset: str = "lowest", structure: str = "block") -> LstLayout:
    """Subset columns, remaining columns and the blocks of ``T`` (eq. 32-34; see module docstring)."""
    _check_choice("structure", structure, STRUCTURES)
    members = subset_coefficients(degree, subset)
    member_of_order = {lm[1]: lm for lm in members}
    subset_columns = _columns(members)
    row_of_column = {int(c): i for i, c in enumerate(subset_columns)}
    all_coeffs = [sh_index.degree_order(k) for k in range(1, sh_index.num_coeffs(degree))]
    remaining = tuple(lm for lm in all_coeffs if lm not in set(members))

    def rows(coeffs: Sequence[Coeff]) -> np.ndarray:
        out = np.array([row_of_column[int(c)] for c in _columns(coeffs)], dtype=np.int64)
        out.setflags(write=False)
        return out

    blocks: list[LstBlock] = []
    if structure == "block":
        for l in sorted({l for l, _ in remaining}):
            outputs = tuple(sorted((lm for lm in remaining if lm[0] == l), key=lambda lm: lm[1]))
            inputs = tuple(member_of_order[m] for _, m in outputs)
            blocks.append(LstBlock(f"t_{l}", l, inputs, outputs, rows(inputs), _columns(outputs)))
    elif remaining:
        blocks.append(LstBlock(DENSE_KEY, None, members, remaining, rows(members), _columns(remaining)))
    return LstLayout(
        degree=degree,
        subset=subset,
        structure=structure,
        subset_coeffs=members,
        subset_columns=subset_columns,
        remaining_coeffs=remaining,
        remaining_columns=_columns(remaining),
        blocks=tuple(blocks),
    )


def num_transform_params(degree: int, subset: str = "lowest", structure: str = "block") -> int:
    """P_T of eq. (34) (``sum_{l=2}^{L} [3(2l-1)]^2`` for the block structure)."""
    return lst_layout(degree, subset, structure).n_params


def compression_ratio(n_gaussians: int, degree: int, n_params: int | None = None) -> float:
    """CR_LST = (N(3 + d) + P_T) / (N K) (eq. 38); -> 2/(L+1) as N grows (eq. 39)."""
    if n_gaussians < 1:
        raise ValidationError(f"the number of Gaussians must be positive, got {n_gaussians}")
    layout = lst_layout(degree)
    p_t = layout.n_params if n_params is None else n_params
    k = 3 * sh_index.num_coeffs(degree)
    return (n_gaussians * (3 + layout.d) + p_t) / (n_gaussians * k)


# ------------------------------------------------------------------------------ stage
@register_stage
class ShacLST(ShStage):
    """SHAC-LST as an SH stage: features ``S`` (eq. 32), reconstruction ``S T`` (eq. 33).

    Parameters
    ----------
    degree
        SH degree L (1-4); inferred from the matrix in :meth:`fit` when ``None``.
    subset
        ``"lowest"`` (eq. 32) or ``"highest"`` (ablation, Table VII).
    structure
        ``"block"`` (eq. 33-34) or ``"dense"`` (ablation, Table IX).
    ridge
        Weight of the scale penalty of the post-hoc fit (eq. 36 form, see :meth:`fit`).
    refit_subset
        Rounds of alternating least squares that also re-optimise ``S`` (encoder side
        only; see :meth:`fit`). 0 (default) = the paper's post-hoc reading: ``S`` is
        the selected columns of ``A`` (eq. 32).

    Fitted attributes: ``degree_``, ``layout_`` and ``blocks_`` (block key -> float32
    array; the only side information, stored as is).
    """

    name = "lst"
    summary = "SHAC-LST: a per-Gaussian SH subset S and a shared block-diagonal T (eq. 32-36), post-hoc fit"
    feature_kind = "coefficients"
    rate_attribute = "sh_features"
    inverts_row_blocks = True  # each row's A~ = S T (eq. 33) from its own S row
    params = (
        StageParam("degree", "int", None, "subset degree L (default: the scene's degree)", flag="degree",
                   lo=1, hi=sh_index.MAX_SH_DEGREE),
        StageParam("subset", "choice", "lowest", "which coefficients form S", choices=SUBSET_STRATEGIES),
        StageParam("structure", "choice", "block", "structure of T (eq. 33-34)", choices=STRUCTURES),
        StageParam("ridge", "float", DEFAULT_RIDGE, "strength of the post-hoc scale penalty", lo=0.0),
        StageParam("refit_subset", "int", 0, "alternating refits of S after T", lo=0, hi=1000),
    )

    def feature_columns(self) -> np.ndarray | None:
        return None if self.layout_ is None else np.asarray(self.layout_.subset_columns)

    def __init__(
        self,
        degree: int | None = None,
        subset: str = "lowest",
        structure: str = "block",
        ridge: float = DEFAULT_RIDGE,
        refit_subset: int = 0,
    ) -> None:
        _check_choice("subset", subset, SUBSET_STRATEGIES)
        _check_choice("structure", structure, STRUCTURES)
        if degree is not None:
            _check_lst_degree(degree)
        if isinstance(ridge, bool) or not isinstance(ridge, numbers.Real) or not (np.isfinite(ridge) and ridge >= 0):
            raise ValidationError(f"ridge must be a finite number >= 0, got {ridge!r}")
        if isinstance(refit_subset, bool) or not isinstance(refit_subset, (int, np.integer)) or refit_subset < 0:
            raise ValidationError(f"refit_subset must be an integer >= 0, got {refit_subset!r}")
        self.refit_subset = int(refit_subset)
        self.degree = degree
        self.subset = subset
        self.structure = structure
        self.ridge = float(ridge)
        self.degree_: int | None = None
        self.layout_: LstLayout | None = None
        self.blocks_: dict[str, np.ndarray] | None = None

    # ------------------------------------------------------------------ fitting
    def fit(self, ac: np.ndarray) -> "ShacLST":
        """Post-hoc closed-form fit of every block from a pretrained AC matrix.

        Each block ``t`` (inputs ``X = S[:, rows]``, targets ``Y = A[:, cols]``) minimises
        ``(1/N) ||X t - Y||_F^2 + ridge * ||t||_F^2 / P_t``: eq. (37) with the render loss
        replaced by the mean squared AC error per Gaussian, and the eq. (36) scale
        penalty per block (``ridge`` plays ``lambda_t``). The blocks are independent, so
        this is one ridge regression per block, solved in float64 and stored float32.

        With ``refit_subset = R > 0`` the fit alternates R times between that block
        step and the per-Gaussian step ``S = argmin ||A - S T||_F = A T^T (T T^T)^-1``
        (``T T^T >= I`` thanks to the identity part, so always solvable): a post-hoc
        stand-in for training ``S`` and ``T`` jointly (eq. 37) with the AC error as loss.
        :meth:`transform` then returns that least-squares ``S`` instead of the
        selected columns; :meth:`inverse_transform` (the decoder) is unchanged.
        """
        ac = check_ac_matrix(ac)
        degree = self._degree_for(ac.shape[1])
        if ac.shape[0] == 0:
            raise ValidationError("cannot fit SHAC-LST on an empty AC matrix (N = 0)")
        layout = lst_layout(degree, self.subset, self.structure)
        a64 = ac.astype(np.float64)
        s = a64[:, layout.subset_columns]
        for round_ in range(self.refit_subset + 1):
            blocks = {
                b.key: ridge_solve(s[:, b.input_rows], a64[:, b.output_columns], self.ridge / b.n_params)
                for b in layout.blocks
            }
            if round_ < self.refit_subset:
                s = _project(a64, layout.transform_matrix(blocks))
        self._set_fitted(degree, {key: value.astype(np.float32) for key, value in blocks.items()})
        return self

    @classmethod
    def from_blocks(
        cls,
        blocks: Mapping[Any, Any] | Sequence[Any],
        *,
        degree: int,
        subset: str = "lowest",
        structure: str = "block",
    ) -> "ShacLST":
        """A fitted stage from given blocks (e.g. learned by fine-tuning).

        ``blocks`` is a sequence in layout order, or a mapping keyed by block key
        (``"t_2"``, ``"t_dense"``) or, for the block structure, by degree (``2``).
        """
        stage = cls(degree=degree, subset=subset, structure=structure)
        layout = lst_layout(degree, subset, structure)
        if isinstance(blocks, Mapping):
            named = {(f"t_{k}" if isinstance(k, (int, np.integer)) else str(k)): v for k, v in blocks.items()}
            unknown = sorted(set(named) - set(layout.block_keys))
            missing = sorted(set(layout.block_keys) - set(named))
            if unknown or missing:
                raise ValidationError(
                    f"blocks must be exactly {list(layout.block_keys)} for this layout "
                    f"(missing {missing}, unexpected {unknown})"
                )
        else:
            blocks = list(blocks)
            if len(blocks) != len(layout.blocks):
                raise ValidationError(f"expected {len(layout.blocks)} blocks for this layout, got {len(blocks)}")
            named = dict(zip(layout.block_keys, blocks))
        checked = {}
        for b in layout.blocks:
            value = np.asarray(named[b.key])
            if value.shape != b.shape:
                raise ValidationError(f"block {b.key} must have shape {b.shape}, got {value.shape}")
            if not np.isfinite(value).all():
                raise ValidationError(f"block {b.key} has non-finite values")
            checked[b.key] = value.astype(np.float32)
        stage._set_fitted(degree, checked)
        return stage

    @classmethod
    def zeros(cls, degree: int, subset: str = "lowest", structure: str = "block") -> "ShacLST":
        """The zero-initialised ``T`` (Sec. VII-E5): reconstruction = truncation to the subset."""
        layout = lst_layout(degree, subset, structure)
        return cls.from_blocks([np.zeros(b.shape) for b in layout.blocks], degree=degree, subset=subset, structure=structure)

    # ------------------------------------------------------------------ transform
    def transform(self, ac: np.ndarray) -> np.ndarray:
        """(N, K') -> S (N, d): the subset columns of eq. (32), the features to code
        (with ``refit_subset > 0``: the least-squares ``S`` for the fitted ``T``)."""
        layout = self._fitted_layout()
        ac = check_ac_matrix(ac, layout.n_ac_columns)
        if self.refit_subset:
            return _project(ac.astype(np.float64), self.transform_matrix()).astype(ac.dtype)
        return np.ascontiguousarray(ac[:, layout.subset_columns])

    def inverse_transform(self, features: np.ndarray) -> np.ndarray:
        """S (N, d) -> A~ = S T (N, K') (eq. 33); subset columns are copied exactly."""
        layout = self._fitted_layout()
        s = check_ac_matrix(features, layout.d)
        out = np.zeros((s.shape[0], layout.n_ac_columns), dtype=s.dtype)
        out[:, layout.subset_columns] = s
        s64 = s.astype(np.float64)
        for b in layout.blocks:
            out[:, b.output_columns] = s64[:, b.input_rows] @ self.blocks_[b.key].astype(np.float64)
        return out

    def transform_matrix(self) -> np.ndarray:
        """The dense ``T`` (d x K', float64) of eq. (33)."""
        return self._fitted_layout().transform_matrix(self.blocks_)

    # ------------------------------------------------------------------ sizes
    @property
    def n_features(self) -> int:
        return self._fitted_layout().d

    @property
    def n_params(self) -> int:
        """P_T: stored entries of ``T`` (eq. 34 for the block structure)."""
        return self._fitted_layout().n_params

    def compression_ratio(self, n_gaussians: int) -> float:
        """Eq. (38) with this stage's P_T (values counted, DC and S included)."""
        return compression_ratio(n_gaussians, self._fitted_layout().degree, self.n_params)

    def compression_ratio_bytes(self, n_gaussians: int, bytes_per_value: int = 4, *, with_header: bool = False) -> float:
        """Eq. (38) from real bytes: ``N(3+d)`` values of ``bytes_per_value`` plus the
        stored side information (``state().nbytes()``, or the whole serialised state
        when ``with_header``), over ``N K`` values of ``bytes_per_value``."""
        layout = self._fitted_layout()
        if n_gaussians < 1:
            raise ValidationError(f"the number of Gaussians must be positive, got {n_gaussians}")
        state = self.state()
        side = len(state.to_bytes()) if with_header else state.nbytes()
        k = 3 * sh_index.num_coeffs(layout.degree)
        return (n_gaussians * (3 + layout.d) * bytes_per_value + side) / (n_gaussians * k * bytes_per_value)

    # ------------------------------------------------------------------ state
    def state(self) -> StageState:
        layout = self._fitted_layout()
        return StageState(
            self.name,
            {
                "degree": layout.degree,
                "subset": layout.subset,
                "structure": layout.structure,
                "ridge": self.ridge,
                "refit_subset": self.refit_subset,
            },
            {key: np.ascontiguousarray(self.blocks_[key], dtype=np.float32) for key in layout.block_keys},
        )

    @classmethod
    def from_state(cls, state: StageState) -> "ShacLST":
        params = state.params
        try:
            degree = int(params["degree"])
            subset = str(params.get("subset", "lowest"))
            structure = str(params.get("structure", "block"))
        except (KeyError, TypeError, ValueError):
            raise GscodecError("SHAC-LST state is corrupt (missing or bad 'degree')") from None
        try:
            stage = cls.from_blocks(dict(state.arrays), degree=degree, subset=subset, structure=structure)
        except ValidationError as exc:
            raise GscodecError(f"SHAC-LST state is corrupt: {exc}") from None
        try:
            stage.ridge = float(params.get("ridge", DEFAULT_RIDGE))
            stage.refit_subset = int(params.get("refit_subset", 0))
        except (TypeError, ValueError):
            raise GscodecError("SHAC-LST state is corrupt (bad 'ridge' or 'refit_subset')") from None
        return stage

    # ------------------------------------------------------------------ helpers
    def _degree_for(self, n_columns: int) -> int:
        if n_columns % 3:
            raise ValidationError(f"AC matrix must have 3 * ((L+1)^2 - 1) columns, got {n_columns}")
        degree = sh_index.degree_from_rest_count(n_columns // 3)
        if self.degree is not None and degree != self.degree:
            raise ValidationError(
                f"AC matrix has {n_columns} columns (SH degree {degree}) but this stage was set to degree {self.degree}"
            )
        _check_lst_degree(degree)
        return degree

    def _set_fitted(self, degree: int, blocks: dict[str, np.ndarray]) -> None:
        self.degree_ = degree
        self.layout_ = lst_layout(degree, self.subset, self.structure)
        self.blocks_ = blocks

    def _fitted_layout(self) -> LstLayout:
        if self.layout_ is None or self.blocks_ is None:
            raise ValidationError("this SHAC-LST stage is not fitted; call fit() or from_blocks() first")
        return self.layout_

    def __repr__(self) -> str:
        fitted = f", P_T={self.n_params}" if self.layout_ is not None else ""
        return f"ShacLST(degree={self.degree_ or self.degree}, subset={self.subset!r}, structure={self.structure!r}{fitted})"


def ridge_solve(x: np.ndarray, y: np.ndarray, penalty: float) -> np.ndarray:
    """argmin_t (1/N) ||x t - y||_F^2 + penalty ||t||_F^2 (least squares when penalty = 0)."""
    n = x.shape[0]
    if penalty > 0:
        gram = x.T @ x / n + penalty * np.eye(x.shape[1])
        return np.linalg.solve(gram, x.T @ y / n)
    return np.linalg.lstsq(x, y, rcond=None)[0]


def _project(ac: np.ndarray, t: np.ndarray) -> np.ndarray:
    """S = argmin_S ||A - S T||_F = A T^T (T T^T)^-1 (T T^T >= I by the identity part)."""
    return np.linalg.solve(t @ t.T, t @ ac.T).T


def _columns(coeffs: Sequence[Coeff]) -> np.ndarray:
    """AC columns (R, G, B each) of the given (l, m), in the given order (read-only: layouts are cached)."""
    columns = np.array([sh_index.ac_column(l, m, c) for l, m in coeffs for c in range(3)], dtype=np.int64)
    columns.setflags(write=False)
    return columns


def _check_lst_degree(degree: Any) -> None:
    if not isinstance(degree, (int, np.integer)) or not 1 <= degree <= sh_index.MAX_SH_DEGREE:
        raise ValidationError(f"SHAC-LST needs an SH degree from 1 to {sh_index.MAX_SH_DEGREE}, got {degree!r}")


def _check_choice(what: str, value: Any, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValidationError(f"{what} must be one of {', '.join(map(repr, choices))}, got {value!r}")
