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
    objects_summary,
    rmse,
    startup_summary,
    time_series,
)


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


def test_startup_summary_counts_locked_vehicles_at_whole_seconds():
    ts = [round(0.1 * k, 1) for k in range(31)]
    # vehicle 0: map matching from 0.5 s, accurate; 1: map matching from 1.5 s but 2 m off; 2: never, 4 m off
    locks = [[t, i, float(t >= m), e] for t in ts for i, (m, e) in enumerate(((0.5, 0.1), (1.5, 2.0), (99, 4.0)))]
    out = startup_summary([_run(locks=locks), _run(locks=locks)], duration_s=3.1)
    assert set(out["at"]) == {"1", "2", "3"}
    one, two = out["at"]["1"], out["at"]["2"]
    assert one["map_matching"] == pytest.approx(1 / 3, abs=1e-4) and one["locked"] == pytest.approx(1 / 3, abs=1e-4)
    assert two["map_matching"] == pytest.approx(2 / 3, abs=1e-4) and two["locked"] == pytest.approx(1 / 3, abs=1e-4)
    assert two["gross"] == pytest.approx(1 / 3, abs=1e-4) and two["vehicles"] == 6
    f = out["first_locked_s"]
    assert f["vehicles"] == 6 and f["never"] == 4 and f["median"] == pytest.approx(0.5)


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
