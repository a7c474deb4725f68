"""mapc experiment scale end to end on the small SUMO grid (sumo-grid; the default scene, sumo-town, costs
minutes per run) at two fleet sizes (the roads extra)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytest.importorskip("libsumo")  # the roads extra; CI installs it
pytestmark = pytest.mark.slow


def test_experiment_scale_runs_both_modes_and_measures_cost_traffic_and_accuracy(tmp_path):
    out = tmp_path / "scale"
    proc = subprocess.run(
        [sys.executable, "-m", "mapcontainer.cli", "experiment", "scale", "--out", str(out), "--sizes", "2,4", "--scenario", "sumo-grid",
         "--duration", "4", "--warmup", "2", "--quiet"],
        capture_output=True, text=True, timeout=900, check=True,
    )  # fmt: skip
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert summary["points"] == 4
    doc = json.loads((out / "results.json").read_text())
    rows = doc["rows"]
    from mapcontainer.fusion.compiled import COMPILED

    assert doc["meta"]["host_compiled"] is COMPILED
    for mode in ("distributed", "centralized"):  # the largest N up to which every size's cycle fits 100 ms
        cpu = {r["vehicles"]: r["host_cpu_ms_per_cycle"] for r in rows if r["mode"] == mode}
        fits = [n for n in (2, 4) if all(cpu[m] <= 100.0 for m in (2, 4) if m <= n)]
        assert doc["analysis"][mode]["realtime_vehicles"] == (fits[-1] if fits else None)
    by = {(r["mode"], r["vehicles"]): r for r in rows}
    for mode in ("distributed", "centralized"):
        small, large = by[(mode, 2)], by[(mode, 4)]
        assert large["bytes_per_s_total"] > 2 * small["bytes_per_s_total"]  # 3 senders against 1
        assert large["host_cpu_ms_per_cycle"] > small["host_cpu_ms_per_cycle"] > 0
        for r in (small, large):
            assert r["delivered_fraction"] > 0.9 and r["dropped_queue_fraction"] == 0.0  # far below 6 Mbit/s
            assert r["vehicle_rmse_m"] < 1.0 and r["object_rmse_m"] < 1.5 and r["obstacles_in_scope"] > 0
    # the raw data costs several times the priors' bytes on the same traffic (sumo-grid: about 3.5x; in
    # sumo-town's denser traffic the priors carry more objects and the ratio is about 2.4x)
    assert by[("centralized", 4)]["bytes_per_s_per_vehicle"] > 2.5 * by[("distributed", 4)]["bytes_per_s_per_vehicle"]
    for name in ("scale.csv", "scale.md", "scale_cost.png", "scale_channel.png"):
        assert (out / name).stat().st_size > 0
