"""What a fleet run prints: the live line, the crash and restart notices, the table at the end."""

from __future__ import annotations

import json
from pathlib import Path

from services.launcher.report import (
    console_event,
    down_reasons,
    format_report,
    make_summary,
    scenario_time,
    summary_line,
)

EV = {
    "t_meas_last": 19.9,
    "burnin_s": 5.0,
    "vehicle_rmse_m": 1.2345678901234,
    "vehicle_rmse_steady_m": 0.0812345678,
    "vehicle_rmse_by_id_m": {"cv0": 0.1, "cv1": 2.5},
    "vehicle_rmse_steady_by_id_m": {"cv0": 0.07, "cv1": 0.09},
    "object_rmse_m": 0.41,
    "object_rmse_steady_m": 0.38,
    "object_coverage_steady": 0.62,
    "false_track_fraction_steady": 0.031,
    "e2e_latency_ms_p50": 97.4,
    "e2e_latency_ms_p99": 301.0,
    "delivered_fraction": 0.985,
    "tx_bytes_per_msg": {"cv0": 221.3, "cv1": 205.9},
}
PARAMS = {"scenario": "paper-urban", "mode": "distributed", "network": "dsrc", "ego": "cv0"}
PROCS = [{"name": "host", "restarts": 1}, {"name": "world", "restarts": 0}]


def test_summary_line_counts_scenario_time_and_says_who_is_down() -> None:
    m = {
        "vehicle_rmse_m": 0.123,
        "object_rmse_m": None,
        "tx_bytes_per_s": {"cv0": 3700.0},
        "delivered_fraction": 0.98,
        "window_s": 5.0,
    }
    line = summary_line(12.34, 20.0, 7, 8, m, "world done")
    assert line.startswith("t  12.3/20 s | up 7/8 (world done) |")
    assert "RMSE last 5s veh 0.12 m" in line and "obj -" in line and "cv0 3.7" in line  # a windowed figure
    assert "delivered 0.980" in line
    assert summary_line(None, None, 0, 0, None).startswith("t - s | up 0/0 |")


def test_scenario_time_from_the_worlds_clock(tmp_path) -> None:
    assert scenario_time(tmp_path, 10**18) is None  # the world has not started its clock
    (tmp_path / "world-clock.json").write_text(json.dumps({"epoch_wall_ns": 10**18, "time_scale": 2.0}))
    assert scenario_time(tmp_path, 10**18 + 3 * 10**9) == 6.0
    assert scenario_time(tmp_path, 10**18 - 10**9) == 0.0  # before the epoch (its start delay)


def test_down_reasons() -> None:
    procs = [
        {"name": "world", "alive": False, "state": "exited", "returncode": 0},
        {"name": "host", "alive": False, "state": "backoff", "returncode": -9},
        {"name": "cv2", "alive": False, "state": "failed", "returncode": 1},
        {"name": "cv1", "alive": True, "state": "ready", "returncode": None},
        {"name": "cv3", "alive": False, "state": "ready", "returncode": None},  # ended, not yet reaped
    ]
    assert down_reasons(procs) == "world done, host restarting, cv2 failed, cv3 exiting"


def test_crashes_and_restarts_are_announced_but_a_normal_stop_is_not() -> None:
    assert console_event("exited", "host", {"returncode": -9, "ran_s": 5.2}, False) == (
        "host crashed (killed by signal 9 after 5.2 s)"
    )
    assert console_event("restart_scheduled", "host", {"in_s": 0.5, "restarts": 1}, False) == (
        "host restarts in 0.5 s (restart 1)"
    )
    assert console_event("started", "host", {"pid": 42, "restarts": 1}, False) == "host restarted (pid 42)"
    assert "killed" in console_event("frozen_kill", "cv1", {"pid": 7}, False)
    assert console_event("exited", "world", {"returncode": 0, "ran_s": 20.0}, False) is None  # it finished
    assert console_event("exited", "host", {"returncode": -2, "ran_s": 20.0}, True) is None  # we stopped it
    assert console_event("started", "host", {"pid": 42, "restarts": 0}, False) is None
    assert console_event("stop_timeout", "host", {"pid": 42}, True) == "host did not stop in time: killed"


def test_final_table_and_json_summary(tmp_path) -> None:
    (tmp_path / "birdseye.png").write_bytes(b"png")
    s = make_summary("demo", tmp_path, PARAMS, PROCS, EV, 24.04)
    assert s["vehicle_rmse_m"] == 1.2346 and s["wall_s"] == 24.0  # rounded for people
    assert s["birdseye"] == str(tmp_path / "birdseye.png") and s["errors"] is None
    assert s["restarts"] == 1 and s["restarts_by_process"] == {"host": 1}
    assert json.loads(json.dumps(s)) == s
    table = format_report(s)
    lines = table.splitlines()
    assert lines[0] == "fleet demo: paper-urban, distributed, network dsrc; 19.9 s of scenario time in 24.0 s"
    assert "RMSE steady (t >= 5 s)" in lines[1] and "RMSE whole run" in lines[1]
    cv0 = next(line for line in lines if line.strip().startswith("cv0 (ego)")).split()
    assert cv0[2:] == ["0.070", "m", "0.100", "m", "221"]
    cv1 = next(line for line in lines if line.strip().startswith("cv1")).split()
    assert cv1[1:] == ["0.090", "m", "2.500", "m", "206"]
    assert "coverage 62.0 %, false tracks 3.1 %" in table
    assert "p50 97 ms, p99 301 ms" in table and "98.5 %" in table
    assert "restarts      1 (host 1)" in table and "birdseye.png" in table and "errors.png" not in table
    assert max(len(line) for line in lines if "run dir" not in line) < 110


def test_a_run_without_evaluation_still_has_a_table(tmp_path) -> None:
    s = make_summary("demo", tmp_path, PARAMS, [], None, 3.0)
    table = format_report(s)
    assert "fleet demo" in table and "objects" in table and " - " in table


def test_flagged_vehicles_are_in_the_table() -> None:
    s = make_summary("f", Path("/r"), {}, [], {**EV, "flagged_first_t": {"cv1": 2.9}}, 10.0)
    assert "flagged       cv1 from t = 2.9 s" in format_report(s)
    assert "flagged" not in format_report(make_summary("f", Path("/r"), {}, [], EV, 10.0))


def test_the_closing_table_says_how_the_clock_went(tmp_path) -> None:
    from services.launcher.report import format_report, make_summary

    (tmp_path / "world-clock.json").write_text(
        json.dumps({"epoch_wall_ns": 1, "time_scale": 1.0, "achieved_time_scale": 0.26, "paused_s": 57.3,
                    "waits_timed_out": 0, "skipped_frames": 0})
    )  # fmt: skip
    s = make_summary("f", tmp_path, {"time_scale": "auto"}, [], {}, 100.0)
    assert s["achieved_time_scale"] == 0.26 and s["time_scale"] == "auto"
    line = next(x for x in format_report(s).splitlines() if "time scale" in x)
    assert (
        line == "  time scale    auto: 0.26 achieved, every frame processed (the clock paused 57.3 s for the services)"
    )
    (tmp_path / "world-clock.json").write_text(json.dumps({"epoch_wall_ns": 1, "time_scale": 0.5, "skipped_frames": 7}))
    s = make_summary("f", tmp_path, {"time_scale": 0.5}, [], {}, 100.0)
    assert "  time scale    0.5; the world dropped 7 frames to keep up" in format_report(s).splitlines()
