"""mapcontainer.evaluation: exact figures of the secondary outputs (NEES sums, horizontal-only errors, scopes,
age of information, the summary's empty cases), so a wrong constant or a dropped filter fails a test."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from mapcontainer import evaluation as ev

from .test_evaluation import HALF, fused_state, truth_state

DIAG_POSE = np.diag([0.01, 0.04, 0.25, 1e-4, 4e-4, 9e-4])  # sigmas 0.1, 0.2, 0.5 m; 0.01, 0.02, 0.03 rad


def _one_vehicle_frame(err6, t=1.0, cov=DIAG_POSE, objects=(), obstacles=(), obj_cov=None) -> ev.FrameScore:
    truth_pose = np.array([10.0, -5.0, 1.0, 0.0, 0.0, 0.5])
    fused = fused_state(
        t, poses=[truth_pose + np.asarray(err6, float)], pose_covs=cov[None], objects=objects, obj_covs=obj_cov
    )
    return ev.score_frame(fused, truth_state(t, poses=[truth_pose], obstacles=obstacles))


def test_vehicle_error_is_horizontal_and_nees_is_six_dof() -> None:
    s = _one_vehicle_frame([0.1, 0.2, 0.5, 0.01, 0.02, 0.03])  # one sigma on every axis
    assert s.vehicle_sq.tolist() == pytest.approx([0.05])  # x, y only: the 0.5 m height error is left out
    assert s.vehicle_nees.tolist() == pytest.approx([6.0])
    assert s.vehicle_err.shape == (1, 6) and s.vehicle_cov.shape == (1, 6, 6)
    assert s.vehicle_cov[0] == pytest.approx(DIAG_POSE)
    row = ev.frame_row(s)
    assert row["vehicle_sq_sum_m2"] == pytest.approx(0.05) and row["vehicle_nees_sum"] == pytest.approx(6.0)
    assert (row["vehicle_pairs"], row["t_meas"]) == (1, 1.0)


def test_object_error_is_horizontal_and_nees_is_three_dof() -> None:
    cov = np.diag([0.04, 0.09, 0.16])[None]
    s = _one_vehicle_frame(np.zeros(6), objects=[[0.2, 0.3, 0.4]], obstacles=[[0, 0, 0]], obj_cov=cov)
    assert s.object_sq.tolist() == pytest.approx([0.13])
    assert s.object_nees.tolist() == pytest.approx([3.0])
    assert s.object_err == pytest.approx(np.array([[0.2, 0.3, 0.4]]))
    assert s.object_truth_ids.tolist() == [0] and s.object_cov[0] == pytest.approx(cov[0])
    row = ev.frame_row(s)
    assert (row["object_sq_sum_m2"], row["object_nees_sum"]) == (pytest.approx(0.13), pytest.approx(3.0))
    assert (row["object_pairs"], row["obstacles"], row["objects"], row["false_tracks"]) == (1, 1, 1, 0)
    assert (row["gospa_localization_m2"], row["gospa_missed_m2"], row["gospa_false_m2"]) == (
        pytest.approx(0.13),
        0.0,
        0.0,
    )


def test_empty_frames_have_empty_nees() -> None:
    s = ev.score_frame(fused_state(poses=np.zeros((0, 6))), truth_state())
    assert s.vehicle_nees.shape == (0,) and s.object_nees.shape == (0,)
    assert s.coverage is None and s.n_matched == 0


def test_totals_vehicle_nees_and_in_band_count() -> None:
    lo6, hi6 = stats.chi2.ppf([0.025, 0.975], 6)
    tot = ev.Totals()
    tot.add(_one_vehicle_frame([0.1, 0.2, 0.5, 0.01, 0.02, 0.03], t=1.0))  # NEES 6: in band
    tot.add(_one_vehicle_frame([0.3, 0.6, 1.5, 0.03, 0.06, 0.09], t=2.0))  # NEES 54: above
    tot.add(_one_vehicle_frame([0.0, 0.0, 0.0, 0.0, 0.0, 0.0], t=3.0))  # NEES 0: below
    assert lo6 < 6.0 < hi6 < 54.0
    s = tot.summary()
    v = s["vehicle_nees"]
    assert v["anees"] == pytest.approx(20.0) and v["cells"] == 3
    assert v["nees_in_band"] == pytest.approx(1 / 3)
    assert v["anees_band"] == pytest.approx(list(stats.chi2.ppf([0.025, 0.975], 18) / 3))
    assert s["vehicle_rmse_m"] == pytest.approx(np.sqrt((0.05 + 0.45 + 0.0) / 3))
    assert s["vehicle_pairs"] == 3 and s["vehicle_rmse_by_id_m"] == {"cv0": pytest.approx(s["vehicle_rmse_m"])}
    assert s["object_nees"] == {"anees": None, "anees_band": None, "nees_in_band": None, "cells": 0}
    assert (s["object_rmse_m"], s["object_pairs"], s["coverage"]) == (None, 0, None)
    assert (s["false_tracks_per_frame"], s["false_track_fraction"]) == (0.0, None)
    assert (s["gospa_m"], s["gospa_localization_m2"], s["gospa_missed_m2"], s["gospa_false_m2"]) == (0.0, 0.0, 0.0, 0.0)


def test_totals_object_in_band_uses_the_three_dof_band() -> None:
    lo3, hi3 = stats.chi2.ppf([0.025, 0.975], 3)
    cov = np.eye(3)[None]
    tot = ev.Totals()
    for e in (0.5, 3.0):  # NEES 0.75 (in the 3-dof band, below the 6-dof one), 27 (above)
        tot.add(_one_vehicle_frame(np.zeros(6), objects=[[e, e, e]], obstacles=[[0, 0, 0]], obj_cov=cov))
    assert lo3 < 0.75 < hi3 and 0.75 < stats.chi2.ppf(0.025, 6)
    o = tot.summary()["object_nees"]
    assert (o["cells"], o["nees_in_band"]) == (1, 1.0)  # the 3 m error is beyond the GOSPA cutoff: no pair
    assert o["anees"] == pytest.approx(0.75)


def test_an_empty_summary() -> None:
    s = ev.Totals().summary()
    assert s["frames"] == 0 and s["vehicle_rmse_by_id_m"] == {}
    for k in (
        "vehicle_rmse_m",
        "object_rmse_m",
        "coverage",
        "false_tracks_per_frame",
        "false_track_fraction",
        "gospa_m",
        "gospa_localization_m2",
        "gospa_missed_m2",
        "gospa_false_m2",
    ):
        assert s[k] is None, k
    assert s["vehicle_nees"] == {"anees": None, "anees_band": None, "nees_in_band": None, "cells": 0}


def test_totals_over_two_vehicles_by_id() -> None:
    truth = truth_state(poses=[[0, 0, 0, 0, 0, 0], [50, 0, 0, 0, 0, 0]], ids=["cv0", "cv1"])
    tot = ev.Totals()
    tot.add(ev.score_frame(fused_state(poses=[[0.3, 0.4, 0, 0, 0, 0], [50, 1, 0, 0, 0, 0]], ids=["cv0", "cv1"]), truth))
    tot.add(ev.score_frame(fused_state(poses=[[50, 3, 0, 0, 0, 0]], ids=["cv1"]), truth))
    s = tot.summary()
    assert s["vehicle_rmse_by_id_m"] == {"cv0": pytest.approx(0.5), "cv1": pytest.approx(np.sqrt(5.0))}
    assert s["vehicle_rmse_m"] == pytest.approx(np.sqrt((0.25 + 1 + 9) / 3)) and s["vehicle_pairs"] == 3


def test_obstacle_errors_keep_only_the_obstacles_within() -> None:
    truth = truth_state(obstacles=[[0, 0, 0], [10, 0, 0], [20, 0, 0]])
    cov = np.stack([np.eye(3) * k for k in (1.0, 2.0, 3.0)])
    fused = fused_state(objects=[[20.5, 0, 0], [0.1, 0, 0], [10, 0.2, 0]], obj_covs=cov)
    ids, err, c = ev.obstacle_errors(fused, truth)
    assert ids.tolist() == [0, 1, 2]
    assert err == pytest.approx(np.array([[0.1, 0, 0], [0, 0.2, 0], [0.5, 0, 0]]))
    assert [float(x[0, 0]) for x in c] == [2.0, 3.0, 1.0]
    ids, err, c = ev.obstacle_errors(fused, truth, within=np.array([True, False, True]))
    assert ids.tolist() == [0, 2] and err == pytest.approx(np.array([[0.1, 0, 0], [0.5, 0, 0]]))
    assert [float(x[0, 0]) for x in c] == [2.0, 1.0]
    ids, err, _ = ev.obstacle_errors(fused, truth, gate_m=0.3)
    assert ids.tolist() == [0, 1]


def test_relative_target_errors_in_the_ego_frame() -> None:
    """Ego at the origin facing +y (yaw pi/2), fused 0.1 m off in x: a target ahead is seen 0.1 m to the side."""
    truth = truth_state(poses=[[0, 0, 0, 0, 0, np.pi / 2]], obstacles=[[0, 10, 0], [0, 60, 0]])
    fused = fused_state(poses=[[0.1, 0, 0, 0, 0, np.pi / 2]], objects=[[0, 10, 0], [0, 60, 0]])
    ids, err, n_near = ev.relative_target_errors(fused, truth, "cv0", radius_m=50.0)
    assert ids.tolist() == [0] and n_near == 1
    assert err == pytest.approx(np.array([[0.0, 0.1]]), abs=1e-6)  # body frame: x ahead, y left (float32 on the wire)
    ids, err, n_near = ev.relative_target_errors(fused, truth, "cv0", radius_m=60.0)
    assert ids.tolist() == [0, 1] and n_near == 2
    ids, err, n_near = ev.relative_target_errors(fused, truth, "cv9", radius_m=50.0)
    assert (ids.shape, err.shape, n_near) == ((0,), (0, 2), 0) and ids.dtype == np.int64
    ids, err, _ = ev.relative_target_errors(fused, truth, "cv0", radius_m=50.0)
    assert ids.dtype == np.int64 and err.shape == (1, 2)


def test_within_radius_is_horizontal_and_inclusive() -> None:
    p = [[3, 4, 100], [3, 4.0001, 0], [0, 0, 0]]
    assert ev.within_radius(p, [0, 0, -50], 5.0).tolist() == [True, False, True]
    assert ev.within_radius(np.zeros((0, 3)), [0, 0], 5.0).shape == (0,)


def test_age_of_information_counts_from_t_start_and_from_the_newest_arrival() -> None:
    deliveries = [
        ("a", 10.0, 10.05),  # a's message stamped 10.0 arrives 10.05
        ("a", 10.2, 10.4),  # later stamp, late arrival
        ("a", 10.1, 10.15),
        ("b", 10.3, 10.31),
    ]
    times = [10.0, 10.1, 10.2, 10.5]
    age = ev.age_of_information(deliveries, ["a", "b", "c"], times, t_start=9.5)
    expected = np.array(
        [
            [0.5, 0.5, 0.5],  # nothing arrived yet: counted from t_start
            [0.1, 0.6, 0.6],  # a's 10.0 arrived at 10.05
            [0.1, 0.7, 0.7],  # a's 10.1 arrived at 10.15
            [0.3, 0.2, 1.0],  # a's 10.2 arrived at 10.4; b's 10.3 at 10.31
        ]
    )
    assert age == pytest.approx(expected, abs=1e-12)
    # an arrival exactly at a fuse time counts; a later stamp arriving earlier is the newest
    at = ev.age_of_information([("a", 1.0, 2.0), ("a", 0.5, 2.5)], ["a"], [2.0, 3.0], t_start=0.0)
    assert at[:, 0] == pytest.approx([1.0, 2.0])


def test_rmse_vs_time_refuses_a_zero_bucket_and_buckets_by_width() -> None:
    for b in (0.0, -1.0):
        with pytest.raises(ValueError, match="bucket_s must be > 0"):
            ev.rmse_vs_time([0.0], [1.0], [0], bucket_s=b)
    r = ev.rmse_vs_time([0.0, 0.4, 0.6, 2.0], [1.0, 9.0, 4.0, 16.0], [0, 0, 0, 0], bucket_s=0.5)
    assert r.t_start.tolist() == [0.0, 0.5, 2.0]
    assert r.mean.tolist() == pytest.approx([np.sqrt(5.0), 2.0, 4.0])
    assert r.runs.tolist() == [1, 1, 1] and r.lo.tolist() == pytest.approx(r.mean.tolist())
    with pytest.raises(ValueError, match="1-D"):
        ev.rmse_vs_time(np.zeros((1, 1)), np.zeros((1, 1)), np.zeros((1, 1)))
    band = ev.rmse_vs_time([0.1] * 5, [1.0, 4.0, 9.0, 16.0, 25.0], [0, 1, 2, 3, 4], band=(25.0, 75.0))
    assert (band.lo.tolist(), band.hi.tolist(), band.mean.tolist()) == ([2.0], [4.0], [3.0])


def test_gospa_parts_and_distance() -> None:
    g = ev.gospa_parts([1.0, 2.0], n_missed=1, n_false=2)
    assert g == ev.Gospa(5.0, HALF, 2 * HALF) and g.total == pytest.approx(5.0 + 3 * HALF)
    assert g.distance == pytest.approx(np.sqrt(5.0 + 13.5))
    assert ev.gospa_parts([], 0, 0).distance == 0.0
    with pytest.raises(ValueError, match="below the cutoff 3.0"):
        ev.gospa_parts([3.0], 0, 0)
    g1 = ev.gospa([[1.0, 0.0], [9.0, 0.0]], [[0.0, 0.0]], c=2.5, p=1)
    assert (g1.localization, g1.missed, g1.false, g1.p) == (1.0, 0.0, 1.25, 1)
    p1 = ev.gospa_parts([1.0, 2.0], 1, 0, c=2.5, p=1)
    assert (p1.localization, p1.missed, p1.p, p1.distance) == (3.0, 1.25, 1, pytest.approx(4.25))


def test_nees_band_and_anees_at_another_confidence() -> None:
    assert ev.nees_band(3, 0.9) == pytest.approx(tuple(stats.chi2.ppf([0.05, 0.95], 3)))
    a = ev.anees([2.0, 4.0], 3, confidence=0.5)
    assert (a.value, a.n) == (3.0, 2) and (a.lo, a.hi) == pytest.approx(tuple(stats.chi2.ppf([0.25, 0.75], 6) / 2))
    assert a.inside and not ev.Anees(a.hi + 1e-9, a.lo, a.hi, 2).inside and ev.Anees(a.lo, a.lo, a.hi, 2).inside
    assert ev.fraction_in_band([0.0, 3.0, 100.0], 3) == pytest.approx(1 / 3)
    assert ev.fraction_in_band([0.2, 3.0], 3, confidence=0.5) == 0.5
    e = ev.anees([], 3)
    assert np.isnan(e.value) and np.isnan(e.lo) and np.isnan(e.hi)


def test_match_vehicles_and_vehicle_pose() -> None:
    ti, fi = ev.match_vehicles(["cv2", "x", "cv0"], ["cv0", "cv1", "cv2"])
    assert (ti.tolist(), fi.tolist()) == ([2, 0], [0, 2])
    ti, fi = ev.match_vehicles([], ["cv0"])
    assert (ti.tolist(), fi.tolist()) == ([], []) and ti.dtype.kind == fi.dtype.kind == "i"
    truth = truth_state(poses=[[1, 2, 3, 0, 0, 0]], ids=["cv5"])
    assert ev.vehicle_pose(truth, "cv5").tolist() == [1, 2, 3, 0, 0, 0] and ev.vehicle_pose(truth, "cv0") is None


def test_helpers() -> None:
    assert ev.horizontal_sq_error([1, 2, 30], [0, 0, 0]) == 5.0
    assert ev.horizontal_sq_error([3, 5, 0], [2, 3, 7]) == 5.0
    assert ev.rmse_sq([1.0, 9.0]) == pytest.approx(np.sqrt(5.0)) and ev.rmse_sq(np.array([4.0])) == 2.0
    assert np.isnan(ev.rmse_sq([]))
    assert ev.pose_error([[0, 0, 0, 0, 0, 3.0]], [[1, 0, 0, 0, 0, -3.0]]) == pytest.approx(
        np.array([[-1, 0, 0, 0, 0, 6.0 - 2 * np.pi]])
    )
    assert (ev.GOSPA_P, ev.GOSPA_ALPHA, ev.GOSPA_C_M, ev.GATE_M, ev.CONFIDENCE) == (2, 2, 3.0, 3.0, 0.95)
    assert (ev.VEHICLE_DOF, ev.OBJECT_DOF) == (6, 3)


def test_score_frame_names_bad_scope_masks() -> None:
    fused, truth = fused_state(objects=[[0, 0, 0]]), truth_state(obstacles=[[0, 0, 0], [5, 0, 0]])
    with pytest.raises(ValueError, match=r"scope masks \(3,\), \(1,\) for 2 obstacles, 1 objects"):
        ev.score_frame(fused, truth, truth_in_scope=np.ones(3, bool))


def test_gospa_of_a_frame_checks_each_pair_against_the_cutoff() -> None:
    """Two pairs 2.5 m off: each below the 3 m cutoff (together 3.5 m: not a reason to refuse)."""
    s = ev.score_frame(fused_state(objects=[[2.5, 0, 0], [22.5, 0, 0]]), truth_state(obstacles=[[0, 0, 0], [20, 0, 0]]))
    assert s.gospa == ev.Gospa(pytest.approx(12.5), 0.0, 0.0) and s.n_matched == 2


def test_rmse_vs_time_of_nothing_is_empty_arrays() -> None:
    r = ev.rmse_vs_time([], [], [])
    assert [a.shape for a in (r.t_start, r.mean, r.lo, r.hi, r.runs)] == [(0,)] * 5 and r.runs.dtype.kind == "i"
