"""Where the tiles of a reconstruction (and the row blocks of a lens derivation) are computed.

One interface, three engines, the same task functions, so every engine gives bit-identical
results (each task is a pure function of its inputs, computed by the same numpy code):

* ``workers=1``: in this process, one task after another;
* ``workers=N`` (default: every core): N local worker processes (``concurrent.futures``);
* Dask (``dask=True`` for a ``distributed.LocalCluster`` of ``workers`` processes, or
  ``scheduler="tcp://host:8786"`` for an existing cluster). Stores are zarr on a path every
  worker can read.

The caller keeps at most ``max_in_flight`` tasks submitted, so memory stays bounded whatever
the number of tasks.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
from collections.abc import Callable
from typing import Any


def default_workers() -> int:
    """Worker processes used when none are asked for: every core this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


class _Done:
    """A finished result with the future interface used here."""

    def __init__(self, fn: Callable, args: tuple) -> None:
        self._value = fn(*args)

    def result(self) -> Any:
        return self._value


class Engine:
    """Submit tasks, collect them as they finish; a context manager that shuts down what it
    started (never an existing Dask cluster)."""

    def __init__(self, workers: int | None = None, *, dask: bool = False,
                 scheduler: str | None = None) -> None:
        self.workers = default_workers() if workers is None else int(workers)
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.kind = "dask" if (dask or scheduler) else ("serial" if self.workers == 1
                                                       else "processes")
        self._pool: cf.Executor | None = None
        self._client = None
        self._cluster = None
        if self.kind == "processes":
            ctx = multiprocessing.get_context("forkserver")
            self._pool = cf.ProcessPoolExecutor(self.workers, mp_context=ctx,
                                                initializer=_single_threaded)
        elif self.kind == "dask":
            from distributed import Client, LocalCluster

            if scheduler:
                self._client = Client(scheduler)
                self.workers = max(1, len(self._client.scheduler_info()["workers"]))
            else:
                self._cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1,
                                             processes=True, dashboard_address=None)
                self._client = Client(self._cluster)

    @property
    def max_in_flight(self) -> int:
        """Tasks to keep submitted: two per worker (one running, one queued)."""
        return 2 * self.workers

    def describe(self) -> str:
        if self.kind == "dask":
            where = self._client.scheduler.address if self._client is not None else "?"
            return f"dask ({self.workers} workers at {where})"
        return f"{self.kind} ({self.workers} worker{'s' if self.workers > 1 else ''})"

    def submit(self, fn: Callable, *args: Any):
        if self.kind == "serial":
            return _Done(fn, args)
        if self.kind == "processes":
            return self._pool.submit(fn, *args)
        return self._client.submit(fn, *args, pure=False)

    def wait_some(self, pending: set) -> tuple[set, set]:
        """(finished, still pending): at least one finished when any is pending."""
        if self.kind == "serial" or not pending:
            return set(pending), set()
        if self.kind == "processes":
            done, rest = cf.wait(pending, return_when=cf.FIRST_COMPLETED)
            return set(done), set(rest)
        from distributed import wait

        done, rest = wait(list(pending), return_when="FIRST_COMPLETED")
        return set(done), set(rest)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def run_ordered(engine: Engine, tasks, on_result: Callable[[Any, Any], None]) -> None:
    """Submit ``(key, fn, args)`` from the iterable ``tasks`` keeping at most
    ``engine.max_in_flight`` in flight; call ``on_result(key, value)`` for each as it
    finishes (in completion order). An exception in a task is raised here."""
    pending: dict = {}

    def harvest(block_until_one: bool) -> None:
        if not pending:
            return
        done, _ = engine.wait_some(set(pending)) if block_until_one else (set(), set())
        for fut in done:
            key = pending.pop(fut)
            on_result(key, fut.result())

    for key, fn, args in tasks:
        while len(pending) >= engine.max_in_flight:
            harvest(True)
        pending[engine.submit(fn, *args)] = key
        if engine.kind == "serial":
            harvest(True)
    while pending:
        harvest(True)


def _single_threaded() -> None:
    """Worker initialiser: one thread of maths per process (the processes are the cores)."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
