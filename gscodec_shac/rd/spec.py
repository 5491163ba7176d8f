"""The sweep specification (YAML) and its validation.

A sweep is scenes x methods x rate points::

    name: bonsai                          # optional; names the sweep in reports
    rate_points: [paper_table3:rp1, paper_table3:rp2, paper_table3:rp3, paper_table3:rp4]
    settings:                             # optional, see EvalSettings
      sort: null                          # override every rate point's sort (plas|morton|random|none)
      preset: null                        # x265 speed preset for the lossy codecs
      anchor: baseline                    # BD-rates are measured against this method
      compare: {shac-auto: shac-auto-nosh}   # extra BD-rates: a method against its own anchor
      retries: 1                          # in-run retries of a run that raised
      max_retries: 2                      # re-runs of a run whose worker died (Ray: max_retries)
      threads: null                       # threads per run (default: CPUs / workers)
      lpips_weights: null                 # LPIPS-VGG weights file (else LPIPS is left empty)
    scenes:
      - name: bonsai
        ply: /data/bonsai/point_cloud.ply # or meta.json/.sog/.spz/.splat/.compressed.ply/.pt (converted to a PLY)
        cameras: /data/bonsai/cameras.json   # any format gscodec_shac.io.cameras.load_cameras reads
        images: /data/mipnerf360_bonsai/images   # optional ground truth (resized with INTER_AREA)
        background: [0, 0, 0]
        test_every: 8                     # test views = every 8th camera in name order
        calibration: null                 # optional other cameras for rate control and recovery (default:
                                          # the cameras that are not test views)
        max_views: null                   # optional cap, evenly spaced over the test views
      - name: kacy
        ply: kacy.ply
        orbit: {n: 16, width: 200, height: 150, fov_y: 50, elevation: 20}   # no cameras: orbit views
      - name: synthetic
        synthetic: {n: 20000, seed: 0}    # made in code; orbit cameras of the generator
    methods:
      - baseline                          # a bare recipe name is a method of that name
      - {name: pca-er0.99, recipe: pca, energy_retention: 0.99}
      - {name: lst-ft, recipe: lst, finetuned: {bonsai: bonsai.lst.npz}}

Relative paths are relative to the YAML file. Every problem raises
:class:`SweepSpecError` naming the file and the key.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

from gscodec_shac.errors import GscodecError
from gscodec_shac.validate import Where
from gscodec_shac.yaml_file import read_yaml_file

#: Scene inputs that are not Inria PLYs and are converted to one first (native readers, else splat-transform).
CONVERTIBLE_SUFFIXES = (".sog", ".spz", ".splat", ".ksplat", ".json", ".pt", ".pth")
SORT_METHODS = ("plas", "morton", "random", "none")

_TOP_KEYS = {"name", "description", "rate_points", "settings", "scenes", "methods"}
_SCENE_KEYS = {"name", "ply", "synthetic", "cameras", "orbit", "images", "background", "test_every", "max_views",
               "calibration", "note"}
_SYNTHETIC_KEYS = {"n", "seed", "n_cameras", "width", "height", "ground_truth"}
_ORBIT_KEYS = {"n", "width", "height", "fov_y", "elevation", "radius", "center", "up"}
_SETTINGS_KEYS = {"sort", "preset", "anchor", "compare", "retries", "max_retries", "threads", "lpips_weights",
                  "cache_sort"}


class SweepSpecError(GscodecError):
    """A sweep YAML file is missing, malformed or names unknown settings."""


# --------------------------------------------------------------------------- dataclasses
@dataclass(frozen=True)
class OrbitSpec:
    """Orbit cameras around a scene without cameras (centre, radius and up found from the cloud when absent)."""

    n: int = 16
    width: int = 200
    height: int = 150
    fov_y: float = 50.0
    elevation: float = 20.0
    radius: float | None = None
    center: tuple[float, float, float] | None = None
    up: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class SyntheticSpec:
    """The built-in synthetic scene (:func:`gscodec_shac.synthetic.make_synthetic_scene`)."""

    n: int = 20_000
    seed: int = 0
    n_cameras: int = 24
    width: int = 320
    height: int = 240
    ground_truth: bool = True  # render the noise-free model as ground-truth images


@dataclass(frozen=True)
class SceneSpec:
    """One scene: a model plus the cameras (and optional ground truth) it is judged from."""

    name: str
    ply: str | None = None
    synthetic: SyntheticSpec | None = None
    cameras: str | None = None
    orbit: OrbitSpec | None = None
    images: str | None = None
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    test_every: int = 8
    max_views: int | None = None
    #: cameras the rate controller and the recovery use instead of the non-test ones (a scene whose test
    #: views are a file of their own, like NeRF-Synthetic's official split)
    calibration: str | None = None
    note: str = ""

    @property
    def needs_conversion(self) -> bool:
        """The input is not an Inria PLY (SOG, SPZ, .splat, compressed.ply, checkpoint, ...) and is converted first."""
        if self.ply is None:
            return False
        path = Path(self.ply)
        return (path.suffix.lower() in CONVERTIBLE_SUFFIXES or path.name.lower().endswith(".compressed.ply")
                or path.is_dir())

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class MethodSpec:
    """A named recipe (see :mod:`gscodec_shac.rd.methods`) with its parameters."""

    name: str
    recipe: str
    params: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "recipe": self.recipe, "params": self.params}


@dataclass(frozen=True)
class EvalSettings:
    """Sweep-wide settings; only :meth:`result_json` ones change a run's result (and key)."""

    sort: str | None = None
    preset: str | None = None
    anchor: str = "baseline"
    compare: dict[str, str] = field(default_factory=dict)  # method -> its own anchor (extra BD-rates; report only)
    retries: int = 1
    max_retries: int = 2
    threads: int | None = None
    lpips_weights: str | None = None
    cache_sort: bool = True

    def result_json(self) -> dict[str, Any]:
        """The settings a row's numbers depend on (hashed into its key)."""
        return {"sort": self.sort, "preset": self.preset, "lpips_weights": self.lpips_weights}


@dataclass(frozen=True)
class SweepSpec:
    """A validated sweep."""

    name: str
    scenes: tuple[SceneSpec, ...]
    methods: tuple[MethodSpec, ...]
    rate_points: tuple[str, ...]
    settings: EvalSettings = field(default_factory=EvalSettings)
    source: str = "<dict>"
    description: str = ""

    def with_settings(self, **changes: Any) -> "SweepSpec":
        return replace(self, settings=replace(self.settings, **changes))


# --------------------------------------------------------------------------- keys
def stable_hash(value: Any, length: int = 12) -> str:
    """A short SHA-256 of the canonical JSON of ``value``."""
    text = json.dumps(value, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:length]


def file_fingerprint(path: str | os.PathLike) -> str:
    """Cheap content fingerprint of a file: its size and the SHA-256 of its first and last MiB."""
    path = Path(path)
    size = path.stat().st_size
    digest = hashlib.sha256(str(size).encode())
    with path.open("rb") as handle:
        digest.update(handle.read(1 << 20))
        if size > 2 << 20:
            handle.seek(-(1 << 20), os.SEEK_END)
            digest.update(handle.read())
    return digest.hexdigest()[:16]


def run_key(scene: str, method: str, rate_point: str, settings_hash: str) -> str:
    """The stable identity of a run: ``scene/method/rate_point/settings_hash``."""
    return f"{scene}/{method}/{rate_point}/{settings_hash}"


# --------------------------------------------------------------------------- loading
def load_sweep(path: str | os.PathLike) -> SweepSpec:
    """Read and validate a sweep YAML file."""
    path = Path(path)
    data = read_yaml_file(path, "sweep file", SweepSpecError)
    return parse_sweep(data, source=str(path), base=path.parent)


def parse_sweep(data: Any, source: str = "<dict>", base: str | os.PathLike | None = None) -> SweepSpec:
    """Validate an already-parsed sweep document; relative paths are resolved against ``base``."""
    err = Where(source, SweepSpecError)
    base_dir = Path(base) if base is not None else Path.cwd()
    if not isinstance(data, dict):
        raise err.error("", "a sweep must be a mapping with 'scenes', 'methods' and 'rate_points'")
    err.only(data, _TOP_KEYS, "")
    for key in ("scenes", "methods", "rate_points"):
        if key not in data:
            raise err.error(key, "is required")
    settings = _settings(data.get("settings") or {}, err, base_dir)
    scenes = err.sequence(data["scenes"], "scenes")
    methods = err.sequence(data["methods"], "methods")
    rate_points = _rate_points(data["rate_points"], err, base_dir)
    scene_specs = tuple(_scene(raw, f"scenes[{i}]", err, base_dir) for i, raw in enumerate(scenes))
    method_specs = tuple(_method(raw, f"methods[{i}]", err, base_dir) for i, raw in enumerate(methods))
    _unique([s.name for s in scene_specs], "scenes", err)
    _unique([m.name for m in method_specs], "methods", err)
    name = data.get("name", Path(source).stem if source != "<dict>" else "sweep")
    if not isinstance(name, str) or not name:
        raise err.error("name", f"must be a non-empty string, got {name!r}")
    description = data.get("description", "")
    if not isinstance(description, str):
        raise err.error("description", "must be a string")
    return SweepSpec(name, scene_specs, method_specs, rate_points, settings, source, description)


def _unique(names: list[str], key: str, err: Where) -> None:
    seen: set[str] = set()
    for name in names:
        if name in seen:
            raise err.error(key, f"name {name!r} is used twice")
        seen.add(name)


def _name(value: Any, key: str, err: Where) -> str:
    if not isinstance(value, str) or not value or any(c in value for c in "/\\:\n") or value.startswith("."):
        raise err.error(key, f"must be a non-empty name without '/', '\\', ':' or a leading '.', got {value!r}")
    return value


def _path(value: Any, key: str, err: Where, base: Path, *, must_exist: bool = True) -> str:
    if not isinstance(value, (str, os.PathLike)) or not str(value):
        raise err.error(key, f"must be a path, got {value!r}")
    path = Path(os.path.expanduser(str(value)))
    path = path if path.is_absolute() else (base / path)
    if must_exist and not path.exists():
        raise err.error(key, f"{path} does not exist")
    return str(path.resolve())


def _int(raw: Mapping, name: str, key: str, err: Where, default: int | None, lo: int, hi: int | None = None) -> int | None:
    value = raw.get(name, default)
    return None if value is None else err.integer(value, key, lo, hi)


def _bool(raw: Mapping, name: str, key: str, err: Where, default: bool) -> bool:
    return err.boolean(raw.get(name, default), key)


def _number(raw: Mapping, name: str, key: str, err: Where, default: float | None, lo: float, hi: float) -> float | None:
    value = raw.get(name, default)
    return None if value is None else err.number(value, key, lo, hi)


def _settings(raw: Any, err: Where, base: Path) -> EvalSettings:
    if not isinstance(raw, dict):
        raise err.error("settings", "must be a mapping")
    err.only(raw, _SETTINGS_KEYS, "settings")
    sort = raw.get("sort")
    if sort is not None and sort not in SORT_METHODS:
        raise err.error("settings.sort", f"must be one of {', '.join(SORT_METHODS)} or null, got {sort!r}")
    preset = raw.get("preset")
    if preset is not None and (not isinstance(preset, str) or not preset):
        raise err.error("settings.preset", f"must be an x265 preset name, got {preset!r}")
    anchor = raw.get("anchor", "baseline")
    if not isinstance(anchor, str) or not anchor:
        raise err.error("settings.anchor", f"must be a method name, got {anchor!r}")
    compare = err.mapping(raw.get("compare"), "settings.compare")
    for method, other in compare.items():
        if not isinstance(method, str) or not method or not isinstance(other, str) or not other or method == other:
            raise err.error(f"settings.compare.{method}", f"must map a method name to another method name, got {other!r}")
    cache_sort = _bool(raw, "cache_sort", "settings.cache_sort", err, True)
    weights = raw.get("lpips_weights")
    return EvalSettings(
        sort=sort,
        preset=preset,
        anchor=anchor,
        compare=dict(compare),
        retries=_int(raw, "retries", "settings.retries", err, 1, 0, 10),
        max_retries=_int(raw, "max_retries", "settings.max_retries", err, 2, 0, 10),
        threads=_int(raw, "threads", "settings.threads", err, None, 1, 256),
        lpips_weights=_path(weights, "settings.lpips_weights", err, base) if weights is not None else None,
        cache_sort=cache_sort,
    )


def _rate_points(raw: Any, err: Where, base: Path) -> tuple[str, ...]:
    from gscodec_shac.codec.rate_points import builtin_rate_point_files, load_rate_point

    if isinstance(raw, str):
        raw = [raw]
    items = err.sequence(raw, "rate_points")
    refs = []
    builtin = builtin_rate_point_files()
    for i, ref in enumerate(items):
        key = f"rate_points[{i}]"
        if not isinstance(ref, str) or not ref:
            raise err.error(key, f"must be a rate-point reference like paper_table3:rp1, got {ref!r}")
        if ":" not in ref and ref in builtin:  # a whole shipped file: every point in it
            from gscodec_shac.codec.rate_points import load_rate_point_file

            refs += [f"{ref}:{name}" for name in load_rate_point_file(builtin[ref])]
            continue
        head, _, point = ref.rpartition(":") if ":" in ref else (ref, "", "")
        if head and head not in builtin:  # a YAML file: resolve it against the sweep file
            ref = _path(head, key, err, base) + (f":{point}" if point else "")
        elif not head and ref.endswith((".yaml", ".yml")):
            ref = _path(ref, key, err, base)
        try:
            load_rate_point(ref)
        except GscodecError as exc:
            raise err.error(key, str(exc)) from None
        refs.append(ref)
    if len(set(refs)) != len(refs):
        raise err.error("rate_points", "lists a rate point twice")
    return tuple(refs)


def _scene(raw: Any, key: str, err: Where, base: Path) -> SceneSpec:
    if not isinstance(raw, dict):
        raise err.error(key, "must be a mapping with 'name' and 'ply' (or 'synthetic')")
    err.only(raw, _SCENE_KEYS, key)
    name = _name(raw.get("name"), f"{key}.name", err)
    has_ply, has_synth = raw.get("ply") is not None, raw.get("synthetic") is not None
    if has_ply == has_synth:
        raise err.error(key, "give exactly one of 'ply' (a file) or 'synthetic' (the built-in scene)")
    synthetic = None
    if has_synth:
        syn = raw["synthetic"]
        if syn is True:
            syn = {}
        if not isinstance(syn, dict):
            raise err.error(f"{key}.synthetic", "must be a mapping like {n: 20000, seed: 0}")
        err.only(syn, _SYNTHETIC_KEYS, f"{key}.synthetic")
        synthetic = SyntheticSpec(
            n=_int(syn, "n", f"{key}.synthetic.n", err, 20_000, 1_000, 1_000_000),
            seed=_int(syn, "seed", f"{key}.synthetic.seed", err, 0, 0, 2**32 - 1),
            n_cameras=_int(syn, "n_cameras", f"{key}.synthetic.n_cameras", err, 24, 1, 4096),
            width=_int(syn, "width", f"{key}.synthetic.width", err, 320, 8, 8192),
            height=_int(syn, "height", f"{key}.synthetic.height", err, 240, 8, 8192),
            ground_truth=_bool(syn, "ground_truth", f"{key}.synthetic.ground_truth", err, True),
        )
    ply = _path(raw["ply"], f"{key}.ply", err, base) if has_ply else None
    if raw.get("cameras") is not None and raw.get("orbit") is not None:
        raise err.error(key, "give either 'cameras' or 'orbit', not both")
    cameras = _path(raw["cameras"], f"{key}.cameras", err, base) if raw.get("cameras") is not None else None
    orbit = None
    if raw.get("orbit") is not None or (cameras is None and synthetic is None):
        orbit = _orbit(raw.get("orbit") or {}, f"{key}.orbit", err)
    if synthetic is not None and orbit is not None and raw.get("orbit") is not None:
        raise err.error(f"{key}.orbit", "the synthetic scene brings its own orbit cameras; set them under 'synthetic'")
    images = _path(raw["images"], f"{key}.images", err, base) if raw.get("images") is not None else None
    if images is not None and not Path(images).is_dir():
        raise err.error(f"{key}.images", f"{images} is not a folder")
    if images is not None and cameras is None:
        raise err.error(f"{key}.images", "ground-truth images need the 'cameras' they were taken with")
    background = err.vector3(raw.get("background", [0, 0, 0]), f"{key}.background", 0.0, 1.0)
    calibration = _path(raw["calibration"], f"{key}.calibration", err, base) \
        if raw.get("calibration") is not None else None
    if calibration is not None and cameras is None:
        raise err.error(f"{key}.calibration", "calibration cameras need the scene's 'cameras' (its test views)")
    note = raw.get("note", "")
    if not isinstance(note, str):
        raise err.error(f"{key}.note", "must be a string")
    return SceneSpec(
        name=name, ply=ply, synthetic=synthetic, cameras=cameras, orbit=orbit, images=images,
        background=background,
        test_every=_int(raw, "test_every", f"{key}.test_every", err, 8, 1, 10_000),
        max_views=_int(raw, "max_views", f"{key}.max_views", err, None, 1, 100_000),
        calibration=calibration, note=note,
    )


def _orbit(raw: Any, key: str, err: Where) -> OrbitSpec:
    if not isinstance(raw, dict):
        raise err.error(key, "must be a mapping like {n: 16, width: 200, height: 150}")
    err.only(raw, _ORBIT_KEYS, key)
    return OrbitSpec(
        n=_int(raw, "n", f"{key}.n", err, 16, 1, 4096),
        width=_int(raw, "width", f"{key}.width", err, 200, 8, 8192),
        height=_int(raw, "height", f"{key}.height", err, 150, 8, 8192),
        fov_y=_number(raw, "fov_y", f"{key}.fov_y", err, 50.0, 1.0, 170.0),
        elevation=_number(raw, "elevation", f"{key}.elevation", err, 20.0, -89.0, 89.0),
        radius=_number(raw, "radius", f"{key}.radius", err, None, 1e-9, 1e12),
        center=err.vector3(raw["center"], f"{key}.center") if raw.get("center") is not None else None,
        up=err.vector3(raw["up"], f"{key}.up") if raw.get("up") is not None else None,
    )


def _method(raw: Any, key: str, err: Where, base: Path) -> MethodSpec:
    from gscodec_shac.rd.methods import RECIPES, MethodError

    if isinstance(raw, str):
        raw = {"name": raw, "recipe": raw}
    if not isinstance(raw, dict):
        raise err.error(key, "must be a recipe name or a mapping {name, recipe, ...parameters}")
    raw = dict(raw)
    name = _name(raw.pop("name", raw.get("recipe")), f"{key}.name", err)
    recipe = raw.pop("recipe", name)
    if not isinstance(recipe, str) or recipe not in RECIPES:
        raise err.error(f"{key}.recipe", f"unknown recipe {recipe!r} (known: {', '.join(RECIPES.names())})")
    try:
        params = RECIPES.get(recipe).check(raw, base)
    except MethodError as exc:
        raise err.error(key, str(exc)) from None
    return MethodSpec(name, recipe, params)
