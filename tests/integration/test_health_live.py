"""`mapc health` as a user reads it on a real fleet: `starting` in the cold start (exit 0), `finished`
after a replay ended (exit 0, not "not keeping up"), every line within 100 columns."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.integration, pytest.mark.slow]

HEALTHY = {"ok", "starting", "finished"}


def _health(mapc, fleet: str, table: bool = False) -> tuple[int, list[dict], str]:
    """(exit code, the --json rows, the table when asked for: a second call)."""
    js = mapc("health", "--fleet", fleet, "--json")
    rows = json.loads(js.stdout) if js.stdout.strip() else []
    return js.returncode, rows, mapc("health", "--fleet", fleet).stdout if table else ""


def test_a_cold_start_is_starting_and_a_replay_that_ended_is_finished(tmp_path, fleet_name, mapc, wait_for) -> None:
    runs = tmp_path / "runs"
    up = mapc("fleet", "up", "--detach", "--json", "--record", "--duration", "14", "--fleet", fleet_name,
              "--runs-dir", str(runs), timeout=240)  # fmt: skip
    assert up.returncode == 0, up.stdout + up.stderr
    run_dir = Path(json.loads(up.stdout)["run_dir"])
    seen: list[tuple[float, int, dict[str, str]]] = []
    try:
        while True:  # the first 10 s of the scenario (the world's clock, at time scale 1)
            rc, rows, table = _health(mapc, fleet_name, table=len(seen) == 1)
            world = next((r for r in rows if r["role"] == "world"), None)
            if world is not None and world.get("figures", {}).get("t", 0.0) >= 10.0:
                break
            states = {f"{r['role']}/{r['id']}": r["state"] for r in rows}
            seen.append((time.monotonic(), rc, states))
            if table:
                assert max(len(line) for line in table.splitlines()) <= 100, table
                assert "starting" in table, table
    finally:
        mapc("fleet", "down", "--fleet", fleet_name, timeout=120)
    assert len(seen) >= 2, seen  # (a call takes one to three seconds)
    assert all(rc == 0 for _, rc, _ in seen), [s for s in seen if s[1] != 0]
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
