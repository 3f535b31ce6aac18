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
import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from station.errors import StationError

PARENT_POLL_S = 0.5  # how often a worker's watchdog looks for the main process


class Terminated(KeyboardInterrupt):
    """SIGTERM reached the main process while an engine ran: handled like Ctrl-C (the
    command stops cleanly, releases its lock and prints how to resume)."""

    def __str__(self) -> str:
        return "terminated (SIGTERM)"


class WorkersDied(StationError):
    """A worker process of the local pool died while it computed (killed, out of memory, or
    a script that starts workers importing itself again); the message says what to do."""


WORKERS_DIED = ("a worker process died while it computed: out of memory, killed, or a Python "
                "script without `if __name__ == \"__main__\":` around its top level (every "
                "worker imports the script); guard the script, free memory, or run in this "
                "process (workers=1, --workers 1)")


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated()


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
        self._old_sigterm: Any = None
        if threading.current_thread() is threading.main_thread():
            self._old_sigterm = signal.signal(signal.SIGTERM, _raise_terminated)
        if self.kind == "processes":
            ctx = multiprocessing.get_context("forkserver")
            self._pool = cf.ProcessPoolExecutor(self.workers, mp_context=ctx,
                                                initializer=_worker_init,
                                                initargs=(os.getpid(),))
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
            if self._pool is None:
                raise RuntimeError("submit on a closed engine")
            return self._pool.submit(fn, *args)
        if self._client is None:
            raise RuntimeError("submit on a closed engine")
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

    def close(self, interrupted: bool = False) -> None:
        """Shut down what this engine started; ``interrupted`` (Ctrl-C, SIGTERM): end the
        running tasks at once rather than wait for them (a task is pure; nothing is lost)."""
        if self._pool is not None:
            if interrupted:
                for proc in list(getattr(self._pool, "_processes", {}).values()):
                    proc.terminate()
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None
        if self._old_sigterm is not None:
            signal.signal(signal.SIGTERM, self._old_sigterm)
            self._old_sigterm = None

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        self.close(interrupted=exc_type is not None and issubclass(exc_type, KeyboardInterrupt))


def run_ordered(engine: Engine, tasks, on_result: Callable[[Any, Any], None]) -> None:
    """Submit ``(key, fn, args)`` from the iterable ``tasks`` keeping at most
    ``engine.max_in_flight`` in flight; call ``on_result(key, value)`` for each as it
    finishes (in completion order). An exception in a task is raised here; a worker process
    that dies raises ``WorkersDied``."""
    pending: dict = {}

    def harvest(block_until_one: bool) -> None:
        if not pending:
            return
        done, _ = engine.wait_some(set(pending)) if block_until_one else (set(), set())
        for fut in done:
            key = pending.pop(fut)
            try:
                value = fut.result()
            except cf.process.BrokenProcessPool as exc:
                raise WorkersDied(WORKERS_DIED) from exc
            on_result(key, value)

    for key, fn, args in tasks:
        while len(pending) >= engine.max_in_flight:
            harvest(True)
        pending[engine.submit(fn, *args)] = key
        if engine.kind == "serial":
            harvest(True)
    while pending:
        harvest(True)


def _single_threaded() -> None:
    """One thread of maths per process (the processes are the cores)."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def _worker_init(main_pid: int) -> None:
    """Worker initialiser: single-threaded maths, and the worker ends when the main process
    ``main_pid`` does (killed by SIGKILL, SIGTERM or the OOM killer): the kernel sends it
    SIGKILL when its parent (the forkserver, which exits with the main process) dies, and a
    watchdog thread checks every ``PARENT_POLL_S`` for systems without that."""
    _single_threaded()
    parent = os.getppid()
    if sys.platform.startswith("linux"):
        try:
            PR_SET_PDEATHSIG = 1
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL),
                                                    0, 0, 0)
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent or not _alive(main_pid):  # died before prctl took effect
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent, main_pid), daemon=True,
                     name="ltc-parent-watchdog").start()


def _alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except (OSError, IndexError):
        return True


def _watch_parent(parent: int, main_pid: int) -> None:
    while os.getppid() == parent and _alive(main_pid):
        time.sleep(PARENT_POLL_S)
    os._exit(1)
