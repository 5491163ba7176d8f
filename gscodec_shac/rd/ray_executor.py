"""The Ray executor: every run of a sweep is one Ray task.

``address=None`` starts a local Ray instance sized to ``workers`` runs at once (no
dashboard) and shuts it down afterwards; ``address="auto"`` or ``"HOST:PORT"`` joins a
running cluster (``ray start --head`` on one machine, ``ray start --address HOST:PORT``
on the others). Every node needs this package installed and must see the sweep's input
and output folders at the same paths (a shared file system): inputs travel by path, and
only the result rows travel back through Ray, to the driver, which alone writes them.

Faults: a task whose worker process or node dies is re-executed by Ray up to
``max_retries`` times (Ray's ``max_retries``; exceptions inside a run are retried by the
run itself, see :func:`~gscodec_shac.rd.runner.execute_run`); after that the run is
recorded as failed with Ray's error. ``num_cpus`` is the CPUs Ray reserves per run
(default: ``threads``), which bounds how many runs share a node.
"""

from __future__ import annotations

from typing import Any, Iterator, Sequence

from gscodec_shac.errors import GscodecError
from gscodec_shac.rd.executors import Executor
from gscodec_shac.rd.runner import RunTask, execute_run, failed_row, worker_env

INSTALL_HINT = 'pip install "gscodec-shac[distributed]"'


class RayUnavailableError(GscodecError):
    """The ray executor was asked for but Ray is not installed."""


def import_ray() -> Any:
    """The ``ray`` module, or one clear error saying how to install it."""
    try:
        import ray
    except ImportError:
        raise RayUnavailableError(f"the ray executor needs Ray, which is not installed: {INSTALL_HINT}") from None
    return ray


class RayExecutor(Executor):
    """One Ray task per run (see module docstring)."""

    name = "ray"

    def __init__(
        self, address: str | None = None, workers: int = 1, num_cpus: float | None = None,
        threads: int = 1, max_retries: int = 2,
    ) -> None:
        self.ray = import_ray()
        if num_cpus is not None and num_cpus <= 0:
            raise GscodecError(f"--num-cpus must be positive, got {num_cpus}")
        self.address, self.workers, self.threads = address, max(1, workers), max(1, threads)
        self.num_cpus = float(num_cpus) if num_cpus is not None else float(self.threads)
        self.max_retries = max_retries
        self.slots = self.workers

    def describe(self) -> str:
        where = self.address or f"a local Ray instance ({self.workers} run(s) at once)"
        return f"ray on {where}, {self.num_cpus:g} CPU(s) per run"

    def _connect(self) -> bool:
        """Initialise Ray unless the caller already did; True when this executor started it."""
        ray = self.ray
        if ray.is_initialized():
            return False
        if self.address:
            try:
                ray.init(address=self.address, log_to_driver=False)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                raise GscodecError(f"cannot connect to the Ray cluster at {self.address}: {exc}") from None
        else:
            ray.init(num_cpus=max(1, int(round(self.workers * self.num_cpus))), include_dashboard=False,
                     log_to_driver=False)
        return True

    def run(self, tasks: Sequence[RunTask]) -> Iterator[dict[str, Any]]:
        if not tasks:
            return
        ray = self.ray
        started = self._connect()
        try:
            remote = ray.remote(execute_run).options(
                num_cpus=self.num_cpus, max_retries=self.max_retries, retry_exceptions=False,
                runtime_env={"env_vars": worker_env(self.threads)},
            )
            refs = {remote.remote(task): task for task in tasks}
            while refs:
                done, _ = ray.wait(list(refs), num_returns=1)
                for ref in done:
                    task = refs.pop(ref)
                    try:
                        row = ray.get(ref)
                    except ray.exceptions.RayError as exc:  # the worker/node was lost beyond max_retries
                        message = str(exc).strip().splitlines()
                        row = failed_row(task, f"{type(exc).__name__}: {message[0][:500] if message else ''}",
                                         self.max_retries + 1)
                    yield row
            refs = {}
        finally:
            for ref in list(locals().get("refs", {})):
                try:
                    ray.cancel(ref, force=True)
                except Exception:  # noqa: BLE001 - best effort on interrupt
                    pass
            if started:
                ray.shutdown()
