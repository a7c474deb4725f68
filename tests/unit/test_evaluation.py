"""mapcontainer.evaluation: matching, GOSPA (against Stone Soup and by hand), NEES bands, coverage, totals."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from mapcontainer import evaluation as ev
from mapcontainer.fusion.poses import upper_from_sym
from schemas import FusedState, GroundTruth

C = ev.GOSPA_C_M
HALF = C**ev.GOSPA_P / 2  # what one miss or one false track costs


def truth_state(t=1.0, poses=((0, 0, 0, 0, 0, 0),), ids=None, obstacles=()) -> GroundTruth:
    poses = np.asarray(poses, float).reshape(-1, 6)
    obstacles = np.asarray(obstacles, float).reshape(-1, 3)
    n = len(obstacles)
    return GroundTruth(
        fleet="f", sender="world", seq=1, t_meas=t, t_sent=t,
        vehicle_ids=ids or [f"cv{i}" for i in range(len(poses))],
        vehicle_pose=poses, vehicle_v_map=np.zeros((len(poses), 3)),
        obstacle_id=np.arange(n, dtype=np.uint32), obstacle_cls=np.zeros(n, np.uint8),
        obstacle_p_map=obstacles, obstacle_v_map=np.zeros((n, 3)), obstacle_yaw=np.zeros(n),
    )  # fmt: skip


def fused_state(t=1.0, poses=((0, 0, 0, 0, 0, 0),), pose_covs=None, ids=None, objects=(), obj_covs=None):
    poses = np.asarray(poses, float).reshape(-1, 6)
    objects = np.asarray(objects, float).reshape(-1, 3)
    n = len(objects)
    pose_covs = (
        np.broadcast_to(np.diag([0.01] * 3 + [1e-4] * 3), (len(poses), 6, 6)) if pose_covs is None else pose_covs
    )
    obj_covs = np.broadcast_to(np.eye(3) * 0.04, (n, 3, 3)) if obj_covs is None else obj_covs
    return FusedState(
        fleet="f", sender="host", seq=1, t_meas=t, t_sent=t,
        vehicle_ids=ids or [f"cv{i}" for i in range(len(poses))],
        vehicle_pose=poses, vehicle_pose_cov=upper_from_sym(np.asarray(pose_covs)),
        object_id=np.arange(n, dtype=np.uint32), object_cls=np.zeros(n, np.uint8),
        object_p_map=objects, object_v_map=np.zeros((n, 3)), object_cov=upper_from_sym(np.asarray(obj_covs)),
    )  # fmt: skip


# ----------------------------------------------------------------------------- GOSPA

# Reference values computed once with Stone Soup 1.9.1:
#   GOSPAMetric(c=3.0, p=2, measure=Euclidean(mapping=(0, 1))).compute_gospa_metric(estimates, truths)
# (alpha = 2, its default); Stone Soup's parts are in m^p like ours: distance = (loc + missed + false)^(1/p).
STONE_SOUP_CASES = {
    # a close pair, a pair at 2.5 m, a miss, a pair at 3.5 m beyond the cutoff (miss + false), two false
    "mixed": (
        [[0, 0], [10, 0], [20, 0], [30, 0]],
        [[0.5, 0], [10, 2.5], [30.0, 3.5], [40, 0], [50, 1]],
        {"distance": 5.385164807134504, "localisation": 6.5, "missed": 9.0, "false": 13.5},
    ),
    # obstacles 1 m apart: the assignment minimising sum d^2 (not sum d) decides the pairs
    "crowded": (
        [[0, 0], [1.0, 0], [2.0, 0.5]],
        [[0.4, 0.3], [1.6, -0.2], [2.2, 1.9], [-2.5, 0]],
        {"distance": 2.6739483914241875, "localisation": 2.6499999999999995, "missed": 0.0, "false": 4.5},
    ),
}


@pytest.mark.parametrize("case", sorted(STONE_SOUP_CASES))
def test_gospa_equals_stone_soup(case):
    truths, estimates, ref = STONE_SOUP_CASES[case]
    g = ev.gospa(estimates, truths)
    assert g.localization == pytest.approx(ref["localisation"], abs=1e-12)
    assert g.missed == pytest.approx(ref["missed"], abs=1e-12)
    assert g.false == pytest.approx(ref["false"], abs=1e-12)
    assert g.distance == pytest.approx(ref["distance"], abs=1e-12)


def test_gospa_of_empty_sets_and_single_errors():
    empty = np.zeros((0, 3))
    assert ev.gospa(empty, empty).total == 0.0
    assert ev.gospa(empty, [[1, 2, 0]]) == ev.Gospa(0.0, HALF, 0.0)  # one miss costs c^p / 2
    assert ev.gospa([[1, 2, 0]], empty) == ev.Gospa(0.0, 0.0, HALF)  # one false track too
    assert ev.gospa([[0.3, 0.4, 9.0]], [[0, 0, 0]]).localization == pytest.approx(0.25)  # horizontal only
    assert ev.gospa([[0, 3.0 + 1e-9, 0]], [[0, 0, 0]]) == ev.Gospa(0.0, HALF, HALF)  # beyond c: miss + false
    assert ev.gospa([[0, 2.999, 0]], [[0, 0, 0]]).total == pytest.approx(2.999**2)  # below c: cheaper than c^p


def test_gospa_is_a_metric_on_random_sets():
    rng = np.random.default_rng(3)
    sets = [rng.uniform(0, 8, (rng.integers(0, 6), 2)) for _ in range(12)]
    d = np.array([[ev.gospa(a, b).distance for b in sets] for a in sets])
    assert np.allclose(d, d.T)  # symmetric (missed and false swap)
    assert np.allclose(np.diag(d), 0.0)
    for i in range(len(sets)):
        for j in range(len(sets)):
            assert np.all(d[i, j] <= d[i, :] + d[:, j] + 1e-9)  # triangle inequality
    assert ev.gospa(sets[0], sets[1]).missed == ev.gospa(sets[1], sets[0]).false


def test_match_objects_is_the_gospa_assignment():
    truths, estimates, _ = STONE_SOUP_CASES["crowded"]
    ti, fi = ev.match_objects(np.asarray(estimates, float), np.asarray(truths, float))
    d2 = np.sum((np.asarray(estimates)[fi] - np.asarray(truths)[ti]) ** 2, axis=1)
    assert len(ti) == 3 and d2.sum() == pytest.approx(2.65)
    with pytest.raises(ValueError):
        ev.match_objects(np.zeros((1, 3)), np.zeros((1, 3)), gate_m=0.0)


# ----------------------------------------------------------------------------- one frame


def test_score_frame_counts_matches_misses_and_false_tracks():
    obstacles = [[0, 0, 0], [10, 0, 0], [20, 0, 0]]
    fused = fused_state(objects=[[0.3, 0.4, 0.1], [10, 1, 0]])
    s = ev.score_frame(fused, truth_state(obstacles=obstacles))
    assert (s.n_truth, s.n_fused, s.n_false, s.n_matched) == (3, 2, 0, 2)
    assert s.coverage == pytest.approx(2 / 3)
    assert s.object_sq.tolist() == pytest.approx([0.25, 1.0])
    assert s.gospa == ev.Gospa(pytest.approx(1.25), HALF, 0.0)
    # one extra false track: the false part grows by c^p / 2, nothing else moves
    more = ev.score_frame(
        fused_state(objects=[[0.3, 0.4, 0.1], [10, 1, 0], [50, 50, 0]]), truth_state(obstacles=obstacles)
    )
    assert more.gospa.false - s.gospa.false == pytest.approx(HALF)
    assert (more.gospa.localization, more.gospa.missed) == (pytest.approx(s.gospa.localization), s.gospa.missed)
    assert (more.n_false, more.n_fused, more.coverage) == (1, 3, s.coverage)


def test_score_frame_scope():
    obstacles = [[0, 0, 0], [10, 0, 0], [40, 0, 0]]
    fused = fused_state(objects=[[0.2, 0, 0], [41, 0, 0], [45, 0, 0], [5, 5, 0]])
    truth = truth_state(obstacles=obstacles)
    t_in = ev.within_radius(truth.obstacle_p_map, [0, 0], 20.0)
    e_in = ev.within_radius(fused.object_p_map, [0, 0], 20.0)
    s = ev.score_frame(fused, truth, truth_in_scope=t_in, est_in_scope=e_in)
    # in scope: obstacles 0 and 10 (one matched, one missed); estimates at 0.2 (matched) and (5, 5) (false)
    assert (s.n_truth, s.n_matched, s.n_false, s.n_fused) == (2, 1, 1, 2)
    assert s.gospa == ev.Gospa(pytest.approx(0.04), HALF, HALF)
    with pytest.raises(ValueError):
        ev.score_frame(fused, truth, truth_in_scope=np.ones(2, bool))


def test_vehicles_pair_by_id_and_yaw_wraps():
    truth = truth_state(poses=[[0, 0, 0, 0, 0, np.pi - 0.01], [5, 5, 0, 0, 0, 0]], ids=["cv0", "cv1"])
    fused = fused_state(poses=[[1, 1, 0, 0, 0, 0], [0, 0, 0, 0, 0, -np.pi + 0.01]], ids=["cv1", "cv0"])
    s = ev.score_frame(fused, truth)
    assert s.vehicle_ids == ("cv1", "cv0")
    assert s.vehicle_sq.tolist() == pytest.approx([32.0, 0.0])
    assert s.vehicle_err[1, 5] == pytest.approx(0.02, abs=1e-6)  # not -2 pi + 0.02
    assert ev.pose_error([0, 0, 0, np.pi - 0.1, 0, 0], [0, 0, 0, -np.pi + 0.1, 0, 0])[3] == pytest.approx(-0.2)


# ----------------------------------------------------------------------------- consistency


def _random_cov(rng, sig) -> np.ndarray:
    A = rng.normal(size=(len(sig), len(sig)))
    Q, _ = np.linalg.qr(A)
    D = np.diag(np.asarray(sig) ** 2)
    return Q @ D @ Q.T


def _vehicle_frames(rng, n_frames: int, scale: float) -> list[ev.FrameScore]:
    """Vehicles whose errors are drawn from P over [x, y, z, roll, pitch, yaw], reported as scale * P."""
    out = []
    sig = [0.1, 0.08, 0.05, 0.004, 0.005, 0.01]
    for k in range(n_frames):
        poses_t, poses_f, covs = [], [], []
        for _ in range(4):
            P = _random_cov(rng, sig)
            p = np.array([rng.uniform(-100, 100), rng.uniform(-100, 100), 0.3, 0.01, -0.02, np.pi - 0.005])
            e = rng.multivariate_normal(np.zeros(6), P)
            q = p + e
            q[3:] = (q[3:] + np.pi) % (2 * np.pi) - np.pi  # yaw near pi: the estimate wraps to near -pi
            poses_t.append(p)
            poses_f.append(q)
            covs.append(scale * P)
        out.append(ev.score_frame(fused_state(k * 0.1, poses_f, np.array(covs)), truth_state(k * 0.1, poses_t)))
    return out


def test_six_dof_nees_passes_with_the_right_covariance_and_fails_when_it_is_too_small():
    rng = np.random.default_rng(7)
    good = np.concatenate([f.vehicle_nees for f in _vehicle_frames(rng, 150, 1.0)])
    a = ev.anees(good, ev.VEHICLE_DOF)
    assert a.n == 600 and a.inside, a
    assert ev.fraction_in_band(good, 6) == pytest.approx(0.95, abs=0.03)
    small = np.concatenate([f.vehicle_nees for f in _vehicle_frames(np.random.default_rng(7), 150, 0.5)])
    assert not ev.anees(small, ev.VEHICLE_DOF).inside  # a covariance 2x too small: ANEES about 12
    assert ev.anees(small, 6).value == pytest.approx(12.0, rel=0.1)
    assert ev.fraction_in_band(small, 6) < 0.8


def test_object_nees_and_totals_consistency():
    rng = np.random.default_rng(11)
    totals, cells = ev.Totals(), []
    for _ in range(100):
        p_true = rng.uniform(-50, 50, (6, 3))
        covs = np.array([_random_cov(rng, [0.2, 0.15, 0.1]) for _ in range(6)])
        err = np.array([rng.multivariate_normal(np.zeros(3), P) for P in covs])
        s = ev.score_frame(fused_state(objects=p_true + err, obj_covs=covs), truth_state(obstacles=p_true))
        totals.add(s)
        cells.append(s.object_nees)
    cells = np.concatenate(cells)
    summ = totals.summary()
    assert summ["object_nees"]["cells"] == 600
    assert summ["object_nees"]["anees"] == pytest.approx(cells.mean())
    assert summ["object_nees"]["nees_in_band"] == pytest.approx(ev.fraction_in_band(cells, 3))
    assert summ["object_nees"]["anees_band"][0] < summ["object_nees"]["anees"] < summ["object_nees"]["anees_band"][1]


def test_bands_are_chi_square_quantiles():
    assert ev.nees_band(6) == pytest.approx(tuple(stats.chi2.ppf([0.025, 0.975], 6)))
    a = ev.anees(np.full(10, 3.0), 3)
    assert (a.lo, a.hi) == pytest.approx(tuple(stats.chi2.ppf([0.025, 0.975], 30) / 10))
    assert ev.anees([], 3).n == 0 and np.isnan(ev.fraction_in_band([], 3))


def test_totals_summary_matches_the_frames():
    frames = [
        ev.score_frame(fused_state(t, poses=[[0.1 * t, 0, 0, 0, 0, 0]], objects=[[0.5, 0, 0], [9, 9, 0]]),
                       truth_state(t, obstacles=[[0, 0, 0], [20, 0, 0]]))
        for t in (1.0, 2.0, 3.0)
    ]  # fmt: skip
    tot = ev.Totals()
    for f in frames:
        tot.add(f)
    s = tot.summary()
    assert s["frames"] == 3
    assert s["vehicle_rmse_m"] == pytest.approx(np.sqrt(np.mean([0.01, 0.04, 0.09])))
    assert s["vehicle_rmse_by_id_m"] == {"cv0": pytest.approx(s["vehicle_rmse_m"])}
    assert s["object_rmse_m"] == pytest.approx(0.5)
    assert (s["coverage"], s["false_tracks_per_frame"], s["false_track_fraction"]) == (0.5, 1.0, 0.5)
    assert (s["gospa_localization_m2"], s["gospa_missed_m2"], s["gospa_false_m2"]) == (pytest.approx(0.25), HALF, HALF)
    assert s["gospa_m"] == pytest.approx(np.sqrt(0.25 + 2 * HALF))
    row = ev.frame_row(frames[0])
    assert (row["object_pairs"], row["false_tracks"], row["obstacles"]) == (1, 1, 2)
    assert ev.Totals().summary()["vehicle_rmse_m"] is None


# ----------------------------------------------------------------------------- over time


def test_rmse_vs_time_buckets_runs_then_averages():
    r = ev.rmse_vs_time([0.1, 0.5, 1.2, 0.3, 1.5, 1.9], [1, 1, 4, 9, 16, 16], [0, 0, 0, 1, 1, 1])
    assert r.t_start.tolist() == [0.0, 1.0]
    assert r.mean.tolist() == pytest.approx([2.0, 3.0])  # bucket 0: runs 1 and 3; bucket 1: runs 2 and 4
    assert r.runs.tolist() == [2, 2]
    assert r.lo.tolist() == pytest.approx([1.1, 2.1]) and r.hi.tolist() == pytest.approx([2.9, 3.9])
    assert ev.rmse_vs_time([], [], []).t_start.size == 0
    with pytest.raises(ValueError):
        ev.rmse_vs_time([0.0], [1.0, 2.0], [0])


def test_frame_row_fields_are_the_rows_keys():
    s = ev.score_frame(fused_state(objects=[[0, 0, 0]]), truth_state(obstacles=[[0.1, 0, 0]]))
    assert list(ev.frame_row(s)) == ev.frame_row_fields()
