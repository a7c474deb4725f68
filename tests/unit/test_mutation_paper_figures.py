"""mapcontainer.experiments.paper.figures: the whole-scenario figures (sim_figures, efficiency, rv_figures,
losses of lock, pooled series) and the efficiency and target rows, each figure against a hand computation."""

from __future__ import annotations

import math

import pytest

from mapcontainer.experiments.paper import figures as fg


def _run(seed=0, series=None, nees=None, objects=None, **extra) -> dict:
    return {
        "kind": "sim",
        "key": "urban",
        "variant": "dense",
        "seed": seed,
        "vehicles": ["cv0", "cv1"],
        "series": series or {},
        "nees": nees or {},
        "objects": objects or {},
        "locks": [],
        **extra,
    }


def _sim_runs() -> list[dict]:
    """Two runs, burn-in 1 s: squared errors (m^2) chosen so every figure is a short hand computation."""
    r0 = _run(
        0,
        series={
            "cv0:cooperative": [[0.5, 100.0], [1.0, 0.04], [2.0, 0.04]],
            "cv1:cooperative": [[1.0, 0.09]],
            "cv0:centralized": [[1.0, 0.01]],
            "cv1:centralized": [[1.0, 0.04]],
            "cv0:onboard": [[0.5, 100.0], [1.0, 1.0]],  # 1 m in a scored frame: not beyond the 1 m gross error
            "cv0:gnss": [[1.0, 4.0]],
            "targets:cooperative": [[1.0, 0.25]],
            "targets:centralized": [[1.0, 0.16]],
            "targets:ego_only": [[1.0, 1.0]],
            "targets_common:ego_only": [[1.0, 0.36]],
            "objects:cooperative": [[1.0, 0.09]],
            "objects:centralized": [[1.0, 0.0729]],  # 0.27 m
        },
        tx_bytes=1000,
        tx_msgs=10,
        tx_bytes_centralized=5000,
        tx_msgs_centralized=10,
    )
    r1 = _run(
        1,
        series={"cv0:cooperative": [[1.0, 0.16]], "cv1:onboard": [[2.0, 4.0]]},  # cv1 2 m off: lost lock
        tx_bytes=1000,
        tx_msgs=10,
        tx_bytes_centralized=5000,
        tx_msgs_centralized=10,
    )
    return [r1, r0]


def test_sim_figures() -> None:
    f = fg.sim_figures(_sim_runs(), burnin_s=1.0)
    assert f["runs"] == 2
    assert f["ego_rmse_m"]["cooperative"] == round(math.sqrt(0.08), 4)
    assert f["ego_rmse_m"]["onboard"] == 1.0 and f["ego_rmse_m"]["gnss"] == 2.0
    assert math.isnan(f["ego_rmse_m"]["map_matching"])
    assert f["vehicles_rmse_m"]["cooperative"] == round(math.sqrt((0.04 + 0.04 + 0.09 + 0.16) / 4), 4)
    assert f["vehicles_rmse_m"]["centralized"] == round(math.sqrt(0.025), 4)
    assert f["per_vehicle_rmse_m"]["cv1"]["cooperative"] == 0.3 and f["per_vehicle_rmse_m"]["cv1"]["onboard"] == 2.0
    assert set(f["per_vehicle_rmse_m"]) == {"cv0", "cv1"} and set(f["ego_rmse_m"]) == set(fg.ESTIMATES)
    assert f["target_rmse_m"] == {"ego_only": 1.0, "cooperative": 0.5, "centralized": 0.4}
    assert f["target_rmse_common_m"]["ego_only"] == 0.6 and math.isnan(f["target_rmse_common_m"]["cooperative"])
    assert f["object_rmse_m"]["cooperative"] == 0.3 and f["object_rmse_m"]["centralized"] == 0.27
    assert f["objects"]["cooperative"] == {"frames": 0}
    assert f["lost_lock_runs"] == {"ego": 0, "any_vehicle": 1}
    assert set(f["consistency"]) == {
        "objects_cooperative_3d",
        "objects_centralized_3d",
        "vehicles_cooperative_6dof",
        "vehicles_onboard_6dof",
        "vehicles_map_matching_6dof",
        "vehicles_centralized_6dof",
    }
    assert f["consistency"]["objects_cooperative_3d"] == {"dof": 3, "runs": 0}


def test_efficiency_is_centralized_mse_over_distributed_mse() -> None:
    e = fg.sim_figures(_sim_runs(), burnin_s=1.0)["efficiency"]
    assert e["vehicles"] == {"cv0": round((0.1 / round(math.sqrt(0.08), 4)) ** 2, 4), "cv1": round((0.2 / 0.3) ** 2, 4)}
    coop, cent = round(math.sqrt(0.0825), 4), round(math.sqrt(0.025), 4)
    assert e["all_vehicles"] == round((cent / coop) ** 2, 4)
    assert e["targets"] == round((0.4 / 0.5) ** 2, 4) and e["objects"] == round((0.27 / 0.3) ** 2, 4)
    assert e["bytes_per_message"] == {"distributed": 100.0, "centralized": 500.0}
    assert e["bytes_ratio"] == 5.0 and e["runs"] == 2
    only_one = fg.sim_figures(
        [
            _run(
                0,
                series={"cv0:cooperative": [[1.0, 0.04]]},
                tx_bytes=0,
                tx_msgs=0,
                tx_bytes_centralized=10,
                tx_msgs_centralized=1,
            )
        ],
        1.0,
    )["efficiency"]
    assert math.isnan(only_one["bytes_ratio"]) and math.isnan(only_one["all_vehicles"])
    assert only_one["bytes_per_message"] == {"distributed": 0.0, "centralized": 10.0}
    assert fg.sim_figures([_run(0)], 1.0)["efficiency"] == {}  # no centralized estimate


def test_efficiency_ratio_needs_a_positive_distributed_figure() -> None:
    fig = {
        "per_vehicle_rmse_m": {"cv0": {"centralized": 0.1, "cooperative": 0.0}},
        "vehicles_rmse_m": {"centralized": float("nan"), "cooperative": 0.2},
        "target_rmse_m": {"centralized": 0.1, "cooperative": float("nan")},
        "object_rmse_m": {"centralized": 0.3, "cooperative": 0.2},
    }
    e = fg.efficiency(fig, [{"tx_bytes": 10, "tx_msgs": 1, "tx_bytes_centralized": 30, "tx_msgs_centralized": 1}])
    assert math.isnan(e["vehicles"]["cv0"]) and math.isnan(e["all_vehicles"]) and math.isnan(e["targets"])
    assert e["objects"] == 2.25 and e["bytes_ratio"] == 3.0 and e["runs"] == 1


def test_rv_figures_overlap() -> None:
    r = _run(
        series={
            "obstacle:ego_car": [[1.0, 0.09]],
            "obstacle:connected_car": [[1.0, 0.16]],
            "obstacle:fused": [[1.0, 0.04]],
            "cv1:onboard": [[1.0, 1.21]],
        }
    )
    out = fg.rv_figures("overlap", [r], burnin_s=1.0)
    assert (out["ego_car_m"], out["connected_car_m"], out["fused_m"]) == (0.3, 0.4, 0.2)
    assert out["independent_fusion_m"] == 0.24  # (1/0.09 + 1/0.16)^-1/2 = 0.12 / 0.5
    assert out["lost_lock_runs"] == 1 and out["runs"] == 1  # the connected car 1.1 m off
    assert set(out["objects"]) == {"ego_car", "connected_car", "fused"}
    none = fg.rv_figures("overlap", [_run(series={"obstacle:ego_car": [[1.0, 0.09]]})], 1.0)
    assert math.isnan(none["independent_fusion_m"]) and none["lost_lock_runs"] == 0


def test_rv_figures_blind_spot() -> None:
    r = _run(
        series={
            "cv1:cooperative": [[1.0, 0.01]],
            "cv1:onboard": [[1.0, 0.04]],
            "cv1:map_matching": [[1.0, 0.09]],
            "obstacle:cooperative": [[1.0, 0.16]],
            "obstacle:ego_only": [[1.0, 0.25]],
        }
    )
    out = fg.rv_figures("blindspot", [r, r], burnin_s=1.0)
    assert out == {
        "connected_car_m": 0.1,
        "connected_car_onboard_m": 0.2,
        "connected_car_map_matching_m": 0.3,
        "obstacle_m": 0.4,
        "ego_only_obstacle_m": 0.5,
        "objects": {"ego_only": {"frames": 0}, "cooperative": {"frames": 0}},
        "lost_lock_runs": 0,
        "runs": 2,
    }


def test_group_orders_each_cell_by_seed() -> None:
    rs = [{"kind": "a", "key": "k", "variant": "v", "seed": s} for s in (3, 1, 2)] + [
        {"kind": "a", "key": "k", "variant": "w", "seed": 0}
    ]
    g = fg.group(rs)
    assert [r["seed"] for r in g[("a", "k", "v")]] == [1, 2, 3] and len(g[("a", "k", "w")]) == 1 and len(g) == 2


def test_run_rmse_and_burnin_edge() -> None:
    r = _run(series={"x": [[0.9999999999, 9.0], [2.0, 1.0], [3.0, 4.0]]})
    assert fg.run_rmse(r, "x", 1.0) == pytest.approx(math.sqrt(14 / 3))  # within 1e-9 of the burn-in: scored
    assert fg.run_rmse(r, "x", 2.5) == 2.0 and math.isnan(fg.run_rmse(r, "y", 0.0))
    assert fg.rmse([r], "x", 2.5) == 2.0 and math.isnan(fg.rmse([], "x", 0.0))
    assert fg.rmse([r], "x", 1.5) == round(math.sqrt(2.5), 4)


def test_time_series_of_no_runs_and_buckets() -> None:
    assert fg.time_series([], "x") == []
    ts = fg.time_series([_run(series={"x": [[0.2, 1.0], [0.7, 9.0]]})], "x", bucket_s=0.5)
    assert ts == [[0.0, 1.0, 1.0, 1.0, 1], [0.5, 3.0, 3.0, 3.0, 1]]


def test_pooled_consistency_keeps_vehicles_apart_and_averages_cells() -> None:
    runs = [_run(j, nees={"cv0:cooperative": [[1.0, 7, 6.0]], "cv1:cooperative": [[1.0, 7, 12.0]]}) for j in range(5)]
    c = fg.sim_figures(runs, 1.0)["consistency"]["vehicles_cooperative_6dof"]
    assert c["runs"] == 5 and c["anees"] == 9.0 and c["cells"] == 2  # cell 7 of cv0 and of cv1: two cells
    assert c["dof"] == 6 and c["per_run_p5_p50_p95"] == [9.0, 9.0, 9.0]
    assert c["cells_inside_fraction"] == 0.5  # 6 inside the 5-run band of 6 dof, 12 above it
    four = fg.consistency([_run(j, nees={"x": [[1.0, 1, 3.0]]}) for j in range(4)], "x", 3, 1.0)
    assert four["cells"] == 0 and math.isnan(four["cells_inside_fraction"])  # fewer than 5 runs per cell


def test_objects_summary_without_truth_or_fused() -> None:
    s = fg.objects_summary([_run(objects={"v": [[1.0, 0, 0, 0, 0.0, 0.0, 0.0, 0.0]]})], "v", 1.0)
    assert math.isnan(s["coverage"]) and math.isnan(s["false_fraction"])
    assert (s["false_per_frame"], s["gospa_m"], s["frames"]) == (0.0, 0.0, 1)
    two = fg.objects_summary(
        [
            _run(objects={"v": [[1.0, 2, 1, 1, 4.5, 0.0, 4.5, 0.0]]}),
            _run(objects={"v": [[2.0, 2, 2, 3, 4.5, 0.0, 0.0, 4.5]]}),
        ],
        "v",
        1.0,
    )
    assert (two["coverage"], two["false_per_frame"], two["false_fraction"], two["frames"]) == (0.75, 0.5, 0.25, 2)
    assert (two["gospa_missed_m2"], two["gospa_false_m2"]) == (2.25, 2.25)


def test_efficiency_targets_and_bytes_rows() -> None:
    res = {
        "overlap": {},
        "blindspot": {},
        "simulation": {
            "urban": {
                "consistency": {"objects_cooperative_3d": {}},
                "efficiency": {
                    "all_vehicles": 0.9,
                    "objects": 0.89,
                    "bytes_ratio": 5.0,
                    "valid": {"vehicles": True, "objects": True},
                },
            }
        },
        "bytes": {"ratio": 10.0},
    }
    rows = {t["target"]: t for t in fg.evaluate_targets(res)}
    v = rows["urban: distributed efficiency (centralized MSE / distributed MSE), vehicles >= 0.9"]
    assert v == {"target": v["target"], "value": 0.9, "threshold": 0.9, "pass": True}
    assert not rows["urban: distributed efficiency, objects >= 0.9"]["pass"]
    assert rows["urban: centralized bytes per message / distributed >= 5"]["pass"]
    assert rows["distributed bytes/message >= 10x smaller than centralized"]["pass"]
    assert len(rows) == 4
    # against a reference whose NEES is outside its band, an efficiency that would pass fails as not valid
    res["simulation"]["urban"]["efficiency"]["valid"] = {"vehicles": False, "objects": True}
    rows = {t["target"]: t for t in fg.evaluate_targets(res)}
    invalid = "urban: distributed efficiency (centralized MSE / distributed MSE), vehicles >= 0.9"
    invalid += " (not valid: the reference's NEES is outside its band)"
    assert rows[invalid] == {"target": invalid, "value": 0.9, "threshold": 0.9, "pass": False}


def test_overlap_and_blind_spot_target_bounds() -> None:
    res = {
        "overlap": {"sparse": {"fused_m": 0.264, "independent_fusion_m": 0.24}},
        "blindspot": {"ii": {"sparse": {"connected_car_m": 0.18, "obstacle_m": 0.35}}},
        "simulation": {},
    }
    rows = {t["target"]: t for t in fg.evaluate_targets(res)}
    o = rows["overlap (sparse): fused <= 1.1 (1/a^2 + 1/b^2)^-1/2"]
    assert (o["value"], o["threshold"], o["pass"]) == (0.264, 0.264, True)  # at the bound: passes
    assert rows["blind spot (ii, sparse): connected car <= 0.18 m"]["pass"]
    assert rows["blind spot (ii, sparse): obstacle <= 0.35 m"]["threshold"] == 0.35
    assert len(rows) == 3
    assert fg._row("x", float("nan"), 1.0, ">=")["pass"] is False and fg._row("x", 1.0, 1.0, ">=")["pass"] is True


def test_bytes_per_message_to_a_tenth() -> None:
    r = _run(
        0,
        series={"cv0:cooperative": [[1.0, 0.04]]},
        tx_bytes=1000,
        tx_msgs=3,
        tx_bytes_centralized=2000,
        tx_msgs_centralized=3,
    )
    e = fg.sim_figures([r], 1.0)["efficiency"]
    assert e["bytes_per_message"] == {"distributed": 333.3, "centralized": 666.7} and e["bytes_ratio"] == 2.0


def test_independent_fusion_of_a_perfect_view_is_not_computed() -> None:
    r = _run(
        series={
            "obstacle:ego_car": [[1.0, 0.09]],
            "obstacle:connected_car": [[1.0, 0.0]],
            "obstacle:fused": [[1.0, 0.04]],
        }
    )
    out = fg.rv_figures("overlap", [r], 1.0)
    assert out["connected_car_m"] == 0.0 and math.isnan(out["independent_fusion_m"])


def test_time_to_localize_is_rounded_to_10_ms() -> None:
    """Frames every 0.125 s; within from the fourth frame on: localized 0.375 s after the first, reported 0.38 s."""
    locks = [[0.125 * k, 0, 1, 0.5 if k < 3 else 0.1] for k in range(24)]
    st = fg.startup_summary([_run(locks=locks)], duration_s=3.0)
    f = st["time_to_localize_s"]
    assert (f["median"], f["p90"], f["p95"], f["max"], f["never"], f["vehicles"]) == (0.38, 0.38, 0.38, 0.38, 0, 1)


def test_consistency_per_run_percentiles() -> None:
    runs = [_run(j, nees={"x": [[1.0, 1, float(v)]]}) for j, v in enumerate([1, 2, 3, 4, 10])]
    c = fg.consistency(runs, "x", 3, 1.0)
    assert c["per_run_p5_p50_p95"] == [1.2, 3.0, 8.8] and c["anees"] == 4.0 and c["cells"] == 1


def test_centralized_objects_consistency_is_three_dof() -> None:
    assert fg.sim_figures(_sim_runs(), 1.0)["consistency"]["objects_centralized_3d"] == {"dof": 3, "runs": 0}


def test_overlap_objects_per_view() -> None:
    rows = {n: [[1.0, 2, k, k, 0.0, 0.0, 0.0, 0.0]] for k, n in enumerate(("ego_car", "connected_car", "fused"))}
    out = fg.rv_figures("overlap", [_run(objects={f"obstacle:{n}": v for n, v in rows.items()})], 1.0)
    assert [out["objects"][n]["coverage"] for n in ("ego_car", "connected_car", "fused")] == [0.0, 0.5, 1.0]


def test_silent_frames_add_up_over_the_vehicles_of_a_run() -> None:
    """Two vehicles of one run, each localized from the start, then silent (1.5 m off, saying map matching)."""
    locks = [[0.125 * k, i, 1, 1.5 if k >= 10 + i else 0.1] for i in (0, 1) for k in range(16)]
    st = fg.startup_summary([_run(locks=locks)], duration_s=2.0)
    a = st["after_localized"]
    assert (a["frames"], a["gross_frames"], a["silent_frames"], a["silent_runs"]) == (32, 11, 11, 1)


def test_a_target_claim_needs_a_strictly_smaller_error() -> None:
    sim = {
        key: {
            "ego_rmse_m": {"cooperative": 0.1, "onboard": 0.2, "gnss": 2.0},
            "per_vehicle_rmse_m": {},
            "target_rmse_m": {"cooperative": 0.3, "ego_only": 0.3},
            "objects": {"cooperative": {"coverage": 0.9}, "ego_only": {"coverage": 0.9}},
        }
        for key in ("urban", "suburban")
    }
    verdict = {c["claim"]: c["holds"] for c in fg.evaluate_claims(sim)}
    assert verdict["urban: targets cooperative < ego only (at no less coverage)"] is False
