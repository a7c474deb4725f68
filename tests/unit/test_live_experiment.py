"""The live network experiment's row from a fleet report (pure parts of services.launcher.live_experiment)."""

from __future__ import annotations

import math

import pytest

from mapcontainer.channel import load_profile
from mapcontainer.experiments.network import NETWORK_COLUMNS
from services.launcher.live_experiment import compare_rows, live_row

REPORT = {
    "summary": {"wall_s": 12.0, "restarts": 0, "run_dir": "runs/x"},
    "params": {"scenario": "paper-urban", "mode": "distributed", "seed": 3},
    "evaluation": {
        "vehicle_rmse_m": 0.5,
        "object_rmse_m": 0.4,
        "e2e_latency_ms_p50": 80.0,
        "e2e_latency_ms_p99": 200.0,
        "delivered_fraction": 0.98,
        "tx_bytes_total": {"cv0": 9999, "cv1": 4000, "cv2": 6000},
        "tx_msgs_total": {"cv0": 99, "cv1": 100, "cv2": 100},
    },
}


def test_live_row_has_the_sweep_columns_and_leaves_the_ego_out():
    row = live_row(REPORT, load_profile("lossy"), duration_s=10.0)
    assert set(NETWORK_COLUMNS) <= set(row)
    assert row["source"] == "live" and row["profile"] == "lossy" and row["seed"] == 3
    assert row["bytes_per_s_per_vehicle"] == pytest.approx((4000 + 6000) / 10.0 / 2)
    assert row["bytes_per_message"] == pytest.approx(50.0)
    assert row["msgs_per_s_per_vehicle"] == pytest.approx(10.0)
    assert row["loss"] == pytest.approx(load_profile("lossy").mean_loss) and row["loss"] > 0.2
    assert row["e2e_latency_ms_p50"] == 80.0 and math.isnan(row["age_s_mean"])


def test_live_row_without_an_evaluation_is_empty_not_an_error():
    row = live_row({"params": {}, "summary": {}}, load_profile("ideal"), duration_s=5.0)
    assert math.isnan(row["vehicle_rmse_m"]) and math.isnan(row["bytes_per_s_per_vehicle"])
    with pytest.raises(ValueError, match="duration_s"):
        live_row(REPORT, load_profile("ideal"), duration_s=0.0)


def test_compare_rows_pairs_live_and_inprocess_by_profile_and_mode():
    live = [live_row(REPORT, load_profile("dsrc"), duration_s=10.0)]
    inproc = [{"profile": "dsrc", "mode": "distributed", "object_rmse_m": 0.3, "vehicle_rmse_m": 0.2}]
    (row,) = compare_rows(live, inproc)
    assert row["object_rmse_m_live"] == 0.4 and row["object_rmse_m_inprocess"] == 0.3
    assert math.isnan(row["delivered_fraction_inprocess"])
