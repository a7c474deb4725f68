"""``mapc fleet up --detach`` / ``status`` / ``down``: running fleets, found through the user's fleet registry."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from . import shm
from .app import LauncherSettings, already_running, log_tail, make_run_dir, registry_dir
from .supervisor import is_ours, kill_group, pid_alive

__all__ = ["active_fleets", "detach", "down", "launcher_argv", "to_stop"]


def _read(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def active_fleets() -> list[dict[str, Any]]:
    """Every registered fleet: its pointer, its state.json and whether its launcher lives.

    ``cwd`` is the launcher's working directory (None in the entries of launchers older than it).

    When the launcher is gone, state.json is its last word: each process is checked again and one
    that has exited is shown as ``gone``.
    """
    out = []
    d = registry_dir()
    for ptr in sorted(d.glob("*.json")) if d.is_dir() else []:
        p = _read(ptr)
        if not isinstance(p, dict) or not isinstance(p.get("run_dir"), str):
            continue  # not one of our entries
        state = _read(Path(p["run_dir"]) / "state.json")
        state = state if isinstance(state, dict) else {}
        pid = p.get("launcher_pid")
        launcher_alive = isinstance(pid, int) and is_ours(pid)
        procs = state.get("processes", [])
        if not launcher_alive:
            procs = [_recheck(q) for q in procs]
        out.append(
            {
                "fleet": p.get("fleet", ptr.stem),
                "manifest": p.get("manifest"),
                "cwd": p.get("cwd"),
                "pointer": str(ptr),
                "run_dir": p.get("run_dir"),
                "launcher_pid": pid,
                "launcher_alive": launcher_alive,
                "endpoints": state.get("endpoints") or p.get("endpoints") or [],
                "zenoh_login": p.get("zenoh_login"),  # the operator's login to a secure mesh (mesh.py)
                "insecure": bool(p.get("insecure")),
                "keys_dir": p.get("keys_dir"),  # a signed fleet's keys (None: unsigned, or a launcher before it)
                "status": state.get("status"),
                "processes": procs,
                "params": state.get("params", {}),
            }
        )
    return out


def _where(f: dict[str, Any]) -> str:
    """Where a registered fleet was started from: the launcher's working directory, the manifest, the run
    directory."""
    cwd = f"started in {f['cwd']}, " if f.get("cwd") else ""
    return f"{cwd}manifest {f['manifest']}, run dir {f['run_dir']}"


def to_stop(fleet: str | None, every: bool = False) -> tuple[list[dict[str, Any]], str | None]:
    """The registry entries ``mapc fleet down`` stops (:func:`active_fleets` rows), or why it stops none.

    ``every``: all. ``fleet``: that fleet's (one entry per manifest part); a name not in the registry is
    refused. Neither: the one fleet there is, nothing when there is none; several are refused, since the
    others may be another checkout's or another job's. A refusal lists the registered fleets.
    """
    fleets = active_fleets()
    names = sorted({f["fleet"] for f in fleets})
    if every or (fleet is None and len(names) <= 1):
        return fleets, None
    if fleet in names:
        return [f for f in fleets if f["fleet"] == fleet], None
    listing = "".join(
        f"\n  {f['fleet']}: launcher {f['launcher_pid']}{'' if f['launcher_alive'] else ' (gone)'}, {_where(f)}"
        for f in fleets
    )
    if fleet is None:
        return [], f"{len(names)} fleets are running; pick one with --fleet NAME, or stop them all with --all:{listing}"
    return [], f"no fleet {fleet!r} is running" + (f"; the registered ones:{listing}" if fleets else " (none is)")


def _recheck(proc: dict[str, Any]) -> dict[str, Any]:
    """A process row of an orphaned state.json, with ``alive`` as it is now."""
    pid = proc.get("pid")
    alive = isinstance(pid, int) and is_ours(pid)
    return {**proc, "alive": alive, "state": proc.get("state") if alive else "gone", "uptime_s": None}


def launcher_argv(s: LauncherSettings, run_dir: Path) -> list[str]:
    """The command line of a detached launcher running ``s`` in ``run_dir``."""
    p = s.params
    argv = [
        sys.executable,
        "-m",
        "services.launcher",
        "--fleet",
        p.fleet,
        "--scenario",
        p.scenario,
        "--network",
        p.network,
        "--mode",
        p.mode,
        "--seed",
        str(p.seed),
        "--time-scale",
        str(p.time_scale),
        "--runs-dir",
        str(s.runs_dir),
        "--run-dir",
        str(run_dir),
        "--listen",
        s.listen,
        "--no-summary",
    ]
    if p.vehicles is not None:
        argv += ["--vehicles", str(p.vehicles)]
    argv.append("--standby" if p.standby else "--no-standby")
    if p.record:
        argv.append("--record")
    if s.ros2:
        argv.append("--ros2")
    if not p.signing:
        argv.append("--no-signing")
    if p.keys is not None:
        argv += ["--keys", p.keys]
    if p.duration_s is not None:
        argv += ["--duration", str(p.duration_s)]
    if s.manifest:
        argv += ["--manifest", str(s.manifest)]
    if s.join:
        argv += ["--join", s.join]
    if p.zenoh_config:
        argv += ["--zenoh-config", p.zenoh_config]
    if p.insecure:
        argv.append("--insecure")
    return argv


def detach(s: LauncherSettings, timeout_s: float = 180.0) -> tuple[int, dict[str, Any]]:
    """Start the launcher in the background and wait until the fleet is running (or failed).

    (0, the fleet's state) when it runs; (1, with ``error``: the end of launcher.out) when it did not
    come up; (2, with ``error``) when a fleet of that name is running already (nothing is started).
    """
    refused = already_running(s)
    if refused:
        return 2, {"error": refused}
    run_dir = make_run_dir(s)
    with open(run_dir / "launcher.out", "ab") as out:
        proc = subprocess.Popen(
            launcher_argv(s, run_dir),
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            close_fds=True,
        )
    deadline = time.monotonic() + timeout_s
    state: dict[str, Any] = {}
    while time.monotonic() < deadline:
        state = _read(run_dir / "state.json") or {}
        if state.get("status") == "running":
            return 0, {"run_dir": str(run_dir), "launcher_pid": proc.pid, **state}
        if proc.poll() is not None:
            break
        time.sleep(0.2)  # polling another process's file: nothing to wait on
    tail = log_tail(run_dir / "launcher.out", 15)
    why = f"fleet {s.params.fleet} did not come up (launcher output in {run_dir / 'launcher.out'})"
    return 1, {
        "run_dir": str(run_dir),
        "launcher_pid": proc.pid,
        "returncode": proc.poll(),
        **state,
        "error": f"{why}:\n{tail}" if tail else why,
    }


def down(fleets: list[dict[str, Any]], timeout_s: float = 90.0) -> tuple[int, list[dict]]:
    """Stop these fleets (:func:`to_stop`): SIGTERM each launcher, wait, then sweep leftovers.

    The launcher stops its services (SIGINT, then SIGKILL) and writes the report. Whatever is still
    alive afterwards (a launcher that hung or was killed) is killed by process group from state.json.
    Returns (0 if nothing of ours is left, 1 otherwise; what was done per fleet). A pid that now runs
    something else (recycled) does not count, so a stale entry is cleared.
    """
    results = []
    rc = 0
    for f in fleets:
        res: dict[str, Any] = {
            "fleet": f["fleet"],
            "run_dir": f["run_dir"],
            "launcher_pid": f["launcher_pid"],
        }
        pid = f["launcher_pid"]
        if pid and f["launcher_alive"]:
            os.kill(int(pid), signal.SIGTERM)
            deadline = time.monotonic() + timeout_s
            while pid_alive(int(pid)) and time.monotonic() < deadline:
                time.sleep(0.1)  # not our child: no wait() possible
            if pid_alive(int(pid)):
                os.kill(int(pid), signal.SIGKILL)
                res["launcher_killed"] = True
        state = _read(Path(f["run_dir"]) / "state.json")
        state = state if isinstance(state, dict) else {"processes": f["processes"]}
        swept = []
        for p in state.get("processes", []):
            ppid = p.get("pid")
            if isinstance(ppid, int) and is_ours(ppid):
                kill_group(int(ppid), signal.SIGKILL)
                swept.append(p.get("name"))
        deadline = time.monotonic() + 2.0
        procs = state.get("processes", [])
        while time.monotonic() < deadline and any(p.get("pid") and is_ours(int(p["pid"])) for p in procs):
            time.sleep(0.05)  # SIGKILL is asynchronous: wait until the kernel has reaped them
        left = [p.get("name") for p in procs if p.get("pid") and is_ours(int(p["pid"]))]
        if pid and is_ours(int(pid)):
            left.append("launcher")
        removed = shm.release(state.get("shm") or []) if not left else []  # what killed processes left
        res.update(swept=swept, left=left, status=state.get("status"), shm_removed=len(removed))
        if left:
            rc = 1
        else:
            Path(f["pointer"]).unlink(missing_ok=True)
        results.append(res)
    return rc, results
