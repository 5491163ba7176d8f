"""The Gaussian model that flows through every stage: :class:`GaussianCloud`.

Attributes are stored exactly as the Inria 3DGS PLY stores them (pre-activation):

============  ==============  ==========================================
attribute     shape           meaning
============  ==============  ==========================================
means         (N, 3)          centre positions
scales        (N, 3)          log of the per-axis standard deviations
quats         (N, 4)          rotation quaternion, **w first**, unnormalised
opacities     (N,)            logit of the opacity
sh_dc         (N, 3)          DC SH coefficient per colour channel
sh_rest       (N, K-1, 3)     AC SH coefficients, coefficient-major
============  ==============  ==========================================

``sh_degree`` is derived from ``sh_rest.shape[1]`` (0, 3, 8, 15, 24 -> degree 0..4).
Extra per-Gaussian PLY properties (normals, custom fields) are kept in ``extra``
so that nothing read from a file is silently dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np

from gscodec_shac import sh_index
from gscodec_shac.errors import ValidationError

#: Attribute names and their per-Gaussian trailing shapes (``None`` = SH-dependent).
CORE_ATTRIBUTES: tuple[str, ...] = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")
_TRAILING_SHAPES: dict[str, tuple[int, ...] | None] = {
    "means": (3,),
    "scales": (3,),
    "quats": (4,),
    "opacities": (),
    "sh_dc": (3,),
    "sh_rest": None,
}


@dataclass(eq=False)
class GaussianCloud:
    """A 3DGS model as plain float32 numpy arrays (see module docstring)."""

    means: np.ndarray
    scales: np.ndarray
    quats: np.ndarray
    opacities: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in CORE_ATTRIBUTES:
            setattr(self, name, _as_float32(name, getattr(self, name)))
        if self.sh_rest.ndim == 2 and self.sh_rest.shape[1] == 0:
            self.sh_rest = self.sh_rest.reshape(-1, 0, 3)
        self.extra = {k: np.asarray(v) for k, v in self.extra.items()}
        self.validate()

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        """Raise :class:`ValidationError` naming the first problem found."""
        n = self.means.shape[0] if self.means.ndim >= 1 else -1
        for name in CORE_ATTRIBUTES:
            array = getattr(self, name)
            trailing = _TRAILING_SHAPES[name]
            if trailing is None:  # sh_rest
                if array.ndim != 3 or array.shape[2] != 3:
                    raise ValidationError(
                        f"sh_rest must have shape (N, K-1, 3) (coefficient-major), got {array.shape}"
                    )
                sh_index.degree_from_rest_count(array.shape[1])
            elif array.shape[1:] != trailing or array.ndim != 1 + len(trailing):
                expected = "(N" + "".join(f", {t}" for t in trailing) + ")"
                raise ValidationError(f"{name} must have shape {expected}, got {array.shape}")
            if array.shape[0] != n:
                raise ValidationError(
                    f"{name} has {array.shape[0]} rows but means has {n}: all attributes need one row per Gaussian"
                )
            _check_finite(name, array)
        for key, array in self.extra.items():
            if array.ndim < 1 or array.shape[0] != n:
                raise ValidationError(f"extra property {key!r} has shape {array.shape}, expected ({n}, ...)")

    # ------------------------------------------------------------- properties
    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    def __len__(self) -> int:
        return self.num_gaussians

    @property
    def sh_degree(self) -> int:
        return sh_index.degree_from_rest_count(self.sh_rest.shape[1])

    @property
    def num_parameters_per_gaussian(self) -> int:
        """Learnable floats per Gaussian (59 for SH degree 3, eq. 4 of the paper)."""
        return 3 + 3 + 4 + 1 + 3 * sh_index.num_coeffs(self.sh_degree)

    @property
    def num_sh_parameters_per_gaussian(self) -> int:
        """SH floats per Gaussian: K = 3(L+1)^2 (48 for L = 3)."""
        return 3 * sh_index.num_coeffs(self.sh_degree)

    # ---------------------------------------------------------------- SH views
    def ac_matrix(self) -> np.ndarray:
        """AC matrix A (N, K') in the paper's column order (R, G, B of each (l, m) adjacent)."""
        return sh_index.ac_matrix(self.sh_rest)

    def with_ac_matrix(self, ac: np.ndarray) -> "GaussianCloud":
        """A copy whose SH AC coefficients come from a paper-order AC matrix."""
        return self.replace(sh_rest=sh_index.sh_rest_from_ac(np.asarray(ac)))

    def sh_coefficients(self) -> np.ndarray:
        """All SH coefficients (N, (L+1)^2, 3), DC first."""
        return np.concatenate([self.sh_dc[:, None, :], self.sh_rest], axis=1)

    # -------------------------------------------------------------- transforms
    def replace(self, **changes: np.ndarray) -> "GaussianCloud":
        """A new cloud with some attributes replaced (others shared, not copied)."""
        values = {name: getattr(self, name) for name in CORE_ATTRIBUTES}
        values["extra"] = dict(self.extra)
        values.update(changes)
        return GaussianCloud(**values)

    def select(self, index: np.ndarray | Sequence[int] | slice) -> "GaussianCloud":
        """Subset or reorder by an integer index array, boolean mask or slice."""
        if not isinstance(index, slice):
            index = np.asarray(index)
            if index.dtype == bool and index.shape != (self.num_gaussians,):
                raise ValidationError(
                    f"boolean mask has shape {index.shape}, expected ({self.num_gaussians},)"
                )
        values = {name: getattr(self, name)[index] for name in CORE_ATTRIBUTES}
        values["extra"] = {k: v[index] for k, v in self.extra.items()}
        return GaussianCloud(**values)

    def reorder(self, permutation: np.ndarray) -> "GaussianCloud":
        """Reorder by a permutation of ``range(N)`` (checked)."""
        permutation = np.asarray(permutation)
        if permutation.shape != (self.num_gaussians,) or not _is_permutation(permutation):
            raise ValidationError(f"reorder needs a permutation of range({self.num_gaussians})")
        return self.select(permutation)

    @staticmethod
    def concat(clouds: Iterable["GaussianCloud"]) -> "GaussianCloud":
        """Concatenate clouds of equal SH degree and equal extra properties."""
        clouds = list(clouds)
        if not clouds:
            raise ValidationError("concat needs at least one cloud")
        degrees = {c.sh_degree for c in clouds}
        if len(degrees) != 1:
            raise ValidationError(f"cannot concatenate clouds of SH degrees {sorted(degrees)}")
        keys = [tuple(c.extra) for c in clouds]
        if len(set(keys)) != 1:
            raise ValidationError("cannot concatenate clouds whose extra properties differ")
        values = {name: np.concatenate([getattr(c, name) for c in clouds]) for name in CORE_ATTRIBUTES}
        values["extra"] = {k: np.concatenate([c.extra[k] for c in clouds]) for k in keys[0]}
        return GaussianCloud(**values)

    def take(self) -> "GaussianCloud":
        """Move the arrays into a new cloud and leave this one empty (zero Gaussians, the same SH
        degree and extra properties): a caller hands over its only copy, and the receiver can free
        the arrays as soon as it is done with them (e.g. ``Encoder.encode(..., release_input=True)``)."""
        values = {name: getattr(self, name) for name in CORE_ATTRIBUTES}
        values["extra"] = dict(self.extra)
        for name in CORE_ATTRIBUTES:
            setattr(self, name, getattr(self, name)[:0].copy())
        self.extra = {k: v[:0].copy() for k, v in self.extra.items()}
        return GaussianCloud(**values)

    def copy(self) -> "GaussianCloud":
        values = {name: getattr(self, name).copy() for name in CORE_ATTRIBUTES}
        values["extra"] = {k: v.copy() for k, v in self.extra.items()}
        return GaussianCloud(**values)

    def truncate_sh(self, degree: int) -> "GaussianCloud":
        """Drop SH coefficients above ``degree`` (post-hoc truncation)."""
        if degree > self.sh_degree:
            raise ValidationError(f"cannot truncate SH degree {self.sh_degree} to higher degree {degree}")
        return self.replace(sh_rest=self.sh_rest[:, : sh_index.num_rest_coeffs(degree)])

    # ---------------------------------------------------------- activations
    def activated_opacities(self) -> np.ndarray:
        """sigmoid(opacity logits) in [0, 1]."""
        return 1.0 / (1.0 + np.exp(-self.opacities.astype(np.float64)))

    def activated_scales(self) -> np.ndarray:
        """exp(log scales): standard deviations per axis."""
        return np.exp(self.scales.astype(np.float64))

    def normalized_quats(self) -> np.ndarray:
        """Unit quaternions (w first); zero quaternions become the identity."""
        q = self.quats.astype(np.float64)
        norm = np.linalg.norm(q, axis=1, keepdims=True)
        out = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), np.array([1.0, 0, 0, 0]))
        return out

    def equals(self, other: "GaussianCloud") -> bool:
        """Bit-exact equality of all attributes and extra properties."""
        if set(self.extra) != set(other.extra):
            return False
        pairs = [(getattr(self, n), getattr(other, n)) for n in CORE_ATTRIBUTES]
        pairs += [(self.extra[k], other.extra[k]) for k in self.extra]
        return all(a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes() for a, b in pairs)

    def __repr__(self) -> str:
        extra = f", extra={list(self.extra)}" if self.extra else ""
        return f"GaussianCloud(N={self.num_gaussians}, sh_degree={self.sh_degree}{extra})"


def _as_float32(name: str, value: np.ndarray) -> np.ndarray:
    array = np.asarray(value)
    if not np.issubdtype(array.dtype, np.floating):
        raise ValidationError(f"{name} must be a floating-point array, got dtype {array.dtype}")
    return np.ascontiguousarray(array, dtype=np.float32)


def _check_finite(name: str, array: np.ndarray) -> None:
    # min and max propagate NaN and reach +-inf: two allocation-free passes decide the common case.
    if array.size == 0 or (np.isfinite(array.min()) and np.isfinite(array.max())):
        return
    finite = np.isfinite(array)
    bad_rows = np.nonzero(~finite.reshape(finite.shape[0], -1).all(axis=1))[0]
    count = int((~finite).sum())
    shown = ", ".join(str(i) for i in bad_rows[:5]) + (", ..." if bad_rows.size > 5 else "")
    raise ValidationError(
        f"{name} has {count} non-finite value(s) (NaN or inf) in {bad_rows.size} Gaussian(s), rows {shown}"
    )


def _is_permutation(index: np.ndarray) -> bool:
    if not np.issubdtype(index.dtype, np.integer):
        return False
    seen = np.zeros(index.shape[0], dtype=bool)
    if index.size and (index.min() < 0 or index.max() >= index.shape[0]):
        return False
    seen[index] = True
    return bool(seen.all())
