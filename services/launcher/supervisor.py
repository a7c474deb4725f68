"""Process supervision: start, watch, restart with backoff, stop (SIGINT -> wait -> SIGKILL).

Each service runs as ``python -m services.<role> ...`` in its own session and process group
(``start_new_session``), so a terminal's Ctrl-C reaches only the launcher, and stopping a service
signals its whole group (the host's solver worker included). Services get ``MAPC_WATCH_PARENT=1``
and stop by themselves if the launcher dies. :meth:`Supervisor.step` is the reconcile loop: call it
a few times a second; it never blocks.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .manifest import ProcessSpec

__all__ = ["ManagedProcess", "Supervisor", "is_ours", "kill_group", "pid_alive"]

log = logging.getLogger("mapc.launcher")


def pid_alive(pid: int) -> bool:
    """True if ``pid`` exists and is not a zombie."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return True


def is_ours(pid: int) -> bool:
    """``pid`` is alive and a process of this project: one of its arguments is a ``services.*`` module
    (``python -m services.host``) or the ``mapc`` script (guards against a recycled pid)."""
    try:
        args = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\x00")
    except OSError:
        return False
    ours = any(a.startswith(b"services.") or os.path.basename(a) == b"mapc" for a in args)
    return ours and pid_alive(pid)


def kill_group(pgid: int, sig: int) -> bool:
    """Signal a process group; False if it no longer exists."""
    try:
        os.killpg(pgid, sig)
        return True
    except ProcessLookupError:
        return False
    except PermissionError:
        log.warning("not allowed to signal process group %d", pgid)
        return False


@dataclass
class ManagedProcess:
    spec: ProcessSpec
    popen: subprocess.Popen | None = None
    state: str = "pending"  # pending starting ready backoff exited failed stopping stopped
    restarts: int = 0
    consecutive: int = 0
    started_mono: float | None = None
    next_start_mono: float | None = None
    returncode: int | None = None
    alive: bool = False  # its liveliness token is present
    alive_lost_mono: float | None = None
    exit_codes: list[int] = field(default_factory=list)

    @property
    def pid(self) -> int | None:
        return self.popen.pid if self.popen is not None else None

    def running(self) -> bool:
        return self.popen is not None and self.popen.poll() is None

    def to_json(self) -> dict[str, Any]:
        up = time.monotonic() - self.started_mono if self.started_mono and self.running() else None
        return {
            "name": self.spec.name,
            "role": self.spec.role,
            "id": self.spec.id,
            "pid": self.pid,
            "pgid": self.pid,
            "state": self.state,
            "alive": self.alive,
            "restarts": self.restarts,
            "uptime_s": None if up is None else round(up, 1),
            "returncode": self.returncode,
            "exit_codes": self.exit_codes[-10:],
            "argv": self.spec.argv,
        }


class Supervisor:
    """Runs a fleet's processes; ``event`` is called with (event, process name, details)."""

    def __init__(
        self,
        specs: list[ProcessSpec],
        log_dir: Path,
        env: dict[str, str] | None = None,
        event: Callable[[str, str, dict], None] | None = None,
        frozen_kill_s: float = 5.0,
    ):
        self.procs = {s.name: ManagedProcess(s) for s in specs}
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.env = {**os.environ, "MAPC_WATCH_PARENT": "1", "PYTHONUNBUFFERED": "1", **(env or {})}
        self._event = event or (lambda e, n, d: None)
        self.frozen_kill_s = frozen_kill_s
        self.stopping = False

    def by_key(self, role: str, sid: str) -> ManagedProcess | None:
        for p in self.procs.values():
            if p.spec.role == role and p.spec.id == sid:
                return p
        return None

    # -- starting ---------------------------------------------------------------------------
    def start(self, p: ManagedProcess) -> None:
        logf = open(self.log_dir / f"{p.spec.name}.log", "ab")  # noqa: SIM115 - handed to the child
        try:
            logf.write(
                f"\n===== {time.strftime('%Y-%m-%d %H:%M:%S')} start: {' '.join(p.spec.argv)}\n".encode()
            )
            logf.flush()
            p.popen = subprocess.Popen(
                p.spec.argv,
                stdin=subprocess.DEVNULL,
                stdout=logf,
                stderr=subprocess.STDOUT,
                env={**self.env, **p.spec.env},
                start_new_session=True,
                close_fds=True,
            )
        finally:
            logf.close()
        p.state = "starting"
        p.started_mono = time.monotonic()
        p.next_start_mono = None
        p.returncode = None
        p.alive_lost_mono = None
        self._event("started", p.spec.name, {"pid": p.pid, "restarts": p.restarts})

    def start_group(self, order: int) -> list[ManagedProcess]:
        group = [p for p in self.procs.values() if p.spec.start_order == order and p.state == "pending"]
        for p in group:
            self.start(p)
        return group

    def orders(self) -> list[int]:
        return sorted({p.spec.start_order for p in self.procs.values()})

    # -- liveliness -------------------------------------------------------------------------
    def on_alive(self, role: str, sid: str, present: bool) -> None:
        p = self.by_key(role, sid)
        if p is None:
            return
        now = time.monotonic()
        if present and not p.alive:
            p.alive = True
            p.alive_lost_mono = None
            if p.state == "starting":
                p.state = "ready"
                self._event("ready", p.spec.name, {"after_s": round(now - (p.started_mono or now), 2)})
            else:
                self._event("alive", p.spec.name, {})
        elif not present and p.alive:
            p.alive = False
            p.alive_lost_mono = now
            self._event("alive_lost", p.spec.name, {"pid": p.pid, "running": p.running()})

    # -- the reconcile loop -----------------------------------------------------------------
    def step(self) -> None:
        now = time.monotonic()
        for p in self.procs.values():
            if p.popen is not None and p.state in ("starting", "ready") and p.popen.poll() is not None:
                rc = p.popen.returncode
                p.returncode = rc
                p.exit_codes.append(rc)
                p.alive = False
                ran = now - (p.started_mono or now)
                if ran >= p.spec.restart.reset_after_s:
                    p.consecutive = 0
                self._event("exited", p.spec.name, {"returncode": rc, "ran_s": round(ran, 1)})
                if not self.stopping and p.spec.restart.wants_restart(rc, p.restarts):
                    p.consecutive += 1
                    delay = p.spec.restart.delay_s(p.consecutive)
                    p.state = "backoff"
                    p.next_start_mono = now + delay
                    self._event("restart_scheduled", p.spec.name, {"in_s": delay, "restarts": p.restarts + 1})
                else:
                    p.state = "exited" if rc == 0 else "failed"
            elif p.state == "backoff" and not self.stopping and now >= (p.next_start_mono or now):
                p.restarts += 1
                self.start(p)
            elif (
                p.state == "ready"
                and not p.alive
                and p.alive_lost_mono is not None
                and now - p.alive_lost_mono > self.frozen_kill_s
                and p.running()
            ):
                # token gone but the process still there: frozen (lease expired) -> kill, restart follows
                self._event("frozen_kill", p.spec.name, {"pid": p.pid})
                kill_group(p.pid, signal.SIGKILL)
                p.alive_lost_mono = None

    def all_ready(self, procs: list[ManagedProcess]) -> bool:
        return all(p.state == "ready" and p.alive for p in procs)

    # -- stopping ---------------------------------------------------------------------------
    def stop_all(self) -> None:
        """Reverse start order; per group SIGINT to every process group, wait, SIGKILL the rest."""
        self.stopping = True
        for order in reversed(self.orders()):
            group = [p for p in self.procs.values() if p.spec.start_order == order]
            live = [p for p in group if p.running()]
            for p in live:
                p.state = "stopping"
                kill_group(p.pid, signal.SIGINT)
            deadline = time.monotonic() + max((p.spec.stop_timeout_s for p in live), default=0)
            for p in live:
                try:
                    p.popen.wait(timeout=max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    self._event("stop_timeout", p.spec.name, {"pid": p.pid})
                    kill_group(p.pid, signal.SIGKILL)
                    p.popen.wait(timeout=5)
                # the group may hold children (the host's worker): make sure they are gone
                kill_group(p.pid, signal.SIGKILL)
                p.returncode = p.popen.returncode
                p.exit_codes.append(p.returncode)
                self._event("stopped", p.spec.name, {"returncode": p.returncode})
            for p in group:
                p.alive = False
                if p.state in ("stopping", "pending", "backoff", "starting", "ready"):
                    p.state = "stopped"
