"""`mapc health` as a user reads it on a real fleet: `starting` in the cold start (exit 0), `finished`
after a replay ended (exit 0, not "not keeping up"), every line within 100 columns."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from services.health import exit_code, fleet_health
from services.runtime import ZenohSettings, open_session

pytestmark = [pytest.mark.integration, pytest.mark.slow]

HEALTHY = {"ok", "starting", "finished"}


def _health(mapc, fleet: str, table: bool = False) -> tuple[int, list[dict], str]:
    """(exit code, the --json rows, the table when asked for: a second call)."""
    js = mapc("health", "--fleet", fleet, "--json")
    rows = json.loads(js.stdout) if js.stdout.strip() else []
    return js.returncode, rows, mapc("health", "--fleet", fleet).stdout if table else ""


def _world_t(rows: list[dict]) -> float:
    """The world's scenario time in health rows (0 before it answers)."""
    world = next((r for r in rows if r["role"] == "world"), None)
    return 0.0 if world is None else world.get("figures", {}).get("t", 0.0)


def test_a_cold_start_is_starting_and_a_replay_that_ended_is_finished(tmp_path, fleet_name, mapc, wait_for) -> None:
    runs = tmp_path / "runs"
    up = mapc("fleet", "up", "--detach", "--json", "--record", "--duration", "14", "--fleet", fleet_name,
              "--runs-dir", str(runs), timeout=240)  # fmt: skip
    assert up.returncode == 0, up.stdout + up.stderr
    run_dir = Path(json.loads(up.stdout)["run_dir"])
    state = json.loads((run_dir / "state.json").read_text())
    endpoint = next(e for e in state["endpoints"] if "127.0.0.1" in e)
    seen: list[tuple[float, int, dict[str, str]]] = []  # (scenario time, exit code, states)
    health_notes: dict[str, str | None] = {}  # why a service was not healthy
    session = open_session(ZenohSettings(connect=[endpoint], config_file=state["zenoh_login"]))  # the operator
    try:
        # `mapc health` itself at once (a call takes a second or more), then polled in process
        rc, rows, table = _health(mapc, fleet_name, table=True)
        t_cli = _world_t(rows)
        assert rc == 0 and t_cli < 10.0, (rc, t_cli, rows)
        assert max(len(line) for line in table.splitlines()) <= 100, table
        assert any(r["role"] == "vehicle" and r["state"] == "starting" for r in rows), table
        while True:  # the first 10 s of the scenario (the world's clock, at time scale 1)
            views = fleet_health(session, fleet_name, expected={(r["role"], r["id"]) for r in rows}, timeout_s=0.5)
            rows_now = [v.to_json() for v in views]
            t = _world_t(rows_now)
            if t >= 10.0:
                break
            seen.append((t, exit_code(views), {f"{v.role}/{v.id}": v.state for v in views}))
            bad = [v for v in views if v.state not in HEALTHY]
            health_notes.update({f"{v.role}/{v.id}": v.status and v.status.last_error for v in bad})
            time.sleep(0.2)
    finally:
        session.close()
        down = mapc("fleet", "down", "--fleet", fleet_name, timeout=120)
    # a detached fleet's down prints the run's closing table, as the foreground fleet does
    assert down.returncode == 0, down.stderr
    assert down.stdout.startswith(f"fleet {fleet_name}: paper-urban, distributed, network dsrc;"), down.stdout
    assert "RMSE whole run" in down.stdout and "  objects " in down.stdout, down.stdout
    assert len(seen) >= 5, seen
    unhealthy = [(t, {k: st for k, st in states.items() if st not in HEALTHY}) for t, rc, states in seen if rc != 0]
    assert not unhealthy, (unhealthy, health_notes)
    assert all(set(states.values()) <= HEALTHY for _, _, states in seen)
    starting = [k for _, _, states in seen for k, st in states.items() if st == "starting"]
    assert any(k.startswith("vehicle/") for k in starting), seen  # cold starts search for their poses

    # the recording replayed onto a fleet of a host and an evaluator: once it ended, they say finished
    (rec,) = run_dir.glob("recording.mcap")
    again = f"{fleet_name}r"
    up = mapc("fleet", "up", "--manifest", "replay", "--fleet", again, "--no-signing", "--detach", "--json",
              "--runs-dir", str(tmp_path / "replay-runs"), timeout=240)  # fmt: skip
    assert up.returncode == 0, up.stdout + up.stderr
    try:
        r = mapc("replay", str(rec), "--fleet", again, "--speed", "2", timeout=240)
        assert r.returncode == 0, r.stderr[-2000:]

        def finished():
            rc, rows, table = _health(mapc, again, table=True)
            host = next((x for x in rows if x["role"] == "host"), None)
            return (rc, host, table) if host is not None and host["state"] == "finished" else None

        rc, host, table = wait_for(finished, timeout=30, what="the host to say finished", every=0.5)
        assert rc == 0, table
        assert "keeping up" not in (host.get("last_error") or "")
        assert "no world runs" in host["last_error"]
        assert max(len(line) for line in table.splitlines()) <= 100, table
    finally:
        mapc("fleet", "down", "--fleet", again, timeout=120)
