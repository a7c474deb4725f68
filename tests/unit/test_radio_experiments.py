"""The radio sweeps' scenario builders and the 10 %-degradation read-out (mapcontainer.experiments.network_radio)."""

from __future__ import annotations

import math

import pytest

from mapcontainer.experiments.network_radio import degradation, density_scenario, gap_scenario, vehicles_per_km


def test_gap_scenario_moves_the_connected_vehicle_and_its_obstacle():
    sc = gap_scenario(150.0)
    ego, cv1 = sc.connected
    assert cv1.s0_m - ego.s0_m == pytest.approx(150.0)
    assert len(sc.obstacle_vehicles) == 1 and sc.obstacle_vehicles[0].s0_m - ego.s0_m == pytest.approx(162.0)


def test_density_scenario_adds_vehicles_over_the_lanes():
    base, dense = density_scenario(0), density_scenario(40)
    assert len(dense.obstacle_vehicles) == len(base.obstacle_vehicles) + 40
    assert {v.lane for v in dense.obstacle_vehicles[-40:]} == {0, 1, 2, 3}
    assert vehicles_per_km(dense) == pytest.approx(vehicles_per_km(base) + 40 / 0.36, rel=1e-6)


def _row(mode, dcc, x, ratio, seed=0):
    return {
        "sweep": "density",
        "seed": seed,
        "mode": mode,
        "radio_profile": "its-g5",
        "dcc": dcc,
        "cpm": False,
        "vehicles_per_km": x,
        "rmse_vs_ideal": ratio,
    }


def test_degradation_interpolates_the_density_of_a_10_percent_loss():
    rows = [_row("distributed", False, x, r) for x, r in ((30, 1.0), (100, 1.05), (200, 1.25))]
    rows += [_row("distributed", True, x, r) for x, r in ((30, 1.0), (100, 1.02), (200, 1.04))]
    rows += [_row("centralized", False, x, r) for x, r in ((30, 1.3), (100, 1.4))]
    rows.append({**_row("distributed", False, 30, 1.0), "radio_profile": "ideal"})
    got = {(d["mode"], d["dcc"]): d["degrades_10pct_at_per_km"] for d in degradation(rows)}
    assert got[("distributed", False)] == pytest.approx(100 + 100 * 0.05 / 0.20)
    assert got[("distributed", True)] is None
    assert got[("centralized", False)] == 30
    below = {(d["mode"], d["dcc"]): d["degrades_10pct_at_per_km_at_or_below_lowest_density"] for d in degradation(rows)}
    assert below == {("distributed", False): False, ("distributed", True): False, ("centralized", False): True}
    assert len(got) == 3
    assert not math.isnan(got[("distributed", False)])


def test_degradation_reads_the_mean_over_seeds_and_reports_their_spread():
    rows = [_row("distributed", False, x, r, seed=0) for x, r in ((30, 1.0), (100, 1.3))]
    rows += [_row("distributed", False, x, r, seed=1) for x, r in ((30, 1.0), (100, 0.9))]
    (d,) = degradation(rows)
    assert d["rmse_vs_ideal"] == [1.0, pytest.approx(1.1)] and d["rmse_vs_ideal_seeds"] == [2, 2]
    assert d["rmse_vs_ideal_min"] == [1.0, 0.9] and d["rmse_vs_ideal_max"] == [1.0, 1.3]
    assert d["degrades_10pct_at_per_km"] == pytest.approx(100.0)  # the mean reaches 1.1 there, not seed 0's 1.3
    rows.append(_row("distributed", False, 200, float("nan"), seed=0))  # a run without a fused vehicle
    assert degradation(rows)[0]["rmse_vs_ideal_seeds"] == [2, 2, 0]


def test_rmse_vs_ideal_pairs_each_run_with_the_ideal_run_of_its_seed():
    from mapcontainer.experiments.network_radio import _reference

    rows = []
    for seed, ideal, radio in ((0, 0.2, 0.22), (1, 0.4, 0.4)):
        rows.append(
            {**_row("distributed", False, 30, None, seed), "radio_profile": "ideal", "x": 0, "vehicle_rmse_m": ideal}
        )
        rows.append({**_row("distributed", False, 30, None, seed), "x": 0, "vehicle_rmse_m": radio})
    rows.append({**_row("distributed", False, 90, None, 0), "x": 40, "vehicle_rmse_m": 0.44})  # denser, seed 0
    _reference(rows)
    assert [r["rmse_vs_ideal"] for r in rows if r["radio_profile"] != "ideal"][:2] == [pytest.approx(1.1), 1.0]
    assert math.isnan(rows[-1]["rmse_vs_ideal"])  # no ideal run at that density
    assert rows[-1]["rmse_vs_sparsest"] == pytest.approx(2.0)  # against seed 0's its-g5 run at the lowest density
    assert rows[1]["rmse_vs_sparsest"] == 1.0


@pytest.mark.slow
def test_link_cost_times_the_channel_of_each_profile():
    from mapcontainer.experiments.radio import link_cost

    doc = link_cost(vehicles=2, duration_s=0.6, profiles=("ideal", "its-g5"))
    ideal, radio = doc["runs"]
    assert doc["connected_vehicles"] == 2 and ideal["run_cpu_vs_first"] == 1.0
    assert radio["calls"]["observe"] >= 5 and radio["calls"]["send"] >= 5  # a frame each 0.1 s; a prior each
    assert 0 < radio["channel_cpu_s"] <= radio["run_cpu_s"] and "observe" not in ideal["calls"]


def test_radio_figures_of_a_run():
    from mapcontainer.experiments.network_radio import radio_figures
    from mapcontainer.pipeline import PipelineResult

    res = PipelineResult("s", 0, "distributed", "its-g5", "cv0", duration_s=2.0)
    res.tx_msgs.update({"cv1": 20, "cv2": 20})
    res.tx_bytes.update({"cv1": 10000, "cv2": 10000})
    res.channel_stats = {
        "offered_msgs": 40,
        "radio_drops": {"dcc": 4, "sensing": 2, "propagation": 0, "collision": 2, "half_duplex": 0},
        "radio_drop_bytes": {"dcc": 2000},
        "cbr": {"cv0": {"mean": 0.1, "max": 0.2}, "cv1": {"mean": 0.3, "max": 0.4}, "7": {"mean": 0.9, "max": 1.0}},
        "link_states": {"los": 6, "nlosv": 2, "nlos": 2},
    }
    f = radio_figures(res)
    assert f["cbr_mean"] == pytest.approx(0.2)  # the ego and the senders, not the background vehicle 7
    assert f["drop_dcc_fraction"] == pytest.approx(0.1) and f["drop_collision_fraction"] == pytest.approx(0.05)
    assert f["state_nlos_fraction"] == pytest.approx(0.2)
    assert f["bytes_on_air_per_s_per_vehicle"] == pytest.approx((20000 - 2000) / 2.0 / 2)
    res.channel_stats = {"offered_msgs": 40}  # a classic link
    assert math.isnan(radio_figures(res)["cbr_mean"])
