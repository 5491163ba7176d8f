"""Method recipes: how one run turns a scene's model into bytes and back into a model.

Every SH stage of :data:`gscodec_shac.shac.base.STAGES` is a recipe of the same name
(stage ``none`` is the recipe ``baseline``) whose parameters are the stage's own
(``StageParam`` declarations: e.g. ``pca`` takes ``energy_retention`` or
``n_components``); a new stage is a new recipe with no change here. Besides them:

=========  ==================================================================  ==========
recipe     what it does                                                        parameters
=========  ==================================================================  ==========
lst        also: the fine-tuned model and its trained T from a compact          finetuned (path |
           ``.lst.npz`` instead of the post-hoc fit                             {scene: path})
spz        Niantic SPZ written and read back by splat-transform                version (4)
sog        PlayCanvas SOG written (CPU) and read back by splat-transform       iterations (10)
fault      harness self-test: fails its first ``times`` attempts (``raise``    mode, times
           or ``exit`` of the worker process), then runs as ``baseline``
=========  ==================================================================  ==========

Codec recipes run at every rate point of the sweep; ``spz`` and ``sog`` have no rate
points of ours and run once per scene (rate point ``native``). Recipes are found in
:data:`RECIPES` (a :class:`~gscodec_shac.registry.Registry`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from gscodec_shac.errors import GscodecError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.registry import Registry
from gscodec_shac.shac.base import STAGES
from gscodec_shac.validate import Where

NATIVE = "native"  # the rate-point label of formats with their own fixed settings


class MethodError(GscodecError):
    """A method's parameters are invalid."""


class RunSkipped(GscodecError):
    """A run that cannot happen on this scene (recorded as a skipped row with this reason)."""


@dataclass
class Outcome:
    """What a recipe hands back: the decoded model and what it cost."""

    decoded: GaussianCloud
    bytes: int
    sizes: dict[str, int]
    encode_s: float
    decode_s: float
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class RunContext:
    """Everything a recipe may use; built by :mod:`gscodec_shac.rd.runner`."""

    scene: str
    load_cloud: Callable[[], GaussianCloud]
    ply_path: Path
    rate_point: Any  # RatePoint | None for native formats
    sort: str | None
    preset: str | None
    threads: int
    cache_dir: Path | None  # sort cache (None: off)
    work_dir: Path  # scratch files of this run
    fault_dir: Path  # attempt counters of the fault recipe
    key: str
    label: str = ""  # the rate-point label of this run (a rate point, NATIVE or a target)
    calibration_views: Callable[[], list] = list  # the scene's views that are not test views (rate control)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)  # the scene's render background


class Recipe(ABC):
    """One kind of method."""

    name: str = ""
    external: bool = False  # runs once per scene instead of once per rate point

    def check(self, raw: dict[str, Any], base: Path) -> dict[str, Any]:
        """Validated parameters (paths resolved against ``base``); raises :class:`MethodError`."""
        self.where.only(raw, ())
        return {}

    @property
    def where(self) -> Where:
        """Errors about this recipe's parameters."""
        return Where(f"recipe {self.name!r}", MethodError)

    def skip_reason(self, params: dict[str, Any], scene: str) -> str | None:
        """Why this method cannot run on ``scene`` here (recorded as a skipped row), or None."""
        return None

    def points(self, params: dict[str, Any], rate_points: tuple[str, ...]) -> tuple[str, ...]:
        """The rate-point labels the method runs at: the sweep's rate points (``native`` for external formats)."""
        return (NATIVE,) if self.external else rate_points

    @abstractmethod
    def run(self, ctx: RunContext, params: dict[str, Any]) -> Outcome:
        """Encode, decode and measure bytes and seconds."""


# ------------------------------------------------------------------ codec recipes
def codec_run(ctx: RunContext, stage: Any, sh_params: dict[str, Any], cloud: GaussianCloud | None = None,
              fit_stage: bool = True) -> Outcome:
    """Encode with our pipeline (sort cached), serialise, decode."""
    from gscodec_shac.codec import Decoder, Encoder, tiers
    from gscodec_shac.rd.sortcache import cached_grid_order

    cloud = ctx.load_cloud() if cloud is None else cloud
    encoder = Encoder(ctx.rate_point, sh_stage=stage, sort=ctx.sort, sh_params=sh_params or None,
                      codec_options={"preset": ctx.preset} if ctx.preset else None,
                      fit_stage=fit_stage, workers=ctx.threads)
    grid, cached, sort_s = None, None, None
    if ctx.cache_dir is not None:
        grid, cached, sort_s = cached_grid_order(encoder, cloud, ctx.cache_dir)
    tic = time.perf_counter()
    stream = encoder.encode(cloud, grid=grid)
    data = stream.to_bytes()
    encode_s = time.perf_counter() - tic
    tic = time.perf_counter()
    decoded = Decoder(workers=ctx.threads).decode(data)
    decode_s = time.perf_counter() - tic
    extra = {
        "timings": {k: round(v, 4) for k, v in encoder.timings_.items()},
        "sort_cached": cached,
        "sort_s": sort_s if sort_s is not None else encoder.timings_.get("sort"),
        "sh_features": tiers.sh_features(stream),
    }
    return Outcome(decoded, len(data), dict(stream.attribute_sizes()), encode_s, decode_s, extra)


class StageRecipe(Recipe):
    """Our codec with one SH stage; the parameters are the stage's own."""

    def __init__(self, name: str, stage: str) -> None:
        self.name, self.stage = name, stage

    def check(self, raw: dict[str, Any], base: Path) -> dict[str, Any]:
        return STAGES.get(self.stage).check_params(raw, self.where)

    def run(self, ctx: RunContext, params: dict[str, Any]) -> Outcome:
        return codec_run(ctx, self.stage, dict(params))


class Lst(StageRecipe):
    """SHAC-LST: the post-hoc fit, or a fine-tuned model with its trained T (``finetuned``)."""

    def __init__(self) -> None:
        super().__init__("lst", "lst")

    def check(self, raw: dict[str, Any], base: Path) -> dict[str, Any]:
        raw = dict(raw)
        finetuned = raw.pop("finetuned", None)
        params = super().check(raw, base)
        if finetuned is None:
            return params
        if isinstance(finetuned, (str, os.PathLike)):
            finetuned = {"*": finetuned}
        if not isinstance(finetuned, dict) or not finetuned:
            raise self.where.error("finetuned", "must be a path or a mapping scene -> path")
        if params:
            raise self.where.error("finetuned", "the post-hoc fit parameters do not apply to a finetuned model")
        resolved = {}
        for scene, path in finetuned.items():
            p = Path(os.path.expanduser(str(path)))
            p = p if p.is_absolute() else base / p
            if not p.is_file():
                raise self.where.error("finetuned", f"file for {scene!r} not found: {p}")
            resolved[str(scene)] = str(p.resolve())
        return {"finetuned": resolved}

    def _file(self, params: dict[str, Any], scene: str) -> str | None:
        files = params.get("finetuned") or {}
        return files.get(scene, files.get("*"))

    def skip_reason(self, params: dict[str, Any], scene: str) -> str | None:
        if params.get("finetuned") and self._file(params, scene) is None:
            return f"no fine-tuned SHAC-LST file given for scene {scene!r}"
        return None

    def run(self, ctx: RunContext, params: dict[str, Any]) -> Outcome:
        path = self._file(params, ctx.scene) if params.get("finetuned") else None
        if path is None:
            return super().run(ctx, params)
        from gscodec_shac.train.finetune import load_finetuned

        tuned, stage = load_finetuned(path)
        original = ctx.load_cloud()
        if tuned.num_gaussians != original.num_gaussians:
            raise MethodError(
                f"fine-tuned file {path} has {tuned.num_gaussians:,} Gaussians, the scene {original.num_gaussians:,}"
            )
        outcome = codec_run(ctx, stage, {}, cloud=tuned, fit_stage=False)
        outcome.extra["finetuned"] = path
        return outcome


class Auto(Recipe):
    """SHAC-auto: the rate controller at each listed target (``bpg``, ``sizes`` or ``psnr``).

    Runs once per target (labels ``bpg-120``, ``size-2.5MB``, ``psnr-35``), not per rate point;
    the controller calibrates on the scene's views that are not test views (fitted once per
    scene and worker process); ``encode_s`` includes that fit. ``sh: none`` runs the same
    controller without an SH stage (:func:`template_without_sh`): the row that isolates what
    the SH stage gains; ``sh: {stage: NAME, ...}`` with another stage (:func:`template_with_sh`).
    """

    name = "auto"
    _KINDS = {"bpg": "bpg", "sizes": "size", "psnr": "psnr"}

    def check(self, raw: dict[str, Any], base: Path) -> dict[str, Any]:
        from gscodec_shac.codec.rate_control import TEMPLATE, VERSION, parse_size

        self.where.only(raw, (*self._KINDS, "template", "sh", "recover"))
        given = [k for k in self._KINDS if k in raw]
        if len(given) != 1:
            raise self.where.error("", "give exactly one list of targets: bpg, sizes or psnr")
        kind = given[0]
        values = self.where.sequence(raw[kind], kind)
        for i, value in enumerate(values):
            if kind == "sizes":
                try:
                    parse_size(value)
                except GscodecError as exc:
                    raise self.where.error(f"{kind}[{i}]", str(exc)) from None
            else:
                self.where.number(value, f"{kind}[{i}]", 0.0, 1e6, open_lo=True)
        template = raw.get("template", TEMPLATE)
        self.where.string(template, "template")
        params = {kind: list(values), "template": template, "controller_version": VERSION}
        if "sh" in raw:  # only when given, so the keys of the runs with the template's stage stay the same
            params["sh"] = self._check_sh(raw["sh"])
        if "recover" in raw:  # prune by importance and distil first (gscodec_shac/train/recover.py)
            params["recover"] = self._check_recover(raw["recover"])
        return params

    def _check_sh(self, raw: Any) -> str | dict[str, Any]:
        """``none`` (the template without its SH stage) or ``{stage: NAME, ...}``: the template with that SH
        stage and those parameters instead of its own (e.g. ``pca-spatial``, docs/ablations.md)."""
        if not isinstance(raw, dict):
            return self.where.choice(raw, ("none",), "sh")
        where = self.where.at("sh")
        stage = where.choice(raw.get("stage"), tuple(STAGES.names()), "stage")
        checked = STAGES.get(stage).check_params({k: v for k, v in raw.items() if k != "stage"}, where)
        return {"stage": stage, **checked}

    def _check_recover(self, raw: Any) -> dict[str, Any]:
        from gscodec_shac.train.recover import DEFAULT_ITERATIONS

        raw = self.where.mapping(raw, "recover", optional=False)
        where = self.where.at("recover")
        where.only(raw, ("keep", "iterations"))
        if "keep" not in raw:
            raise where.error("keep", "give the share of the Gaussians kept, in (0, 1], or a list of shares "
                              "(the controller then also codes the model itself and keeps the best file)")
        iterations = where.integer(raw.get("iterations", DEFAULT_ITERATIONS), "iterations", 0, 100_000)
        if isinstance(raw["keep"], list):  # a choice between the model and its recovered versions (rate_recover)
            shares = [where.number(v, f"keep[{i}]", 0.0, 1.0, open_lo=True)
                      for i, v in enumerate(where.sequence(raw["keep"], "keep"))]
            return {"choose": shares, "iterations": iterations}
        return {"keep": where.number(raw["keep"], "keep", 0.0, 1.0, open_lo=True), "iterations": iterations}

    def points(self, params: dict[str, Any], rate_points: tuple[str, ...]) -> tuple[str, ...]:
        kind = next(k for k in self._KINDS if k in params)
        return tuple(f"{self._KINDS[kind]}-{value:g}" if kind != "sizes" else f"size-{value}" for value in params[kind])

    def run(self, ctx: RunContext, params: dict[str, Any]) -> Outcome:
        from gscodec_shac.codec import Decoder, tiers
        from gscodec_shac.codec.rate_control import TargetUnreachableError, make_target

        cloud = ctx.load_cloud()  # bits per Gaussian count the scene's Gaussians, also with a recovery
        kind, _, value = ctx.label.partition("-")
        target = make_target(cloud.num_gaussians, size=value if kind == "size" else None,
                             bpg=float(value) if kind == "bpg" else None, psnr=float(value) if kind == "psnr" else None)
        tic = time.perf_counter()
        controller, fitted_s = _fitted_controller(ctx, params["template"], params.get("sh"), params.get("recover"))
        try:
            outcome = controller.encode(target)
        except TargetUnreachableError as exc:
            raise RunSkipped(str(exc)) from None
        data = outcome.stream.to_bytes()
        encode_s = time.perf_counter() - tic + fitted_s
        tic = time.perf_counter()
        decoded = Decoder(workers=ctx.threads).decode(data)
        decode_s = time.perf_counter() - tic
        extra = {"rate_control": outcome.summary(), "fit_s": round(fitted_s, 3),
                 "sh_features": tiers.sh_features(outcome.stream)}
        if "keep" in params.get("recover", {}):  # a fixed recovered source (a choice reports in rate_control)
            extra["recovery"] = _RECOVERIES[_recovery_key(ctx, params["recover"])].summary()
        return Outcome(decoded, len(data), dict(outcome.stream.attribute_sizes()), encode_s, decode_s, extra)


_CONTROLLERS: dict[tuple, tuple[Any, float]] = {}
#: QP steps of the AC coefficients' degree ladder (degrees 1, 2, 3) of the controller without an SH stage:
#: the baseline's (``rate_points/shac_ladder.yaml``, ``sh_ac: [q, q+5, q+10]``)
NO_SH_LADDER = (0, 5, 10)


def template_with_sh(template: str, sh: dict[str, Any]) -> Any:
    """The rate-control template with another SH stage (``sh``: ``{stage: NAME, ...its parameters}``)."""
    from gscodec_shac.codec.rate_points import load_rate_point

    params = {k: v for k, v in sh.items() if k != "stage"}
    point = load_rate_point(template).with_overrides(sh_stage=sh["stage"], sh_params=params)
    return dataclasses.replace(point, name=f"{point.name}+{sh['stage']}")


def template_without_sh(template: str) -> Any:
    """The rate-control template with SH stage ``none``: the AC coefficients coded with the baseline's
    degree ladder, whose first QP the controller chooses as it chooses the SH features' base QP."""
    from gscodec_shac.codec.rate_points import load_rate_point

    point = load_rate_point(template).with_overrides(sh_stage="none")
    attributes = dict(point.attributes)
    base = attributes["sh_features"].qp_for_degree(1)
    attributes["sh_ac"] = dataclasses.replace(attributes["sh_ac"], qp=tuple(min(51, base + s) for s in NO_SH_LADDER),
                                              allocation="degree")
    return dataclasses.replace(point, attributes=attributes, name=f"{point.name}+nosh")


_RECOVERIES: dict[tuple, Any] = {}


def _recovery_key(ctx: RunContext, recover: dict[str, Any]) -> tuple:
    return (str(ctx.ply_path), str(recover.get("keep", recover.get("choose"))), recover["iterations"], ctx.background)


def _recovered(ctx: RunContext, recover: dict[str, Any]) -> GaussianCloud:
    """The scene pruned by importance and distilled to its renders on the calibration views
    (:func:`gscodec_shac.train.recover.prune_and_recover`), once per scene and setting in this process."""
    from gscodec_shac.train.recover import prune_and_recover

    key = _recovery_key(ctx, recover)
    if key not in _RECOVERIES:
        _RECOVERIES.clear()  # one scene's recovery at a time
        _RECOVERIES[key] = prune_and_recover(ctx.load_cloud(), ctx.calibration_views() or None,
                                             keep_share=recover["keep"], iterations=recover["iterations"],
                                             background=ctx.background)
    return _RECOVERIES[key].cloud


def _fitted_controller(ctx: RunContext, template: str, sh: str | dict[str, Any] | None = None,
                       recover: dict[str, Any] | None = None) -> tuple[Any, float]:
    """One fitted rate controller per (scene file, template, SH stage, recovery, preset) in this process,
    and the seconds its fit took, a recovery included (``sh``: ``none`` for the template without its
    SH stage, a mapping for another stage (:func:`template_with_sh`); ``recover``: fitted on the pruned
    and recovered scene)."""
    from gscodec_shac.codec.rate_control import RateController

    key = (str(ctx.ply_path), template, json.dumps(sh, sort_keys=True), ctx.preset, ctx.threads, ctx.background,
           None if recover is None else _recovery_key(ctx, recover))
    if key not in _CONTROLLERS:
        tic = time.perf_counter()
        if sh == "none":
            point = template_without_sh(template)
        elif isinstance(sh, dict):
            point = template_with_sh(template, sh)
        else:
            point = template
        options = {"workers": ctx.threads, "background": ctx.background,
                   "codec_options": {"preset": ctx.preset} if ctx.preset else None}
        if recover is not None and "choose" in recover:
            from gscodec_shac.codec.rate_recover import RecoveringController

            controller: Any = RecoveringController(ctx.load_cloud(), point, ctx.calibration_views() or None,
                                                   shares=recover["choose"], iterations=recover["iterations"],
                                                   controller_options=options).fit()
        else:
            source = ctx.load_cloud() if recover is None else _recovered(ctx, recover)
            controller = RateController(source, point, ctx.calibration_views() or None, **options).fit()
        _CONTROLLERS.clear()  # keep one scene's controller at a time
        _CONTROLLERS[key] = (controller, time.perf_counter() - tic)
    return _CONTROLLERS[key]


class Fault(Recipe):
    """Fails on purpose (tests of retries and failure records); then behaves as ``baseline``."""

    name = "fault"

    def check(self, raw: dict[str, Any], base: Path) -> dict[str, Any]:
        self.where.only(raw, ("mode", "times"))
        return {"mode": self.where.choice(raw.get("mode", "raise"), ("raise", "exit"), "mode"),
                "times": self.where.integer(raw.get("times", 1), "times", 0, 1000)}

    def run(self, ctx: RunContext, params: dict[str, Any]) -> Outcome:
        ctx.fault_dir.mkdir(parents=True, exist_ok=True)
        counter = ctx.fault_dir / (ctx.key.replace("/", "__") + ".attempts")
        with counter.open("a") as handle:  # one line per attempt, across processes and retries
            handle.write("x\n")
        attempts = len(counter.read_text().splitlines())
        if attempts <= params["times"]:
            if params["mode"] == "exit":
                os._exit(17)  # a lost worker, as the executor sees it
            raise RuntimeError(f"injected fault (attempt {attempts} of {params['times']} failing ones)")
        return codec_run(ctx, "none", {})


# --------------------------------------------------------------- external recipes
class _External(Recipe):
    external = True
    suffix = ""

    def skip_reason(self, params: dict[str, Any], scene: str) -> str | None:
        from gscodec_shac.rd.external import unavailable_reason

        return unavailable_reason()

    def _encode(self, ply: Path, out: Path, params: dict[str, Any], threads: int) -> None:
        raise NotImplementedError

    def _sizes(self, path: Path) -> dict[str, int]:
        return {"file": path.stat().st_size}

    def run(self, ctx: RunContext, params: dict[str, Any]) -> Outcome:
        from gscodec_shac.rd.external import convert_to_ply, read_decoded_ply, tool_version

        ctx.work_dir.mkdir(parents=True, exist_ok=True)
        coded = ctx.work_dir / f"scene{self.suffix}"
        decoded_ply = ctx.work_dir / "decoded.ply"
        tic = time.perf_counter()
        self._encode(ctx.ply_path, coded, params, ctx.threads)
        encode_s = time.perf_counter() - tic
        tic = time.perf_counter()
        convert_to_ply(coded, decoded_ply)
        decoded, clamped = read_decoded_ply(decoded_ply)
        decode_s = time.perf_counter() - tic
        size = coded.stat().st_size
        sizes = self._sizes(coded)
        for path in (coded, decoded_ply):
            path.unlink(missing_ok=True)
        return Outcome(decoded, size, sizes, encode_s, decode_s,
                       {"tool": tool_version(), "opacity_logits_clamped": clamped})


class Spz(_External):
    name = "spz"
    suffix = ".spz"

    def check(self, raw: dict[str, Any], base: Path) -> dict[str, Any]:
        self.where.only(raw, ("version",))
        return {"version": self.where.choice(raw.get("version", 4), (3, 4), "version")}

    def _encode(self, ply: Path, out: Path, params: dict[str, Any], threads: int) -> None:
        from gscodec_shac.rd.external import encode_spz

        encode_spz(ply, out, params["version"])


class Sog(_External):
    name = "sog"
    suffix = ".sog"

    def check(self, raw: dict[str, Any], base: Path) -> dict[str, Any]:
        self.where.only(raw, ("iterations",))
        return {"iterations": self.where.integer(raw.get("iterations", 10), "iterations", 1, 1000)}

    def _encode(self, ply: Path, out: Path, params: dict[str, Any], threads: int) -> None:
        from gscodec_shac.rd.external import encode_sog

        encode_sog(ply, out, params["iterations"], workers=threads)

    def _sizes(self, path: Path) -> dict[str, int]:
        from gscodec_shac.rd.external import sog_member_sizes

        return sog_member_sizes(path)


RECIPES: Registry[Recipe] = Registry("recipe", __name__, (), error=MethodError)
for _recipe in (Lst(), Auto(), Spz(), Sog(), Fault()):
    RECIPES.register(_recipe)
for _stage in STAGES.names():  # every other stage: a plain stage recipe ("none" is the baseline)
    if _stage not in [getattr(r, "stage", None) for _, r in RECIPES.items()]:
        RECIPES.register(StageRecipe("baseline" if _stage == "none" else _stage, _stage))


def points_for(method: Any, rate_points: tuple[str, ...]) -> tuple[str, ...]:
    """The rate-point labels a sweep method (a :class:`~gscodec_shac.rd.spec.MethodSpec`) runs at."""
    return RECIPES.get(method.recipe).points(method.params, rate_points)
