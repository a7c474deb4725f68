"""The fleet registry: running fleets are found from any directory, a dead launcher's processes are
checked again, and a fleet that runs already is refused before anything starts."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.launcher.app import (
    LauncherSettings,
    already_running,
    pointer_path,
    registry_dir,
    run,
    running_launcher,
)
from services.launcher.control import active_fleets, detach
from services.launcher.manifest import MANIFEST_DIR, FleetParams
from services.launcher.supervisor import is_ours

REPO = Path(__file__).resolve().parents[2]
MANIFESTS = ("fleet-host-a.yaml", "fleet-host-b.yaml")


@pytest.fixture
def registry(tmp_path, monkeypatch):
    monkeypatch.setenv("MAPC_STATE_DIR", str(tmp_path / "state"))
    d = registry_dir()
    d.mkdir(parents=True)
    return d


@pytest.fixture
def ours():
    """A live process that counts as one of ours (its command line names a services module)."""
    p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", "services.launcher"])
    deadline = time.monotonic() + 10
    while not is_ours(p.pid) and time.monotonic() < deadline:
        time.sleep(0.01)  # /proc/<pid>/cmdline shows the new command line a moment after Popen returns
    yield p.pid
    p.kill()
    p.wait()


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _register(registry, tmp_path, fleet: str, launcher_pid: int, processes: list[dict], part: str = "local") -> None:
    run_dir = tmp_path / f"run-{fleet}"
    run_dir.mkdir()
    (run_dir / "state.json").write_text(
        json.dumps({"status": "running", "endpoints": ["tcp/127.0.0.1:1"], "processes": processes})
    )
    pointer = {"fleet": fleet, "manifest": part, "run_dir": str(run_dir), "launcher_pid": launcher_pid}
    pointer_path(fleet, part).write_text(json.dumps(pointer))


def test_the_registry_is_per_user_not_per_directory(monkeypatch, tmp_path) -> None:
    monkeypatch.delenv("MAPC_STATE_DIR", raising=False)
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "xdg"))
    assert registry_dir() == tmp_path / "xdg" / "mapcontainer" / "fleets"
    monkeypatch.chdir(tmp_path)
    assert registry_dir().is_absolute()
    monkeypatch.setenv("MAPC_STATE_DIR", str(tmp_path / "s"))
    assert registry_dir() == tmp_path / "s" / "fleets"


def test_a_dead_launchers_processes_are_checked_again(registry, tmp_path, ours) -> None:
    dead = _dead_pid()
    procs = [
        {"name": "world", "pid": dead, "alive": True, "state": "ready", "restarts": 0, "uptime_s": 4.0},
        {"name": "host", "pid": ours, "alive": True, "state": "ready", "restarts": 0, "uptime_s": 4.0},
    ]
    _register(registry, tmp_path, "orphan", dead, procs)
    (f,) = active_fleets()
    assert f["fleet"] == "orphan" and not f["launcher_alive"]
    rows = {p["name"]: p for p in f["processes"]}
    assert rows["world"]["alive"] is False and rows["world"]["state"] == "gone"
    assert rows["host"]["alive"] is True and rows["host"]["state"] == "ready"
    assert running_launcher("orphan", "local") is None  # a stale pointer does not block the name


def test_a_running_fleet_is_refused_before_anything_starts(registry, tmp_path, ours, capsys) -> None:
    _register(registry, tmp_path, "busy", ours, [])
    assert running_launcher("busy", "local")["launcher_pid"] == ours
    s = LauncherSettings(params=FleetParams(fleet="busy"), runs_dir=str(tmp_path / "runs"))
    rc, info = detach(s)
    assert rc == 2 and "already running" in info["error"] and str(ours) in info["error"]
    assert run(s) == 2
    assert "already running" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()  # no run directory left behind


def test_the_parts_of_a_split_fleet_run_side_by_side(registry, tmp_path, ours) -> None:
    """The fleet-host-a and fleet-host-b manifests on one machine: one fleet, two launchers."""
    _register(registry, tmp_path, "split", ours, [], part="host-b")
    part = {
        m: LauncherSettings(params=FleetParams(fleet="split"), manifest=str(MANIFEST_DIR / m)) for m in MANIFESTS
    }
    assert already_running(part["fleet-host-a.yaml"]) is None
    assert "already running" in already_running(part["fleet-host-b.yaml"])
    assert [(f["fleet"], f["manifest"]) for f in active_fleets()] == [("split", "host-b")]


def test_entries_that_are_not_ours_are_skipped(registry, tmp_path) -> None:
    (registry / "list@local.json").write_text("[1, 2]")
    (registry / "half@local.json").write_text("{")
    (registry / "odd@local.json").write_text(json.dumps({"fleet": "odd", "run_dir": 7}))
    assert active_fleets() == []


def test_a_recycled_pid_is_not_ours() -> None:
    """Only a command line with a services module or the mapc script counts, not any mention of it."""
    p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)  # services. mapc multiprocessing"])
    try:
        cmdline = Path(f"/proc/{p.pid}/cmdline")
        while b"sleep(60)" not in cmdline.read_bytes():
            time.sleep(0.01)  # the new command line shows a moment after Popen returns
        assert not is_ours(p.pid)
    finally:
        p.kill()
        p.wait()
