"""A small paper experiment gives the same files whatever runs it (one process, a local pool, a Dask LocalCluster
of 2 worker processes), and an experiment killed half-way (SIGKILL, or Ctrl-C's SIGINT to its process group) and
run again finishes with the same files as one uninterrupted run."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mapcontainer.experiments.executors import Executor
from mapcontainer.experiments.paper import PaperSettings, run_paper_experiment

pytestmark = [pytest.mark.slow, pytest.mark.integration]

# paper-urban alone, 2 development seeds of 2.5 s, no sensitivity table: 2 runs and 2 byte-count runs
SETTINGS = PaperSettings(runs=2, seed=2, scenarios=("paper-urban",), sensitivity_runs=0, duration_s=2.5, burnin_s=1.5)
ARGS = (
    "experiment", "paper", "--runs", "2", "--seed", "2", "--scenario", "paper-urban", "--sensitivity-runs", "0",
    "--duration", "2.5", "--burnin", "1.5",
)  # fmt: skip
SAME = ("results.json", "runs.csv", "report.md")


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """The experiment in this process, one run after another."""
    out = tmp_path_factory.mktemp("one-process")
    run_paper_experiment(out, SETTINGS, Executor(workers=1), progress=False)
    return out


def _same_files(a: Path, b: Path) -> None:
    for name in SAME:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_a_dask_cluster_and_a_local_pool_give_the_files_of_one_process_byte_for_byte(reference, dask_cluster, tmp_path):
    on_dask = run_paper_experiment(
        tmp_path / "dask", SETTINGS, Executor("dask", scheduler=dask_cluster.scheduler_address), progress=False
    )
    _same_files(reference, tmp_path / "dask")
    run_paper_experiment(tmp_path / "pool", SETTINGS, Executor(workers=2), progress=False)
    _same_files(reference, tmp_path / "pool")
    assert on_dask["resumed"] == 0 and "timing.json" in {Path(f).name for f in on_dask["files"]}


def _terminal_signals() -> None:
    """In the child before it starts: SIGINT as at a terminal. A job a non-interactive shell puts in the background
    (nohup ... &, a CI runner's) starts with SIGINT ignored, its children inherit that, and Python then installs
    no KeyboardInterrupt: the Ctrl-C below would be lost and the run end normally (it did, in 2 of 2 slow-suite
    runs started that way: exit 0, all tasks done)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _mapc(out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "mapcontainer.cli", *ARGS, "--out", str(out), *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group: Ctrl-C reaches the workers too, and cleanup finds them
        preexec_fn=_terminal_signals,
    )


def _stop_group(proc: subprocess.Popen) -> str:
    """Kill what is left of the process group (workers); the process's stderr."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    return proc.communicate(timeout=60)[1]


def _kill_after_a_task(proc: subprocess.Popen, out: Path, sig: int, group: bool) -> None:
    """Wait until a task is stored (and the process still runs), then send ``sig`` (to its group: Ctrl-C)."""
    deadline = time.monotonic() + 600
    try:
        while not [p for p in (out / "tasks").glob("*.json") if p.name != "settings.json"]:
            assert proc.poll() is None, proc.communicate()[1]
            assert time.monotonic() < deadline, "no task finished in 600 s"
            time.sleep(0.2)
        if group:
            os.killpg(proc.pid, sig)
        else:
            proc.send_signal(sig)
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            _stop_group(proc)


def test_killed_half_way_and_run_again_it_gives_the_files_of_an_uninterrupted_run(reference, tmp_path):
    pytest.importorskip("distributed")  # resumed on Dask (the cluster extra)
    out = tmp_path / "killed"
    proc = _mapc(out, "--workers", "1")
    _kill_after_a_task(proc, out, signal.SIGKILL, group=False)
    _stop_group(proc)
    assert proc.returncode == -signal.SIGKILL and not (out / "results.json").exists()
    # run again, on another executor: only the missing tasks run
    again = subprocess.run(
        [sys.executable, "-m", "mapcontainer.cli", *ARGS, "--out", str(out), "--executor", "dask", "--workers", "2"],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert again.returncode == 0, again.stderr
    assert "experiment paper: 1 of 2 tasks done earlier" in again.stderr, again.stderr  # one task at a time
    _same_files(reference, out)


def test_ctrl_c_keeps_the_finished_tasks_and_says_how_to_resume(reference, tmp_path):
    out = tmp_path / "interrupted"
    proc = _mapc(out, "--workers", "2")
    _kill_after_a_task(proc, out, signal.SIGINT, group=True)
    err = _stop_group(proc)
    assert proc.returncode == 130, err
    assert "interrupted; the finished tasks are kept in" in err and "the same command resumes" in err
    # settings that differ are refused, before anything runs
    other = subprocess.run(
        [sys.executable, "-m", "mapcontainer.cli", *ARGS[:-2], "--burnin", "1.0", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert other.returncode == 2 and "burnin_s differ" in other.stderr and "--fresh" in other.stderr
    resumed = subprocess.run(
        [sys.executable, "-m", "mapcontainer.cli", *ARGS, "--out", str(out), "--workers", "1"],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert resumed.returncode == 0, resumed.stderr
    assert "tasks done earlier" in resumed.stderr
    _same_files(reference, out)
