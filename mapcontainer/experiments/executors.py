"""Where an experiment's tasks run: here, a local process pool, or a Dask cluster.

:class:`Executor` says which; :func:`open_pool` opens it as a :class:`Pool` the runner
(:func:`mapcontainer.experiments.runner.run_all`) submits tasks to and waits on. The three differ only
in where a task runs, never in what it computes: every task carries its own seed.

* ``local`` with ``workers == 1``: in this process, one task after another.
* ``local``: a pool of ``workers`` spawned processes (:class:`concurrent.futures.ProcessPoolExecutor`),
  each with one BLAS thread. A worker that dies breaks the pool: its tasks and those waiting fail, and
  the finished ones are kept (a rerun does the rest).
* ``dask``: Dask's distributed scheduler (the ``cluster`` extra). ``scheduler`` is the address of a
  running scheduler (``tcp://host:8786``: ``dask scheduler`` and ``dask worker ADDRESS --nthreads 1`` on
  the machines); without one, a :class:`distributed.LocalCluster` of ``workers`` processes on loopback.
  A task whose worker dies is rescheduled by Dask (up to ``distributed.scheduler.allowed-failures``
  times, then it fails with ``KilledWorker``): the progress line counts those as retried.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import multiprocessing as mp
import os
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from typing import Any

from ..fusion.blas import limit_blas_threads

__all__ = ["EXECUTORS", "LOCAL_CLUSTER_CONFIG", "Executor", "Pool", "Session", "local_cluster", "open_pool"]

EXECUTORS = ("local", "dask")
_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Executor:
    """``kind`` "local" or "dask"; ``workers``: local processes (1: this process), or the processes of the
    LocalCluster started when ``scheduler`` (a Dask scheduler's address) is not given."""

    kind: str = "local"
    workers: int = 2
    scheduler: str | None = None

    def __post_init__(self):
        if self.kind not in EXECUTORS:
            raise ValueError(f"executor must be one of {', '.join(EXECUTORS)}, got {self.kind!r}")
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        if self.scheduler is not None and self.kind != "dask":
            raise ValueError(f"a scheduler address ({self.scheduler}) needs executor 'dask', got {self.kind!r}")

    def describe(self) -> str:
        if self.kind == "local":
            return "this process" if self.workers == 1 else f"a local pool of {self.workers} processes"
        if self.scheduler:
            return f"the Dask scheduler at {self.scheduler}"
        return f"a Dask LocalCluster of {self.workers} processes"


# Dask's configuration of the LocalCluster the runner starts (docs/cluster.md, "Overhead and speed-up"; a cluster of
# one's own takes the same settings from its YAML or environment):
LOCAL_CLUSTER_CONFIG = {
    # its statistical profiler samples the running task every 10 ms: 5-7 % of a paper task's CPU
    "distributed.worker.profile.enabled": False,
    # Dask's nanny starts every worker with MALLOC_TRIM_THRESHOLD_=65536, and glibc, once that is set, also stops
    # raising its mmap threshold above 128 kB: every larger numpy array of a task is then mapped and unmapped afresh,
    # 8-9 times the page faults, about 20 % more CPU per paper task in system time. None: the variable is not set.
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
    # the worker's event loop wakes for its own bookkeeping (every 20 ms, 100 ms, 500 ms by default) and takes the
    # interpreter from the task each time: 8-11 ms of CPU per second of a task's wall time, 3-4 ms at these
    # intervals (no dashboard reads them; a worker over its memory limit is still paused or stopped within 1 s)
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "1s",
}

_BLAS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
_one_thread = False


def one_blas_thread() -> None:
    """This worker process uses one BLAS thread: the libraries loaded now (threadpoolctl) and those loaded later
    (they read the environment when they load; importing a task's modules loads scipy's own OpenBLAS after
    numpy's). Once per process."""
    global _one_thread
    if not _one_thread:
        os.environ.update(dict.fromkeys(_BLAS_ENV, "1"))
        limit_blas_threads(1)
        _one_thread = True


def _on_worker(fn: Callable[[Any], Any], task: Any) -> Any:
    """``fn(task)`` in a Dask worker, with one BLAS thread in its process (as the local pool's workers)."""
    one_blas_thread()
    return fn(task)


class Pool:
    """What the runner needs of an executor: submit, wait with a timeout, and what is running or was retried."""

    def submit(self, fn: Callable[[Any], Any], task: Any, key: str) -> Any:
        raise NotImplementedError

    def wait(self, pending: set, timeout_s: float) -> tuple[set, set]:
        """(finished, still pending) after at most ``timeout_s`` (at least one finished if any can)."""
        raise NotImplementedError

    def outcome(self, fut: Any) -> Any:
        """The task's return value; raises what the executor raised (a lost worker, a broken pool)."""
        return fut.result()

    def running(self, pending: set) -> int:
        raise NotImplementedError

    def retried(self, keys: list[str]) -> int:
        """Runs of the tasks named ``keys`` started again after their worker was lost (0 where the executor never
        retries)."""
        return 0


class _Here(Pool):
    """Runs one task per ``wait``, in this process, in submission order."""

    def __init__(self) -> None:
        self._calls: dict[cf.Future, tuple] = {}

    def submit(self, fn, task, key):
        fut: cf.Future = cf.Future()
        self._calls[fut] = (fn, task)
        return fut

    def wait(self, pending, timeout_s):
        fut = next(f for f in self._calls if f in pending)
        fn, task = self._calls.pop(fut)
        fut.set_result(fn(task))  # fn catches the task's own exceptions (runner._call)
        return {fut}, pending - {fut}

    def running(self, pending):
        return 0  # between waits nothing runs here


class _Local(Pool):
    def __init__(self, ex: cf.ProcessPoolExecutor, workers: int):
        self.ex, self.workers = ex, workers

    def submit(self, fn, task, key):
        return self.ex.submit(fn, task)

    def wait(self, pending, timeout_s):
        done, rest = cf.wait(pending, timeout=timeout_s, return_when=cf.FIRST_COMPLETED)
        return set(done), set(rest)

    def running(self, pending):
        return min(self.workers, len(pending))  # the pool keeps every worker busy while tasks wait


def _suspicious(dask_scheduler=None, keys=()) -> dict:
    """On the scheduler: how often each task's worker died under it (Dask's own count of its retries)."""
    tasks = dask_scheduler.tasks
    return {k: tasks[k].suspicious for k in keys if k in tasks}


class _Dask(Pool):
    def __init__(self, client):
        self.client = client
        self._retried: dict[str, int] = {}
        self._done: set[str] = set()

    def submit(self, fn, task, key):
        return self.client.submit(_on_worker, fn, task, key=key, pure=False)

    def wait(self, pending, timeout_s):
        from distributed import wait

        try:
            done, rest = wait(list(pending), timeout=timeout_s, return_when="FIRST_COMPLETED")
        except TimeoutError:
            return set(), pending
        return set(done), set(rest)

    def running(self, pending):
        keys = {f.key for f in pending}
        return sum(k in keys for ks in self.client.processing().values() for k in ks)

    def _ask(self, keys: list[str]) -> None:
        for k, n in self.client.run_on_scheduler(_suspicious, keys=keys).items():
            self._retried[k] = max(n, self._retried.get(k, 0))

    def retried(self, keys):
        self._ask([k for k in keys if k not in self._done])
        return sum(self._retried.get(k, 0) for k in keys)

    def outcome(self, fut):
        self._ask([fut.key])  # its last count, before it is let go and the scheduler forgets it
        self._done.add(fut.key)
        return fut.result()


@contextmanager
def open_pool(executor: Executor) -> Iterator[Pool]:
    """The executor's pool, shut down on leaving (a LocalCluster started here is closed; a cluster given by
    address is left running, only this client leaves it)."""
    if executor.kind == "local" and executor.workers == 1:
        yield _Here()
    elif executor.kind == "local":
        ctx = mp.get_context("spawn")
        ex = cf.ProcessPoolExecutor(executor.workers, mp_context=ctx, initializer=one_blas_thread)
        try:
            yield _Local(ex, executor.workers)
        finally:
            ex.shutdown(wait=True, cancel_futures=True)
    else:
        try:
            from distributed import Client
        except ImportError:
            raise ValueError(
                "executor 'dask' needs Dask's distributed scheduler: pip install 'mapcontainer[cluster]'"
            ) from None
        if executor.scheduler:
            with Client(executor.scheduler) as client:
                _warn_threads(client)
                yield _Dask(client)
        else:
            with local_cluster(executor.workers) as cluster, Client(cluster) as client:
                yield _Dask(client)


@contextmanager
def local_cluster(workers: int) -> Iterator[Any]:
    """A :class:`distributed.LocalCluster` of ``workers`` processes of one thread on loopback, no dashboard, with
    :data:`LOCAL_CLUSTER_CONFIG` (its nannies and scheduler read it as they start, and give the workers a copy: this
    process's configuration is restored at once); closed on leaving."""
    import dask
    from distributed import LocalCluster

    with dask.config.set(LOCAL_CLUSTER_CONFIG):
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            # no dashboard, but the scheduler's HTTP server (health routes) starts anyway, on Dask's fixed 8787
            # unless told: a free loopback port, so that two clusters (tests, users) never collide
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
            silence_logs=logging.ERROR,
        )
    with cluster:
        yield cluster


def _warn_threads(client) -> None:
    """Our tasks hold the GIL: a worker with several threads runs them one at a time, slower than it reports. And a
    worker started with Dask's MALLOC_TRIM_THRESHOLD_ spends about 20 % more CPU on a paper task."""
    many = {w["name"]: w["nthreads"] for w in client.scheduler_info()["workers"].values() if w["nthreads"] > 1}
    if many:
        _log.warning("Dask workers with more than one thread (%s): start them with --nthreads 1", many)
    trimmed = sorted(k for k, v in client.run(os.environ.get, "MALLOC_TRIM_THRESHOLD_").items() if v is not None)
    if trimmed:
        _log.warning(
            "Dask workers with MALLOC_TRIM_THRESHOLD_ set (%s): a paper task takes about 20 %% more CPU there; "
            "see docs/cluster.md for the setting that starts them without it",
            ", ".join(trimmed),
        )


class Session:
    """An executor opened once for all the phases of an experiment (the paper's runs, then its byte counts):
    its pool or cluster starts at the first task that has to run (none when every task is stored) and stops
    on leaving the ``with`` block."""

    def __init__(self, executor: Executor):
        self.executor = executor
        self._stack = ExitStack()
        self._pool: Pool | None = None

    def pool(self) -> Pool:
        if self._pool is None:
            self._pool = self._stack.enter_context(open_pool(self.executor))
        return self._pool

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()


# ------------------------------------------------------------------------ the executors' own cost per task


def _payload(task: tuple) -> dict:
    """A task that does almost nothing but return a paper run's worth of JSON (about 70 kB)."""
    (seed,) = task
    return {"seed": seed, "series": [[0.1 * i, 1.0 / (i + 1)] for i in range(2000)]}


def main(argv: list[str] | None = None) -> int:
    """``python -m mapcontainer.experiments.executors``: each executor's wall time per near-empty task (the cost
    it adds to every task of an experiment), after 4 tasks that warm the workers up."""
    import argparse
    import time

    from .runner import run_all

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("--tasks", type=int, default=400)
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args(argv)
    tasks = [(i,) for i in range(a.tasks)]
    with local_cluster(a.workers) as cluster:
        executors = {
            "this process": Executor(workers=1),
            f"local pool of {a.workers} (its start included)": Executor(workers=a.workers),
            f"Dask, a running LocalCluster of {a.workers}": Executor("dask", scheduler=cluster.scheduler_address),
        }
        for name, ex in executors.items():
            run_all(_payload, tasks[:4], "warm-up", str, ex, progress=False)
            t0 = time.perf_counter()
            b = run_all(_payload, tasks, "tasks", str, ex, progress=False)
            per_task_ms = 1e3 * (time.perf_counter() - t0) / a.tasks
            cpu_ms = 1e3 * sum(t["cpu_s"] for t in b.timing) / a.tasks
            print(f"{name}: {per_task_ms:.1f} ms per task, of which the task's own CPU {cpu_ms:.1f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
