"""Executors: where the runs of a sweep execute. Each yields rows as runs finish.

* :class:`SerialExecutor` - in this process, one after another (debugging, tests).
* :class:`LocalExecutor` - ``workers`` long-lived local processes (``spawn``), one run
  each at a time. A worker that dies (crash, out of memory, ``os._exit``) costs only the
  run it was executing: that run is re-queued up to ``max_retries`` times, then recorded as
  failed; the worker is replaced.
* :class:`~gscodec_shac.rd.ray_executor.RayExecutor` - one Ray task per run.

:func:`gscodec_shac.rd.sweep.make_executor` builds one by name. Runs are :func:`~gscodec_shac.rd.runner.execute_run` calls, which turn exceptions into
failed rows themselves (bounded retries), so an executor only deals with lost workers.
Worker processes start with single-threaded BLAS and ``threads`` numba/OpenMP threads
(:func:`~gscodec_shac.rd.runner.worker_env`): spinning BLAS threads slow small matrix
products by 10-30x on a busy machine.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
from abc import ABC, abstractmethod
from collections import deque
from multiprocessing.connection import wait
from typing import Any, Iterator, Sequence

from gscodec_shac.errors import GscodecError
from gscodec_shac.rd.runner import RunTask, execute_run, failed_row, worker_env



class Executor(ABC):
    """Runs tasks; :meth:`run` yields one row per task, in completion order."""

    name: str = ""
    #: Runs that can execute at once (for the default threads per run).
    slots: int = 1

    @abstractmethod
    def run(self, tasks: Sequence[RunTask]) -> Iterator[dict[str, Any]]:
        """Yield a row for every task (never raises for a failing run)."""

    def describe(self) -> str:
        return self.name


class SerialExecutor(Executor):
    """Every run in the calling process, one at a time."""

    name = "serial"

    def run(self, tasks: Sequence[RunTask]) -> Iterator[dict[str, Any]]:
        for task in tasks:
            yield execute_run(task)


@contextlib.contextmanager
def patched_environ(values: dict[str, str]) -> Iterator[None]:
    """Set environment variables for the block (child processes started in it inherit them)."""
    saved = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for key, old in saved.items():
            if old is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = old


def _worker_loop(conn: Any) -> None:
    """Body of a local worker process: receive a task, send back its row, until told to stop."""
    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):
            return
        if task is None:
            return
        conn.send(execute_run(task))


class _Worker:
    def __init__(self, ctx: Any, env: dict[str, str]) -> None:
        self.conn, child = ctx.Pipe()
        self.process = ctx.Process(target=_worker_loop, args=(child,), daemon=True)
        with patched_environ(env):
            self.process.start()
        child.close()

    def stop(self, timeout: float = 5.0) -> None:
        with contextlib.suppress(OSError, BrokenPipeError):
            self.conn.send(None)
        self.process.join(timeout)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(timeout)
        self.conn.close()


class LocalExecutor(Executor):
    """``workers`` local processes (see module docstring)."""

    name = "local"

    def __init__(self, workers: int = 1, threads: int = 1, max_retries: int = 2) -> None:
        if workers < 1:
            raise GscodecError(f"--workers must be at least 1, got {workers}")
        self.workers, self.threads, self.max_retries = workers, threads, max_retries
        self.slots = workers

    def describe(self) -> str:
        return f"local ({self.workers} worker process{'es' if self.workers != 1 else ''}, {self.threads} thread(s) each)"

    def run(self, tasks: Sequence[RunTask]) -> Iterator[dict[str, Any]]:
        if not tasks:
            return
        ctx = multiprocessing.get_context("spawn")
        env = worker_env(self.threads)
        pending = deque(tasks)
        lost: dict[str, int] = {}
        idle: list[_Worker] = []
        running: dict[_Worker, RunTask] = {}
        try:
            idle = [_Worker(ctx, env) for _ in range(min(self.workers, len(tasks)))]
            while pending or running:
                while idle and pending:
                    worker, task = idle.pop(), pending.popleft()
                    try:
                        worker.conn.send(task)
                    except (OSError, BrokenPipeError):  # died while idle: replace it, keep the task
                        worker.stop(0.5)
                        idle.append(_Worker(ctx, env))
                        pending.appendleft(task)
                        continue
                    running[worker] = task
                ready = wait([w.conn for w in running] + [w.process.sentinel for w in running])
                for worker in list(running):
                    if worker.conn in ready or worker.conn.poll():
                        try:
                            row = worker.conn.recv()
                        except (EOFError, OSError):
                            row = None
                        if row is not None:
                            del running[worker]
                            idle.append(worker)
                            yield row
                            continue
                    if worker.process.sentinel in ready or not worker.process.is_alive():
                        task = running.pop(worker)
                        worker.process.join(1.0)
                        code = worker.process.exitcode
                        worker.stop(0.5)
                        lost[task.key] = lost.get(task.key, 0) + 1
                        if lost[task.key] <= self.max_retries:
                            pending.appendleft(task)
                        else:
                            yield failed_row(task, f"worker process died (exit code {code}) "
                                                   f"{lost[task.key]} time(s); gave up", lost[task.key])
                        if pending:
                            idle.append(_Worker(ctx, env))
        finally:
            for worker in idle + list(running):
                worker.stop(2.0)
