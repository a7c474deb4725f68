"""The fleet registry: running fleets are found from any directory, a dead launcher's processes are
checked again, a fleet that runs already is refused before anything starts, and ``fleet down`` stops
only the fleet it is told to (or the only one)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.cli import main
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
def start_ours():
    """Starts live processes that count as ours (their command line names a services module): fake
    launchers, which SIGTERM ends."""
    procs = []

    def start() -> int:
        p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", "services.launcher"])
        procs.append(p)
        deadline = time.monotonic() + 10
        while not is_ours(p.pid) and time.monotonic() < deadline:
            time.sleep(0.01)  # /proc/<pid>/cmdline shows the new command line a moment after Popen returns
        return p.pid

    yield start
    for p in procs:
        p.kill()
        p.wait()


@pytest.fixture
def ours(start_ours):
    """A live process that counts as one of ours."""
    return start_ours()


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _register(
    registry, tmp_path, fleet: str, launcher_pid: int, processes: list[dict], part: str = "local", **extra
) -> Path:
    """A registry entry as the launcher writes it (``extra``: more pointer fields, e.g. ``cwd``); its pointer."""
    run_dir = tmp_path / f"run-{fleet}"
    run_dir.mkdir()
    (run_dir / "state.json").write_text(
        json.dumps({"status": "running", "endpoints": ["tcp/127.0.0.1:1"], "processes": processes})
    )
    pointer = {"fleet": fleet, "manifest": part, "run_dir": str(run_dir), "launcher_pid": launcher_pid, **extra}
    path = pointer_path(fleet, part)
    path.write_text(json.dumps(pointer))
    return path


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


def _two_fleets(registry, tmp_path, start_ours) -> dict[str, tuple[int, Path]]:
    """Fleets a and b, each with a live launcher, started in checkouts ``ck-a`` and ``ck-b``: name -> (pid, pointer)."""
    out = {}
    for name in ("a", "b"):
        pid = start_ours()
        out[name] = pid, _register(registry, tmp_path, name, pid, [], cwd=str(tmp_path / f"ck-{name}"))
    return out


def test_a_bare_down_stops_the_only_fleet(registry, tmp_path, ours, capsys) -> None:
    pointer = _register(registry, tmp_path, "solo", ours, [])
    assert main(["fleet", "down"]) == 0
    assert not is_ours(ours) and not pointer.exists()
    assert f"fleet solo down ({tmp_path / 'run-solo'}); no process left" in capsys.readouterr().out


def test_down_clears_a_stale_entry_whose_pids_run_something_else(registry, tmp_path, capsys) -> None:
    """A launcher and a service that are gone, their pids reused by a process that is not ours."""
    me = os.getpid()  # pytest: alive, not ours, and never signalled
    pointer = _register(registry, tmp_path, "stale", me, [{"name": "world", "pid": me, "restarts": 0}])
    assert main(["fleet", "down"]) == 0
    assert not pointer.exists() and "stale down" in capsys.readouterr().out


def test_a_bare_down_with_nothing_running_says_so_and_succeeds(registry, capsys) -> None:
    assert main(["fleet", "down"]) == 0
    assert capsys.readouterr().out == "no fleet is running\n"


def test_a_bare_down_with_several_fleets_stops_none_and_lists_them(registry, tmp_path, start_ours, capsys) -> None:
    """They may be another checkout's or another job's: the user picks."""
    fleets = _two_fleets(registry, tmp_path, start_ours)
    assert main(["fleet", "down"]) == 2
    assert all(is_ours(pid) and pointer.exists() for pid, pointer in fleets.values())
    out, err = capsys.readouterr()
    assert out == ""
    assert "2 fleets are running" in err and "--fleet NAME" in err and "--all" in err
    for name, (pid, _) in fleets.items():
        line = next(x for x in err.splitlines() if x.startswith(f"  {name}: "))
        assert f"launcher {pid}," in line and f"started in {tmp_path / f'ck-{name}'}," in line
        assert f"run dir {tmp_path / f'run-{name}'}" in line


def test_down_all_stops_every_fleet(registry, tmp_path, start_ours, capsys) -> None:
    fleets = _two_fleets(registry, tmp_path, start_ours)
    assert main(["fleet", "down", "--all", "--json"]) == 0
    assert sorted(r["fleet"] for r in json.loads(capsys.readouterr().out)) == ["a", "b"]
    assert not any(is_ours(pid) or pointer.exists() for pid, pointer in fleets.values())


def test_down_of_a_named_fleet_stops_that_one_only(registry, tmp_path, start_ours) -> None:
    fleets = _two_fleets(registry, tmp_path, start_ours)
    assert main(["fleet", "down", "--fleet", "b"]) == 0
    (pid_a, pointer_a), (pid_b, pointer_b) = fleets["a"], fleets["b"]
    assert is_ours(pid_a) and pointer_a.exists()
    assert not is_ours(pid_b) and not pointer_b.exists()


def test_down_of_an_unknown_fleet_is_an_error_naming_the_running_ones(registry, tmp_path, start_ours, capsys) -> None:
    fleets = _two_fleets(registry, tmp_path, start_ours)
    assert main(["fleet", "down", "--fleet", "typo"]) == 2
    assert all(is_ours(pid) and pointer.exists() for pid, pointer in fleets.values())
    err = capsys.readouterr().err
    assert "no fleet 'typo' is running" in err and "\n  a: " in err and "\n  b: " in err
    for _, pointer in fleets.values():
        pointer.unlink()
    assert main(["fleet", "down", "--fleet", "typo"]) == 2  # also with nothing running: a typo is a typo
    assert "(none is)" in capsys.readouterr().err


def test_status_says_where_each_fleet_was_started(registry, tmp_path, start_ours, capsys) -> None:
    _register(registry, tmp_path, "new", start_ours(), [], cwd="/home/me/checkout")
    _register(registry, tmp_path, "old", start_ours(), [])  # a launcher from before ``cwd`` was recorded
    assert main(["fleet", "status"]) == 0
    out = capsys.readouterr().out
    assert "  started in: /home/me/checkout\n" in out and out.count("started in") == 1
    assert f"  run dir: {tmp_path / 'run-old'}" in out
    assert main(["fleet", "status", "--json"]) == 0
    assert {f["fleet"]: f["cwd"] for f in json.loads(capsys.readouterr().out)} == {
        "new": "/home/me/checkout",
        "old": None,
    }
