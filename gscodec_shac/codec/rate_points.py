"""Rate points: YAML data that says how each attribute is coded (no code per point).

A rate-point file holds shared ``defaults`` and named ``points``; each point is
deep-merged over the defaults, then validated into a :class:`RatePoint`::

    description: MPEG GSC video anchor ...          # free text (optional)
    source: where the numbers come from             # free text (optional)
    defaults:
      codec: hevc                                   # grid codec of every attribute ...
      codec_options: {preset: slow}
      bits: 10                                      # ... and its bit depth
      color: ycbcr                                  # rgb | ycbcr (SH colour triplets)
      attributes:                                   # per-attribute overrides
        positions: {bits: 16, layout: split8}       # split8 | single | set (lossless only)
      sh: {stage: none}                             # SH stage and its parameters (and dc_only_share)
      sort: {method: plas, policy: pad, multiple: 8, seed: 0, weights: {xyz: 1.0}}
      prune: {min_opacity: 0.0, keep_share: 1.0}    # drop Gaussians below this opacity; keep this
                                                    # share of the input, the most important by render
    points:
      rp01:
        qp: {opacity: 22, rotation: 17, scale: 12, sh_dc: 7, sh_ac: [32, 37, 42]}

Attributes: ``positions, rotation, scale, opacity, sh_dc, sh_ac, sh_features,
sh_labels``. No QP means lossless; lossless data of 9-16 bits goes into one
plane (``layout: single``, the default except for positions and labels) or
two 8-bit planes (``split8``). ``sh_ac`` takes one QP or one per SH degree
(1, 2, 3, ...): the ladder. ``rotation`` takes one QP or two: ``[x, y, z, w]``'s QP for the
x, y, z chunk and one for the w chunk (the renderer normalises the quaternion, so most of w's
error does not show: docs/rate_control.md, "Controller version 7"). ``sh_features`` (default: as ``sh_ac``) codes the
output of a transforming stage (pca, lst); ``sh_labels`` (default: the codec and
layout of ``positions``) codes the integer labels of the ``vq`` stage. With
``allocation: waterfill`` (``sh_ac`` / ``sh_features``, one base QP) every feature gets its
own QP by reverse water-filling (:func:`gscodec_shac.codec.allocation.waterfill_qps`): the
base QP goes to the feature with the widest weighted range, the others a QP that gives the
same weighted error, and trailing features whose QP would exceed 51 are dropped (for
SHAC-PCA this chooses the rank M). That base QP may be a multiple of 0.25 (``sh_features: 20.75``):
the features' QPs stay integers, and those whose offsets round up move first.
Positions may instead be coded as a set (``layout: set``, :mod:`gscodec_shac.codec.positions`):
the grid order then follows from the decoded positions (Morton order), so the ``sort``
settings do not apply.
Positions and labels are always lossless. ``prune.keep_share`` (in (0, 1], default 1) keeps that
share of the input Gaussians, those with the highest render-based importance
(:mod:`gscodec_shac.codec.importance`), after the opacity threshold. ``sh.dc_only_share`` (in
[0, 1), default 0) codes that share of the kept Gaussians with their DC colour only, those whose
view-dependent colour is weakest (:mod:`gscodec_shac.codec.sh_degree`); ``sh.dc_only_weight``
(``alpha``, the default, or ``render``) is what that energy is weighted by; ``sh.dc_only_energy``
(in [0, 1), instead of a share) codes DC-only as many as drop at most that fraction of the energy.

References: ``"paper_table3:rp2"`` (a file shipped in
``rate_points/`` at the repository root, shipped in the wheel), ``"my.yaml:fast"`` or ``"my.yaml"`` (a file
with a single point). Every problem raises :class:`RatePointError` naming the
file, the point, the key and what is wrong.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

from gscodec_shac.codec.allocation import BASE_QP_STEP
from gscodec_shac.codec.attributes import ROTATION_FORMS
from gscodec_shac.codec.grid.base import CODECS
from gscodec_shac.errors import RatePointError
from gscodec_shac.shac.base import STAGES, ShStage
from gscodec_shac.validate import Where
from gscodec_shac.yaml_file import read_yaml_file

ATTRIBUTES = ("positions", "rotation", "scale", "opacity", "sh_dc", "sh_ac", "sh_features", "sh_labels")
LOSSLESS_ATTRIBUTES = ("positions", "sh_labels")
LAYOUTS = ("split8", "single", "set")
COLORS = ("rgb", "ycbcr")
SORT_METHODS = ("plas", "morton", "random", "none")
SORT_POLICIES = ("pad", "drop")
SORT_FEATURES = ("xyz", "scale", "opacity", "dc", "rotation")
QP_RANGE = (0, 51)

_FILE_KEYS = {"description", "source", "defaults", "points"}
_POINT_KEYS = {"description", "codec", "codec_options", "bits", "color", "qp", "attributes", "sh", "sort", "prune",
               "tiers"}
_ATTRIBUTE_KEYS = {"codec", "codec_options", "bits", "qp", "layout", "allocation", "form"}

#: How an SH attribute's features share out QPs: ``degree`` (the QP ladder by SH degree) or
#: ``waterfill`` (reverse water-filling: one QP per feature from the stage's feature weights).
ALLOCATIONS = ("degree", "waterfill")
_SORT_KEYS = {"method", "policy", "multiple", "seed", "weights", "normalize", "schedule"}
_PRUNE_KEYS = {"min_opacity", "keep_share"}
_TIER_KEYS = {"shares", "qp_offsets", "spread"}
#: At most this many importance tiers per rate point (:class:`TierSpec`).
MAX_TIERS = 8
#: What may set the tiers' QP spread per encode (``tiers.spread``; absent: the offsets as given).
TIER_SPREADS = ("importance",)
#: The most a spread set per encode scales the given offsets by.
MAX_SPREAD_FACTOR = 3.0
#: What a Gaussian's AC energy is weighted by when choosing the DC-only ones (:mod:`.sh_degree`).
DC_ONLY_WEIGHTS = ("alpha", "render")
_DEFAULT_WEIGHTS = {"xyz": 1.0, "scale": 1.0, "opacity": 1.0, "dc": 1.0, "rotation": 0.0}


@dataclass(frozen=True)
class AttributeSpec:
    """How one attribute is coded: codec (+ options), bit depth, QP(s), lossless layout."""

    codec: str
    bits: int
    qp: int | float | tuple[int, ...] | None = None  # a float: a fractional water-filling base QP
    options: dict[str, Any] = field(default_factory=dict)
    layout: str = "single"
    allocation: str = "degree"
    form: str = "quaternion"  # the rotation's only: quaternion or rotation vector

    @property
    def lossless(self) -> bool:
        return self.qp is None

    def qp_for_degree(self, degree: int) -> int | float | None:
        """QP for SH degree ``degree`` (1-based) from a ladder; the last entry repeats."""
        if not isinstance(self.qp, tuple):
            return self.qp
        return self.qp[min(degree, len(self.qp)) - 1]

    def to_json(self) -> dict[str, Any]:
        qp = list(self.qp) if isinstance(self.qp, tuple) else self.qp
        out = {"codec": self.codec, "bits": self.bits, "qp": qp, "options": dict(self.options), "layout": self.layout}
        if self.allocation != "degree":
            out["allocation"] = self.allocation
        if self.form != "quaternion":
            out["form"] = self.form
        return out


@dataclass(frozen=True)
class SortSpec:
    """How Gaussians are placed on the grid (see :mod:`sorting`)."""

    method: str = "plas"
    policy: str = "pad"
    multiple: int = 8
    seed: int = 0
    normalize: str = "minmax"
    weights: dict[str, float] = field(default_factory=lambda: dict(_DEFAULT_WEIGHTS))
    schedule: dict[str, Any] = field(default_factory=dict)  # PLAS schedule keywords

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class TierSpec:
    """Importance tiers (:mod:`gscodec_shac.codec.tiers`): the kept Gaussians split by render-based
    importance, most important first, ``shares`` of them per tier; each tier is coded as a stream of
    its own with every lossy QP (the SH features' base QP too) moved by its ``qp_offsets`` entry.
    With ``spread="importance"`` the offsets are a shape, scaled per encode to the spread the scene's
    importance asks for (:meth:`with_spread`, :func:`gscodec_shac.codec.tiers.importance_spread`)."""

    shares: tuple[float, ...]
    qp_offsets: tuple[int, ...]
    spread: str | None = None

    def to_json(self) -> dict[str, Any]:
        return {"shares": list(self.shares), "qp_offsets": list(self.qp_offsets),
                **({"spread": self.spread} if self.spread else {})}

    def with_spread(self, spread: float) -> "TierSpec":
        """Fixed offsets whose spread (last minus first) is ``spread`` QPs, the shape of :attr:`qp_offsets`
        (each scaled by the same factor, rounded; at most :data:`MAX_SPREAD_FACTOR` times the given ones)."""
        given = self.qp_offsets[-1] - self.qp_offsets[0]
        factor = 0.0 if given <= 0 else min(max(spread, 0.0) / given, MAX_SPREAD_FACTOR)
        return TierSpec(self.shares, tuple(round(v * factor) for v in self.qp_offsets))


@dataclass(frozen=True)
class RatePoint:
    """A validated rate point (see module docstring)."""

    name: str
    attributes: dict[str, AttributeSpec]
    color: str = "rgb"
    sh_stage: str = "none"
    sh_params: dict[str, Any] = field(default_factory=dict)
    sort: SortSpec = field(default_factory=SortSpec)
    min_opacity: float = 0.0
    description: str = ""
    keep_share: float = 1.0
    #: Share of the kept Gaussians coded DC-only, and the weight of their AC energy (:mod:`.sh_degree`).
    dc_only_share: float = 0.0
    dc_only_weight: str = "alpha"
    dc_only_energy: float = 0.0
    #: Importance tiers, each coded as its own stream with its own QPs (None: one stream).
    tiers: TierSpec | None = None

    @property
    def dc_only(self) -> bool:
        """Whether some Gaussians may be coded DC-only (a share or an energy bar is set)."""
        return self.dc_only_share > 0 or self.dc_only_energy > 0

    @property
    def rotation_form(self) -> str:
        """How the rotation is coded: ``quaternion`` (w | x, y, z) or ``vector`` (angle * axis)."""
        return self.attributes["rotation"].form

    @property
    def positions_as_set(self) -> bool:
        """Positions coded as a set, the grid order following from them (layout ``set``)."""
        return self.attributes["positions"].layout == "set"

    def prune_json(self) -> dict[str, float]:
        """The pruning settings as recorded (``keep_share`` only when it prunes, so streams without it
        keep their bytes)."""
        out = {"min_opacity": self.min_opacity}
        if self.keep_share < 1.0:
            out["keep_share"] = self.keep_share
        return out

    def grid_settings(self) -> dict[str, Any]:
        """Everything the grid order depends on (besides the cloud): pruning, and the sort settings
        or, for set-coded positions, their bit depth."""
        if self.positions_as_set:
            return {**self.prune_json(), "positions": self.attributes["positions"].to_json()}
        return {**self.prune_json(), "sort": self.sort.to_json()}

    def with_overrides(
        self,
        *,
        sh_stage: str | None = None,
        sh_params: Mapping[str, Any] | None = None,
        sort_method: str | None = None,
        seed: int | None = None,
        codec_options: Mapping[str, Any] | None = None,
        keep_share: float | None = None,
        dc_only_share: float | None = None,
        dc_only_energy: float | None = None,
        dc_only_weight: str | None = None,
        tiers: Mapping[str, Any] | None = None,
    ) -> "RatePoint":
        """A copy with the SH stage, sorting, lossy-codec options, importance pruning, DC-only settings or
        importance tiers replaced (CLI overrides).

        ``sh_params`` replace the point's stage parameters when the stage changes
        and are merged into them otherwise. ``codec_options`` are merged into the
        options of every attribute that has a QP (the lossy ones).
        """
        point = self
        if sh_stage is not None or sh_params:
            stage = sh_stage or self.sh_stage
            base = dict(self.sh_params) if stage == self.sh_stage else {}
            base.update(sh_params or {})
            if stage not in STAGES:
                raise RatePointError(f"unknown SH stage {stage!r}; known: {', '.join(STAGES.names())}")
            point = dataclasses.replace(point, sh_stage=stage, sh_params=base)
        if sort_method is not None and point.positions_as_set:
            raise RatePointError(f"{point.name} codes positions as a set: its grid order follows from the "
                                 f"positions, so a sort method ({sort_method}) does not apply")
        if sort_method is not None or seed is not None:
            sort = point.sort
            if sort_method is not None:
                if sort_method not in SORT_METHODS:
                    raise RatePointError(f"unknown sort method {sort_method!r}; known: {', '.join(SORT_METHODS)}")
                sort = dataclasses.replace(sort, method=sort_method)
            if seed is not None:
                sort = dataclasses.replace(sort, seed=int(seed))
            point = dataclasses.replace(point, sort=sort)
        if codec_options:
            attributes = {
                name: spec if spec.lossless else dataclasses.replace(spec, options={**spec.options, **codec_options})
                for name, spec in point.attributes.items()
            }
            point = dataclasses.replace(point, attributes=attributes)
        if keep_share is not None:
            point = dataclasses.replace(point, keep_share=check_keep_share(keep_share, "the keep share"))
        if dc_only_share is not None:
            if not _is_dc_only_share(dc_only_share):
                raise RatePointError(f"the DC-only share must be a number in [0, 1), got {dc_only_share!r}")
            point = dataclasses.replace(point, dc_only_share=float(dc_only_share), dc_only_energy=0.0)
        if dc_only_energy is not None:
            if not _is_dc_only_share(dc_only_energy):
                raise RatePointError(f"the DC-only energy bar must be a number in [0, 1), got {dc_only_energy!r}")
            point = dataclasses.replace(point, dc_only_energy=float(dc_only_energy), dc_only_share=0.0)
        if dc_only_weight is not None:
            if dc_only_weight not in DC_ONLY_WEIGHTS:
                raise RatePointError(f"unknown DC-only weight {dc_only_weight!r}; known: {', '.join(DC_ONLY_WEIGHTS)}")
            point = dataclasses.replace(point, dc_only_weight=dc_only_weight)
        if tiers is not None:  # ``{shares: [...], qp_offsets: [...]}``, as in a rate-point file
            point = dataclasses.replace(point, tiers=_tiers(Where(point.name, RatePointError), dict(tiers)))
        return point

    def tier_point(self, index: int) -> "RatePoint":
        """The rate point of tier ``index``: every lossy QP moved by its offset, no pruning (the tiers split
        Gaussians already pruned) and no tiers. Where a QP is too fine for the finest tier's offset (QP 2
        and an offset of -3), every tier's offset of that attribute shrinks in proportion (to 2/3 of it,
        rounded): the tiers spread around the QP as far as the finest can go, and at QP 0 not at all."""
        assert self.tiers is not None
        offsets = self.tiers.qp_offsets
        attributes = {name: spec if spec.qp is None
                      else dataclasses.replace(spec, qp=_offset_qp(spec.qp, _room(spec.qp, offsets) * offsets[index]))
                      for name, spec in self.attributes.items()}
        return dataclasses.replace(self, attributes=attributes, tiers=None, keep_share=1.0, min_opacity=0.0,
                                   name=f"{self.name}/tier{index}")

    def sh_json(self) -> dict[str, Any]:
        """The SH settings as recorded (the DC-only share only when it is used, so streams without it
        keep their bytes)."""
        out = {"stage": self.sh_stage, **self.sh_params}
        if self.dc_only_share > 0:
            out["dc_only_share"] = self.dc_only_share
        if self.dc_only_energy > 0:
            out["dc_only_energy"] = self.dc_only_energy
        if self.dc_only:
            out["dc_only_weight"] = self.dc_only_weight
        return out

    def to_json(self) -> dict[str, Any]:
        """The resolved rate point, as recorded in a container header."""
        return {
            "name": self.name,
            "description": self.description,
            "color": self.color,
            "sh": self.sh_json(),
            "sort": self.sort.to_json(),
            "prune": self.prune_json(),
            "attributes": {name: spec.to_json() for name, spec in self.attributes.items()},
            **({"tiers": self.tiers.to_json()} if self.tiers is not None else {}),
        }


# ------------------------------------------------------------------ loading
def rate_point_folder() -> Path:
    """Where the shipped rate points are: inside an installed wheel, else the checkout's ``rate_points/``."""
    installed = Path(str(resources.files("gscodec_shac"))) / "rate_points"
    return installed if installed.is_dir() else Path(__file__).resolve().parents[2] / "rate_points"


def builtin_rate_point_files() -> dict[str, Path]:
    """Shipped rate-point files by stem (``"paper_table3"`` -> path)."""
    return {p.stem: p for p in sorted(rate_point_folder().iterdir()) if p.suffix in (".yaml", ".yml")}


def list_rate_points() -> list[str]:
    """Every shipped rate point as a reference, e.g. ``"paper_table3:rp2"``."""
    refs = []
    for stem, path in sorted(builtin_rate_point_files().items()):
        refs += [f"{stem}:{name}" for name in load_rate_point_file(path)]
    return refs


def load_rate_point(ref: "str | Path | RatePoint") -> RatePoint:
    """Resolve a reference (see module docstring) to a validated :class:`RatePoint`."""
    if isinstance(ref, RatePoint):
        return ref
    text = str(ref)
    path, point = _split_reference(text)
    points = load_rate_point_file(path)
    # name the file as the user did: a shipped set by its name (shac_ladder), a file by its path
    shown = text.rsplit(":", 1)[0] if point is not None else text
    if point is None:
        if len(points) != 1:
            raise RatePointError(f"{shown}: holds {len(points)} rate points ({', '.join(points)}); name one as "
                                 f"{shown}:POINT")
        return next(iter(points.values()))
    if point not in points:
        raise RatePointError(f"{shown}: no rate point {point!r}; it has {', '.join(points)}")
    return points[point]


def load_rate_point_file(path: str | Path) -> dict[str, RatePoint]:
    """All points of one YAML file, validated, by name."""
    path = Path(path)
    data = read_yaml_file(path, "rate-point file", RatePointError)
    return parse_rate_points(data, str(path), stem=path.stem)


def parse_rate_points(data: Any, source: str, stem: str = "") -> dict[str, RatePoint]:
    """Validate an already-parsed rate-point document (see module docstring)."""
    where = Where(source, RatePointError)
    if not isinstance(data, dict):
        raise where.error("", "a rate-point file must be a mapping with 'points'")
    where.only(data, _FILE_KEYS)
    defaults = data.get("defaults") or {}
    if not isinstance(defaults, dict):
        raise where.error("defaults", "must be a mapping")
    points = data.get("points")
    if not isinstance(points, dict) or not points:
        raise where.error("points", "must be a non-empty mapping of point name -> settings")
    out = {}
    for name, raw in points.items():
        if not isinstance(name, str) or not name or ":" in name:
            raise where.error(f"points.{name}", "point names must be non-empty strings without ':'")
        raw = where.mapping(raw, f"points.{name}")
        merged = _deep_merge(defaults, raw)
        merged.setdefault("description", data.get("description", ""))
        out[name] = _build_point(merged, source, f"{stem}:{name}" if stem else name, point=name)
    return out


# -------------------------------------------------------------- validation
def _build_point(raw: dict, source: str, full_name: str, point: str | None = None) -> RatePoint:
    where = Where(source, RatePointError, f"point {point or full_name!r}")
    where.only(raw, _POINT_KEYS)
    codec = where.string(raw.get("codec", "hevc"), "codec")
    options = where.mapping(raw.get("codec_options"), "codec_options")
    bits = where.integer(raw.get("bits", 10), "bits", 1, 16)
    color = where.choice(raw.get("color", "rgb"), COLORS, "color")
    qps = where.mapping(raw.get("qp"), "qp")
    overrides = where.mapping(raw.get("attributes"), "attributes")
    for key in list(qps) + list(overrides):
        if key not in ATTRIBUTES:
            prefix = "qp" if key in qps else "attributes"
            raise where.error(f"{prefix}.{key}", f"unknown attribute (known: {', '.join(ATTRIBUTES)})")

    attributes: dict[str, AttributeSpec] = {}
    for name in ATTRIBUTES:
        if name in ("sh_features", "sh_labels") and name not in overrides and name not in qps:
            continue
        over = where.mapping(overrides.get(name), f"attributes.{name}")
        where.only(over, _ATTRIBUTE_KEYS, f"attributes.{name}")
        default_bits = 16 if name == "positions" else bits
        spec_codec = where.string(over.get("codec", codec), f"attributes.{name}.codec")
        inherited = options if spec_codec == codec else {}  # options belong to the file's codec
        spec_options = {**inherited, **where.mapping(over.get("codec_options"), f"attributes.{name}.codec_options")}
        spec_bits = where.integer(over.get("bits", default_bits), f"attributes.{name}.bits", 1, 16)
        qp_key = f"attributes.{name}.qp" if "qp" in over else f"qp.{name}"
        qp = _qp(where, over["qp"] if "qp" in over else qps.get(name), qp_key,
                 ladder=name in ("sh_ac", "sh_features", "rotation"), fractional=name in ("sh_ac", "sh_features"))
        if name == "rotation" and isinstance(qp, tuple) and len(qp) > 2:
            raise where.error(qp_key, f"rotation takes one QP or two (x, y, z and w), got {len(qp)}")
        default_layout = "split8" if name in LOSSLESS_ATTRIBUTES else "single"
        layout = where.choice(over.get("layout", default_layout), LAYOUTS, f"attributes.{name}.layout")
        allocation = where.choice(over.get("allocation", "degree"), ALLOCATIONS, f"attributes.{name}.allocation")
        if allocation == "waterfill" and (name not in ("sh_ac", "sh_features") or not isinstance(qp, (int, float))):
            raise where.error(f"attributes.{name}.allocation",
                              "waterfill applies to sh_ac / sh_features with one base QP")
        if isinstance(qp, float) and allocation != "waterfill":
            raise where.error(qp_key, f"a fractional QP ({qp}) is a water-filling base QP: it needs allocation: waterfill")
        if layout == "set" and name != "positions":
            raise where.error(f"attributes.{name}.layout", "only positions can be coded as a set")
        if name in LOSSLESS_ATTRIBUTES and qp is not None:
            raise where.error(qp_key, f"{name} are coded losslessly; remove the QP")
        form = where.choice(over.get("form", "quaternion"), tuple(ROTATION_FORMS), f"attributes.{name}.form")
        if form != "quaternion" and name != "rotation":
            raise where.error(f"attributes.{name}.form", "only the rotation has a form")
        if form == "vector" and isinstance(qp, tuple):
            raise where.error(qp_key, "a rotation vector takes one QP (two are for a quaternion's x, y, z and w)")
        _check_codec(where, spec_codec, qp, f"attributes.{name}.codec")
        attributes[name] = AttributeSpec(spec_codec, spec_bits, qp, spec_options, layout, allocation, form)
    if "sh_features" not in attributes:
        attributes["sh_features"] = attributes["sh_ac"]
    if "sh_labels" not in attributes:
        pos = attributes["positions"]
        layout = "split8" if pos.layout == "set" else pos.layout
        attributes["sh_labels"] = AttributeSpec(pos.codec, 16, None, dict(pos.options), layout)

    sh = raw.get("sh") or {}
    if not isinstance(sh, dict):
        raise where.error("sh", "must be a mapping like {stage: pca, energy_retention: 0.99}")
    sh = dict(sh)
    stage = sh.pop("stage", "none")
    dc_only_share = sh.pop("dc_only_share", 0.0)
    if not _is_dc_only_share(dc_only_share):
        raise where.error("sh.dc_only_share", f"must be a number in [0, 1), got {dc_only_share!r}")
    dc_only_weight = where.choice(sh.pop("dc_only_weight", "alpha"), DC_ONLY_WEIGHTS, "sh.dc_only_weight")
    dc_only_energy = sh.pop("dc_only_energy", 0.0)
    if not _is_dc_only_share(dc_only_energy):
        raise where.error("sh.dc_only_energy", f"must be a number in [0, 1), got {dc_only_energy!r}")
    if dc_only_share and dc_only_energy:
        raise where.error("sh.dc_only_energy", "give a DC-only share or an energy bar, not both")
    sh = _stage_class(stage, where, "sh.stage").check_params(sh, where, "sh")

    sort_raw = where.mapping(raw.get("sort"), "sort")
    where.only(sort_raw, _SORT_KEYS, "sort")
    weights_raw = sort_raw.get("weights", {})
    if not isinstance(weights_raw, dict):
        raise where.error("sort.weights", "must be a mapping of feature -> weight")
    weights = dict(_DEFAULT_WEIGHTS)
    for key, value in weights_raw.items():
        if key not in SORT_FEATURES:
            raise where.error(f"sort.weights.{key}", f"unknown sort feature (known: {', '.join(SORT_FEATURES)})")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
            raise where.error(f"sort.weights.{key}", f"must be a number >= 0, got {value!r}")
        weights[key] = float(value)
    sort = SortSpec(
        method=where.choice(sort_raw.get("method", "plas"), SORT_METHODS, "sort.method"),
        policy=where.choice(sort_raw.get("policy", "pad"), SORT_POLICIES, "sort.policy"),
        multiple=where.integer(sort_raw.get("multiple", 8), "sort.multiple", 1, 1024),
        seed=where.integer(sort_raw.get("seed", 0), "sort.seed", 0, 2**32 - 1),
        normalize=where.choice(sort_raw.get("normalize", "minmax"), ("minmax", "std"), "sort.normalize"),
        weights=weights,
        schedule=where.mapping(sort_raw.get("schedule"), "sort.schedule"),
    )
    if sort.schedule and sort.method != "plas":
        raise where.error("sort.schedule", "schedule options apply to the plas method only")

    prune = where.mapping(raw.get("prune"), "prune")
    where.only(prune, _PRUNE_KEYS, "prune")
    min_opacity = prune.get("min_opacity", 0.0)
    if isinstance(min_opacity, bool) or not isinstance(min_opacity, (int, float)) or not 0 <= min_opacity < 1:
        raise where.error("prune.min_opacity", f"must be a number in [0, 1), got {min_opacity!r}")
    keep_share = prune.get("keep_share", 1.0)
    if not _is_share(keep_share):
        raise where.error("prune.keep_share", f"must be a number in (0, 1], got {keep_share!r}")

    tiers = _tiers(where, raw.get("tiers"))
    description = raw.get("description", "")
    if not isinstance(description, str):
        raise where.error("description", "must be a string")
    return RatePoint(
        name=full_name,
        attributes=attributes,
        color=color,
        sh_stage=stage,
        sh_params=sh,
        sort=sort,
        min_opacity=float(min_opacity),
        description=description.strip(),
        keep_share=float(keep_share),
        dc_only_share=float(dc_only_share),
        dc_only_weight=dc_only_weight,
        dc_only_energy=float(dc_only_energy),
        tiers=tiers,
    )


def _tiers(where: Where, value: Any) -> TierSpec | None:
    """``tiers: {shares: [...], qp_offsets: [...]}``: 2 to :data:`MAX_TIERS` tiers, shares > 0 adding up to 1."""
    if value is None:
        return None
    raw = where.mapping(value, "tiers")
    where.only(raw, _TIER_KEYS, "tiers")
    shares, offsets = raw.get("shares"), raw.get("qp_offsets")
    if not isinstance(shares, list) or not 2 <= len(shares) <= MAX_TIERS or not all(_is_share(v) for v in shares):
        raise where.error("tiers.shares", f"must be a list of 2 to {MAX_TIERS} numbers in (0, 1], got {shares!r}")
    if abs(sum(shares) - 1.0) > 1e-6:
        raise where.error("tiers.shares", f"must add up to 1, got {sum(shares):g}")
    if not isinstance(offsets, list) or len(offsets) != len(shares) or not all(
            isinstance(v, int) and not isinstance(v, bool) and -QP_RANGE[1] <= v <= QP_RANGE[1] for v in offsets):
        raise where.error("tiers.qp_offsets", f"must be a list of {len(shares)} integers in "
                          f"[-{QP_RANGE[1]}, {QP_RANGE[1]}] (one per share), got {offsets!r}")
    spread = raw.get("spread")
    if spread is not None and spread not in TIER_SPREADS:
        raise where.error("tiers.spread", f"must be one of {', '.join(TIER_SPREADS)} (or absent), got {spread!r}")
    if spread is not None and offsets[-1] - offsets[0] <= 0:
        raise where.error("tiers.qp_offsets", f"must rise from the first tier to the last to be scaled by "
                          f"tiers.spread, got {offsets!r}")
    return TierSpec(tuple(float(v) for v in shares), tuple(int(v) for v in offsets), spread)


def _room(qp: int | float | tuple, offsets: tuple[int, ...]) -> float:
    """The share of the tiers' offsets a QP takes: 1, or less when the most negative offset would pass
    below QP 0 (a ladder: its first QP)."""
    first = qp[0] if isinstance(qp, tuple) else qp
    finest = min(offsets)
    return 1.0 if finest >= 0 or first + finest >= QP_RANGE[0] else max(first, 0) / -finest


def _offset_qp(qp: int | float | tuple, offset: float) -> int | float | tuple:
    """A QP (a fractional water-filling base, or a ladder) moved by ``offset`` (rounded to a whole QP, a
    fractional base to a quarter), within 0-51."""
    if isinstance(qp, tuple):
        return tuple(_offset_qp(q, offset) for q in qp)
    if isinstance(qp, float):
        return float(min(max(qp + round(4 * offset) / 4, QP_RANGE[0]), QP_RANGE[1]))
    return int(min(max(qp + int(round(offset)), QP_RANGE[0]), QP_RANGE[1]))


def _is_share(value: Any) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float)) and 0 < value <= 1


def _is_dc_only_share(value: Any) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float)) and 0 <= value < 1


def check_keep_share(value: Any, what: str) -> float:
    """``value`` as a share of Gaussians to keep, in (0, 1]; a :class:`RatePointError` naming ``what`` otherwise."""
    if not _is_share(value):
        raise RatePointError(f"{what} must be a number in (0, 1] (the share of the Gaussians kept), got {value!r}")
    return float(value)


def _qp(where: Where, value: Any, key: str, *, ladder: bool,
        fractional: bool = False) -> int | float | tuple[int, ...] | None:
    """A QP, a ladder of them (``ladder``), or with ``fractional`` a multiple of
    :data:`~gscodec_shac.codec.allocation.BASE_QP_STEP` (a water-filling base QP; whole values stay ints)."""
    if value is None:
        return None
    if ladder and isinstance(value, list):
        if not value:
            raise where.error(key, "a QP ladder needs at least one QP (one per SH degree)")
        return tuple(_qp(where, v, f"{key}[{i}]", ladder=False) for i, v in enumerate(value))
    lo, hi = QP_RANGE
    if fractional and isinstance(value, float) and math.isfinite(value) and lo <= value <= hi \
            and (value / BASE_QP_STEP).is_integer():
        return int(value) if value.is_integer() else value
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        what = "an integer QP or a list of QPs (one per SH degree)" if ladder else "an integer"
        if fractional:
            what += f" (a water-filling base QP may also be a multiple of {BASE_QP_STEP})"
        raise where.error(key, f"QP must be {what} in {lo}-{hi}, got {value!r}")
    return value


def _check_codec(where: Where, name: str, qp: Any, key: str) -> None:
    if name not in CODECS:
        raise where.error(key, f"unknown codec {name!r} (known: {', '.join(CODECS.names())})")
    if qp is not None and CODECS.get(name).lossless_only:
        raise where.error(key, f"codec {name!r} is lossless only but a QP is given")


def _stage_class(stage: Any, where: Where, key: str) -> type[ShStage]:
    if not isinstance(stage, str) or stage not in STAGES:
        raise where.error(key, f"unknown SH stage {stage!r} (known: {', '.join(STAGES.names())})")
    return STAGES.get(stage)


def _deep_merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _split_reference(text: str) -> tuple[Path, str | None]:
    """``"stem:point"``, ``"file.yaml:point"`` or ``"file.yaml"`` -> (file, point)."""
    builtin = builtin_rate_point_files()
    candidate = Path(text)
    if candidate.suffix in (".yaml", ".yml") and candidate.is_file():
        return candidate, None
    if ":" in text:
        head, point = text.rsplit(":", 1)
        if head in builtin:
            return builtin[head], point
        path = Path(head)
        if path.suffix in (".yaml", ".yml") or path.is_file():
            if not path.is_file():
                raise RatePointError(f"{path}: rate-point file not found")
            return path, point
        raise RatePointError(
            f"unknown rate-point file {head!r} in {text!r}; shipped: {', '.join(sorted(builtin))} "
            "(or give a path to a .yaml file)"
        )
    if text in builtin:
        return builtin[text], None
    if candidate.suffix in (".yaml", ".yml"):
        raise RatePointError(f"{candidate}: rate-point file not found")
    raise RatePointError(
        f"unknown rate point {text!r}; use FILE:POINT, e.g. paper_table3:rp2 "
        f"(shipped files: {', '.join(sorted(builtin))})"
    )
