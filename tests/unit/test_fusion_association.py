"""Association: map-frame transform and its covariance, gating, Hungarian, track birth/death/merge."""

import numpy as np
import pytest

from mapcontainer import geometry as geo
from mapcontainer.fusion import FusionParams
from mapcontainer.fusion.association import Detection, Tracker, VehicleCandidate, cv_predict, protection_gate
from mapcontainer.fusion.mapframe import mahalanobis_logdet, mahalanobis_matrix, observations_to_map
from schemas import ObjectClass

PED, VEH = int(ObjectClass.PEDESTRIAN), int(ObjectClass.VEHICLE)
S = np.diag([0.3, 0.2, 0.05]) ** 2


def test_map_transform_and_covariance_propagation_numerically():
    pose = np.array([3.0, -1.0, 0.2, 0.02, -0.01, 1.2])
    z = np.array([[12.0, 3.0, 0.5], [30.0, -8.0, 0.0]])
    m, Sm = observations_to_map(pose, np.zeros((6, 6)), z, np.zeros((2, 3, 3)))
    np.testing.assert_allclose(m, geo.transform_points(geo.pose_to_matrix(pose), z), atol=1e-12)
    # pose part of the covariance: J = d m / d pose, by central differences
    C_pose = np.diag([0.1, 0.2, 0.05, 0.01, 0.02, 0.03]) ** 2
    _, Sp = observations_to_map(pose, C_pose, z, np.zeros((2, 3, 3)))
    for n in range(2):
        J = np.zeros((3, 6))
        for i in range(6):
            d = np.zeros(6)
            d[i] = 1e-6
            J[:, i] = (
                geo.transform_points(geo.pose_to_matrix(pose + d), z[n])
                - geo.transform_points(geo.pose_to_matrix(pose - d), z[n])
            ) / 2e-6
        np.testing.assert_allclose(Sp[n], J @ C_pose @ J.T, rtol=1e-6, atol=1e-12)
    # detection part: rotated
    _, Sz = observations_to_map(pose, np.zeros((6, 6)), z[:1], S[None])
    R = geo.rpy_to_matrix(*pose[3:])
    np.testing.assert_allclose(Sz[0], R @ S @ R.T, atol=1e-15)


def test_mahalanobis_matrix():
    m = np.array([[0.0, 0, 0], [10.0, 0, 0]])
    c = np.array([[1.0, 0, 0]])
    d2 = mahalanobis_matrix(m, np.stack([np.eye(3)] * 2), c, np.stack([np.eye(3)]))
    np.testing.assert_allclose(d2, [[0.5], [40.5]])
    assert mahalanobis_matrix(m, np.stack([np.eye(3)] * 2), np.zeros((0, 3)), np.zeros((0, 3, 3))).shape == (2, 0)


def test_cv_predict():
    x = np.array([0.0, 0, 0, 2.0, -1.0, 0])
    P = np.eye(6) * 0.01
    x1, P1 = cv_predict(x, P, 0.5, [1.0, 1.0, 0.0])
    np.testing.assert_allclose(x1[:3], [1.0, -0.5, 0.0])
    assert P1[0, 0] == pytest.approx(0.01 + 0.25 * 0.01 + 0.5**3 / 3)
    xb, Pb = cv_predict(x1, P1, -0.5, [1.0, 1.0, 0.0])  # backwards for late detections
    np.testing.assert_allclose(xb, x)
    assert np.all(np.linalg.eigvalsh(Pb) > 0)


def _det(p, t, sender="cv0", cls=VEH, index=0, cov=S):
    p = np.asarray(p, dtype=float)
    return Detection(sender, t, index, p, cov, cls, p, cov)


def _feed(tracker, frames):
    """frames: list of (t, [positions]) from cv0; returns all assignments."""
    out = []
    for t, ps in frames:
        a, _ = tracker.associate([_det(p, t, index=i) for i, p in enumerate(ps)], [])
        out += a
    return out


def test_birth_after_m_hits_and_stable_ids():
    tr = Tracker(FusionParams(birth_hits=3))
    a = _feed(tr, [(0.0, [[10, 0, 0]]), (0.1, [[10.5, 0, 0]])])
    assert a == [] and len(tr.tracks) == 1 and not tr.confirmed()
    a = _feed(tr, [(0.2, [[11.0, 0, 0]])])
    assert [x.target for x in a] == [1, 1, 1]  # the held detections enter the graph on confirmation
    assert [x.det.t for x in a] == [0.0, 0.1, 0.2]
    a = _feed(tr, [(0.3, [[11.5, 0, 0], [40, 40, 0]])])
    assert [(x.kind, x.target, x.det.index) for x in a] == [("track", 1, 0)]
    assert tr.counts["new_tentative"] == 2 and list(tr.confirmed()) == [1]


def test_gating_rejects_far_detections_and_hungarian_picks_the_best_pairs():
    tr = Tracker(FusionParams(birth_hits=1))
    _feed(tr, [(0.0, [[0, 0, 0], [4, 0, 0]])])  # two confirmed tracks at once
    assert sorted(tr.confirmed()) == [1, 2]
    for t in tr.tracks.values():
        t.P = np.diag([0.01, 0.01, 0.01, 0.01, 0.01, 0.01])
    # detections swapped in order and slightly off: each goes to its own track
    dets = [_det([4.1, 0.1, 0], 0.1, index=0), _det([0.2, -0.1, 0], 0.1, index=1), _det([2.0, 0, 0], 0.1, index=2)]
    a, _ = tr.associate(dets, [])
    got = {x.det.index: x.target for x in a}
    assert got[0] == 2 and got[1] == 1
    assert got[2] == 3  # the one in between (2 m from both) is outside both gates: a new track


def test_classes_must_agree():
    tr = Tracker(FusionParams(birth_hits=1))
    _feed(tr, [(0.0, [[0, 0, 0]])])
    a, _ = tr.associate([_det([0.1, 0, 0], 0.1, cls=PED)], [])
    assert [x.target for x in a] == [2]  # a pedestrian detection does not update vehicle track 1


def test_connected_vehicles_are_matched_to_their_reported_position():
    tr = Tracker(FusionParams())
    cv = VehicleCandidate("cv1", np.array([6.0, -3.5, 0.0]), np.eye(3) * 0.01)
    a, _ = tr.associate([_det([6.2, -3.4, 0.05], 0.0), _det([20.0, 0, 0], 0.0, index=1)], [cv])
    assert [(x.kind, x.target, x.det.index) for x in a] == [("vehicle", "cv1", 0)]
    assert len(tr.tracks) == 1  # the other one starts a tentative track; the vehicle does not
    a, _ = tr.associate([_det([6.2, -3.4, 0.05], 0.1, cls=PED)], [cv])
    assert a == []  # a pedestrian is not a vehicle


def test_mahalanobis_logdet_is_the_log_determinant_of_the_summed_covariances():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(2, 3, 3))
    S_m, S_c = A @ A.transpose(0, 2, 1) + np.eye(3), np.stack([np.diag([0.5, 2.0, 3.0])])
    d2, ld = mahalanobis_logdet(rng.normal(size=(2, 3)), S_m, np.zeros((1, 3)), S_c)
    np.testing.assert_allclose(ld[:, 0], np.linalg.slogdet(S_m + S_c[0])[1])
    assert d2.shape == ld.shape == (2, 1)


def test_a_wide_vehicle_does_not_capture_the_detection_of_a_tight_one_next_to_it():
    """The traced failure: cv1, 5-7 m off its report with sigma 1.6 m, reported next to cv2; cv0's detections of
    cv2 were nearer cv1 in Mahalanobis distance (its width makes every distance short) and were assigned to
    cv1. The likelihood (distance plus the log-determinant) prefers cv2, which reported itself well."""
    tr = Tracker(FusionParams())
    cv2 = VehicleCandidate("cv2", np.array([20.4, 0.3, 0.0]), np.diag([0.1, 0.1, 0.05]) ** 2)
    cv1 = VehicleCandidate("cv1", np.array([20.8, 0.8, 0.0]), np.diag([1.6, 1.6, 0.3]) ** 2)
    det = _det([20.0, 0.0, 0.0], 0.0)
    assert (
        mahalanobis_matrix([det.p_map], [det.cov_map], [cv1.p_map], [cv1.cov])[0, 0]
        < mahalanobis_matrix([det.p_map], [det.cov_map], [cv2.p_map], [cv2.cov])[0, 0]
    )  # by distance alone cv1 would win
    a, _ = tr.associate([det], [cv1, cv2])
    assert [(x.kind, x.target) for x in a] == [("vehicle", "cv2")]


def test_a_detection_two_vehicles_explain_alike_constrains_neither():
    """Two connected vehicles reported side by side with the same covariance, a detection between them: each
    is it with probability ~1/2, so neither pose is constrained by it, and it starts no track."""
    tr = Tracker(FusionParams())
    cov = np.diag([1.0, 1.0, 0.2]) ** 2
    a_, b_ = (
        VehicleCandidate("a", np.array([20.0, 1.0, 0.0]), cov),
        VehicleCandidate("b", np.array([20.0, -1.0, 0]), cov),
    )
    a, _ = tr.associate([_det([20.0, 0.0, 0.0], 0.0)], [a_, b_])
    assert a == [] and tr.counts["vehicle_ambiguous"] == 1 and not tr.tracks
    a, _ = tr.associate([_det([20.0, 1.8, 0.0], 0.1)], [a_, b_])  # a, with probability 0.97
    assert [(x.kind, x.target) for x in a] == [("vehicle", "a")]


def test_a_lone_track_in_a_wide_gate_is_not_sure_where_the_observer_sees_untracked_objects():
    """Development seed 1006, traced: a GNSS-grade observer (sigma ~2 m) saw, in its first frame with
    detections, an object nobody tracked 7.5 m from a confirmed track alone in its gate; the update pinned it
    onto the wrong object. Against the density of objects not yet tracked (all of them, for an observer whose
    detections no shared track explained yet), the lone track is not sure; the same detection from a
    well-localized pose, or from an observer whose recent detections were all of shared tracks, is."""
    p = FusionParams(birth_hits=1)
    wide, tight = np.diag([2.0, 2.0, 0.3]) ** 2, np.diag([0.2, 0.2, 0.1]) ** 2

    def tracker_with_track():
        tr = Tracker(p)
        tr.associate([_det([0.0, 0.0, 0.0], 0.0, sender="cv1")], [])  # confirmed at once (birth_hits 1)
        tr.sync(1, 0.0, np.zeros(6), np.diag([0.3, 0.3, 0.1, 0.5, 0.5, 0.1]) ** 2)
        return tr

    tr = tracker_with_track()
    assert tr.untracked_density("cv0") == pytest.approx(p.clutter_density_m3 + p.object_density_m3)
    (a,), _ = tr.associate([_det([1.5, 1.0, 0.0], 0.1, cov=wide)], [])
    assert a.target == 1 and a.p < p.vehicle_association_probability
    tr = tracker_with_track()
    (a,), _ = tr.associate([_det([0.15, 0.1, 0.0], 0.1, cov=tight)], [])
    assert a.target == 1 and a.p > 0.99
    tr = tracker_with_track()
    for k in range(10):  # cv0's detections, all of the shared track: nothing untracked around it
        tr.associate([_det([0.0, 0.0, 0.0], 0.1 + 0.1 * k, cov=tight)], [])
        tr.sync(1, 0.1 + 0.1 * k, np.zeros(6), np.diag([0.3, 0.3, 0.1, 0.5, 0.5, 0.1]) ** 2)
    assert tr.untracked_density("cv0") < 0.01 * p.object_density_m3
    (a,), _ = tr.associate([_det([1.5, 1.0, 0.0], 1.1, cov=wide)], [])
    assert a.target == 1 and a.p > 0.95


def test_unassigned_detection_close_to_an_untaken_track_starts_no_duplicate():
    tr = Tracker(FusionParams(birth_hits=1))
    _feed(tr, [(0.0, [[0, 0, 0]])])
    tr.sync(1, 0.0, tr.tracks[1].x, np.eye(6) * 1e-4)  # a confident track
    # just outside the 99 % gate, well inside the 99.99 % birth exclusion
    a, _ = tr.associate([_det([0.0, 0.75, 0.0], 0.0)], [])
    assert a == [] and len(tr.tracks) == 1 and tr.counts["birth_suppressed"] == 1


def test_death_after_silence():
    tr = Tracker(FusionParams(birth_hits=2, tentative_timeout_s=0.3, death_s=0.8))
    _feed(tr, [(0.0, [[0, 0, 0], [50, 0, 0]]), (0.1, [[0.5, 0, 0]])])
    assert list(tr.confirmed()) == [1] and len(tr.tracks) == 2
    assert tr.expire(0.35) == [] and len(tr.tracks) == 2  # timeout in measurement time: no newer data yet
    tr.observe(0.35)
    assert tr.expire(0.35) == [] and len(tr.tracks) == 1  # the tentative one went
    assert tr.expire(0.85) == []
    assert tr.expire(0.95) == [1] and not tr.tracks


def test_duplicate_tracks_are_merged_into_the_older_id():
    tr = Tracker(FusionParams(birth_hits=1, merge_cycles=3))
    a, _ = tr.associate([_det([0, 0, 0], 0.0, sender="cv0")], [])
    b, _ = tr.associate([_det([30, 0, 0], 0.0, sender="cv1")], [])
    t2 = tr.tracks[2]
    t2.x[:3] = [0.05, 0.0, 0.0]  # the same object, seen by another vehicle, as a second track
    for k in range(2):
        assert tr.merge_duplicates(0.1 * k) == []
    assert tr.merge_duplicates(0.2) == [2]
    assert list(tr.confirmed()) == [1] and tr.counts["merged"] == 1


def test_objects_seen_together_by_one_vehicle_are_never_merged():
    tr = Tracker(FusionParams(birth_hits=1, merge_cycles=1))
    tr.associate([_det([0, 0, 0], 0.0, index=0), _det([0.4, 0, 0], 0.0, index=1)], [])
    for t in tr.tracks.values():
        t.P = np.eye(6)  # very uncertain: statistically indistinguishable
    assert tr.merge_duplicates(0.0) == [] and len(tr.confirmed()) == 2


def test_tentative_timeout_counts_measurement_time_not_latency():
    """A fuse time far ahead of the data (V2X latency) does not drop tentative tracks; silence in
    measurement time does; and the death limit in fuse time still ends tracks of silent senders."""
    tr = Tracker(FusionParams(birth_hits=3, tentative_timeout_s=0.35, death_s=1.0))
    _feed(tr, [(0.0, [[0, 0, 0]])])
    assert tr.expire(0.6) == [] and len(tr.tracks) == 1  # 600 ms latency: kept
    _feed(tr, [(0.1, [[0.05, 0, 0]])])
    assert tr.expire(0.7) == [] and len(tr.tracks) == 1
    tr.observe(0.5)  # the senders reported up to 0.5 without it: 0.4 s of silence
    assert tr.expire(0.9) == [] and not tr.tracks and tr.counts["tentative_dropped"] == 1
    _feed(tr, [(2.0, [[9, 0, 0]])])
    assert tr.expire(2.9) == [] and len(tr.tracks) == 1
    assert tr.expire(3.05) == [] and not tr.tracks  # nothing measured after it for 1 s of fuse time


def test_a_track_that_is_a_connected_vehicle_is_deleted():
    """Born from cv1's detections while its reported pose was off, a track sits on cv1 once its pose is
    good: after merge_cycles calls within its gate and 1.5 m it goes; a track 3 m away, one cv1 detected
    itself and one beside a vehicle that reports itself uncertain stay."""
    tr = Tracker(FusionParams(birth_hits=1, merge_cycles=3))
    tr.associate([_det([10.0, 0, 0], 0.0, sender="cv0", index=0), _det([13.0, 0, 0], 0.0, sender="cv0", index=1)], [])
    tr.associate([_det([30.0, 0, 0], 0.0, sender="cv1")], [])  # cv1 sees track 3: not cv1 itself
    tr.associate([_det([50.0, 0, 0], 0.0, sender="cv0", index=2)], [])
    for t in tr.tracks.values():
        t.P = np.eye(6) * 0.01
    good = VehicleCandidate("cv1", np.array([10.1, 0.1, 0.0]), np.eye(3) * 0.01)
    at_3 = VehicleCandidate("cv1", np.array([30.2, 0.0, 0.0]), np.eye(3) * 0.01)
    vague = VehicleCandidate("cv2", np.array([52.5, 0.0, 0.0]), np.eye(3) * 9.0)  # GNSS: 2.5 m off is in its gate
    for k in range(2):
        assert tr.vehicle_shadows(0.1 * k, [good, at_3, vague]) == []
    assert tr.vehicle_shadows(0.2, [good, at_3, vague]) == [1]
    assert sorted(tr.confirmed()) == [2, 3, 4] and tr.counts["vehicle_shadow"] == 1
    assert tr.vehicle_shadows(0.3, []) == [] and tr._shadow_streak == {}


def test_a_vehicle_is_gated_by_its_protection_levels_where_it_claims_integrity():
    """A vehicle whose reported covariance is wide (here 1.5 m: the host adds the repeated error and the motion
    since its frame) but which claims integrity with protection levels of 0.6 m across and 1.0 m along cannot
    take a detection 2.5 m across its road: that is another car. Without a protection level its covariance
    alone gates it."""
    cov = np.diag([1.5, 1.5, 0.2]) ** 2
    k = 3.29  # the Gaussian quantile of an integrity risk of 1e-3 per axis
    claims = VehicleCandidate("cv1", np.array([20.0, 0.0, 0.0]), cov, (0.0, 0.6, 1.0, k))
    silent = VehicleCandidate("cv1", np.array([20.0, 0.0, 0.0]), cov)
    det = _det([20.0, 2.5, 0.0], 0.0, cov=np.diag([0.2, 0.1, 0.05]) ** 2)
    along = _det([20.9, 0.1, 0.0], 0.0, cov=np.diag([0.2, 0.1, 0.05]) ** 2)
    ok = protection_gate(np.array([det.p_map, along.p_map]), np.array([det.cov_map, along.cov_map]), [claims, silent])
    assert ok.tolist() == [[False, True], [True, True]]
    # rotated: the vehicle heads north, so y is along its road: within 1.0 + k * 0.1 = 1.33 m
    north = VehicleCandidate("cv1", np.array([20.0, 0.0, 0.0]), cov, (np.pi / 2, 0.6, 1.0, k))
    assert not protection_gate(np.array([det.p_map]), np.array([det.cov_map]), [north])[0, 0]  # 2.5 > 1.33
    near = _det([20.0, 1.2, 0.0], 0.0, cov=np.diag([0.2, 0.1, 0.05]) ** 2)
    assert protection_gate(np.array([near.p_map]), np.array([near.cov_map]), [north])[0, 0]  # 1.2 <= 1.33
    tr = Tracker(FusionParams())
    a, _ = tr.associate([det], [claims])
    assert not [x for x in a if x.kind == "vehicle"] and tr.counts["vehicle_ambiguous"] == 0  # not a candidate
    # without: a candidate, assigned; at a cold start (every object around untracked) 2.5 m off a 1.5 m sigma
    # is not sure enough to constrain it, and it is counted so
    tr = Tracker(FusionParams())
    a, _ = tr.associate([det], [silent])
    assert not a and tr.counts["vehicle_ambiguous"] == 1
    tr = Tracker(FusionParams(object_density_m3=1e-9))
    a, _ = tr.associate([det], [silent])
    assert [(x.kind, x.target) for x in a] == [("vehicle", "cv1")]
