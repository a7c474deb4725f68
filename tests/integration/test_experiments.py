"""`mapc experiment paper|network`, `mapc bench fusion|localization` end to end (fixed seeds, no wall-clock bounds)."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys

import pytest

from mapcontainer.experiments import NETWORK_COLUMNS
from mapcontainer.sim.errors import ERROR_SOURCES


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
        "experiment", "paper", "--runs", "2", "--seed", "2", "--workers", "2", "--duration", "2.5", "--burnin", "1.5",
        "--rv-runs", "1", "--sensitivity-runs", "1", "--out", str(out), "--check", check=False,
    )  # fmt: skip
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert summary["runs"] == 2 and set(summary["targets"].values()) <= {"PASS", "FAIL"}
    # res1 x 2 densities, res2 x 2 x 2 x 2, consistency x 2 x 2, cold start x 3 x 2, efficiency x 3 x 2, bytes
    assert len(summary["targets"]) == 27
    assert proc.returncode == (1 if "FAIL" in summary["targets"].values() else 0)  # --check
    assert "experiment paper [" in proc.stderr  # the progress bar

    res = json.loads((out / "results.json").read_text())
    assert res["seeds"] == "development" and res["settings"]["start"] == "cold"
    for key in ("urban", "suburban"):
        sim = res["simulation"][key]
        assert set(sim["ego_rmse_m"]) == {"gnss", "onboard", "map_matching", "cooperative", "centralized"}
        assert all(_finite(v) for v in sim["ego_rmse_m"].values()), key
        assert all(_finite(sim["target_rmse_m"][v]) for v in ("ego_only", "cooperative", "centralized")), key
        eff = sim["efficiency"]  # the same runs in centralized mode
        assert eff["runs"] == 2 and set(eff["vehicles"]) == set(sim["per_vehicle_rmse_m"])
        assert all(_finite(v) and v > 0 for v in (eff["all_vehicles"], eff["objects"], eff["targets"])), key
        assert eff["bytes_ratio"] > 3, key  # raw observations are several times a prior
        for view in ("ego_only", "cooperative"):
            o = sim["objects"][view]
            assert 0.0 <= o["coverage"] <= 1.0 and o["false_per_frame"] >= 0.0 and o["gospa_m"] >= 0.0
        c = sim["consistency"]["vehicles_cooperative_6dof"]
        assert c["dof"] == 6 and c["runs"] == 2 and c["band"][0] < 6 < c["band"][1]
        assert set(sim["over_time"]) >= {"cv0:onboard", "targets:cooperative"}
        assert [row[0] for row in sim["over_time"]["cv0:gnss"]] == [0.0, 1.0, 2.0]
        st = sim["startup"]
        assert set(st["at"]) == {"1", "2"} and st["runs"] == 2
        assert st["time_to_localize_s"]["vehicles"] == 2 * len(sim["per_vehicle_rmse_m"])  # every vehicle start
    for density in ("dense", "sparse"):
        assert _finite(res["overlap"][density]["fused_m"]), density
        for key in ("ii", "iii"):
            b = res["blindspot"][key][density]
            assert _finite(b["connected_car_m"]) and _finite(b["connected_car_onboard_m"]), (key, density)
    assert set(res["sensitivity"]) == {"all", "none", *(f"no_{s}" for s in ERROR_SOURCES)}
    assert all(_finite(v) for v in res["sensitivity"]["none"].values() if v == v)
    assert res["bytes"]["ratio"] > 1.0 and res["bytes"]["measured"]["seeds"] == [2, 3]

    report = (out / "report.md").read_text()
    for heading in (
        "## Method",
        "## Cold start",
        "Table res1",
        "Table res2",
        "## Consistency",
        "## Sensitivity",
        "## Bandwidth",
    ):
        assert heading in report, heading
    assert "development seeds" in report and "0.23" in report and "| ours, sparse" in report
    for png in ("exp_sim.png", "over_time.png", "real_vehicle.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
    runs = list(csv.DictReader((out / "runs.csv").open()))
    assert sum(r["kind"] == "sim" and r["variant"] == "all" for r in runs) == 4


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
    # the frame's CPU time beside its wall time, and the machine's speed at the time (the yardstick)
    assert 0 < result["cpu_ms_per_frame_p50"] <= result["cpu_ms_per_frame_p99"]
    assert result["yardstick_ms_p50"] > 0 and result["ms_p99_over_yardstick"] > 0
    assert set(result["nees_axes_mean"]) == {"x", "y", "z", "roll", "pitch", "yaw"}
    # the frames not map matched, scored apart (GNSS fallback and the search): their error and consistency
    assert result["fallback_frames"] == 0 or all(
        _finite(result[k]) for k in ("fallback_rmse_m", "fallback_nees_h_mean", "fallback_nees_h_p95")
    )
    assert result["error_sources"] == list(ERROR_SOURCES)  # the scenario's realistic errors, all on
    assert result["startup_accept"] == "landmarks"  # the default start-up rule
    assert result["map_errors"] == "independent"  # the default tracker (opt-in: --map-errors consider)
    # the start-up search's anytime budget (the default) bounds the matcher's solves in every frame: the budget and
    # one start's solves (its lane search and polish) at most
    budget = result["search_budget"]
    assert budget == 6 and budget + 4 >= result["solves_per_frame_max"] >= result["solves_per_frame_p99"] >= 1
    # with them, seed 0's vehicles lock on in about half of the scored frames (the cold-start search
    # misses with map and calibration errors: issue 20), and where they do, they beat GNSS
    assert result["converged_fraction"] > 0.3 and result["mapmatch_rmse_m"] < 0.3 < result["gnss_rmse_m"]
    proc = _mapc(
        "bench", "localization", "--scenario", "paper-urban", "--seeds", "1", "--duration", "4", "--ideal",
        "--startup-accept", "posterior",
    )  # fmt: skip
    ideal = json.loads(proc.stdout.strip().splitlines()[-1])
    assert ideal["error_sources"] == [] and ideal["startup_accept"] == "posterior"
    # exact map and sensors: it locks in 0.92 of the frames (0.61 without the search's budget: the traffic drawn for
    # seed 0 kept a vehicle searching, issue 20), and where it does, map matching beats GNSS by an order of magnitude
    # (0.136 m over those frames, the earlier ones included). Its covariance says so: a lone pole's repeated views
    # count for the travel between them (docs/localization.md), so the accepted basins are wide along the road
    # at first; mean NEES 2.46 against 6 (9.22, overconfident, when each view counted in full, at 0.104 m)
    assert ideal["converged_fraction"] > 0.85 and ideal["mapmatch_rmse_m"] < 0.15 < 0.3 < ideal["gnss_rmse_m"]
    assert ideal["nees_mean"] < 6.0
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
    from mapcontainer.fusion.compiled import COMPILED

    assert result["compiled"] is COMPILED  # which way the host's inner loops ran
    assert result["object_rmse_m"] < 1.0
    phases = result["phases_ms_p50"]  # where the cycle goes: decoding, the container's phases, the solve's
    assert {"ingest", "associate", "prune", "linearize", "eliminate", "covariances", "output"} <= phases.keys()
    assert all(_finite(ms) and ms >= 0 for ms in phases.values())


def test_bench_fusion_sizes_prints_every_run_the_growth_and_the_oracle(tmp_path):
    proc = _mapc(
        "bench", "fusion", "--sizes", "2/4,3/8", "--density", "city", "--window", "3", "--ticks", "10",
        "--batch-samples", "0", "--compare-exact",
    )  # fmt: skip
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["sizes"] == ["2/4", "3/8"] and [r["vehicles"] for r in result["runs"]] == [2, 3]
    for r in result["runs"]:
        assert r["density"] == "city" and r["solver"] == "sparse" and r["detections_per_tick"] > 0
        assert _finite(r["us_per_detection"]) and r["exact"]["object_matches"] == r["object_matches"]
        assert r["rmse_over_exact"] == pytest.approx(1.0, rel=1e-6)
    g = result["growth"]
    assert g["us_per_detection_over_first"][0] == 1.0 and _finite(g["exponent_vs_detections"])
    bad = _mapc("bench", "fusion", "--sizes", "4x14", check=False)
    assert bad.returncode == 2 and "--sizes" in bad.stderr


@pytest.mark.slow
def test_experiment_network_radio_density_over_two_seeds_resumes(tmp_path):
    out = tmp_path / "radio"
    args = (
        "experiment", "network", "--radio", "its-g5", "--sweep", "density", "--seeds", "0,1", "--extra-vehicles", "0",
        "--no-cpm", "--duration", "1.5", "--warmup", "0.5", "--workers", "2", "--quiet", "--out", str(out),
    )  # fmt: skip
    proc = _mapc(*args)
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == {
        "out": str(out), "points": 12, "radio": "its-g5", "seeds": [0, 1]
    }  # fmt: skip
    with open(out / "density.csv") as f:
        rows = list(csv.DictReader(f))
    assert sorted({r["seed"] for r in rows}) == ["0", "1"] and len(rows) == 12  # 2 seeds x 2 modes x 3 links
    doc = json.loads((out / "degradation.json").read_text())
    assert doc["meta"]["seeds"] == [0, 1] and doc["meta"]["tasks"] == 12 and doc["meta"]["resumed"] == 0
    assert {(d["mode"], d["dcc"]) for d in doc["degradation"]} == {
        (m, dcc) for m in ("distributed", "centralized") for dcc in (False, True)
    }
    assert all(d["rmse_vs_ideal_seeds"] == [2] for d in doc["degradation"])
    _mapc(*args)
    assert (
        json.loads((out / "degradation.json").read_text())["meta"]["resumed"] == 12
    )  # every point read back from OUT/tasks
    bad = _mapc(*args[:-2], "--seeds", "0,x", "--out", str(tmp_path / "bad"), check=False)
    assert bad.returncode == 2 and "--seeds" in bad.stderr
