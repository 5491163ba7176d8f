"""The SH stage contract shared by identity, truncation, SHAC-PCA, SHAC-LST and VQ.

An SH stage is a scikit-learn-style transformer on the paper-order AC matrix
``A`` (N x K', see :mod:`gscodec_shac.sh_index`):

* ``fit(A) -> self`` learns shared side information (fitted attributes end in ``_``);
* ``transform(A) -> F`` gives the per-Gaussian features the codec quantises (N x D);
* ``inverse_transform(F) -> A~`` reconstructs the AC matrix (N x K');
* ``state() -> StageState`` is everything a decoder needs, serialisable compactly;
  ``from_state(state)`` rebuilds a fitted stage from it.

A stage whose ``uses_dc`` is true (the include-DC ablation of SHAC-PCA, paper
Sec. VII-D1) takes ``[DC | A]`` (N x (3 + K')) instead and returns the same
layout; the pipeline then does not code the DC separately.

Side information is counted in the rate: ``state().nbytes()`` is the exact size of
the serialised arrays and :meth:`StageState.to_bytes` is what goes into a container.
"""

from __future__ import annotations

import io
import json
import math
import struct
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import numpy as np

from gscodec_shac import sh_index
from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.limits import MAX_NESTING, json_nesting
from gscodec_shac.registry import Registry
from gscodec_shac.row_blocks import GatheredRows
from gscodec_shac.validate import Where

_STATE_MAGIC = b"SHST"
_ALLOWED_DTYPES = {"<f2", "<f4", "<f8", "<i4", "<u2", "<u1", "|u1", "<i8", "|i1"}


@dataclass
class StageState:
    """Parameters (JSON) plus named arrays: what a decoder needs to invert a stage."""

    name: str
    params: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)

    def nbytes(self) -> int:
        """Bytes of the arrays alone (the side information the paper counts, eq. 30/38)."""
        return int(sum(a.nbytes for a in self.arrays.values()))

    def to_bytes(self) -> bytes:
        """Compact binary form: magic, JSON header length, JSON header, raw little-endian arrays."""
        layout = []
        payload = io.BytesIO()
        for key, array in self.arrays.items():
            array = np.ascontiguousarray(array)
            dtype = array.dtype.newbyteorder("<") if array.dtype.byteorder == ">" else array.dtype
            array = array.astype(dtype, copy=False)
            layout.append({"key": key, "dtype": array.dtype.str, "shape": list(array.shape)})
            payload.write(array.tobytes())
        header = json.dumps({"name": self.name, "params": self.params, "arrays": layout}, separators=(",", ":")).encode()
        return _STATE_MAGIC + struct.pack("<I", len(header)) + header + payload.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes) -> "StageState":
        """Inverse of :meth:`to_bytes`; raises :class:`GscodecError` on malformed input."""
        if len(data) < 8 or data[:4] != _STATE_MAGIC:
            raise GscodecError("SH stage state is corrupt (bad magic)")
        (length,) = struct.unpack("<I", data[4:8])
        if 8 + length > len(data):
            raise GscodecError("SH stage state is truncated (header runs past the end)")
        try:
            raw = data[8 : 8 + length]
            if json_nesting(raw) > MAX_NESTING:
                raise ValueError("nested too deep")
            header = json.loads(raw)
            name, params, layout = header["name"], header["params"], header["arrays"]
            if not (isinstance(name, str) and isinstance(params, dict) and isinstance(layout, list)):
                raise TypeError("types")
        except (ValueError, KeyError, TypeError):
            raise GscodecError("SH stage state is corrupt (unreadable header)") from None
        offset = 8 + length
        arrays = {}
        for entry in layout:
            try:
                dtype = np.dtype(entry["dtype"])
                shape = tuple(entry["shape"])
                if not isinstance(entry["key"], str) or entry["key"] in arrays:
                    raise ValueError("key")
            except (KeyError, TypeError, ValueError):
                raise GscodecError("SH stage state is corrupt (bad array entry)") from None
            if (dtype.str not in _ALLOWED_DTYPES or len(shape) > 8
                    or any(isinstance(s, bool) or not isinstance(s, int) or not 0 <= s <= 1 << 32 for s in shape)):
                raise GscodecError(f"SH stage state is corrupt (array {entry.get('key')!r})")
            size = math.prod(shape) * dtype.itemsize
            if offset + size > len(data):
                raise GscodecError(f"SH stage state is truncated (array {entry['key']!r})")
            arrays[entry["key"]] = np.frombuffer(data, dtype=dtype, count=size // dtype.itemsize, offset=offset).reshape(shape).copy()
            offset += size
        if offset != len(data):
            raise GscodecError("SH stage state is corrupt (trailing bytes)")
        return cls(name=name, params=params, arrays=arrays)


@dataclass(frozen=True)
class StageParam:
    """One constructor parameter of a stage, as rate points, the CLI and RD recipes see it.

    ``kind`` is ``int``, ``float``, ``bool`` or ``choice``; numbers must lie in
    ``[lo, hi]`` (``(lo, hi]`` with ``open_lo``). ``flag`` is the ``encode`` option
    that sets it (``"er"`` -> ``--er``), if any; several stages may share a flag.
    ``default`` is what the stage uses when the parameter is absent (shown in help).
    """

    name: str
    kind: str
    default: Any = None
    help: str = ""
    flag: str | None = None
    lo: float | None = None
    hi: float | None = None
    open_lo: bool = False
    choices: tuple[Any, ...] = ()

    def check(self, value: Any, where: Where, key: str) -> Any:
        """``value`` in its proper type, or the error of ``where`` naming ``key``."""
        if self.kind == "int":
            return where.integer(value, key, int(self.lo if self.lo is not None else -2**63),
                                 None if self.hi is None else int(self.hi))
        if self.kind == "float":
            lo = -math.inf if self.lo is None else self.lo
            hi = math.inf if self.hi is None else self.hi
            return where.number(value, key, lo, hi, open_lo=self.open_lo)
        if self.kind == "bool":
            return where.boolean(value, key)
        return where.choice(value, self.choices, key)


#: What a stage's features are, which decides how the pipeline codes them.
FEATURE_KINDS = {
    "coefficients": "AC columns in (R, G, B) triplets: YCbCr may apply, each takes the QP of its SH degree",
    "components": "channels in decreasing importance: the QP ladder follows the MPEG PCA rule",
    "labels": "integers coded losslessly at the stage's feature_bits",
}


class ShStage(ABC):
    """Base class of SH stages (see module docstring).

    Besides the transform, a stage declares what the pipeline needs to code it, so the
    pipeline never tests a stage's name: ``feature_kind`` (a key of :data:`FEATURE_KINDS`),
    ``rate_attribute`` (the rate-point attribute whose codec and QPs code the features),
    ``uses_dc`` and :meth:`feature_degrees`; and its parameters (``params``), from which
    rate-point validation, the ``encode`` options and the RD recipes are built.
    """

    #: Registry name, e.g. ``"pca"``.
    name: ClassVar[str]
    #: One line for ``--help`` and the docs.
    summary: ClassVar[str] = ""
    #: See :data:`FEATURE_KINDS`.
    feature_kind: ClassVar[str] = "coefficients"
    #: ``sh_ac`` (coded like AC coefficients), ``sh_features`` or ``sh_labels``.
    rate_attribute: ClassVar[str] = "sh_features"
    #: The constructor parameters users may set.
    params: ClassVar[tuple[StageParam, ...]] = ()
    #: True when the stage consumes and returns ``[DC | A]`` instead of ``A``.
    uses_dc: bool = False
    #: Show a progress bar while fitting (a stage with a long fit honours it, e.g. vq's k-means);
    #: the :class:`~gscodec_shac.codec.encoder.Encoder` sets it from its own ``progress``.
    progress: bool = False
    #: True when :meth:`fit` also needs the Gaussians' positions (e.g. pca-spatial): the
    #: :class:`~gscodec_shac.codec.encoder.Encoder` hands them over with :meth:`set_positions` first.
    uses_positions: ClassVar[bool] = False
    #: True when :meth:`fit` and :meth:`transform` only read row slices ``ac[a:b]`` of their input:
    #: the :class:`~gscodec_shac.codec.encoder.Encoder` then passes a
    #: :class:`~gscodec_shac.row_blocks.GatheredRows` instead of a grid-order copy (memory).
    reads_row_blocks: ClassVar[bool] = False
    #: True when :meth:`inverse_transform` of a block of rows is that block of the whole inverse,
    #: bit for bit: the :class:`~gscodec_shac.codec.decoder.Decoder` then inverts the features
    #: block by block as it dequantises them (no whole feature matrix is held).
    inverts_row_blocks: ClassVar[bool] = False

    def set_positions(self, positions: np.ndarray) -> None:
        """The (N, 3) positions of the rows the next :meth:`fit` sees (stages with ``uses_positions``)."""
        self.positions_ = np.asarray(positions, dtype=np.float64)

    def restrict_rows(self, index: np.ndarray) -> None:
        """Keep only the per-row side information (if any) of the fitted rows ``index``, in that order: a
        fitted stage applied to a subset of its rows (the rate controller's encodes, which prune and place
        the rows of the cloud it was fitted on). Stages without per-row side information ignore it."""

    def locate_rows(self, positions: np.ndarray) -> None:
        """Per-row side information (if any) for other rows of the scene the stage was fitted on, from their
        (N, 3) ``positions`` (the rate controller's probe codes a sample of the cloud). Ignored by stages
        without per-row side information."""

    def stream_features(self) -> tuple[str, ...]:
        """The container features (:data:`gscodec_shac.codec.container.FEATURES`) a stream of this fitted
        stage's state needs, so that a decoder without them refuses it; none by default."""
        return ()

    @abstractmethod
    def fit(self, ac: np.ndarray) -> "ShStage":
        """Learn the side information from an (N, K') matrix; returns ``self``."""

    @abstractmethod
    def transform(self, ac: np.ndarray) -> np.ndarray:
        """(N, K') -> (N, D) features to code."""

    @abstractmethod
    def inverse_transform(self, features: np.ndarray) -> np.ndarray:
        """(N, D) features -> (N, K') reconstruction."""

    def inverse_transform_into(self, features: np.ndarray, out: np.ndarray) -> None:
        """:meth:`inverse_transform` written into ``out`` ((N, K'), of the result's dtype)."""
        out[...] = self.inverse_transform(features)

    @abstractmethod
    def state(self) -> StageState:
        """Everything needed to invert the fitted stage."""

    @classmethod
    @abstractmethod
    def from_state(cls, state: StageState) -> "ShStage":
        """A fitted stage rebuilt from :meth:`state`."""

    def fit_transform(self, ac: np.ndarray) -> np.ndarray:
        return self.fit(ac).transform(ac)

    @property
    def n_features(self) -> int:
        """D, the number of per-Gaussian values the codec will code (after fit)."""
        raise NotImplementedError

    def side_info_bytes(self) -> int:
        """Exact bytes of the stored side information (arrays of :meth:`state`)."""
        return self.state().nbytes()

    # ------------------------------------------------------- what the codec needs
    def feature_columns(self) -> np.ndarray | None:
        """For ``coefficients`` stages: the AC column (paper order) each feature is; else None."""
        return None

    def feature_degrees(self, n_features: int) -> list[int]:
        """SH degree whose QP each feature takes (the QP ladder of a rate point).

        Coefficient features take their own column's degree; other features follow
        the MPEG PCA rule: the first 9 take the degree-1 QP, the next 15 degree 2, then
        degree 3 (the column counts 3(2l+1) of each degree, in order).
        """
        columns = self.feature_columns()
        if columns is not None and len(columns) == n_features:
            return [sh_index.degree_order(int(c) // 3 + 1)[0] for c in columns]
        bounds = np.cumsum([3 * (2 * l + 1) for l in range(1, sh_index.MAX_SH_DEGREE + 2)])
        return [int(np.searchsorted(bounds, i, side="right")) + 1 for i in range(n_features)]

    def feature_weights(self) -> np.ndarray | None:
        """Squared error in the reconstructed [DC | AC] columns per unit squared error of each feature
        (what :mod:`gscodec_shac.codec.allocation` water-fills over); None: all features alike."""
        return None

    def keep_features(self, count: int) -> None:
        """Keep only the first ``count`` features (rate-point water-filling drops the weakest).

        Only ``components`` stages, whose features come in decreasing importance, can.
        """
        if count != self.n_features:
            raise ValidationError(f"SH stage {self.name!r} cannot drop features (keeps {self.n_features})")

    def ycbcr_applies(self, n_features: int) -> bool:
        """Whether a rate point's YCbCr colour transform applies to the features."""
        return self.feature_kind == "coefficients" and not self.uses_dc and n_features % 3 == 0

    # ------------------------------------------------------------ parameters
    @classmethod
    def check_params(cls, raw: Mapping[str, Any], where: Where, prefix: str = "") -> dict[str, Any]:
        """Validated parameters (only those given, in their proper types)."""
        known = {p.name: p for p in cls.params}
        where.only(raw, known, prefix)
        return {name: known[name].check(value, where, f"{prefix}.{name}" if prefix else name)
                for name, value in raw.items()}


# ------------------------------------------------------------------------ registry
STAGES: Registry[ShStage] = Registry("SH stage", "gscodec_shac.shac", {
    "none": "identity", "trunc": "truncation", "pca": "pca", "lst": "lst", "vq": "vq", "vq-pca": "vq_pca",
    "pca-spatial": "spatial_pca"})
register_stage = STAGES.register


def make_stage(name: str, **params: Any) -> ShStage:
    """Instantiate a registered stage by name with its parameters."""
    cls = STAGES.get(name)
    try:
        return cls(**params)
    except TypeError as exc:
        raise ValidationError(f"bad parameters for SH stage {name!r}: {exc}") from None


def stage_from_state(state: StageState) -> ShStage:
    """Rebuild a fitted stage from its state (looked up by ``state.name``)."""
    if state.name not in STAGES:
        raise GscodecError(f"unknown SH stage {state.name!r} in stored state; known: {', '.join(STAGES.names())}")
    return STAGES.get(state.name).from_state(state)


def check_ac_matrix(ac: np.ndarray | GatheredRows, expected_columns: int | None = None) -> np.ndarray:
    """Validate an AC (or [DC | AC]) matrix and return it as a 2-D float array (a
    :class:`~gscodec_shac.row_blocks.GatheredRows` is checked and returned as it is)."""
    if not isinstance(ac, GatheredRows):
        ac = np.asarray(ac)
    if ac.ndim != 2:
        raise ValidationError(f"expected a 2-D (N, K') matrix, got shape {ac.shape}")
    if not np.issubdtype(ac.dtype, np.floating):
        raise ValidationError(f"expected a floating-point matrix, got dtype {ac.dtype}")
    if expected_columns is not None and ac.shape[1] != expected_columns:
        raise ValidationError(f"expected {expected_columns} columns, got {ac.shape[1]}")
    if isinstance(ac, GatheredRows):
        if not ac.all_finite():
            raise ValidationError("matrix has non-finite values")
    # min and max propagate NaN and reach +-inf: no (N, K') temporary unless something is wrong
    elif ac.size and not (np.isfinite(ac.min()) and np.isfinite(ac.max())):
        raise ValidationError(f"matrix has {int((~np.isfinite(ac)).sum())} non-finite values")
    return ac
