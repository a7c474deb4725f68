"""A fleet of more than a handful of vehicles on loopback: every service healthy at once, every vehicle
scored by the evaluator.

The fleet runs on a clock at a quarter of real time: eight vehicles localizing at 10 Hz, the world
rendering eight cameras, the channel, the host and the evaluator are more than two cores do in real
time (about 2.5 core-seconds per scenario second; sixteen vehicles about 5, see the README).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

pytestmark = [pytest.mark.integration, pytest.mark.slow]

VEHICLES = 8


def test_a_fleet_of_eight_comes_up_healthy_and_every_vehicle_is_scored(tmp_path, fleet_name, mapc, wait_for):
    up = mapc(
        "fleet", "up", "--detach", "--json", "--fleet", fleet_name, "--vehicles", str(VEHICLES),
        "--network", "ideal", "--time-scale", "0.25", "--runs-dir", str(tmp_path / "runs"),
        timeout=240,
    )  # fmt: skip
    assert up.returncode == 0, up.stdout + up.stderr
    run_dir = Path(json.loads(up.stdout)["run_dir"])
    ids = {f"cv{i}" for i in range(VEHICLES)}
    try:

        def every_service_ok():
            h = mapc("health", "--fleet", fleet_name, "--json", "--timeout", "3", cwd=tmp_path)
            rows = json.loads(h.stdout) if h.returncode == 0 and h.stdout.strip() else []
            # the world, the channel, the host and its standby (on by default), the evaluator
            return rows if len(rows) == VEHICLES + 5 and all(r["state"] == "ok" for r in rows) else None

        rows = wait_for(every_service_ok, timeout=240, what="every service ok at once", every=1.0)
        assert {r["id"] for r in rows if r["role"] == "vehicle"} == ids
        world = next(r for r in rows if r["role"] == "world")
        assert world["figures"]["vehicles"] == VEHICLES

        def scored():
            h = mapc("health", "--fleet", fleet_name, "--json", "--timeout", "3", cwd=tmp_path)
            rows = json.loads(h.stdout) if h.returncode == 0 and h.stdout.strip() else []
            ev = next((r for r in rows if r["role"] == "evaluator"), None)
            return ev if ev and (ev["figures"].get("evaluated") or 0) >= 30 else None

        wait_for(scored, timeout=120, what="30 fused frames scored", every=1.0)
    finally:
        down = mapc("fleet", "down", "--fleet", fleet_name, timeout=180, cwd=tmp_path)
    assert down.returncode == 0, down.stdout + down.stderr
    report = json.loads((run_dir / "report.json").read_text())
    assert report["summary"]["restarts"] == 0
    assert all(p["exit_codes"] and p["exit_codes"][-1] == 0 for p in report["processes"]), report["processes"]
    ev = json.loads((run_dir / "eval_summary.json").read_text())
    assert set(ev["vehicle_rmse_by_id_m"]) == ids  # every vehicle's fused pose was scored against the truth
    assert all(math.isfinite(v) for v in ev["vehicle_rmse_by_id_m"].values())
    assert set(ev["tx_msgs_total"]) == ids and min(ev["tx_msgs_total"].values()) > 10
    assert ev["object_rmse_m"] is not None and ev["delivered_fraction"] > 0.9
