"""Fixtures for multi-process tests: a loopback rendezvous, unique fleet names, service processes
in their own process groups (killed at teardown), liveliness watching, and waiting on conditions.

Every test gets its own rendezvous on a free loopback port and its own fleet name, multicast
scouting is off everywhere: parallel test runs cannot cross-talk.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest

from services.runtime import ZenohSettings, listening_locators, open_session

REPO = Path(__file__).resolve().parents[2]


def wait_for(cond: Callable[[], object], timeout: float, what: str = "condition", every: float = 0.05):
    """Poll ``cond`` until it returns something truthy; fail the test after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(every)


def process_groups_alive(pgids: set[int]) -> list[int]:
    """Pids of live (non-zombie) processes whose process group is in ``pgids``."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[0] != "Z" and int(fields[2]) in pgids:
            out.append(int(d.name))
    return out


class LivelinessWatch:
    """Records liveliness PUT/DELETE of a key pattern with their monotonic times."""

    def __init__(self, session, pattern: str):
        import zenoh

        self._cond = threading.Condition()
        self.alive: dict[str, float] = {}
        self.gone: dict[str, float] = {}

        def cb(sample):
            key = str(sample.key_expr)
            with self._cond:
                if sample.kind == zenoh.SampleKind.PUT:
                    self.alive[key] = time.monotonic()
                    self.gone.pop(key, None)
                else:
                    self.alive.pop(key, None)
                    self.gone[key] = time.monotonic()
                self._cond.notify_all()

        self._sub = session.liveliness().declare_subscriber(pattern, cb, history=True)

    def wait(self, pred: Callable[[], bool], timeout: float, what: str) -> None:
        with self._cond:
            if not self._cond.wait_for(pred, timeout):
                raise AssertionError(f"timed out after {timeout} s waiting for {what}; alive: {sorted(self.alive)}")

    def wait_alive(self, key: str, timeout: float = 60.0) -> None:
        self.wait(lambda: key in self.alive, timeout, f"liveliness token {key}")

    def wait_gone(self, key: str, timeout: float = 10.0) -> float:
        self.wait(lambda: key in self.gone, timeout, f"{key} to disappear")
        return self.gone[key]


@pytest.fixture
def fleet_name() -> str:
    return f"t{uuid.uuid4().hex[:10]}"


@pytest.fixture
def rendezvous():
    """A peer session listening on a free loopback port: (session, endpoint)."""
    session = open_session(ZenohSettings(mode="peer", listen=["tcp/127.0.0.1:0"], adminspace=True))
    try:
        endpoint = next(e for e in listening_locators(session) if "127.0.0.1" in e)
        yield session, endpoint
    finally:
        session.close()


@pytest.fixture
def spawn(tmp_path):
    """Start ``python -m <module> args...`` in its own process group, output to a log file."""
    procs: list[tuple[subprocess.Popen, Path]] = []

    def start(module: str, *args: str, name: str | None = None) -> subprocess.Popen:
        log = tmp_path / f"{name or module.rsplit('.', 1)[-1]}-{len(procs)}.log"
        with open(log, "wb") as f:
            p = subprocess.Popen(
                [sys.executable, "-m", module, *args],
                stdout=f,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                start_new_session=True,
                cwd=REPO,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
        p.log_path = log  # type: ignore[attr-defined]
        procs.append((p, log))
        return p

    yield start
    for p, _log in procs:
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait(timeout=10)
        leftover = process_groups_alive({p.pid})
        for pid in leftover:
            os.kill(pid, signal.SIGKILL)


def stop(proc: subprocess.Popen, timeout: float = 20.0) -> int:
    """SIGINT ``proc`` (started by ``spawn``) and return its exit code; if it has not exited within
    ``timeout``, fail with its thread stacks (services dump them on SIGUSR1) and the end of its log."""
    proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGUSR1)
        time.sleep(1.0)
        pytest.fail(f"{proc.args} did not stop within {timeout:.0f} s of SIGINT:\n{proc.log_path.read_text()[-6000:]}")


def mapc(
    *args: str, timeout: float = 120.0, env: dict | None = None, cwd: str | Path = REPO
) -> subprocess.CompletedProcess:
    """Run the ``mapc`` CLI (as ``python -m services.cli``) and capture its output."""
    return subprocess.run(
        [sys.executable, "-m", "services.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(REPO), **(env or {})},
    )


@pytest.fixture(name="wait_for")
def _wait_for_fixture():
    return wait_for


@pytest.fixture(name="stop")
def _stop_fixture():
    return stop


@pytest.fixture(name="mapc")
def _mapc_fixture():
    return mapc


@pytest.fixture
def watch_liveliness():
    return LivelinessWatch


@pytest.fixture(name="process_groups_alive")
def _groups_fixture():
    return process_groups_alive
