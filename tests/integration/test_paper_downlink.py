"""`mapc experiment paper --downlink both` on real runs (development seed 2, paper-urban, 2.5 s): every run with the
downlink off and on from the same seed, the report's on/off table with both rows, and the figures independent of
the order the runs finished in."""

from __future__ import annotations

import csv
import json
import math

import pytest

from mapcontainer import jsonout
from mapcontainer.experiments.executors import Executor
from mapcontainer.experiments.paper import PaperSettings, aggregate, run_paper_experiment

pytestmark = [pytest.mark.slow, pytest.mark.integration]

SETTINGS = PaperSettings(
    runs=1, seed=2, scenarios=("paper-urban",), sensitivity_runs=0, duration_s=2.5, burnin_s=1.5, downlink_compare=True
)


def test_the_paper_experiment_reports_the_downlink_off_and_on_from_the_same_seeds(tmp_path) -> None:
    out = tmp_path / "paper"
    run_paper_experiment(out, SETTINGS, Executor(workers=1), progress=False)
    res = json.loads((out / "results.json").read_text())
    c = res["downlink_on_off"]
    assert c["seeds"] == [2] and c["report_setting"] == "off"
    off, on = c["simulation"]["paper-urban"]["off"], c["simulation"]["paper-urban"]["on"]
    for f in (off, on):
        for k in ("vehicles_onboard_rmse_m", "vehicles_fused_rmse_m", "objects_rmse_m", "onboard_anees_2dof"):
            assert math.isfinite(f[k]) and f[k] > 0, k
        assert math.isfinite(f["efficiency_vehicles"]) and f["up_bytes_per_s"] > 0 and f["runs"] == 1
    assert off["down_bytes_per_s"] == 0 and on["down_bytes_per_s"] > 0 and off["downlink_frames"] == {}
    assert sum(on["downlink_frames"].values()) > 0 and on["downlink_frames"].get("fused", 0) > 0
    # one reference for both settings: the same centralized estimate, and more distributed bytes with the downlink
    assert on["centralized_over_distributed_bytes"] < off["centralized_over_distributed_bytes"]
    assert res["downlink_other"]["simulation"]["paper-urban"]["efficiency"]["runs"] == 1
    assert res["settings"]["downlink"] is False and res["settings"]["downlink_compare"] is True

    report = (out / "report.md").read_text()
    assert "--downlink both`" in report and "## The downlink on and off" in report
    rows = [line for line in report.splitlines() if line.startswith(("| paper-urban | off |", "| paper-urban | on |"))]
    assert [r.split(" | ")[1] for r in rows] == ["off", "on", "off", "on"]
    runs = list(csv.DictReader((out / "runs.csv").open()))
    assert sorted((r["seed"], r["downlink"]) for r in runs) == [("2", "off"), ("2", "on")]
    assert runs[0]["cv0:centralized"] == runs[1]["cv0:centralized"] != ""  # the borrowed reference

    stored = [json.loads(p.read_text()).get("result") for p in sorted((out / "tasks").glob("*.json"))]
    results = [r for r in stored if isinstance(r, dict) and r.get("kind") == "sim"]
    assert len(results) == 2
    again = aggregate(results[::-1], SETTINGS, res["bytes"])  # the other order of finishing
    assert jsonout.dumps(again, indent=2) + "\n" == (out / "results.json").read_text()
