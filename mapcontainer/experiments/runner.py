"""Independent runs of an experiment on an executor, saved as they finish, with a progress line.

:func:`run_all` gives every task's result in the order of ``tasks``, whichever executor ran them and in
whatever order they finished: the experiments aggregate that list, so their figures do not depend on
where or when a task ran. Each task's result goes through JSON once (numpy scalars as Python numbers,
tuples as lists, NaN kept) on the worker, so a result read back from the store on a rerun is the
same object as a fresh one. Time and place of each run are kept apart (``Batch.timing``), since they
are the only things that differ between two runs of the same command.
"""

from __future__ import annotations

import json
import os
import platform
import socket
import time
import traceback
from collections.abc import Callable, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .executors import Executor, Session
from .progress import Progress
from .store import TaskStore, digest

try:
    import resource
except ImportError:  # (not on Windows)
    resource = None  # type: ignore[assignment]

__all__ = ["Batch", "TasksFailed", "run_all", "task_key", "timing_doc", "write_timing"]

REFRESH_S = 1.0  # how often the progress line asks the executor what is running


@dataclass
class Batch:
    """The results of ``run_all`` in task order, each task's timing ({"task", "wall_s", "cpu_s", "worker"}),
    how many were done earlier (read from the store) and this call's wall time."""

    results: list[Any]
    timing: list[dict] = field(default_factory=list)
    resumed: int = 0
    wall_s: float = 0.0


class TasksFailed(RuntimeError):
    """Some tasks raised; the others finished and are saved. ``failures``: (description, traceback text)."""

    def __init__(self, label: str, total: int, failures: list[tuple[str, str]], where: str = ""):
        self.failures = failures
        names = "; ".join(d for d, _ in failures)
        super().__init__(
            f"{label}: {len(failures)} of {total} tasks failed ({names}){where}; "
            "the others are saved: rerun the same command to retry the failed ones"
        )


def task_key(fn: Callable, task: Any) -> str:
    """The task's name in the store: a hash of the function's name and its arguments."""
    return digest([f"{fn.__module__}.{fn.__qualname__}", task])[:24]


def _plain(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"a task result holds {type(o).__name__}, which is not JSON-able")


def _page_faults() -> int | None:
    """The minor page faults of this thread so far (Linux; None elsewhere)."""
    who = getattr(resource, "RUSAGE_THREAD", None) if resource else None
    return None if who is None else resource.getrusage(who).ru_minflt


def _call(job: tuple[Callable[[Any], Any], Any]) -> dict:
    """``fn(task)`` on a worker (``job``: (fn, task)): {"ok": True, "result": JSON text} or
    {"ok": False, "error": traceback}, with its timing: wall seconds, CPU seconds of the worker process
    while it ran (``cpu_s``, all threads: what the task cost the machine), of the thread that ran it
    (``thread_cpu_s``, the task's own computation), the process's CPU seconds before it started
    (``worker_cpu_s``: for a worker's first task, what starting the worker cost), the minor page faults of its
    thread (``page_faults``, Linux) and the worker that ran it."""
    fn, task = job
    t0, c0, th0, f0 = time.perf_counter(), time.process_time(), time.thread_time(), _page_faults()
    try:
        out: dict[str, Any] = {"ok": True, "result": json.dumps(fn(task), default=_plain)}
    except Exception:  # the task's own failure: reported with its seed, the others go on
        out = {"ok": False, "error": traceback.format_exc()}
    out["timing"] = {
        "wall_s": round(time.perf_counter() - t0, 3),
        "cpu_s": round(time.process_time() - c0, 3),
        "thread_cpu_s": round(time.thread_time() - th0, 3),
        "worker_cpu_s": round(c0, 3),
        "page_faults": None if f0 is None else _page_faults() - f0,
        "worker": f"{socket.gethostname()}:{os.getpid()}",
    }
    return out


def run_all(
    fn: Callable[[Any], Any],
    tasks: Sequence,
    label: str,
    describe: Callable[[Any], str],
    executor: Executor | Session | None = None,
    store: TaskStore | None = None,
    progress: bool = True,
) -> Batch:
    """``fn(task)`` for every task on ``executor`` (default: a local pool of 2; a :class:`Session` to share one
    pool between calls); results in task order.

    ``describe(task)`` names a task for people (its seed). With a ``store``, tasks done earlier are read
    from it and not run again, and every task is saved as it finishes. A task that raises is reported
    at once (its description and traceback on stderr and in the store) and the rest go on; at the end
    :class:`TasksFailed` names every failed task. ``fn`` must be importable (it runs in other processes).
    """
    session = executor if isinstance(executor, Session) else Session(executor or Executor())
    t0 = time.perf_counter()
    keys = [task_key(fn, t) for t in tasks]
    if len(set(keys)) != len(keys):
        raise ValueError(f"{label}: the same task twice in the list")
    records = store.load(keys) if store else {}
    results: list[Any] = [records[k]["result"] if k in records else None for k in keys]
    timing: list[dict | None] = [records[k]["timing"] if k in records else None for k in keys]
    todo = [i for i, k in enumerate(keys) if k not in records]
    bar = Progress(len(tasks), label, enabled=progress, done=len(records))
    if records:
        bar.message(f"{label}: {len(records)} of {len(tasks)} tasks done earlier (in {store.dir}): not run again")
    failures: list[tuple[str, str]] = []
    try:
        with nullcontext() if session is executor else session:
            pool = session.pool() if todo else None  # (no pool when nothing is left to run)
            names = [f"{label}-{keys[i]}" for i in todo]  # the executor's names of the tasks
            index = {pool.submit(_call, (fn, tasks[i]), name): i for i, name in zip(todo, names, strict=True)}
            pending = set(index)
            while pending:
                done, pending = pool.wait(pending, REFRESH_S)
                for fut in done:
                    i = index.pop(fut)  # (a finished future let go: Dask frees the result on its worker)
                    try:
                        out = pool.outcome(fut)
                    except Exception as exc:  # the executor lost it (a dead worker, a broken pool)
                        out = {"ok": False, "error": f"{type(exc).__name__}: {exc}\n", "timing": None}
                    if out["ok"]:
                        results[i] = json.loads(out["result"])
                        timing[i] = {"task": describe(tasks[i]), **out["timing"]}
                        if store:
                            store.save(keys[i], timing[i], out["result"])
                        bar.update(note=describe(tasks[i]))
                    else:
                        what = describe(tasks[i])
                        failures.append((what, out["error"]))
                        where = f" (traceback: {store.fail(keys[i], what + chr(10) + out['error'])})" if store else ""
                        bar.fail(f"{label}: {what} failed{where}\n{out['error']}")
                bar.status(running=pool.running(pending), retried=pool.retried(names))
    finally:
        bar.close()
    if failures:
        raise TasksFailed(label, len(tasks), failures, f" (tracebacks in {store.dir / 'failed'})" if store else "")
    return Batch(results, timing, len(records), time.perf_counter() - t0)


def timing_doc(executor: Executor | Session, phases: dict[str, Batch], wall_s: float) -> dict:
    """What the runs cost and where they ran (``timing.json``): the one output that differs between two
    runs of the same command. Per phase: its tasks, how many were done earlier, its wall time, the CPU
    seconds of its tasks, the mean CPU seconds per task of each kind (a task's description less its seed),
    and every task's timing in task order."""
    if isinstance(executor, Session):
        executor = executor.executor
    doc: dict[str, Any] = {
        "executor": executor.describe(),
        "wall_s": round(wall_s, 1),
        "host": {"python": platform.python_version(), "machine": platform.machine(), "name": socket.gethostname()},
        "phases": {},
    }
    for name, b in phases.items():
        kinds: dict[str, list[float]] = {}
        for t in b.timing:
            kinds.setdefault(t["task"].rsplit(" seed ", 1)[0], []).append(t["cpu_s"])
        doc["phases"][name] = {
            "tasks": len(b.results),
            "resumed": b.resumed,
            "wall_s": round(b.wall_s, 1),
            "cpu_s_total": round(sum(t["cpu_s"] for t in b.timing), 1),
            "cpu_s_per_task": {k: round(sum(v) / len(v), 2) for k, v in sorted(kinds.items())},
            "tasks_timing": b.timing,
        }
    return doc


def write_timing(out_dir: str | Path, executor: Executor | Session, phases: dict[str, Batch], wall_s: float) -> Path:
    """``timing_doc`` into ``out_dir/timing.json``."""
    path = Path(out_dir) / "timing.json"
    path.write_text(json.dumps(timing_doc(executor, phases, wall_s), indent=1) + "\n")
    return path
