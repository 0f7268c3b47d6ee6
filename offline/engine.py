"""Executors for pose simulations: a crash-tolerant local process pool and Dask distributed.

Both run ``fn(*args)`` for keyed tasks, keep at most ``max_in_flight`` running, build each task's arguments
only when it is submitted (so a pose can warm-start from the nearest pose solved so far), and yield an
:class:`Outcome` per task as it completes. Tasks write their own result file and return its path, so a run that
dies anywhere resumes by skipping existing files.

The local pool survives dead workers: ``ProcessPoolExecutor`` fails every pending future when one worker dies,
so the pool is rebuilt and the in-flight tasks resubmitted. A task that was in flight during ``max_crashes``
crashes is then run alone; if it kills its worker again it is reported as failed, so one poisonous pose
cannot stall the run or take healthy poses with it. Workers die with the process that started them (``kill -9``
included): on Linux the kernel sends them SIGKILL when their parent dies (``PR_SET_PDEATHSIG``), elsewhere a
thread in each worker notices the parent is gone within half a second and exits.
"""

from __future__ import annotations

import concurrent.futures as cf
import ctypes
import logging
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Hashable, Iterable, Iterator, Sequence
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Outcome:
    """The end of one task: its result (usually a file path) or the error that ended it, and its attempts."""

    key: Hashable
    result: Any = None
    error: str | None = None
    attempts: int = 1

    @property
    def ok(self) -> bool:
        return self.error is None


class Engine(ABC):
    """A pool of workers running keyed tasks; ``run`` yields outcomes in completion order."""

    n_workers: int

    @abstractmethod
    def run(self, fn: Callable[..., Any], keys: Iterable[Hashable], make_args: Callable[[Hashable], Sequence[Any]],
            max_in_flight: int | None = None) -> Iterator[Outcome]:
        """Run ``fn(*make_args(key))`` for every key; ``make_args`` is called at submission time."""

    def close(self) -> None:
        """Release workers and clusters started by this engine."""
        return None

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SerialEngine(Engine):
    """Runs every task in this process, one after another (debugging, tiny runs, tests of the callers)."""

    n_workers = 1

    def __init__(self, retries: int = 0) -> None:
        self.retries = retries

    def run(self, fn, keys, make_args, max_in_flight=None):
        for key in keys:
            for attempt in range(1, self.retries + 2):
                try:
                    result = fn(*make_args(key))
                except Exception as exc:  # a task error is an outcome, not the end of the run
                    if attempt > self.retries:
                        yield Outcome(key, error=f"{type(exc).__name__}: {exc}", attempts=attempt)
                    continue
                yield Outcome(key, result, attempts=attempt)
                break


PR_SET_PDEATHSIG = 1  # prctl option (linux/prctl.h)


def die_with_parent(parent_pid: int) -> None:
    """Make this process end when ``parent_pid`` (its parent) dies, however it dies.

    On Linux the kernel delivers SIGKILL on the parent's death; the parent may have died before the request was
    made, so the parent id is checked after it. Elsewhere a daemon thread polls the parent id every 0.5 s.
    """
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0:
                if os.getppid() != parent_pid:
                    os._exit(1)
                return
        except (OSError, AttributeError):
            pass

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _init_worker(threads: int, parent_pid: int | None = None) -> None:
    if parent_pid is not None:
        die_with_parent(parent_pid)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[var] = str(threads)


class LocalPoolEngine(Engine):
    """Crash-tolerant local process pool (``concurrent.futures.ProcessPoolExecutor``, rebuilt when a worker dies).

    ``max_crashes``: crashes a task may witness before it runs alone; ``retries``: extra attempts for a task
    that raised an exception (exceptions are not crashes and are retried in the normal pool).
    """

    def __init__(self, n_workers: int | None = None, threads_per_worker: int = 1, max_crashes: int = 2,
                 retries: int = 1, start_method: str = "spawn") -> None:
        self.n_workers = max(1, n_workers or (os.cpu_count() or 1))
        self.threads = threads_per_worker
        self.max_crashes = max_crashes
        self.retries = retries
        self._ctx = mp.get_context(start_method)
        self._pool: cf.ProcessPoolExecutor | None = None
        self.rebuilds = 0
        self.max_rebuilds_without_progress = max(8, 4 * self.n_workers)

    def _new_pool(self) -> cf.ProcessPoolExecutor:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
        # Workers are started by the thread that submits (the caller's); PR_SET_PDEATHSIG follows the parent
        # process as long as that thread lives, which it does while the pool is in use.
        self._pool = cf.ProcessPoolExecutor(self.n_workers, mp_context=self._ctx, initializer=_init_worker,
                                            initargs=(self.threads, os.getpid()))
        return self._pool

    def run(self, fn, keys, make_args, max_in_flight=None):
        pending = list(keys)
        pending.reverse()  # pop() from the end keeps the given order
        isolated: list[Hashable] = []  # suspects of crashing workers, run alone
        crashes: dict[Hashable, int] = {}
        errors: dict[Hashable, int] = {}
        limit = max_in_flight or 2 * self.n_workers
        pool = self._pool or self._new_pool()
        running: dict[cf.Future, Hashable] = {}
        args_of: dict[Hashable, Sequence[Any]] = {}
        consecutive = 0  # pool rebuilds since the last finished task

        def submit(queue: list[Hashable]) -> bool:
            """Submit the last key of ``queue``; False (key left queued) when the pool broke meanwhile."""
            key = queue[-1]
            if key not in args_of:
                args_of[key] = tuple(make_args(key))
            try:
                fut = pool.submit(fn, *args_of[key])
            except BrokenProcessPool:  # a worker died since the last wait: nothing of this key ran
                return False
            queue.pop()
            running[fut] = key
            return True

        while pending or isolated or running:
            alone = not running and bool(isolated)
            submitted = True
            if alone:
                submitted = submit(isolated)  # a crash suspect runs with nothing else in flight
            else:
                while submitted and pending and len(running) < limit:
                    submitted = submit(pending)
            if submitted:
                done, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
            else:  # the pool is broken: its in-flight futures fail at once; collect them, then rebuild below
                done, _ = cf.wait(running, timeout=10.0)
            broken: list[Hashable] = []
            for fut in done:
                key = running.pop(fut)
                exc = fut.exception()
                if exc is None:
                    consecutive = 0
                    args_of.pop(key, None)
                    yield Outcome(key, fut.result(), attempts=1 + crashes.get(key, 0) + errors.get(key, 0))
                elif isinstance(exc, BrokenProcessPool):
                    crashes[key] = crashes.get(key, 0) + 1
                    if alone:
                        args_of.pop(key, None)
                        yield Outcome(key, error=f"worker process died running this task alone "
                                      f"({crashes[key]} crashes witnessed)", attempts=crashes[key] + errors.get(key, 0))
                    else:
                        broken.append(key)
                else:
                    errors[key] = errors.get(key, 0) + 1
                    if errors[key] > self.retries:
                        args_of.pop(key, None)
                        yield Outcome(key, error=f"{type(exc).__name__}: {exc}",
                                      attempts=errors[key] + crashes.get(key, 0))
                    else:
                        pending.append(key)
            if not submitted or broken or any(isinstance(f.exception(), BrokenProcessPool) for f in done):
                # Every other in-flight future of a broken pool fails too: count the crash, requeue, rebuild.
                for key in list(running.values()):
                    crashes[key] = crashes.get(key, 0) + 1
                    broken.append(key)
                running.clear()
                for key in broken:
                    (isolated if crashes[key] >= self.max_crashes else pending).append(key)
                self.rebuilds += 1
                consecutive += 1
                if consecutive > self.max_rebuilds_without_progress:
                    raise RuntimeError(f"worker processes died {consecutive} times in a row without finishing any "
                                       "task; they may fail at start-up (check that the task's module imports)")
                log.warning("worker process died; rebuilding the pool (%d rebuilds)", self.rebuilds)
                pool = self._new_pool()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class DaskEngine(Engine):
    """Dask distributed: ``address`` of a running scheduler, or None to start a local cluster here.

    Dask reschedules tasks of dead workers itself (``retries`` covers tasks that raise). Dask's nanny forces
    one OpenMP thread per worker; solver threads are set per task through the task's own arguments.
    """

    def __init__(self, address: str | None = None, n_workers: int | None = None, threads_per_worker: int = 1,
                 retries: int = 1) -> None:
        from dask.distributed import Client, LocalCluster

        self._cluster = None
        if address is None:
            self._cluster = LocalCluster(n_workers=n_workers or (os.cpu_count() or 1),
                                         threads_per_worker=threads_per_worker, processes=True,
                                         dashboard_address=None, silence_logs=logging.ERROR)
            self.client = Client(self._cluster)
        else:
            self.client = Client(address, timeout=10)
        info = self.client.scheduler_info()
        self.n_workers = max(1, len(info.get("workers", {})))
        self.retries = retries

    def run(self, fn, keys, make_args, max_in_flight=None):
        from dask.distributed import as_completed

        pending = list(keys)
        pending.reverse()
        limit = max_in_flight or 2 * self.n_workers
        futures: dict[Any, Hashable] = {}
        ac = as_completed()

        def submit(key: Hashable) -> None:
            fut = self.client.submit(fn, *make_args(key), pure=False, retries=self.retries)
            futures[fut] = key
            ac.add(fut)

        while pending and len(futures) < limit:
            submit(pending.pop())
        for fut in ac:
            key = futures.pop(fut)
            if fut.status == "finished":
                yield Outcome(key, fut.result())
            else:
                exc = fut.exception()
                yield Outcome(key, error=f"{type(exc).__name__}: {exc}", attempts=1 + self.retries)
            fut.release()
            while pending and len(futures) < limit:
                submit(pending.pop())

    def close(self) -> None:
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()


def make_engine(spec: str, n_workers: int | None = None, threads_per_worker: int = 1) -> Engine:
    """``local`` (default), ``serial`` (in this process), ``dask-local`` (start a local Dask cluster) or ``dask://HOST:PORT``."""
    if spec in ("local", "", None):
        return LocalPoolEngine(n_workers, threads_per_worker)
    if spec == "serial":
        return SerialEngine()
    if spec == "dask-local":
        return DaskEngine(None, n_workers, threads_per_worker)
    if spec.startswith("dask://"):
        return DaskEngine("tcp://" + spec[len("dask://"):], n_workers, threads_per_worker)
    if spec.startswith("tcp://"):
        return DaskEngine(spec, n_workers, threads_per_worker)
    raise ValueError(f"unknown engine {spec!r}; use local, dask-local or dask://HOST:PORT")
