"""The paper experiment's figures from synthetic runs: burn-in, RMSE against time, consistency in both
forms, multi-object summaries, start-up, claims and targets (pure, fast)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from mapcontainer.experiments.paper.figures import (
    consistency,
    evaluate_claims,
    evaluate_targets,
    localized_index,
    objects_summary,
    rmse,
    startup_summary,
    time_series,
)
from mapcontainer.experiments.paper.report import _startup as report_startup


def _run(series=None, nees=None, objects=None, locks=None, seed=0) -> dict:
    return {"series": series or {}, "nees": nees or {}, "objects": objects or {}, "locks": locks or [], "seed": seed}


def test_rmse_scores_only_after_the_burnin():
    rows = [[0.5, 100.0], [2.9, 100.0], [3.0, 1.0], [5.0, 9.0]]  # start-up errors of 10 m, then 1 and 3 m
    r = _run({"x": rows})
    assert rmse([r], "x", 3.0) == pytest.approx(math.sqrt(5.0), abs=1e-4)
    assert rmse([r], "x", 0.0) == pytest.approx(math.sqrt(210 / 4), abs=1e-4)
    assert math.isnan(rmse([r], "missing", 3.0))


def test_time_series_gives_each_bucket_the_mean_and_band_over_runs():
    runs = [_run({"x": [[0.1, a**2], [0.6, a**2], [1.2, (2 * a) ** 2]]}) for a in (1.0, 2.0, 3.0)]
    ts = time_series(runs, "x")
    assert [row[0] for row in ts] == [0.0, 1.0] and [row[4] for row in ts] == [3, 3]
    assert ts[0][1] == pytest.approx(2.0) and ts[1][1] == pytest.approx(4.0)
    assert ts[0][2] == pytest.approx(np.percentile([1, 2, 3], 5)) and ts[0][3] == pytest.approx(
        np.percentile([1, 2, 3], 95)
    )


def _nees_runs(rng, n_runs: int, dof: int, scale: float) -> list[dict]:
    """Runs of NEES values of a dof-dimensional estimator whose covariance is ``scale`` times too small:
    e ~ N(0, scale P) scored against P (NEES = scale * chi2(dof)); 10 frames x 3 objects per run."""
    out = []
    for j in range(n_runs):
        rows = [
            [4.0 + 0.1 * k, 100_000 * k + i, scale * float(rng.chisquare(dof))] for k in range(10) for i in range(3)
        ]
        out.append(_run(nees={"x": rows}, seed=j))
    return out


def test_consistency_in_both_forms_catches_a_covariance_two_times_too_small():
    rng = np.random.default_rng(0)
    ok = consistency(_nees_runs(rng, 60, 6, 1.0), "x", 6, burnin_s=3.0)
    lo, hi = stats.chi2.ppf([0.025, 0.975], 60 * 6) / 60
    assert ok["runs"] == 60 and ok["band"] == pytest.approx([lo, hi], abs=1e-3) and ok["inside"]
    assert ok["cells"] == 30 and ok["cells_inside_fraction"] >= 0.85
    bad = consistency(_nees_runs(rng, 60, 6, 2.0), "x", 6, burnin_s=3.0)  # covariance 2x too small
    assert not bad["inside"] and bad["anees"] > bad["band"][1]
    assert bad["cells_inside_fraction"] < 0.2
    late = consistency(_nees_runs(rng, 60, 6, 1.0), "x", 6, burnin_s=10.0)  # every frame in the burn-in
    assert late["runs"] == 0 and "anees" not in late


def test_objects_summary_counts_coverage_false_tracks_and_gospa_parts():
    # per frame: [t, true, matched, fused, GOSPA^2, loc, missed, false]
    rows = [[0.0, 4, 0, 0, 18.0, 0.0, 18.0, 0.0], [3.0, 4, 3, 5, 1.0 + 4.5 + 9.0, 1.0, 4.5, 9.0]]
    s = objects_summary([_run(objects={"v": rows})], "v", burnin_s=3.0)
    assert s["frames"] == 1 and s["coverage"] == pytest.approx(0.75)
    assert s["false_per_frame"] == pytest.approx(2.0) and s["false_fraction"] == pytest.approx(0.4)
    assert s["gospa_m"] == pytest.approx(math.sqrt(14.5), abs=1e-4)
    assert (s["gospa_localization_m2"], s["gospa_missed_m2"], s["gospa_false_m2"]) == (1.0, 4.5, 9.0)
    assert objects_summary([_run()], "v", 3.0) == {"frames": 0}


def _vehicle(i: int, state) -> list[list[float]]:
    """Locks rows [t, i, says map_matching, error] of one vehicle over frames k = 0..40 (t = 0.0..4.0 s);
    ``state(k)`` -> (map_matching, error)."""
    return [[round(0.1 * k, 1), i, *state(k)] for k in range(41)]


NAN = float("nan")
# Vehicle start-ups, frame k -> (says map_matching, horizontal error m); frames every 0.1 s for 4 s.
# Localized = the error stays within 0.3 m for 1 s (or to the run's end).


def _locks_at_1_2(k):  # no pose for 0.4 s, 2 m off in fallback, then within from 1.2 s on
    return (0, NAN) if k < 4 else (0, 2.0) if k < 12 else (1, 0.1)


def _dip_then_at_2_0(k):  # within for one frame at 0.5 s, localizes at 2.0 s
    return (1, 0.2) if k == 5 else (0, 2.0) if k < 20 else (1, 0.1)


def _never(k):  # never within; says map_matching 1.5 m off at 3.0-3.2 s (before localizing)
    return (1, 1.5) if 30 <= k <= 32 else (0, 4.0)


def _silent(k):  # localizes at 0.5 s, then 1.5 m off at 2.0-2.4 s while saying map_matching
    return (0, 2.0) if k < 5 else (1, 1.5) if 20 <= k <= 24 else (1, 0.1)


def _said_so(k):  # localizes at 1.0 s, then 2.5 m off and without a pose at 3.0-3.2 s, in fallback
    return (0, 2.0) if k < 10 else (0, 2.5) if k in (30, 31) else (0, NAN) if k == 32 else (1, 0.1)


def _at_the_end(k):  # within from 3.5 s to the run's end (less than the hold): localized at 3.5 s
    return (0, NAN) if k < 10 else (0, 2.0) if k < 35 else (1, 0.1)


def _startup_runs(*runs) -> list[dict]:
    return [
        _run(locks=[row for i, st in enumerate(vs) for row in _vehicle(i, st)], seed=j) for j, vs in enumerate(runs)
    ]


@pytest.mark.parametrize(
    ("within", "expected"),
    [
        (range(5, 16), 5),  # 0.5-1.5 s: held for 1 s
        (list(range(5, 15)) + list(range(30, 41)), 30),  # 0.5-1.4 s is 0.9 s; from 3.0 s on
        (range(33, 41), 33),  # 3.3 s to the run's end (0.7 s left)
        ([], None),
    ],
)
def test_localized_index_holds_for_a_second_or_to_the_end(within, expected):
    t = np.round(0.1 * np.arange(41), 1)
    err = np.full(41, 0.5)
    err[list(within)] = 0.3  # on the threshold: within
    assert localized_index(t, err) == expected


def test_startup_summary_times_to_localize_and_losses_of_lock_after_it():
    runs = _startup_runs((_locks_at_1_2, _dip_then_at_2_0, _never, _silent), (_said_so, _at_the_end))
    out = startup_summary(runs, duration_s=4.1)
    # times to localize 1.2, 2.0, never, 0.5, 1.0, 3.5: sorted 0.5 1.0 1.2 2.0 3.5 inf; the q-th percentile
    # is the ceil(6 q)-th of them: median the 3rd, p90 and p95 the 6th (never)
    f = out["time_to_localize_s"]
    assert (f["median"], f["p90"], f["p95"], f["max"]) == (1.2, math.inf, math.inf, math.inf)
    assert f["never"] == 1 and f["vehicles"] == 6 and f["never_fraction"] == pytest.approx(1 / 6, abs=1e-4)
    # frames from localizing on: 29 + 21 + 36 + 31 + 6 = 123; gross: 5 silent (map matching) + 3 said so
    a = out["after_localized"]
    assert (a["frames"], a["gross_frames"], a["silent_frames"], a["silent_runs"]) == (123, 8, 5, 1)
    assert a["gross_fraction"] == pytest.approx(8 / 123, abs=1e-6)
    assert out["before_localized"] == {"silent_frames": 3, "silent_runs": 1} and out["runs"] == 2
    assert set(out["at"]) == {"1", "2", "3", "4"}
    # t = 1: localized (and within, map matching) _silent and _said_so; gross the other four (2, 2, 4, 2 m)
    assert out["at"]["1"] == {
        "map_matching": 0.3333,
        "accurate": 0.3333,
        "localized": 0.3333,
        "gross": 0.6667,
        "vehicles": 6,
    }
    # t = 2: map matching all but _never and _at_the_end; _silent is 1.5 m off; _dip_then_at_2_0 localizes now
    assert out["at"]["2"] == {"map_matching": 0.6667, "accurate": 0.5, "localized": 0.6667, "gross": 0.5, "vehicles": 6}

    without_never = startup_summary(
        _startup_runs((_locks_at_1_2, _dip_then_at_2_0, _silent), (_said_so, _at_the_end)), 4.1
    )
    f = without_never["time_to_localize_s"]  # 0.5 1.0 1.2 2.0 3.5: the 3rd, the 5th, the 5th
    assert (f["median"], f["p90"], f["p95"], f["max"], f["never"]) == (1.2, 3.5, 3.5, 3.5, 0)


def test_cold_start_targets_and_their_report():
    clean = startup_summary(_startup_runs((_locks_at_1_2, _dip_then_at_2_0)), 4.1)  # p95 2.0 s, no loss of lock
    lossy = startup_summary(_startup_runs((_locks_at_1_2, _silent), (_said_so, _at_the_end)), 4.1)  # p95 3.5 s
    res = {
        "overlap": {},
        "blindspot": {},
        "simulation": {
            key: {"consistency": {"objects_cooperative_3d": {}}, "startup": st}
            for key, st in (("urban", clean), ("suburban", lossy))
        },
    }
    rows = {t["target"]: t for t in evaluate_targets(res)}
    assert rows["urban: cold start, time to localize p95 <= 3 s"]["pass"]
    assert rows["urban: cold start, gross errors (> 1 m) after localizing <= 0.5 % of vehicle-frames"]["pass"]
    assert rows["urban: cold start, runs where a vehicle loses lock without saying so = 0"]["pass"]
    assert rows["suburban: cold start, time to localize p95 <= 6 s"]["pass"]  # 3.5 s
    gross = rows["suburban: cold start, gross errors (> 1 m) after localizing <= 0.5 % of vehicle-frames"]
    assert not gross["pass"] and gross["value"] == pytest.approx(100 * 8 / (29 + 36 + 31 + 6), abs=1e-4)
    assert rows["suburban: cold start, runs where a vehicle loses lock without saying so = 0"]["value"] == 1
    assert len(rows) == 6

    one_never = startup_summary(_startup_runs((_locks_at_1_2, _never)), 4.1)
    text = "\n".join(report_startup({"urban": {"startup": one_never}}))
    assert "| urban | 2 | 1.2 | never | never | never | 1 (50.0 %) |" in text
    assert "| urban | 29 | 0 (0.00 %) | 0 | 0 of 1 | 3 (1) |" in text  # _locks_at_1_2: frames 1.2-4.0 s


def _sim(coop, onboard, gnss, t_coop, t_ego, cov_coop, cov_ego, per_vehicle=None) -> dict:
    return {
        "ego_rmse_m": {"cooperative": coop, "onboard": onboard, "gnss": gnss, "map_matching": 0.1},
        "per_vehicle_rmse_m": per_vehicle or {"cv0": {"cooperative": coop, "onboard": onboard}},
        "target_rmse_m": {"cooperative": t_coop, "ego_only": t_ego},
        "objects": {"cooperative": {"coverage": cov_coop}, "ego_only": {"coverage": cov_ego}},
    }


def test_claims_use_the_onboard_baseline_and_consider_coverage():
    sim = {
        "urban": _sim(0.05, 0.06, 2.0, 0.3, 0.4, 0.9, 0.6),
        # suburban: fused worse than on-board for cv1; targets better but at less coverage
        "suburban": _sim(
            0.08, 0.09, 2.0, 0.3, 0.5, 0.5, 0.6,
            per_vehicle={"cv0": {"cooperative": 0.08, "onboard": 0.09}, "cv1": {"cooperative": 0.2, "onboard": 0.1}},
        ),
    }  # fmt: skip
    verdict = {c["claim"]: c["holds"] for c in evaluate_claims(sim)}
    assert verdict["urban: ego positioning cooperative < vehicle alone (on-board) < GNSS"]
    assert verdict["urban: cooperation never hurts a vehicle (fused <= on-board, every vehicle)"]
    assert not verdict["suburban: cooperation never hurts a vehicle (fused <= on-board, every vehicle)"]
    assert verdict["urban: targets cooperative < ego only (at no less coverage)"]
    assert not verdict["suburban: targets cooperative < ego only (at no less coverage)"]
    assert verdict["urban better than suburban: ego on-board"]


def test_targets_pass_and_fail_honestly_at_each_density():
    consistent = {"anees": 6.1, "band": [5.5, 6.5], "inside": True, "cells_inside_fraction": 0.93}
    res = {
        "overlap": {"dense": {"fused_m": 0.27, "independent_fusion_m": 0.2401}},
        "blindspot": {
            "ii": {
                "dense": {"connected_car_m": 0.17, "obstacle_m": 0.30},
                "sparse": {"connected_car_m": 0.3, "obstacle_m": 0.5},
            },
            "iii": {"dense": {"connected_car_m": 0.2, "obstacle_m": 0.34}},
        },
        "simulation": {
            "urban": {"consistency": {"objects_cooperative_3d": consistent}},
            "suburban": {
                "consistency": {"objects_cooperative_3d": {**consistent, "inside": False, "cells_inside_fraction": 0.4}}
            },
        },
        "bytes": {"ratio": 6.2},
    }  # fmt: skip
    verdict = {t["target"]: t["pass"] for t in evaluate_targets(res)}
    assert verdict["overlap (dense): fused <= 1.1 (1/a^2 + 1/b^2)^-1/2"] is False  # 0.27 > 1.1 * 0.2401
    assert verdict["blind spot (ii, dense): connected car <= 0.18 m"] is True
    assert verdict["blind spot (ii, sparse): connected car <= 0.18 m"] is False
    assert verdict["blind spot (iii, dense): obstacle <= 0.35 m"] is True
    assert verdict["urban: ANEES of objects (3-D, per run) inside its 95 % band"] is True
    assert verdict["suburban: per-cell object NEES inside its band, fraction >= 0.90"] is False
    assert verdict["distributed bytes/message >= 10x smaller than centralized"] is False
    nan = {**res, "bytes": {"ratio": float("nan")}}
    assert not {t["target"]: t["pass"] for t in evaluate_targets(nan)}[
        "distributed bytes/message >= 10x smaller than centralized"
    ]


def test_an_efficiency_is_valid_only_where_the_references_nees_is_in_its_band():
    from mapcontainer.experiments.paper.figures import efficiency

    fig = {
        "per_vehicle_rmse_m": {"cv0": {"centralized": 0.2, "cooperative": 0.1}},
        "vehicles_rmse_m": {"centralized": 6.14, "cooperative": 1.09},
        "target_rmse_m": {"centralized": 0.3, "cooperative": 0.3},
        "object_rmse_m": {"centralized": 0.29, "cooperative": 0.3},
        "consistency": {
            "vehicles_centralized_6dof": {"anees": 368.0, "band": [4.1, 8.3], "inside": False},
            "objects_centralized_3d": {"anees": 3.1, "band": [1.7, 4.7], "inside": True},
        },
    }
    rs = [{"tx_msgs_centralized": 10, "tx_bytes_centralized": 5000, "tx_msgs": 10, "tx_bytes": 500}]
    eff = efficiency(fig, rs)
    assert eff["valid"] == {"vehicles": False, "objects": True}
    assert eff["reference_nees"]["vehicles"] == {"anees": 368.0, "band": [4.1, 8.3]}
    # the traced suburban case: the distributed host "31.7 times as efficient" as a reference that collapsed
    assert eff["all_vehicles"] == pytest.approx((6.14 / 1.09) ** 2, rel=1e-3)
    sim = {"efficiency": eff, "consistency": {**fig["consistency"], "objects_cooperative_3d": {}}}
    res = {"overlap": {}, "blindspot": {}, "simulation": {"suburban": sim}}
    rows = {t["target"]: t for t in evaluate_targets(res)}
    veh = next(t for k, t in rows.items() if k.startswith("suburban: distributed efficiency (centralized MSE"))
    assert not veh["pass"] and "not valid" in veh["target"]
    obj = rows["suburban: distributed efficiency, objects >= 0.9"]
    assert obj["pass"] and obj["value"] == pytest.approx((0.29 / 0.3) ** 2, rel=1e-3)


def test_the_sensitivity_table_follows_the_fused_estimates_anees():
    from mapcontainer.experiments.paper import _headline

    f = {
        "ego_rmse_m": {"onboard": 0.2, "map_matching": 0.3, "cooperative": 0.15},
        "target_rmse_m": {"ego_only": 0.4, "cooperative": 0.3},
        "objects": {"ego_only": {"coverage": 0.8}, "cooperative": {"coverage": 0.9}},
        "consistency": {"vehicles_cooperative_6dof": {"anees": 22.8}, "objects_cooperative_3d": {"anees": 11.4}},
    }
    h = _headline({"urban": f, "suburban": {**f, "consistency": {}}}, {}, {"ii": {}, "iii": {}})
    assert h["urban: fused vehicles ANEES (6-DoF)"] == 22.8 and h["urban: fused objects ANEES (3-D)"] == 11.4
    assert math.isnan(h["suburban: fused objects ANEES (3-D)"])
