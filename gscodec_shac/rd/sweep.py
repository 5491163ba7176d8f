"""The sweep driver: plan the runs, skip finished ones, execute the rest, record the rows.

Layout of an output folder::

    OUT/sweep.json      the resolved sweep (scenes, methods, rate points, settings)
    OUT/runs.jsonl      append-only run log (see results.py); the newest row per key wins
    OUT/results.csv     one row per run of this sweep (regenerated after every row)
    OUT/results.json    the same rows as JSON
    OUT/scenes/         generated or converted scene inputs (synthetic PLY, orbit cameras)
    OUT/cache/          per-scene caches: reference renders, sort orders

A run's key is ``scene/method/rate_point/settings_hash`` where the hash covers the scene's
content fingerprint and evaluation setup, the method's recipe and parameters, the resolved
rate point and the result-changing settings. Rows whose key is already finished
(``ok`` or ``skipped``) are not run again; failed rows are retried on the next call.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

from tqdm.auto import tqdm

from gscodec_shac.errors import GscodecError
from gscodec_shac.atomic import write_json
from gscodec_shac.rd.cache import DURABLE
from gscodec_shac.rd.executors import Executor, LocalExecutor, SerialExecutor
from gscodec_shac.rd.methods import NATIVE, points_for
from gscodec_shac.rd.results import ResultStore
from gscodec_shac.rd.runner import RunTask, failed_row
from gscodec_shac.rd.scenes import PreparedScene, prepare_scene
from gscodec_shac.rd.spec import SweepSpec, run_key, stable_hash


@dataclass
class SweepOutcome:
    """What a call of :func:`run_sweep` did."""

    out_dir: Path
    rows: list[dict[str, Any]]
    planned: int
    executed: int  # runs handed to the executor this time
    reused: int  # finished rows found and kept
    failed: int  # rows of this sweep whose status is failed
    seconds: float
    executor: str = ""
    scene_errors: dict[str, str] = field(default_factory=dict)


def default_threads(slots: int) -> int:
    """Threads per run: the CPUs divided among the runs executing at once."""
    return max(1, (os.cpu_count() or 1) // max(1, slots))


def plan(spec: SweepSpec, scenes: dict[str, PreparedScene], out_dir: Path, threads: int) -> list[RunTask]:
    """Every run of the sweep, scene by scene, method by method, rate point by rate point."""
    from gscodec_shac.codec.rate_points import load_rate_point

    points = {ref: load_rate_point(ref) for ref in spec.rate_points}
    tasks = []
    for scene in spec.scenes:
        prepared = scenes.get(scene.name)
        for method in spec.methods:
            for ref in points_for(method, spec.rate_points):
                point = points.get(ref)
                settings_hash = stable_hash({
                    "scene": prepared.fingerprint if prepared else scene.to_json(),
                    "method": {"recipe": method.recipe, "params": method.params},
                    "rate_point": point.to_json() if point is not None else NATIVE,
                    "settings": spec.settings.result_json(),
                })
                tasks.append(RunTask(
                    key=run_key(scene.name, method.name, ref, settings_hash), settings_hash=settings_hash,
                    scene_name=scene.name, scene=prepared, method=method, rate_point_name=ref, rate_point=point,  # type: ignore[arg-type]
                    settings=spec.settings, out_dir=str(out_dir), threads=threads,
                ))
    return tasks


def run_sweep(
    spec: SweepSpec,
    out_dir: str | os.PathLike,
    *,
    executor: str | Executor = "local",
    workers: int = 1,
    threads: int | None = None,
    address: str | None = None,
    num_cpus: float | None = None,
    force: bool = False,
    progress: bool = True,
    on_row: Callable[[dict[str, Any]], None] | None = None,
) -> SweepOutcome:
    """Run (or resume) a sweep into ``out_dir``; see the module docstring.

    ``force`` re-runs finished rows too. ``on_row`` is called with each new row after it
    has been recorded.
    """
    tic = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    threads = threads or spec.settings.threads
    if isinstance(executor, str):
        slots = workers
        threads = threads or default_threads(slots)
        executor = make_executor(executor, workers=workers, threads=threads, max_retries=spec.settings.max_retries,
                                 address=address, num_cpus=num_cpus)
    threads = threads or getattr(executor, "threads", None) or default_threads(executor.slots)

    scenes: dict[str, PreparedScene] = {}
    errors: dict[str, str] = {}
    for scene in tqdm(spec.scenes, desc="prepare scenes", unit="scene", disable=not progress, leave=False):
        try:
            scenes[scene.name] = prepare_scene(scene, out)
        except GscodecError as exc:
            errors[scene.name] = str(exc)
        except (OSError, ValueError) as exc:
            errors[scene.name] = f"{type(exc).__name__}: {exc}"
    tasks = plan(spec, scenes, out, threads)
    write_json(out / "sweep.json", {
        "name": spec.name, "description": spec.description, "source": spec.source,
        "settings": asdict(spec.settings), "rate_points": list(spec.rate_points),
        "methods": [m.to_json() for m in spec.methods],
        "scenes": {s.name: (scenes[s.name].to_json() if s.name in scenes else {"spec": s.to_json(), "error": errors.get(s.name)})
                   for s in spec.scenes},
        "executor": executor.describe(),
    }, **DURABLE)

    store = ResultStore(out)
    done = set() if force else store.finished_keys()
    keys = [t.key for t in tasks]
    for task in tasks:  # scenes that could not be prepared: one failed row per run
        if task.scene is None and task.key not in done:
            store.append(failed_row(task, f"scene not prepared: {errors.get(task.scene_name, '?')}", 0))
    todo = [t for t in tasks if t.scene is not None and t.key not in done]
    reused = sum(1 for t in tasks if t.key in done)

    failures = 0
    bar = tqdm(total=len(tasks), initial=len(tasks) - len(todo), desc=f"rd {spec.name}", unit="run",
               disable=not progress, dynamic_ncols=True)
    try:
        for row in executor.run(todo):
            store.append(row)
            store.export(keys)
            failures += row.get("status") == "failed"
            bar.update(1)
            bar.set_postfix_str(f"failed {failures}" if failures else f"last {row.get('method')}@{row.get('rate_point')}")
            if on_row is not None:
                on_row(row)
    finally:
        bar.close()
        rows = store.export(keys)
    return SweepOutcome(
        out_dir=out, rows=rows, planned=len(tasks), executed=len(todo), reused=reused,
        failed=sum(1 for r in rows if r.get("status") == "failed"), seconds=time.perf_counter() - tic,
        executor=executor.describe(), scene_errors=errors,
    )


EXECUTORS = ("local", "serial", "ray")


def make_executor(
    kind: str, *, workers: int = 1, threads: int = 1, max_retries: int = 2,
    address: str | None = None, num_cpus: float | None = None,
) -> Executor:
    """An executor by name (``local``, ``serial`` or ``ray``)."""
    if kind == "serial":
        return SerialExecutor()
    if kind == "local":
        return LocalExecutor(workers, threads, max_retries)
    if kind == "ray":
        from gscodec_shac.rd.ray_executor import RayExecutor

        return RayExecutor(address=address, workers=workers, num_cpus=num_cpus, threads=threads, max_retries=max_retries)
    raise GscodecError(f"unknown executor {kind!r}; use one of {', '.join(EXECUTORS)}")
