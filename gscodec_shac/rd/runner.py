"""One run of a sweep as a pure function: :func:`execute_run` (``RunTask`` -> row dict).

A run encodes a scene with a method at a rate point, decodes it, renders the test views
and scores them against the ground truth (where the scene has it) and against the
renders of the uncompressed model. Inputs arrive by path inside the :class:`RunTask`;
the only files a run writes are caches under ``OUT/cache`` (sort orders, reference
renders; atomic, locked) and scratch files it deletes. The row comes back to the driver,
which alone writes results.

:func:`execute_run` never raises for a failing run: it retries an exception
``settings.retries`` times and then returns a row with ``status="failed"`` and the error.
"""

from __future__ import annotations

import math
import os
import platform
import shutil
import time
import traceback
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from gscodec_shac.rd.methods import NATIVE, RECIPES, RunContext, RunSkipped
from gscodec_shac.rd.scenes import PreparedScene
from gscodec_shac.rd.spec import EvalSettings, MethodSpec

#: Row columns in CSV order (per-attribute ``bytes_<attribute>`` columns follow ``bytes``).
ROW_FIELDS = (
    "key", "scene", "method", "recipe", "rate_point", "settings_hash", "status", "error",
    "n_gaussians", "n_decoded", "sh_degree", "bytes", "megabytes", "bits_per_gaussian",
    "psnr_gt", "ssim_gt", "lpips_gt", "psnr_ref", "ssim_ref", "lpips_ref", "n_views", "has_gt",
    "uncompressed_bytes", "uncompressed_psnr_gt", "uncompressed_ssim_gt",
    "encode_s", "decode_s", "render_s", "sort_s", "sort_cached", "attempts", "host", "finished_at",
    "lpips_note", "params",
)
STATUSES = ("ok", "failed", "skipped")


@dataclass(frozen=True)
class RunTask:
    """Everything one run needs (picklable; files by path, the rate point by value)."""

    key: str
    settings_hash: str
    scene_name: str
    scene: PreparedScene | None  # None: the scene could not be prepared
    method: MethodSpec
    rate_point_name: str
    rate_point: Any  # a RatePoint, or None for native formats
    settings: EvalSettings
    out_dir: str
    threads: int = 1


def worker_env(threads: int) -> dict[str, str]:
    """Environment for a worker process: BLAS single-threaded, numba/OpenMP at ``threads``."""
    return {
        "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OMP_NUM_THREADS": str(threads),
        "NUMBA_NUM_THREADS": str(threads), "OMP_WAIT_POLICY": "PASSIVE",
    }


def set_thread_limits(threads: int) -> None:
    """Apply ``threads`` to numba and torch in this process (BLAS only obeys the environment)."""
    try:
        import numba

        numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    except (ImportError, ValueError):  # pragma: no cover
        pass
    import sys

    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(max(1, threads))


def base_row(task: RunTask) -> dict[str, Any]:
    """The identifying columns of a task's row (every other column None)."""
    return {
        **dict.fromkeys(ROW_FIELDS),
        "key": task.key, "scene": task.scene_name, "method": task.method.name, "recipe": task.method.recipe,
        "rate_point": task.rate_point_name, "settings_hash": task.settings_hash,
        "params": dict(task.method.params), "host": platform.node(),
    }


def failed_row(task: RunTask, error: str, attempts: int, status: str = "failed") -> dict[str, Any]:
    """A row recording that a run did not produce numbers, and why."""
    row = base_row(task)
    row.update(status=status, error=error, attempts=attempts, finished_at=_now())
    return row


def execute_run(task: RunTask) -> dict[str, Any]:
    """Run one task with bounded retries; always returns a row (see module docstring)."""
    set_thread_limits(task.threads)
    recipe = RECIPES.get(task.method.recipe)
    reason = recipe.skip_reason(task.method.params, task.scene.spec.name)
    if reason is not None:
        return failed_row(task, reason, 0, status="skipped")
    error = ""
    attempts = 0
    for attempt in range(1, task.settings.retries + 2):
        attempts = attempt
        try:
            row = _run_once(task)
            row["attempts"] = attempt
            return row
        except RunSkipped as exc:
            return failed_row(task, str(exc), attempt, status="skipped")
        except Exception as exc:  # noqa: BLE001 - every failure becomes a recorded row
            error = f"{type(exc).__name__}: {exc}".strip()
            last = traceback.extract_tb(exc.__traceback__)[-1:] if exc.__traceback__ else []
            if last:
                error += f" (at {Path(last[0].filename).name}:{last[0].lineno})"
    return failed_row(task, error.splitlines()[0][:1000] if error else "unknown error", attempts)


def _run_once(task: RunTask) -> dict[str, Any]:
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.metrics import load_lpips, psnr, ssim
    from gscodec_shac.rd.scenes import calibration_views, evaluation_views, render_all

    out_dir = Path(task.out_dir)
    cache_dir = task.scene.cache_dir(out_dir)
    work_dir = out_dir / "tmp" / f"{task.key.replace('/', '__')}-{os.getpid()}"
    cloud_box: dict[str, Any] = {}

    def load_cloud():
        if "cloud" not in cloud_box:
            cloud_box["cloud"] = read_ply(task.scene.ply)
        return cloud_box["cloud"]

    ctx = RunContext(
        scene=task.scene.spec.name, load_cloud=load_cloud, ply_path=Path(task.scene.ply), rate_point=task.rate_point,
        sort=task.settings.sort, preset=task.settings.preset, threads=task.threads,
        cache_dir=cache_dir if task.settings.cache_sort else None, work_dir=work_dir,
        fault_dir=out_dir / "cache" / "faults", key=task.key, label=task.rate_point_name,
        calibration_views=lambda: calibration_views(task.scene), background=tuple(task.scene.spec.background),
    )
    try:
        outcome = RECIPES.get(task.method.recipe).run(ctx, task.method.params)
    finally:
        shutil.rmtree(work_dir, ignore_errors=True)
    lpips_model, lpips_note = load_lpips(task.settings.lpips_weights)
    views = evaluation_views(task.scene, out_dir, lpips_model)
    tic = time.perf_counter()
    images = render_all(outcome.decoded, views.cameras, task.scene.spec.background)
    render_s = time.perf_counter() - tic
    if images:  # the first test view, kept for the HTML report's image comparison
        from gscodec_shac.rd.renders import save_run_view

        save_run_view(out_dir, task.scene_name, task.method.name, task.rate_point_name, images[0],
                      views.reference[0], views.ground_truth[0] if views.ground_truth is not None else None)

    n_input = int(views.uncompressed.get("n_gaussians") or load_cloud().num_gaussians)
    row = base_row(task)
    row.update(
        status="ok", error="",
        n_gaussians=n_input, n_decoded=outcome.decoded.num_gaussians, sh_degree=outcome.decoded.sh_degree,
        bytes=int(outcome.bytes), megabytes=outcome.bytes / 1e6, bits_per_gaussian=8.0 * outcome.bytes / n_input,
        sizes={k: int(v) for k, v in outcome.sizes.items()},
        psnr_ref=_mean(psnr(a, b) for a, b in zip(images, views.reference)),
        ssim_ref=_mean(ssim(a, b) for a, b in zip(images, views.reference)),
        n_views=len(images), has_gt=views.ground_truth is not None,
        uncompressed_bytes=views.uncompressed.get("bytes"),
        uncompressed_psnr_gt=views.uncompressed.get("psnr_gt"),
        uncompressed_ssim_gt=views.uncompressed.get("ssim_gt"),
        encode_s=outcome.encode_s, decode_s=outcome.decode_s, render_s=render_s,
        sort_s=outcome.extra.get("sort_s"), sort_cached=outcome.extra.get("sort_cached"),
        extra={k: v for k, v in outcome.extra.items() if k not in ("sort_s", "sort_cached")},
        lpips_note="" if lpips_model is not None else (lpips_note or ""),
        finished_at=_now(),
    )
    if views.ground_truth is not None:
        row["psnr_gt"] = _mean(psnr(a, g) for a, g in zip(images, views.ground_truth))
        row["ssim_gt"] = _mean(ssim(a, g) for a, g in zip(images, views.ground_truth))
    if lpips_model is not None:
        row["lpips_ref"] = _mean(lpips_model(a, b) for a, b in zip(images, views.reference))
        if views.ground_truth is not None:
            row["lpips_gt"] = _mean(lpips_model(a, g) for a, g in zip(images, views.ground_truth))
    if task.rate_point_name == NATIVE:
        row["sort_s"] = None
    return row


def _mean(values) -> float:
    items = [float(v) for v in values]
    return float(np.mean(items)) if items else math.nan


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")
