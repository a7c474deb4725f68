"""What an experiment cost on each executor, in CPU seconds (which hold on a loaded machine, unlike wall time).

:func:`worker_accounting` reads a run's ``timing.json`` (:func:`.runner.timing_doc`): per worker process, the CPU it
had spent before its first task (starting the process and importing the task's code), its tasks' CPU (the whole
process while a task ran, and the task's own thread alone: the difference is the worker's other threads, e.g. Dask's
event loop), its CPU between tasks (sending a result back, receiving the next task) and the page faults of the
threads that ran its tasks.

``python -m mapcontainer.experiments.accounting --out DIR -- PAPER OPTIONS`` runs ``mapc experiment paper`` with
those options once per executor (a local pool and the runner's Dask LocalCluster of ``--workers`` processes, one
after the other, ``--repeat`` rounds; ``--executors local dask dask-defaults`` adds a LocalCluster with Dask's own
defaults but the profiler, to see what the runner's settings save) and prints that accounting as JSON, with each
command's wall time and the CPU of its whole process tree (client, scheduler, nannies, workers: from the kernel
when it ends), the load average around it, and whether the executors wrote the same ``results.json``.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["command_accounting", "worker_accounting"]


def _r(x: float) -> float:
    return round(x, 2)


def worker_accounting(timing: dict) -> dict[str, Any]:
    """CPU seconds per worker process and in total, from a ``timing.json`` document (tasks of every phase).

    Per worker: ``start_cpu_s`` (the process's CPU before its first task), ``tasks``, ``task_cpu_s`` (the process
    while its tasks ran), ``task_thread_cpu_s`` (the threads that ran them), ``other_threads_cpu_s`` (the
    difference), ``between_tasks_cpu_s`` (the process's CPU from the end of one task to the start of its next),
    ``first_task_cpu_s``. Tasks read back from a store of an earlier run are left out (their worker is gone)."""
    by_worker: dict[str, list[dict]] = {}
    for phase in timing["phases"].values():
        for t in phase["tasks_timing"]:
            if "worker_cpu_s" in t:
                by_worker.setdefault(t["worker"], []).append(t)
    workers: dict[str, dict[str, float]] = {}
    for name, ts in sorted(by_worker.items()):
        ts = sorted(ts, key=lambda t: t["worker_cpu_s"])  # the process's CPU only grows: its tasks in order
        between = sum(b["worker_cpu_s"] - a["worker_cpu_s"] - a["cpu_s"] for a, b in zip(ts, ts[1:], strict=False))
        workers[name] = {
            "start_cpu_s": _r(ts[0]["worker_cpu_s"]),
            "tasks": len(ts),
            "task_cpu_s": _r(sum(t["cpu_s"] for t in ts)),
            "task_thread_cpu_s": _r(sum(t["thread_cpu_s"] for t in ts)),
            "other_threads_cpu_s": _r(sum(t["cpu_s"] - t["thread_cpu_s"] for t in ts)),
            "between_tasks_cpu_s": _r(max(between, 0.0)),
            "first_task_cpu_s": _r(ts[0]["cpu_s"]),
            "task_page_faults": sum(t.get("page_faults") or 0 for t in ts),
        }
    total = {
        k: _r(sum(w[k] for w in workers.values()))
        for k in ("start_cpu_s", "task_cpu_s", "task_thread_cpu_s", "other_threads_cpu_s", "between_tasks_cpu_s")
    }
    tasks = sum(w["tasks"] for w in workers.values())
    total["task_page_faults"] = sum(w["task_page_faults"] for w in workers.values())
    total["tasks"] = tasks
    total["task_cpu_s_mean"] = _r(total["task_cpu_s"] / tasks) if tasks else None
    return {"executor": timing["executor"], "wall_s": timing["wall_s"], "workers": workers, "total": total}


EXECUTOR_ARGS = {"local": ["--executor", "local"], "dask": ["--executor", "dask"], "dask-defaults": [], "here": []}


def _with_dask_defaults(argv: list[str], out: Path, workers: int) -> dict[str, Any]:
    """:func:`command_accounting` on a LocalCluster with Dask's defaults (the profiler off, as measured apart): the
    cluster runs in this process, so its CPU (from the kernel, once its workers are reaped) is added to the
    command's. This process's environment is restored after it (Dask's nanny sets MALLOC_TRIM_THRESHOLD_ here)."""
    import dask
    from distributed import LocalCluster

    env = dict(os.environ)
    self0, kids0 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    with (
        dask.config.set({"distributed.worker.profile.enabled": False}),
        LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None,
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},  # a free port for its HTTP server, not 8787
        ) as cluster,
    ):
        doc = command_accounting([*argv, "--executor", "dask", "--scheduler", cluster.scheduler_address], out)
    os.environ.clear()
    os.environ.update(env)
    self1, kids1 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = sum(b.ru_utime + b.ru_stime - a.ru_utime - a.ru_stime for a, b in ((self0, self1), (kids0, kids1)))
    doc["command"]["cpu_s"] = _r(max(cpu, doc["command"]["cpu_s"]))  # (the command is one of the children)
    return doc


def command_accounting(argv: list[str], out: Path) -> dict[str, Any]:
    """Run ``mapc experiment paper ARGV --out OUT`` to its end: its wall time, the CPU seconds of its whole
    process tree (every process it started and waited for, as the kernel counts them), the load average at start
    and end, and :func:`worker_accounting` of the ``timing.json`` it wrote."""
    cmd = [sys.executable, "-m", "mapcontainer.cli", "experiment", "paper", *argv, "--out", str(out)]
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
    _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {proc.returncode}")
    doc = worker_accounting(json.loads((out / "timing.json").read_text()))
    doc["command"] = {
        "wall_s": _r(wall),
        "cpu_s": _r(ru.ru_utime + ru.ru_stime),
        "user_s": _r(ru.ru_utime),
        "system_s": _r(ru.ru_stime),
        "minor_faults": ru.ru_minflt,
        "load": [_r(load0), _r(os.getloadavg()[0])],
    }
    return doc


def _ratio(a: float | None, b: float | None) -> float | None:
    return round(a / b, 3) if a and b else None


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(
        prog="python -m mapcontainer.experiments.accounting",
        description="mapc experiment paper on each executor, one after the other: wall time and CPU accounting as "
        "JSON. Options after -- go to mapc experiment paper (not --out, --executor, --workers).",
    )
    ap.add_argument("--out", required=True, type=Path, help="a directory for each run's output (OUT/local-1, ...)")
    ap.add_argument("--workers", type=int, default=2, help="worker processes of either executor (default 2)")
    ap.add_argument(
        "--executors",
        nargs="+",
        choices=sorted(EXECUTOR_ARGS),
        default=["local", "dask"],
        help="local: the local pool; dask: the runner's LocalCluster; dask-defaults: a LocalCluster with Dask's "
        "defaults (profiler off), started here; here: the command's own process, one task after another "
        "(default: local dask)",
    )
    ap.add_argument("--repeat", type=int, default=1, help="rounds of the executors, alternating (default 1)")
    ap.add_argument("paper", nargs=argparse.REMAINDER, help="-- then the options of mapc experiment paper")
    a = ap.parse_args(argv)
    paper = a.paper[1:] if a.paper[:1] == ["--"] else a.paper
    if {"--out", "--executor", "--workers", "--scheduler"} & set(paper):
        ap.error("--out, --executor, --workers and --scheduler are this command's, not the paper options'")
    runs: list[dict] = []
    for i in range(1, a.repeat + 1):
        for name in a.executors:
            out = a.out / f"{name}-{i}"
            workers = 1 if name == "here" else a.workers
            argv_ = [*paper, *EXECUTOR_ARGS[name], "--workers", str(workers), "--fresh", "--quiet"]
            if name == "dask-defaults":
                doc = _with_dask_defaults(argv_, out, a.workers)
            else:
                doc = command_accounting(argv_, out)
            runs.append({"name": name, "round": i, **doc})
            print(f"{name} round {i}: {runs[-1]['command']}", file=sys.stderr)
    results = {(a.out / f"{r['name']}-{r['round']}" / "results.json").read_bytes() for r in runs}
    doc: dict[str, Any] = {"paper_options": paper, "workers": a.workers, "runs": runs}
    doc["same_results_json"] = len(results) == 1
    if {"local", "dask"} <= set(a.executors):
        mean = {
            name: {
                k: sum(f(r) for r in runs if r["name"] == name) / a.repeat
                for k, f in {
                    "wall_s": lambda r: r["command"]["wall_s"],
                    "command_cpu_s": lambda r: r["command"]["cpu_s"],
                    "task_cpu_s": lambda r: r["total"]["task_cpu_s"],
                    "task_thread_cpu_s": lambda r: r["total"]["task_thread_cpu_s"],
                }.items()
            }
            for name in ("local", "dask")
        }
        doc["dask_over_local"] = {k: _ratio(mean["dask"][k], mean["local"][k]) for k in mean["local"]}
    print(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
