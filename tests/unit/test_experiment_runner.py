"""The experiment runner: executors (here, a local pool, Dask), results in task order whatever ran them, the task
store (resume, refuse other settings), failures reported with their seed and traceback, the progress line."""

from __future__ import annotations

import io
import json
import logging
import math
import os
from pathlib import Path

import numpy as np
import pytest

from mapcontainer.experiments import accounting
from mapcontainer.experiments.executors import Executor, Session, open_pool
from mapcontainer.experiments.progress import Progress
from mapcontainer.experiments.runner import TasksFailed, run_all, task_key, timing_doc
from mapcontainer.experiments.store import SettingsChanged, TaskStore

TASKS = [(seed,) for seed in range(6)]


def draw(task: tuple) -> dict:
    """A task of the kind experiments run: numbers from its own seed's stream (numpy types, a NaN, a tuple)."""
    (seed,) = task
    rng = np.random.default_rng(seed)
    return {"seed": seed, "x": rng.normal(size=3), "mean": np.float64(rng.random()), "none": float("nan"), "t": (1, 2)}


CALLS: list[tuple] = []  # the tasks draw_counted ran in this process


def draw_counted(task: tuple) -> dict:
    CALLS.append(task)
    return draw(task)


BROKEN = {3}  # the seeds draw_but_broken fails on (in this process)


def draw_but_broken(task: tuple) -> dict:
    CALLS.append(task)
    if task[0] in BROKEN:
        raise RuntimeError(f"seed {task[0]} is broken")
    return draw(task)


def die_once(task: tuple) -> dict:
    """Kills its worker process the first time it runs (a marker file says it did): Dask must run it again."""
    marker, seed = task
    if not Path(marker).exists():
        Path(marker).touch()
        os._exit(1)
    return draw((seed,))


def _describe(task: tuple) -> str:
    return f"seed {task[-1]}"


def _same(a: list, b: list) -> bool:
    return json.dumps(a) == json.dumps(b)  # NaN != NaN: compare the JSON text, as the experiments write it


def _expected() -> list[dict]:
    return [json.loads(json.dumps(draw(t), default=lambda o: o.tolist())) for t in TASKS]


def test_results_come_in_task_order_through_json_here_and_in_a_local_pool():
    here = run_all(draw, TASKS, "t", _describe, Executor(workers=1), progress=False)
    pool = run_all(draw, TASKS, "t", _describe, Executor(workers=2), progress=False)
    assert _same(here.results, _expected()) and _same(pool.results, _expected())
    r = here.results[0]
    assert isinstance(r["x"], list) and r["t"] == [1, 2] and math.isnan(r["none"]) and type(r["mean"]) is float
    assert [t["task"] for t in pool.timing] == [f"seed {i}" for i in range(6)]
    assert all(t["cpu_s"] >= 0 and t["worker"] for t in pool.timing)
    assert len({t["worker"] for t in here.timing}) == 1  # one process ran them all


@pytest.mark.slow
def test_local_pool_runs_with_one_blas_thread():
    (info,) = run_all(eval, ["__import__('threadpoolctl').threadpool_info()"], "t", str, progress=False).results
    blas = [lib["num_threads"] for lib in info if lib["user_api"] == "blas"]
    assert blas and all(n == 1 for n in blas)


def test_executor_refuses_what_does_not_fit():
    with pytest.raises(ValueError, match="workers"):
        Executor(workers=0)
    with pytest.raises(ValueError, match="executor must be one of"):
        Executor("slurm")
    with pytest.raises(ValueError, match="needs executor 'dask'"):
        Executor("local", scheduler="tcp://127.0.0.1:8786")
    with pytest.raises(ValueError, match="same task twice"):
        run_all(draw, [(1,), (1,)], "t", _describe, Executor(workers=1), progress=False)


def test_a_rerun_skips_the_stored_tasks_and_says_so(tmp_path, capsys):
    store = TaskStore(tmp_path, "toy", {"n": 6})
    first = run_all(draw_counted, TASKS[:4], "t", _describe, Executor(workers=1), store, progress=False)
    assert first.resumed == 0 and len(list(store.dir.glob("*.json"))) == 1 + 4  # settings.json + one per task
    CALLS.clear()
    again = run_all(draw_counted, TASKS, "t", _describe, Executor(workers=1), TaskStore(tmp_path, "toy", {"n": 6}))
    assert CALLS == TASKS[4:] and again.resumed == 4 and _same(again.results, _expected())
    assert [t["task"] for t in again.timing] == [f"seed {i}" for i in range(6)]  # the stored tasks' own timing
    err = capsys.readouterr().err
    assert "t: 4 of 6 tasks done earlier" in err and "not run again" in err
    lines = err.strip().splitlines()
    assert "4/6" in lines[0] and "eta --:--" in lines[0] and "6/6" in lines[-1]  # the ETA from this run's pace


def test_the_store_refuses_other_settings_and_fresh_starts_over(tmp_path):
    store = TaskStore(tmp_path, "toy", {"n": 6, "duration_s": 2.0})
    run_all(draw, TASKS[:2], "t", _describe, Executor(workers=1), store, progress=False)
    with pytest.raises(SettingsChanged, match="duration_s differ.*--fresh"):
        TaskStore(tmp_path, "toy", {"n": 6, "duration_s": 3.0})
    with pytest.raises(SettingsChanged, match="toy"):
        TaskStore(tmp_path, "other", {"n": 6, "duration_s": 2.0})
    fresh = TaskStore(tmp_path, "toy", {"n": 6, "duration_s": 3.0}, fresh=True)
    assert fresh.load([task_key(draw, t) for t in TASKS]) == {}


def test_a_failing_task_is_reported_with_its_seed_and_traceback_the_rest_are_saved_and_a_rerun_retries_it(tmp_path):
    store = TaskStore(tmp_path, "toy", {})
    with pytest.raises(TasksFailed, match=r"1 of 6 tasks failed \(seed 3\).*rerun") as exc:
        run_all(draw_but_broken, TASKS, "toy", _describe, Executor(workers=1), store, progress=False)
    ((what, tb),) = exc.value.failures
    assert what == "seed 3" and "RuntimeError: seed 3 is broken" in tb and "draw_but_broken" in tb
    (failed,) = (store.dir / "failed").glob("*.txt")
    assert failed.read_text().startswith("seed 3\n") and "seed 3 is broken" in failed.read_text()
    assert len(store.load([task_key(draw_but_broken, t) for t in TASKS])) == 5
    with pytest.raises(TasksFailed, match=r"failed \(seed 3\); the others"):  # without a store: no files named
        run_all(draw_but_broken, TASKS, "toy", _describe, Executor(workers=1), progress=False)
    BROKEN.clear()  # (what broke it is fixed) the rerun runs seed 3 alone and forgets its failure
    CALLS.clear()
    rerun = run_all(draw_but_broken, TASKS, "toy", _describe, Executor(workers=1), store, progress=False)
    assert CALLS == [(3,)] and rerun.resumed == 5 and _same(rerun.results, _expected())
    assert not failed.exists()


def test_failures_are_printed_at_once_and_counted_on_the_line():
    buf = io.StringIO()
    bar = Progress(4, "work", stream=buf)
    bar.update(note="seed 0")
    bar.status(running=2, retried=1)
    bar.fail("work: seed 1 failed\nTraceback ...\nValueError: x")
    bar.update(note="seed 2")
    bar.close()
    text = buf.getvalue()
    assert "work: seed 1 failed\nTraceback ...\nValueError: x\n" in text
    assert "running 2 failed 1 retried 1" in text.splitlines()[-1]


def test_timing_is_kept_apart_per_phase_grouped_by_task_kind():
    b = run_all(draw, TASKS[:2], "t", lambda t: f"draw seed {t[0]}", Executor(workers=1), progress=False)
    doc = timing_doc(Executor(workers=1), {"runs": b}, 1.234)
    assert doc["executor"] == "this process" and doc["wall_s"] == 1.2
    phase = doc["phases"]["runs"]
    assert phase["tasks"] == 2 and phase["resumed"] == 0 and list(phase["cpu_s_per_task"]) == ["draw"]
    assert [t["task"] for t in phase["tasks_timing"]] == ["draw seed 0", "draw seed 1"]


@pytest.mark.slow
def test_a_dask_cluster_gives_the_same_results_and_retries_a_task_whose_worker_died(dask_cluster, tmp_path, capsys):
    ex = Executor("dask", scheduler=dask_cluster.scheduler_address)
    b = run_all(draw, TASKS, "t", _describe, ex, progress=False)
    assert _same(b.results, _expected()) and b.resumed == 0
    assert {t["worker"] for t in b.timing} != {f"{os.uname().nodename}:{os.getpid()}"}  # not this process
    capsys.readouterr()
    got = run_all(die_once, [(str(tmp_path / "died"), 7)], "dies", _describe, ex, TaskStore(tmp_path, "toy", {}))
    assert _same(got.results, [json.loads(json.dumps(draw((7,)), default=lambda o: o.tolist()))])
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "1/1" in last and "failed 0 retried 1" in last, last  # Dask ran it again on a live worker


def test_a_session_opens_its_pool_once_and_only_when_a_task_runs(tmp_path):
    store = TaskStore(tmp_path, "toy", {})
    with Session(Executor(workers=1)) as session:
        a = run_all(draw, TASKS[:2], "a", _describe, session, store, progress=False)
        pool = session.pool()
        b = run_all(draw, TASKS[2:], "b", _describe, session, store, progress=False)
        assert session.pool() is pool
    assert _same(a.results + b.results, _expected())
    with Session(Executor("dask", workers=2)) as stored:  # everything stored: no cluster starts
        again = run_all(draw, TASKS, "c", _describe, stored, store, progress=False)
        assert stored._pool is None and again.resumed == 6


def test_each_task_keeps_its_own_threads_cpu_and_its_workers_cpu_before_it():
    b = run_all(draw, TASKS[:3], "t", _describe, Executor(workers=1), progress=False)
    for t in b.timing:
        assert 0 <= t["thread_cpu_s"] <= t["cpu_s"] + 0.002 and t["worker_cpu_s"] > 0  # (each rounded to 1 ms)
        assert t["page_faults"] >= 0
    before = [t["worker_cpu_s"] for t in b.timing]
    assert before == sorted(before)  # one process ran them one after another: its CPU only grows


def test_worker_accounting_splits_start_tasks_other_threads_and_between_tasks():
    def task(worker, before, cpu, thread):
        return {"task": "sim seed 1", "wall_s": 9.0, "cpu_s": cpu, "thread_cpu_s": thread, "worker_cpu_s": before,
                "worker": worker}  # fmt: skip

    timing = {
        "executor": "a local pool of 2 processes",
        "wall_s": 20.0,
        "phases": {
            "runs": {
                "tasks_timing": [task("h:2", 1.5, 4.0, 3.5), task("h:1", 7.5, 2.0, 2.0), task("h:1", 2.0, 5.0, 4.0)]
            },
            "bytes": {"tasks_timing": [task("h:2", 6.0, 1.0, 1.0), {"task": "stored earlier", "cpu_s": 3.0}]},
        },
    }
    acc = accounting.worker_accounting(timing)
    assert acc["workers"]["h:1"] == {
        "start_cpu_s": 2.0,  # before its first task (the one it ran first, whatever the phase order)
        "tasks": 2,
        "task_cpu_s": 7.0,
        "task_thread_cpu_s": 6.0,
        "other_threads_cpu_s": 1.0,
        "between_tasks_cpu_s": 0.5,  # 7.5 - 2.0 - 5.0
        "first_task_cpu_s": 5.0,
        "task_page_faults": 0,  # (not in these records)
    }
    assert acc["workers"]["h:2"]["between_tasks_cpu_s"] == 0.5 and acc["workers"]["h:2"]["start_cpu_s"] == 1.5
    assert acc["total"] == {
        "start_cpu_s": 3.5,
        "task_cpu_s": 12.0,
        "task_thread_cpu_s": 10.5,
        "other_threads_cpu_s": 1.5,
        "between_tasks_cpu_s": 1.0,
        "task_page_faults": 0,
        "tasks": 4,
        "task_cpu_s_mean": 3.0,
    }


def _setting(name: str) -> object:
    """On a worker: an environment variable ("env:NAME") or a Dask setting."""
    import dask

    return os.environ.get(name[4:]) if name.startswith("env:") else dask.config.get(name)


@pytest.mark.slow
def test_the_runners_local_cluster_starts_workers_without_dasks_malloc_trim_threshold(monkeypatch):
    """Dask's nanny would set MALLOC_TRIM_THRESHOLD_=65536, which costs a paper task about 20 % more CPU."""
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)  # (an earlier cluster in this process sets it here)
    names = ["env:MALLOC_TRIM_THRESHOLD_", "env:OMP_NUM_THREADS", "distributed.worker.profile.enabled"]
    names += ["distributed.admin.tick.interval", "distributed.worker.memory.monitor-interval"]
    got = run_all(_setting, names, "env", str, Executor("dask", workers=1), progress=False).results
    assert got == [None, "1", False, "1s", "1s"]


@pytest.mark.slow
def test_a_cluster_whose_workers_have_dasks_malloc_trim_threshold_is_warned_about(dask_cluster, caplog, monkeypatch):
    distributed = pytest.importorskip("distributed")
    with caplog.at_level(logging.WARNING), open_pool(Executor("dask", scheduler=dask_cluster.scheduler_address)):
        pass
    assert "MALLOC_TRIM" not in caplog.text  # the runner's own LocalCluster
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "")  # (undone at the end: Dask's nanny sets it in this process)
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_")
    with (
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=1, host="127.0.0.1", dashboard_address=None,
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
        ) as dask_s,
        caplog.at_level(logging.WARNING),
        open_pool(Executor("dask", scheduler=dask_s.scheduler_address)),
    ):
        pass
    assert "MALLOC_TRIM_THRESHOLD_ set (tcp://127.0.0.1:" in caplog.text


def test_the_accounting_command_keeps_the_executor_options_to_itself(tmp_path, capsys):
    with pytest.raises(SystemExit):
        accounting.main(["--out", str(tmp_path), "--", "--runs", "1", "--executor", "dask"])
    assert "--executor" in capsys.readouterr().err and not any(tmp_path.iterdir())  # nothing ran
