"""The pieces of the experiments: scoring against the pipeline, age of information, ANEES summary,
network rows and outputs, targets, the progress bar (fast: short runs, fixed seeds)."""

from __future__ import annotations

import csv
import io
import json
import math

import numpy as np
import pytest

from mapcontainer.evaluation import age_of_information, relative_target_errors, rmse_sq
from mapcontainer.experiments import NETWORK_COLUMNS, Progress, run_network_point, sweep_profile, write_network_outputs
from mapcontainer.experiments.network import MIN_QUEUE_BYTES
from schemas import FusedState, GroundTruth
from schemas.arrays import cov_to_upper


def test_relative_target_errors_are_in_the_ego_frame_within_the_radius():
    """The ego at (10, 0) heading north (fused 0.2 m north of it): a target 5 m ahead, fused 0.3 m east
    of the truth + the ego's offset, errs 0.3 m to the ego's right; a target 80 m away is out of range."""
    head = [0.0, 0.0, 0.0, 0.0, 0.0, math.pi / 2]
    common = {"fleet": "t", "seq": 0, "t_meas": 1.0, "t_sent": 1.0}
    truth = GroundTruth(
        sender="world", **common, vehicle_ids=["cv0"], vehicle_pose=np.array([[10.0, 0, 0, *head[3:]]]),
        vehicle_v_map=np.zeros((1, 3)), obstacle_id=np.array([7, 8], np.uint32),
        obstacle_cls=np.array([1, 1], np.uint8),
        obstacle_p_map=np.array([[10.0, 5.0, 0.0], [10.0, 80.0, 0.0]]), obstacle_v_map=np.zeros((2, 3)),
        obstacle_yaw=np.zeros(2),
    )  # fmt: skip
    fused = FusedState(
        sender="host", **common, vehicle_ids=["cv0"], vehicle_pose=np.array([[10.0, 0.2, 0, *head[3:]]]),
        vehicle_pose_cov=np.tile(cov_to_upper(np.eye(6) * 0.01), (1, 1)), object_id=np.array([1, 2], np.uint32),
        object_cls=np.array([1, 1], np.uint8), object_p_map=np.array([[10.3, 5.2, 0.0], [10.0, 80.0, 0.0]]),
        object_v_map=np.zeros((2, 3)), object_cov=np.tile(cov_to_upper(np.eye(3) * 0.01), (2, 1)),
    )  # fmt: skip
    ids, err, n_near = relative_target_errors(fused, truth, "cv0", 50.0)
    assert ids.tolist() == [7] and n_near == 1
    np.testing.assert_allclose(err, [[0.0, -0.3]], atol=1e-6)  # x forward (north), y left (west)
    assert rmse_sq([]) != rmse_sq([]) and rmse_sq([9.0, 16.0]) == pytest.approx(math.sqrt(12.5))


def test_age_of_information_is_time_since_the_newest_arrival():
    deliveries = [("a", 0.0, 0.05), ("a", 0.1, 0.35), ("a", 0.2, 0.25), ("b", 0.0, 0.0)]
    age = age_of_information(deliveries, ["a", "b", "c"], [0.0, 0.1, 0.3, 0.4], t_start=0.0)
    # a: nothing by 0.0; t_meas 0.0 by 0.1; 0.2 (arrived 0.25, overtaking 0.1) by 0.3; still 0.2 by 0.4
    np.testing.assert_allclose(age[:, 0], [0.0, 0.1, 0.1, 0.2])
    np.testing.assert_allclose(age[:, 1], [0.0, 0.1, 0.3, 0.4])
    np.testing.assert_allclose(age[:, 2], [0.0, 0.1, 0.3, 0.4])  # never heard from: since the start


def test_network_point_row_on_an_ideal_and_a_starved_link():
    # scored after 2 s of the cold start: in its first 1.5 s a vehicle still on GNSS puts objects metres off
    ideal = run_network_point(sweep_profile(0.0, 0.0, None), "distributed", seed=1, duration=3.0, warmup_s=2.0)
    assert tuple(ideal) == NETWORK_COLUMNS
    assert ideal["delivered_fraction"] == 1.0 and ideal["age_s_mean"] == 0.0 and ideal["latency_s_p50"] == 0.0
    assert ideal["object_rmse_m"] < 0.6 and 0.0 < ideal["object_coverage"] <= 1.0
    assert 100 < ideal["bytes_per_message"] < 1000 and ideal["msgs_per_s_per_vehicle"] == pytest.approx(10.0)
    starved = run_network_point(sweep_profile(100.0, 0.0, 2e4), "centralized", seed=1, duration=1.5)
    assert starved["queue_bytes"] == MIN_QUEUE_BYTES and starved["delivered_fraction"] < 0.2
    assert starved["dropped_queue_fraction"] > 0.8 and starved["age_s_mean"] > ideal["age_s_mean"]


def test_write_network_outputs_accepts_live_rows(tmp_path):
    rows = [
        {"source": "pipeline", "mode": "distributed", "latency_ms": 0.0, "loss": 0.0, "bandwidth_bps": 6e6,
         "object_rmse_m": 0.3, "delivered_fraction": 1.0, "bytes_per_s_per_vehicle": 3700.0},
        {"source": "pipeline", "mode": "distributed", "latency_ms": 0.0, "loss": 0.0, "bandwidth_bps": 2e4,
         "object_rmse_m": 0.4, "delivered_fraction": 0.7, "bytes_per_s_per_vehicle": 3700.0},
        {"source": "pipeline", "mode": "centralized", "latency_ms": 0.0, "loss": 0.0, "bandwidth_bps": 6e6,
         "object_rmse_m": 0.3, "delivered_fraction": 1.0, "bytes_per_s_per_vehicle": 27000.0},
        {"source": "live", "mode": "centralized", "latency_ms": 0.0, "loss": 0.0, "bandwidth_bps": 2e4,
         "object_rmse_m": float("nan"), "delivered_fraction": 0.01, "bytes_per_s_per_vehicle": 27000.0,
         "wall_clock_skew_s": 0.002},
    ]  # fmt: skip
    paths = write_network_outputs(rows, tmp_path, {"seed": 0, "duration_s": 4.0, "warmup_s": 1.0})
    header = next(csv.reader((tmp_path / "network.csv").open()))
    assert header[: len(NETWORK_COLUMNS)] == list(NETWORK_COLUMNS) and header[-1] == "wall_clock_skew_s"
    doc = json.loads((tmp_path / "results.json").read_text())  # strict JSON: NaN written as null
    assert doc["rows"][3]["object_rmse_m"] is None
    md = (tmp_path / "network.md").read_text()
    assert "20 kbit/s" in md and "still fuses" in md
    assert {"csv", "md", "json", "png_latency", "png_bandwidth"} <= set(paths)
    assert all(p.exists() for p in paths.values())


def test_network_md_header_describes_live_presets_truthfully(tmp_path):
    rows = [
        {"source": "live", "mode": "distributed", "profile": p, "latency_ms": lat, "jitter_ms": jit, "loss": 0.0,
         "bandwidth_bps": float("inf"), "object_rmse_m": 0.3, "delivered_fraction": 1.0}
        for p, lat, jit in (("ideal", 0.0, 0.0), ("dsrc", 18.0, 2.0), ("lossy", 20.0, 5.0))
    ]  # fmt: skip
    write_network_outputs(rows, tmp_path, {"source": "live", "seed": 0, "duration_s": 20.0, "warmup_s": 1.0})
    head, key = (tmp_path / "network.md").read_text().split("## Key comparison")
    key = key.split("## All points")[0]
    assert key.count("| distributed |") == 1  # one capacity: one row, not the point compared with itself
    assert "dsrc: 18 ms + U[0, 4] ms jitter" in head and "lossy: 20 ms + U[0, 10] ms jitter" in head
    assert "Gilbert-Elliott" in head and "one shared medium" in head and "warm-up included" in head
    assert "ideal: 0 ms, no jitter" in head and "; no jitter" not in head
    sweep = [{"source": "pipeline", "mode": "distributed", "profile": "lat0ms-loss0pct-bwinf", "jitter_ms": 0.0}]
    write_network_outputs(sweep, tmp_path / "s", {"seed": 0, "duration_s": 4.0, "warmup_s": 1.0})
    head = (tmp_path / "s" / "network.md").read_text().split("## Key comparison")[0]
    assert "Bernoulli loss; no jitter" in head and "first 1.0 s are not scored" in head
    assert "cold start" in head and "Smoke test" not in head
    assert "predicted to the fuse time" in head and "not a prediction" not in head  # what _output does
    write_network_outputs(sweep, tmp_path / "q", {"seed": 0, "duration_s": 2.5, "warmup_s": 1.0, "smoke_test": True})
    head = (tmp_path / "q" / "network.md").read_text().split("## Key comparison")[0]
    assert "**Smoke test** (`--quick`)" in head


def test_a_smoke_tests_pictures_say_so_on_their_face(tmp_path, monkeypatch):
    """A PNG travels without its report: the quick sweep's pictures carry the smoke-test banner, a real
    sweep's do not."""
    from matplotlib.figure import Figure

    from mapcontainer.experiments.network import SMOKE_TEST_BANNER

    titles: dict[str, str] = {}
    save = Figure.savefig

    def recording_save(fig, path, *a, **k):
        titles[f"{path.parent.name}/{path.name}"] = fig._suptitle.get_text() if fig._suptitle else ""
        return save(fig, path, *a, **k)

    monkeypatch.setattr(Figure, "savefig", recording_save)
    rows = [
        {"source": "pipeline", "mode": "distributed", "profile": f"p{lat}", "latency_ms": lat, "loss": 0.0,
         "bandwidth_bps": float("inf"), "object_rmse_m": 0.3, "vehicle_rmse_m": 0.2, "delivered_fraction": 1.0}
        for lat in (0.0, 100.0)
    ]  # fmt: skip
    (tmp_path / "q").mkdir()
    (tmp_path / "s").mkdir()
    write_network_outputs(rows, tmp_path / "q", {"seed": 0, "duration_s": 2.5, "warmup_s": 1.0, "smoke_test": True})
    write_network_outputs(rows, tmp_path / "s", {"seed": 0, "duration_s": 4.0, "warmup_s": 1.0})
    assert titles == {
        "q/network_latency.png": SMOKE_TEST_BANNER,
        "q/network_bandwidth.png": SMOKE_TEST_BANNER,
        "s/network_latency.png": "",
        "s/network_bandwidth.png": "",
    }


def test_progress_bar_writes_deciles_to_a_file():
    buf = io.StringIO()
    bar = Progress(20, "work", stream=buf)
    for _ in range(20):
        bar.update(note="x")
    bar.close()
    lines = buf.getvalue().splitlines()
    assert lines[0].startswith("work [") and "0/20" in lines[0]
    assert len(lines) == 11 and "20/20" in lines[-1] and "done" in lines[-1]
    silent = io.StringIO()
    Progress(3, stream=silent, enabled=False).update()
    assert silent.getvalue() == ""
