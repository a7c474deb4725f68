"""The launcher: brings a fleet up from a manifest, keeps it up, and takes it down leaving nothing behind.

It is the fleet's Zenoh rendezvous: a peer listening on a free loopback port (or ``--listen``),
which every service connects to (``--connect``) and any client can use (``mapc health``,
``mapc fleet status`` prints it). It starts the manifest's processes group by group, a group
when the previous ones are ready (their liveliness tokens seen), restarts crashed ones with
backoff (announcing crashes and restarts on the console), prints a live line each second and, at
the end (duration reached, Ctrl-C, SIGTERM or ``mapc fleet down``), stops everything in reverse
order, writes the report and prints its summary as a table (``--json``: one JSON line); see
:mod:`services.launcher.report`.

Run directory ``runs/<fleet>-<timestamp>/``: ``config.json`` (resolved manifest and parameters),
``state.json`` (live process table, endpoints, launcher pid), ``events.jsonl``, ``metrics.jsonl``
(the evaluator's metrics, one line a second), ``logs/<process>.log``, and at the end
``report.json`` plus the evaluator's ``birdseye.png`` and ``eval_summary.json``. While it runs, a
pointer to the run directory is in the user's fleet registry (:func:`registry_dir`),
so that ``mapc fleet status/down`` and ``mapc health`` find the fleet from any directory.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from mapcontainer.config import ConfigError, validate_model
from mapcontainer.security import (
    CA_NAME,
    VERIFY_WINDOW_S,
    Verifier,
    load_certificate,
    unwrap,
    write_fleet_keys,
)
from schemas import EvalMetrics, Rejection, decode
from schemas.topics import topic

from ..health import split_key
from ..runtime import (
    ZenohSettings,
    listening_locators,
    open_session,
    time_scale_arg,
    write_json,
    zenoh_config,
    zenoh_error_text,
)
from . import mesh, shm
from .manifest import FleetParams, ProcessSpec, keys_dir, load_manifest, manifest_path, resolve, vehicle_ids
from .report import console_event, down_reasons, format_report, make_summary, scenario_time, summary_line
from .supervisor import Supervisor, is_ours

__all__ = [
    "LauncherSettings",
    "already_running",
    "log_tail",
    "main",
    "make_run_dir",
    "new_run_dir",
    "parse_args",
    "plan",
    "pointer_path",
    "registry_dir",
    "run",
    "running_launcher",
]

log = logging.getLogger("mapc.launcher")


class LauncherSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    params: FleetParams
    manifest: str | None = None
    runs_dir: str = Field(default_factory=lambda: os.environ.get("MAPC_RUNS_DIR", "runs"))
    run_dir: str | None = None
    listen: str = "tcp/127.0.0.1:0"
    join: str | None = Field(None, description="join this router as a client instead of being the rendezvous")
    summary: bool = Field(True, description="the live line each second")
    ros2: bool = Field(False, description="with record: also write the recording as a ROS 2 bag, <run dir>/ros2/")
    json_summary: bool = Field(False, description="end with the summary as one JSON line instead of the table")
    frozen_kill_s: float = 5.0
    drain_s: float = 2.0


def _absolute(path: str | None) -> str | None:
    return None if path is None else str(Path(path).resolve())


def registry_dir() -> Path:
    """The user's running fleets, one pointer file each (:func:`pointer_path`), whichever directory
    they run in: ``$MAPC_STATE_DIR/fleets``, else ``$XDG_STATE_HOME/mapcontainer/fleets`` (by default
    ``~/.local/state/mapcontainer/fleets``).
    """
    if os.environ.get("MAPC_STATE_DIR"):
        return Path(os.environ["MAPC_STATE_DIR"]) / "fleets"
    state = os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state"
    return Path(state) / "mapcontainer" / "fleets"


def pointer_path(fleet: str, part: str) -> Path:
    """The registry entry of one launcher: fleet ``fleet`` run from the manifest named ``part``.

    A fleet split over machines has one launcher per manifest (fleet-host-a and fleet-host-b);
    run on one machine, both parts are registered side by side and ``fleet down`` stops both.
    """
    return registry_dir() / f"{fleet}@{part}.json"


def running_launcher(fleet: str, part: str) -> dict[str, Any] | None:
    """The registry's pointer of that launcher if it is alive (a stale pointer does not count)."""
    try:
        ptr = json.loads(pointer_path(fleet, part).read_text())
    except (OSError, ValueError):
        return None
    pid = ptr.get("launcher_pid") if isinstance(ptr, dict) else None
    return ptr if isinstance(pid, int) and is_ours(pid) else None


def already_running(s: LauncherSettings) -> str | None:
    """Why the fleet of ``s`` cannot start (a launcher runs it from the same manifest), or None."""
    fleet = s.params.fleet
    other = running_launcher(fleet, load_manifest(s.manifest).name)
    if other is None:
        return None
    return (
        f"fleet {fleet!r} is already running (launcher pid {other['launcher_pid']}, {other.get('run_dir')}); "
        "use another --fleet or `mapc fleet down`"
    )


def make_run_dir(s: LauncherSettings) -> Path:
    """The run's directory (``--run-dir``, else a new one under ``--runs-dir``), made and absolute;
    ConfigError when it cannot be made."""
    run_dir = Path(s.run_dir) if s.run_dir else new_run_dir(s.runs_dir, s.params.fleet)
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot make the run directory {run_dir}: {exc.strerror}") from None
    return run_dir.resolve()


def write_host_map(path: Path, params: FleetParams) -> Path:
    """The HD map the run's vehicles carry (the scenario's, with its seed's map error) as a file: the host
    container reads its map from a file (``--map``), as a deployment with a real map does."""
    from mapcontainer.hdmap.io import save_map
    from mapcontainer.sim.config import load_scenario
    from mapcontainer.sim.errors import published_map

    return save_map(published_map(load_scenario(params.scenario), params.seed), path)


def new_run_dir(runs_dir: str | Path, fleet: str) -> Path:
    base = Path(runs_dir) / f"{fleet}-{time.strftime('%Y%m%d-%H%M%S')}"
    d, i = base, 1
    while d.exists():
        i += 1
        d = base.with_name(f"{base.name}-{i}")
    return d


def secure_mesh(s: LauncherSettings) -> bool:
    """Whether the launcher makes the fleet's authenticated, least-privilege mesh (services.launcher.mesh):
    unless ``--insecure``, or the mesh is the user's (``--join`` a router, ``--zenoh-config`` a file)."""
    return not (s.params.insecure or s.join or s.params.zenoh_config)


def plan(s: LauncherSettings, run_dir: str | Path, connect: str) -> list[ProcessSpec]:
    """The processes to run; ConfigError (before anything starts) for an unknown scenario or network."""
    from mapcontainer.channel import load_profile
    from mapcontainer.security import CA_NAME, load_certificate
    from mapcontainer.sim.config import load_scenario

    load_scenario(s.params.scenario)
    load_profile(s.params.network)
    if s.params.signing and s.params.keys is not None:  # the given keys: their CA must be readable now
        load_certificate(s.params.keys, CA_NAME)
    zc = s.params.zenoh_config
    if s.join:  # the launcher's own session, as run() opens it: Zenoh's objections now, not later
        zenoh_config(ZenohSettings(mode="client", connect=[s.join], config_file=zc))
    else:
        zenoh_config(ZenohSettings(mode="peer", listen=[s.listen], adminspace=True, config_file=zc))
    logins = Path(run_dir) / "zenoh" if secure_mesh(s) else None
    return resolve(load_manifest(s.manifest), s.params, run_dir, connect, logins=logins)


def add_fleet_args(p: argparse.ArgumentParser, defaults: FleetParams | None = None) -> None:
    """The ``fleet up`` options (shared by ``mapc fleet up`` and ``python -m services.launcher``)."""
    d = defaults or FleetParams()
    p.add_argument("--scenario", default=None, help=f"scenario preset (default {d.scenario})")
    p.add_argument("--vehicles", type=int, default=None, help="connected vehicles (default: the scenario's)")
    p.add_argument("--network", default=None, help=f"network profile (default {d.network})")
    p.add_argument("--duration", type=float, default=None, help="scenario seconds (default: until stopped)")
    p.add_argument("--fleet", default=None, help=f"fleet name, the key namespace (default {d.fleet})")
    p.add_argument("--mode", choices=["distributed", "centralized"], default=None, help="default distributed")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument(
        "--time-scale",
        type=time_scale_arg,
        default=None,
        help="scenario seconds per wall second, or auto (default): as fast as real time, the world's clock "
        "pausing while a vehicle or the host is still on the previous frame, so that every frame is processed",
    )
    p.add_argument(
        "--no-signing",
        dest="signing",
        action="store_false",
        default=None,
        help="vehicles send unsigned messages (for comparison; default: signed with a test CA made for the run)",
    )
    p.add_argument("--keys", default=None, help="the fleet's keys directory (mapc keys init) instead of the run's own")
    p.add_argument(
        "--standby",
        action="store_true",
        default=None,
        help="run a warm standby host that publishes the fused state while the host is gone (the local default)",
    )
    p.add_argument(
        "--no-standby",
        dest="standby",
        action="store_false",
        help="no warm standby: after a crash of the host, no fused output until it is restarted (seconds)",
    )
    p.add_argument(
        "--downlink",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the host sends every vehicle what the others know about its pose, through the channel emulator",
    )
    p.add_argument(
        "--record",
        action="store_true",
        default=None,
        help="record every message of the fleet to <run dir>/recording.mcap (mapc record info, mapc replay)",
    )
    p.add_argument(
        "--ros2",
        action="store_true",
        help="with --record: at the end also write <run dir>/ros2/, a ROS 2 bag (mapc record export --ros2)",
    )
    p.add_argument(
        "--manifest",
        default=None,
        help="fleet manifest: a name (fleet, fleet-host-a, fleet-host-b) or a YAML file (default fleet)",
    )
    p.add_argument("--runs-dir", default=None, help="where run directories go (default ./runs, env MAPC_RUNS_DIR)")
    p.add_argument("--run-dir", default=None, help=argparse.SUPPRESS)
    p.add_argument("--listen", default="tcp/127.0.0.1:0", help="the rendezvous endpoint (port 0: a free one)")
    p.add_argument(
        "--join",
        default=None,
        help="multi-host: join this host's router (client) instead of being the rendezvous",
    )
    p.add_argument(
        "--zenoh-config",
        default=None,
        help="Zenoh JSON5 file for the launcher and every service ({zenoh_config} in the manifest)",
    )
    p.add_argument(
        "--insecure",
        action="store_true",
        default=None,
        help="the open Zenoh mesh of old: no login, no access control (debugging; health and status say so)",
    )
    p.add_argument("--no-summary", action="store_true", help="no live line (start, ready and final lines stay)")


def settings_from_args(a: argparse.Namespace) -> LauncherSettings:
    manifest = load_manifest(a.manifest)
    over = {
        "fleet": a.fleet,
        "scenario": a.scenario,
        "vehicles": a.vehicles,
        "network": a.network,
        "duration_s": a.duration,
        "mode": a.mode,
        "seed": a.seed,
        "time_scale": a.time_scale,
        "standby": a.standby,
        "record": a.record,
        "downlink": a.downlink,
        "signing": True if a.keys is not None and a.signing is None else a.signing,  # keys given: signed
        "keys": a.keys,
        "zenoh_config": a.zenoh_config,
        "insecure": a.insecure,
    }
    params = manifest.defaults.model_copy(update={k: v for k, v in over.items() if v is not None})
    params = validate_model(FleetParams, params.model_dump(), "the command line")  # ConfigError, not a traceback
    kw: dict[str, Any] = {
        "params": params,
        "manifest": a.manifest,
        "run_dir": a.run_dir,
        "listen": a.listen,
        "join": a.join,
        "summary": not a.no_summary,
        "json_summary": bool(getattr(a, "json", False)),
    }
    if a.runs_dir:
        kw["runs_dir"] = a.runs_dir
    if getattr(a, "ros2", False):
        if not params.record:
            raise ConfigError("--ros2 writes the recording as a ROS 2 bag: give --record too")
        kw["ros2"] = True
    return LauncherSettings(**kw)


def parse_args(argv: list[str] | None = None) -> LauncherSettings:
    p = argparse.ArgumentParser(prog="python -m services.launcher", description=__doc__.splitlines()[0])
    add_fleet_args(p)
    return settings_from_args(p.parse_args(argv))


# ---------------------------------------------------------------------------------- the run


class _Run:
    def __init__(self, s: LauncherSettings, run_dir: Path):
        self.s = s
        self.run_dir = run_dir
        self.events_f = open(run_dir / "events.jsonl", "a")  # noqa: SIM115 - closed in run()
        self.metrics_f = open(run_dir / "metrics.jsonl", "a")  # noqa: SIM115
        self.lock = threading.RLock()  # events are written from inside supervisor calls made under it
        self.latest_metrics: dict | None = None
        self.stop = threading.Event()
        self.interrupted = False  # Ctrl-C (SIGINT): the run is cut short, exit 130 after the report
        self.t0 = time.monotonic()
        self.started_wall = time.time()
        self.endpoints: list[str] = []
        self.status = "starting"
        self.sup: Supervisor | None = None
        self.verifier: Verifier | None = None  # signed fleets: the metrics believed are the evaluator's, verified
        self.metrics_refused: dict[str, int] = {}
        self.login: str | None = None  # the operator's Zenoh login (a secure mesh): mapc health etc. use it
        self.shm: set[str] = set()  # shared-memory segments the fleet's processes mapped (removed at the end)

    def event(self, event: str, name: str, details: dict) -> None:
        rec = {
            "t_wall": round(time.time(), 3),
            "t_run": round(time.monotonic() - self.t0, 3),
            "event": event,
            "process": name,
            **details,
        }
        with self.lock:
            self.events_f.write(json.dumps(rec) + "\n")
            self.events_f.flush()
        stopping = self.sup is not None and self.sup.stopping
        crashed = event == "exited" and details.get("returncode") != 0 and not stopping
        trouble = crashed or event in ("frozen_kill", "stop_timeout")
        log.log(logging.WARNING if trouble else logging.INFO, "%s %s %s", name, event, details or "")
        said = console_event(event, name, details, stopping)
        if said:
            print(f"{rec['t_run']:6.1f}s {said}", flush=True)

    def on_metrics(self, sample) -> None:
        inner = unwrap(sample.payload.to_bytes(), self.verifier, time.time(), "evaluator")
        msg = inner if isinstance(inner, Rejection) else decode(inner, EvalMetrics)
        if isinstance(msg, Rejection):
            with self.lock:
                self.metrics_refused[msg.reason] = self.metrics_refused.get(msg.reason, 0) + 1
            return
        m = msg.model_dump(mode="json")
        with self.lock:
            self.latest_metrics = m
            self.metrics_f.write(json.dumps(m) + "\n")
            self.metrics_f.flush()

    def state(self) -> dict:
        return {
            "fleet": self.s.params.fleet,
            "status": self.status,
            "launcher_pid": os.getpid(),
            "run_dir": str(self.run_dir),
            "endpoints": self.endpoints,
            "zenoh_login": self.login,
            "insecure": self.s.params.insecure,
            "started_wall": self.started_wall,
            "updated_wall": time.time(),
            "params": self.s.params.model_dump(),
            "processes": [p.to_json() for p in self.sup.procs.values()] if self.sup else [],
            "shm": sorted(self.shm),
        }

    def write_state(self) -> None:
        if self.sup is not None:
            self.shm |= shm.mapped([p.pid for p in self.sup.procs.values() if p.pid], [os.getpid()])
        write_json(self.run_dir / "state.json", self.state())


def _install_signals(r: _Run) -> dict:
    old = {}

    def on_signal(signum: int, _frame) -> None:
        r.interrupted = r.interrupted or signum == signal.SIGINT
        r.stop.set()

    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            old[sig] = signal.signal(sig, on_signal)
    return old


def run(s: LauncherSettings) -> int:
    """Bring the fleet up, supervise it until the end, stop it and write the report. Exit code."""
    fleet = s.params.fleet
    plan(s, "<run_dir>", "<connect>")  # configuration errors before anything starts
    refused = already_running(s)
    if refused:
        print(f"mapc: {refused}", file=sys.stderr)
        return 2
    part = load_manifest(s.manifest).name
    pointer = pointer_path(fleet, part)
    pointer.parent.mkdir(parents=True, exist_ok=True)
    run_dir = make_run_dir(s)
    logging.basicConfig(
        level=logging.INFO,
        format="%(asctime)s %(levelname)-7s launcher %(message)s",
        handlers=[logging.FileHandler(run_dir / "launcher.log")],
        force=True,
    )
    r = _Run(s, run_dir)
    old_handlers = _install_signals(r)
    session = None
    rc = 0
    try:
        zc = s.params.zenoh_config
        if s.join:  # multi-host: this host's router is the meeting point
            session = open_session(ZenohSettings(mode="client", connect=[s.join], config_file=zc))
            r.endpoints = [s.join]
        elif secure_mesh(s):  # the fleet's router: every process logs in, each may use its own keys only
            router = mesh.write_mesh(run_dir, plan(s, run_dir, "<connect>"), s.params, s.listen)
            session = open_session(ZenohSettings(listen=[s.listen], adminspace=True, config_file=str(router)))
            r.endpoints = listening_locators(session)
            r.login = str(mesh.login_path(run_dir, mesh.OPS))
        else:
            session = open_session(ZenohSettings(mode="peer", listen=[s.listen], adminspace=True, config_file=zc))
            r.endpoints = listening_locators(session)
        if not r.endpoints:
            raise RuntimeError("could not read the rendezvous endpoint from the Zenoh admin space")
        connect = next((e for e in r.endpoints if "127.0.0.1" in e), r.endpoints[0])
        specs = plan(s, run_dir, connect)
        if s.params.signing and s.params.keys is None:  # a test CA and the fleet's credentials for this run
            signers = [p.id for p in specs if p.role != "vehicle"]  # every service signs its health status
            write_fleet_keys(run_dir / "keys", vehicle_ids(s.params), validity_s=7 * 86400.0, services=signers)
        if s.params.signing:
            ca = load_certificate(keys_dir(s.params, run_dir), CA_NAME)
            r.verifier = Verifier(ca, window_s=VERIFY_WINDOW_S)
        write_host_map(run_dir / "map.geojson", s.params)
        write_json(
            run_dir / "config.json",
            {
                "manifest": str(manifest_path(s.manifest)),
                "params": s.params.model_dump(),
                "settings": s.model_dump(),
                "endpoints": r.endpoints,
                "processes": [p.to_json() for p in specs],
            },
        )
        sup = r.sup = Supervisor(specs, run_dir / "logs", event=r.event, frozen_kill_s=s.frozen_kill_s)
        write_json(
            pointer,
            {
                "fleet": fleet,
                "manifest": part,
                "run_dir": str(run_dir.resolve()),
                "launcher_pid": os.getpid(),
                "endpoints": r.endpoints,
                "cwd": os.getcwd(),
                "zenoh_login": r.login,
                "insecure": s.params.insecure,
                "keys_dir": _absolute(keys_dir(s.params, run_dir)),  # its CA: mapc health verifies statuses
            },
        )
        r.write_state()

        def on_alive(sample) -> None:
            import zenoh

            role, sid = split_key(str(sample.key_expr))
            with r.lock:
                sup.on_alive(role, sid, sample.kind == zenoh.SampleKind.PUT)

        keep = [session.liveliness().declare_subscriber(topic("alive").pattern(fleet=fleet), on_alive, history=True)]
        keep.append(
            session.declare_subscriber(topic("metrics").key(fleet=fleet), r.on_metrics)
        )  # until session.close()
        print(f"fleet {fleet}: {len(specs)} processes, rendezvous {connect}, run dir {run_dir}", flush=True)

        # start, group by group
        for order in sup.orders():
            with r.lock:
                group = sup.start_group(order)
            deadline = time.monotonic() + max(p.spec.ready_timeout_s for p in group)
            while not r.stop.is_set():
                with r.lock:
                    sup.step()
                    ready = sup.all_ready(group)
                    # a process that dies before it was ever ready has a configuration or code problem:
                    # restarting it will not help, so the launch fails with its log
                    crashed = [p for p in group if p.exit_codes and p.state != "ready"]
                if ready:
                    names = ", ".join(p.spec.name for p in group)
                    print(f"{time.monotonic() - r.t0:6.1f}s ready: {names}", flush=True)
                    break
                if crashed or time.monotonic() > deadline:
                    missing = [p.spec.name for p in group if not (p.state == "ready" and p.alive)]
                    print(f"mapc: not ready: {', '.join(missing)} (see {run_dir / 'logs'})", file=sys.stderr)
                    for p in crashed:
                        tail = log_tail(run_dir / "logs" / f"{p.spec.name}.log", 15) or "(no log)"
                        print(
                            f"--- {p.spec.name} exited with {p.exit_codes[-1]}; its log ends:\n{tail}",
                            file=sys.stderr,
                        )
                    rc = 1
                    r.stop.set()
                    break
                r.write_state()
                r.stop.wait(0.1)
            if r.stop.is_set():
                break
        if not r.stop.is_set():
            r.status = "running"
            r.event("fleet_ready", "launcher", {"after_s": round(time.monotonic() - r.t0, 2)})
        r.write_state()

        # supervise
        next_print = time.monotonic()
        completed_at = None
        world = next((p for p in sup.procs.values() if p.spec.role == "world"), None)
        while not r.stop.is_set():
            with r.lock:
                sup.step()
                up = sum(p.alive for p in sup.procs.values())
                metrics = r.latest_metrics
            if world is not None and completed_at is None and world.state == "exited" and world.returncode == 0:
                completed_at = time.monotonic()
                r.event("completed", "world", {"drain_s": s.drain_s})
            if completed_at is not None and time.monotonic() - completed_at >= s.drain_s:
                break
            now = time.monotonic()
            if now >= next_print:
                next_print += 1.0
                r.write_state()
                if s.summary:
                    with r.lock:
                        why = down_reasons([p.to_json() for p in sup.procs.values()])
                    t = scenario_time(run_dir, time.time_ns())
                    t = t if t is None or s.params.duration_s is None else min(t, s.params.duration_s)
                    print(summary_line(t, s.params.duration_s, up, len(sup.procs), metrics, why), flush=True)
            r.stop.wait(0.2)
    except Exception as e:
        log.exception("launcher failed")
        print(f"mapc: launcher failed: {zenoh_error_text(e)}", file=sys.stderr)
        rc = 1
    finally:
        r.status = "stopping"
        if r.sup is not None:
            r.write_state()
            print("stopping ...", flush=True)
            r.sup.stop_all()
        r.status = "stopped"
        if session is not None:
            session.close()
        if r.shm:  # what killed processes left in /dev/shm (a clean exit removes its own)
            r.event("shm_released", "launcher", {"removed": len(shm.release(r.shm))})
        if r.sup is not None:
            summary = write_report(r)["summary"]
            r.write_state()
            print(json.dumps(summary) if s.json_summary else format_report(summary), flush=True)
            if s.ros2:
                export_bag(r.run_dir, json_line=s.json_summary)
        r.events_f.close()
        r.metrics_f.close()
        try:
            if json.loads(pointer.read_text()).get("launcher_pid") == os.getpid():
                pointer.unlink()
        except (OSError, ValueError):
            pass
        for sig, h in old_handlers.items():
            signal.signal(sig, h)
    return 130 if rc == 0 and r.interrupted else rc


def export_bag(run_dir: Path, json_line: bool) -> None:
    """The run's recording as a ROS 2 bag in ``run_dir/ros2`` (``--ros2``), and a line saying so."""
    from mapcontainer.recording import RecordingError
    from mapcontainer.recording.ros2 import export_ros2

    rec = run_dir / "recording.mcap"
    try:
        doc = export_ros2(rec, run_dir / "ros2")
    except (RecordingError, ConfigError, OSError) as exc:
        print(f"mapc: no ROS 2 bag: {exc}", file=sys.stderr, flush=True)
        return
    line = json.dumps({"ros2": doc}) if json_line else f"ROS 2 bag: {doc['bag']} ({doc['messages']} messages)"
    print(line, flush=True)


def log_tail(path: Path, n: int) -> str:
    """The last ``n`` lines of a log file; empty when there is none."""
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


def write_report(r: _Run) -> dict:
    """report.json: processes (restarts, exit codes), the last metrics and the evaluator's summary."""
    ev_path = r.run_dir / "eval_summary.json"
    try:
        ev = json.loads(ev_path.read_text())
    except (OSError, ValueError):
        ev = None
    procs = [p.to_json() for p in r.sup.procs.values()]
    params = r.s.params.model_dump()
    summary = make_summary(r.s.params.fleet, r.run_dir, params, procs, ev, time.monotonic() - r.t0)
    report = {
        "summary": summary,
        "params": params,
        "started_wall": r.started_wall,
        "ended_wall": time.time(),
        "endpoints": r.endpoints,
        "processes": procs,
        "last_metrics": r.latest_metrics,
        "metrics_refused": r.metrics_refused,
        "evaluation": ev,
    }
    write_json(r.run_dir / "report.json", report)
    return report


def main(s: LauncherSettings) -> int:
    return run(s)
