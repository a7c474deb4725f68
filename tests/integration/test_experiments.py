"""`mapc experiment paper|network`, `mapc bench fusion|localization` end to end (fixed seeds, no wall-clock bounds)."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys

import pytest

from mapcontainer.experiments import NETWORK_COLUMNS


def _mapc(*args: str, timeout: float = 600, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mapcontainer.cli", *args], capture_output=True, text=True, timeout=timeout, check=check
    )


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


@pytest.mark.slow
def test_experiment_paper_tiny_writes_results_report_and_plots(tmp_path):
    out = tmp_path / "paper"
    proc = _mapc(
        "experiment", "paper", "--runs", "2", "--seed", "2", "--workers", "2", "--duration", "1.6",
        "--rv-runs", "1", "--rv-duration", "2.5", "--out", str(out), "--check", check=False,
    )  # fmt: skip
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert summary["runs"] == 2 and len(summary["targets"]) == 7
    assert set(summary["targets"].values()) <= {"PASS", "FAIL"}
    assert proc.returncode == (1 if "FAIL" in summary["targets"].values() else 0)  # --check
    assert "experiment paper [" in proc.stderr  # the progress bar

    res = json.loads((out / "results.json").read_text())
    sim_shape = {"ego_rmse_m": {"gnss", "map_matching", "cooperative"}, "target_rmse_m": {"ego_only", "cooperative"}}
    for key in ("urban", "suburban"):
        for group, names in sim_shape.items():
            assert set(res["simulation"][key][group]) == names
            assert all(_finite(res["simulation"][key][group][n]) for n in names), (key, group)
    assert all(_finite(res["overlap"][k]) for k in ("ego_car_m", "connected_car_m", "fused_m"))
    for key in ("ii", "iii"):
        assert all(_finite(res["blindspot"][key][k]) for k in ("connected_car_m", "obstacle_m")), key
    an = res["anees"]
    assert _finite(an["value"]) and an["dof"] == 3 and an["n"] == 2
    assert len(an["band"]) == 2 and an["band"][0] < an["dof"] < an["band"][1]
    assert all(_finite(res["bytes_per_message"][k]) for k in ("distributed", "centralized"))
    assert res["runs"] == 2 and res["seed"] == 2
    assert res["settings"]["start"] == "warm" and res["settings"]["warm_start_sigma"]["yaw_deg"] == 1.0
    for key in ("urban", "suburban"):
        cs = res["cold_start"][key]
        assert cs["runs"] == 2 and cs["vehicles"] == 8 and set(cs["at"]) == {"1", "2"}
        assert all(0.0 <= cs["at"]["2"][k] <= 1.0 for k in ("map_matching", "locked", "gross", "ever_map_matching"))

    # accuracy sanity on 2 runs x 6 scored frames (loose bounds that catch a broken pipeline)
    urban = res["simulation"]["urban"]
    assert 0.5 < urban["ego_rmse_m"]["gnss"] < 6.0
    assert urban["ego_rmse_m"]["map_matching"] < 0.5 * urban["ego_rmse_m"]["gnss"]
    assert urban["ego_rmse_m"]["cooperative"] < 0.5 * urban["ego_rmse_m"]["gnss"]
    assert urban["target_rmse_m"]["cooperative"] < 1.0
    assert res["overlap"]["fused_m"] < 1.0
    assert 100 < res["bytes_per_message"]["distributed"] < res["bytes_per_message"]["centralized"]

    report = (out / "report.md").read_text()
    assert "Table res1" in report and "0.23" in report and "| ours" in report
    assert "**Start**: warm" in report and "## Cold start" in report
    assert "PASS" in report or "FAIL" in report
    for png in ("exp_sim.png", "exp_sim_runs.png", "real_vehicle.png", "anees.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
    runs = list(csv.DictReader((out / "runs.csv").open()))
    assert sum(r["kind"] == "sim" for r in runs) == 4


@pytest.mark.slow
def test_experiment_network_quick_writes_table_and_plots(tmp_path):
    out = tmp_path / "net"
    proc = _mapc("experiment", "network", "--quick", "--seed", "0", "--workers", "2", "--out", str(out))
    last = json.loads(proc.stdout.strip().splitlines()[-1])
    assert last["points"] == 16 and "smoke_test" in last

    rows = list(csv.DictReader((out / "network.csv").open()))
    assert len(rows) == 16
    assert list(rows[0].keys()) == list(NETWORK_COLUMNS)
    assert {r["mode"] for r in rows} == {"distributed", "centralized"}
    lowest = min(float(r["bandwidth_bps"]) for r in rows)
    by_point: dict[tuple, dict] = {}
    for r in rows:
        by_point[(float(r["bandwidth_bps"]), float(r["latency_ms"]), float(r["loss"]), r["mode"])] = r
    for (bw, lat, loss, mode), r in by_point.items():
        if bw == lowest and mode == "distributed":
            c = by_point[(bw, lat, loss, "centralized")]
            assert float(c["delivered_fraction"]) < float(r["delivered_fraction"]), (lat, loss)
            assert float(c["bytes_per_s_per_vehicle"]) > 3 * float(r["bytes_per_s_per_vehicle"])
    # the ideal point delivers everything and fuses accurately
    best = by_point[(max(float(r["bandwidth_bps"]) for r in rows), 0.0, 0.0, "distributed")]
    assert float(best["delivered_fraction"]) == 1.0
    assert float(best["object_rmse_m"]) < 1.0 and float(best["age_s_mean"]) == pytest.approx(0.1, abs=0.05)

    md = (out / "network.md").read_text()
    assert "Key comparison" in md and "| distributed |" in md and "| centralized |" in md
    doc = json.loads((out / "results.json").read_text())
    assert len(doc["rows"]) == 16 and doc["meta"]["quick"] is True and doc["meta"]["smoke_test"] is True
    assert "**Smoke test**" in md
    for png in ("network_latency.png", "network_bandwidth.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png


def test_bench_localization_prints_accuracy_consistency_and_speed():
    proc = _mapc("bench", "localization", "--scenario", "paper-urban", "--seeds", "1", "--duration", "4")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["frames"] == 4 * 20  # four vehicles, the 2 s after the warm-up at 10 Hz
    for key in ("gnss_rmse_m", "all_frames_rmse_m", "nees_mean", "ms_per_frame_p50", "prior_rmse_m"):
        assert _finite(result[key]), key
    assert set(result["nees_axes_mean"]) == {"x", "y", "z", "roll", "pitch", "yaw"}
    # seed 0: map matching locks on within the warm-up and beats GNSS by an order of magnitude
    assert result["converged_fraction"] > 0.7 and result["mapmatch_rmse_m"] < 0.3 < result["gnss_rmse_m"]
    bad = subprocess.run(
        [sys.executable, "-m", "mapcontainer.cli", "bench", "localization", "--duration", "1"],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "warm-up" in bad.stderr


def test_bench_fusion_prints_json_last(tmp_path):
    proc = _mapc("bench", "fusion", "--vehicles", "2", "--objects", "4", "--window", "3", "--ticks", "15")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    for key in ("cycle_ms_p50", "cycle_ms_p99", "iterations_mean", "object_rmse_m", "batch_ms_p50", "cycle_over_batch"):
        assert _finite(result[key]), key
    assert result["vehicles"] == 2 and result["objects"] == 4 and result["window"] == 3
    assert result["object_rmse_m"] < 1.0
