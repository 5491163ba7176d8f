"""Method recipes: how one run turns a scene's model into bytes and back into a model.

=========  ==================================================================  ==========
recipe     what it does                                                        parameters
=========  ==================================================================  ==========
baseline   our codec, SH stage ``none`` (every AC coefficient coded)           -
trunc      SH truncated to a lower degree                                      degree (2)
pca        SHAC-PCA (paper eq. 23-30)                                           energy_retention (0.99) | n_components
lst        SHAC-LST, post-hoc ridge fit (eq. 32-36); with ``finetuned``,        refit_subset (0), ridge,
           the fine-tuned model and its trained T from a compact ``.lst.npz``   finetuned (path | {scene: path})
vq         k-means SH (gsplat / GSCodec Studio style)                           n_clusters, centroid_bits, n_iter
spz        Niantic SPZ written and read back by splat-transform                version (4)
sog        PlayCanvas SOG written (CPU) and read back by splat-transform       iterations (10)
fault      harness self-test: fails its first ``times`` attempts (``raise``    mode, times
           or ``exit`` of the worker process), then runs as ``baseline``
=========  ==================================================================  ==========

Codec recipes run at every rate point of the sweep; ``spz`` and ``sog`` have no rate
points of ours and run once per scene (rate point ``native``).
"""

from __future__ import annotations

import math
import os
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from gscodec_shac.errors import GscodecError
from gscodec_shac.gaussians import GaussianCloud

NATIVE = "native"  # the rate-point label of formats with their own fixed settings


class MethodError(GscodecError):
    """A method's parameters are invalid."""


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


class Recipe(ABC):
    """One kind of method."""

    name: str = ""
    external: bool = False  # runs once per scene instead of once per rate point

    def check(self, raw: dict[str, Any], base: Path) -> dict[str, Any]:
        """Validated parameters (paths resolved against ``base``); raises :class:`MethodError`."""
        if raw:
            raise MethodError(f"recipe {self.name!r} takes no parameters, got {', '.join(sorted(raw))}")
        return {}

    def skip_reason(self, params: dict[str, Any], scene: str) -> str | None:
        """Why this method cannot run on ``scene`` here (recorded as a skipped row), or None."""
        return None

    @abstractmethod
    def run(self, ctx: RunContext, params: dict[str, Any]) -> Outcome:
        """Encode, decode and measure bytes and seconds."""


# ------------------------------------------------------------------ codec recipes
def _expect(raw: dict, allowed: dict[str, Callable[[Any], bool]], recipe: str) -> None:
    for key, value in raw.items():
        if key not in allowed:
            raise MethodError(f"recipe {recipe!r}: unknown parameter {key!r} (allowed: {', '.join(sorted(allowed)) or 'none'})")
        if not allowed[key](value):
            raise MethodError(f"recipe {recipe!r}: bad value {value!r} for {key!r}")


def _is_int(lo: int, hi: int) -> Callable[[Any], bool]:
    return lambda v: isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi


def _is_float(lo: float, hi: float) -> Callable[[Any], bool]:
    return lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and lo < v <= hi


def codec_run(ctx: RunContext, stage: Any, sh_params: dict[str, Any], cloud: GaussianCloud | None = None,
              fit_stage: bool = True) -> Outcome:
    """Encode with our pipeline (sort cached), serialise, decode."""
    from gscodec_shac.codec import Decoder, Encoder
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
        "sh_features": (stream.header.get("sh") or {}).get("features"),
    }
    return Outcome(decoded, len(data), dict(stream.attribute_sizes()), encode_s, decode_s, extra)


class Baseline(Recipe):
    name = "baseline"

    def run(self, ctx: RunContext, params: dict[str, Any]) -> Outcome:
        return codec_run(ctx, "none", {})


class Trunc(Recipe):
    name = "trunc"

    def check(self, raw: dict[str, Any], base: Path) -> dict[str, Any]:
        _expect(raw, {"degree": _is_int(0, 3)}, self.name)
        return {"degree": raw.get("degree", 2)}

    def run(self, ctx: RunContext, params: dict[str, Any]) -> Outcome:
        return codec_run(ctx, "trunc", {"degree": params["degree"]})


class Pca(Recipe):
    name = "pca"

    def check(self, raw: dict[str, Any], base: Path) -> dict[str, Any]:
        _expect(raw, {"energy_retention": _is_float(0.0, 1.0), "n_components": _is_int(1, 128)}, self.name)
        if "energy_retention" in raw and "n_components" in raw:
            raise MethodError("recipe 'pca': give energy_retention or n_components, not both")
        return dict(raw) if raw else {"energy_retention": 0.99}

    def run(self, ctx: RunContext, params: dict[str, Any]) -> Outcome:
        return codec_run(ctx, "pca", dict(params))


class Lst(Recipe):
    name = "lst"

    def check(self, raw: dict[str, Any], base: Path) -> dict[str, Any]:
        raw = dict(raw)
        finetuned = raw.pop("finetuned", None)
        ridge_ok = lambda v: _is_float(0.0, 1e9)(v) or (v == 0 and not isinstance(v, bool))  # noqa: E731
        _expect(raw, {"refit_subset": _is_int(0, 1000), "ridge": ridge_ok}, self.name)
        params = dict(raw)
        if finetuned is not None:
            if isinstance(finetuned, (str, os.PathLike)):
                finetuned = {"*": finetuned}
            if not isinstance(finetuned, dict) or not finetuned:
                raise MethodError("recipe 'lst': finetuned must be a path or a mapping scene -> path")
            if raw:
                raise MethodError("recipe 'lst': refit_subset/ridge apply to the post-hoc fit, not to a finetuned model")
            resolved = {}
            for scene, path in finetuned.items():
                p = Path(os.path.expanduser(str(path)))
                p = p if p.is_absolute() else base / p
                if not p.is_file():
                    raise MethodError(f"recipe 'lst': finetuned file for {scene!r} not found: {p}")
                resolved[str(scene)] = str(p.resolve())
            params["finetuned"] = resolved
        return params

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
            return codec_run(ctx, "lst", {k: v for k, v in params.items() if k != "finetuned"})
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


class Vq(Recipe):
    name = "vq"

    def check(self, raw: dict[str, Any], base: Path) -> dict[str, Any]:
        _expect(raw, {"n_clusters": _is_int(1, 1 << 24), "centroid_bits": _is_int(1, 16), "n_iter": _is_int(1, 1000),
                      "seed": _is_int(0, 2**32 - 1)}, self.name)
        return dict(raw)

    def run(self, ctx: RunContext, params: dict[str, Any]) -> Outcome:
        return codec_run(ctx, "vq", dict(params))


class Fault(Recipe):
    """Fails on purpose (tests of retries and failure records); then behaves as ``baseline``."""

    name = "fault"

    def check(self, raw: dict[str, Any], base: Path) -> dict[str, Any]:
        _expect(raw, {"mode": lambda v: v in ("raise", "exit"), "times": _is_int(0, 1000)}, self.name)
        return {"mode": raw.get("mode", "raise"), "times": raw.get("times", 1)}

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
        _expect(raw, {"version": lambda v: v in (3, 4)}, self.name)
        return {"version": raw.get("version", 4)}

    def _encode(self, ply: Path, out: Path, params: dict[str, Any], threads: int) -> None:
        from gscodec_shac.rd.external import encode_spz

        encode_spz(ply, out, params["version"])


class Sog(_External):
    name = "sog"
    suffix = ".sog"

    def check(self, raw: dict[str, Any], base: Path) -> dict[str, Any]:
        _expect(raw, {"iterations": _is_int(1, 1000)}, self.name)
        return {"iterations": raw.get("iterations", 10)}

    def _encode(self, ply: Path, out: Path, params: dict[str, Any], threads: int) -> None:
        from gscodec_shac.rd.external import encode_sog

        encode_sog(ply, out, params["iterations"], workers=threads)

    def _sizes(self, path: Path) -> dict[str, int]:
        from gscodec_shac.rd.external import sog_member_sizes

        return sog_member_sizes(path)


RECIPES: dict[str, Recipe] = {r.name: r for r in (Baseline(), Trunc(), Pca(), Lst(), Vq(), Spz(), Sog(), Fault())}


def rate_points_for(recipe: str, rate_points: tuple[str, ...]) -> tuple[str, ...]:
    """The rate points a method runs at (``native`` only for external formats)."""
    return (NATIVE,) if RECIPES[recipe].external else rate_points
