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


def _row(mode, dcc, x, ratio):
    return {"sweep": "density", "mode": mode, "radio_profile": "its-g5", "dcc": dcc, "cpm": False,
            "vehicles_per_km": x, "rmse_vs_ideal": ratio}


def test_degradation_interpolates_the_density_of_a_10_percent_loss():
    rows = [_row("distributed", False, x, r) for x, r in ((30, 1.0), (100, 1.05), (200, 1.25))]
    rows += [_row("distributed", True, x, r) for x, r in ((30, 1.0), (100, 1.02), (200, 1.04))]
    rows += [_row("centralized", False, x, r) for x, r in ((30, 1.3), (100, 1.4))]
    rows.append({**_row("distributed", False, 30, 1.0), "radio_profile": "ideal"})
    got = {(d["mode"], d["dcc"]): d["degrades_10pct_at_per_km"] for d in degradation(rows)}
    assert got[("distributed", False)] == pytest.approx(100 + 100 * 0.05 / 0.20)
    assert got[("distributed", True)] is None
    assert got[("centralized", False)] == 30
    assert len(got) == 3
    assert not math.isnan(got[("distributed", False)])
