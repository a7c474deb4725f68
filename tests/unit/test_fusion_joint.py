"""The centralized host's joint estimator (mapcontainer.fusion.joint): its two updates are exact on
linear-Gaussian problems, and it runs end to end on raw observations."""

import numpy as np
import pytest

from mapcontainer.fusion import FusionParams
from mapcontainer.fusion.joint import _MIN_DETECTION_SIGMA_M, JointHost, _floored
from mapcontainer.fusion.poses import sym_from_upper
from mapcontainer.hdmap.generator import generate_map
from mapcontainer.sim import load_scenario
from schemas import CameraInfo, RawObservations, encode


@pytest.fixture(scope="module")
def host() -> JointHost:
    return JointHost(generate_map(load_scenario("overlap").map), FusionParams(), "f", "host")


def _joint(host: JointHost, rng, blocks) -> tuple[np.ndarray, np.ndarray]:
    """A random joint Gaussian over ``blocks`` (keys), put into the host's state."""
    host.mu, host.P, host._keys, host._t = np.zeros(0), np.zeros((0, 0)), [], {}
    host._reindex()
    for key in blocks:
        host._set_block(key, np.zeros(host._size(key)), np.eye(host._size(key)), 0.0)
    n = len(host.mu)
    A = rng.normal(size=(n, n))
    host.mu = rng.normal(size=n) * 0.1
    host.P = A @ A.T / n + 0.1 * np.eye(n)
    return host.mu.copy(), host.P.copy()


def test_conditioning_on_a_block_posterior_is_the_joint_kalman_update(host):
    """A vehicle's localizer updates its block alone; conditioning the rest on its result must equal one
    Kalman update of the whole state with the same measurement (with a prediction F, Q first)."""
    rng = np.random.default_rng(3)
    mu, P = _joint(host, rng, [("v", "a"), ("o", 1), ("v", "b"), ("o", 2)])
    key = ("v", "b")
    s = host._sl(key)
    n = len(mu)
    F_v = np.eye(10) + 0.05 * rng.normal(size=(10, 10))
    Q_v = 0.01 * np.eye(10)
    # the joint prediction: F on block s only, Q on it
    F = np.eye(n)
    F[s, s] = F_v
    mu_pred, P_pred = F @ mu, F @ P @ F.T
    P_pred[s, s] += Q_v
    # a linear measurement of block s (yaw difference small: no wrapping at play)
    H_v = rng.normal(size=(4, 10))
    R = 0.05 * np.eye(4)
    z = rng.normal(size=4) * 0.1
    H = np.zeros((4, n))
    H[:, s] = H_v
    K = P_pred @ H.T @ np.linalg.inv(H @ P_pred @ H.T + R)
    mu_ref = mu_pred + K @ (z - H @ mu_pred)
    P_ref = P_pred - K @ H @ P_pred
    # what the localizer does with its block: predict, update
    yv, Pv = mu_pred[s], P_pred[s, s]
    Kv = Pv @ H_v.T @ np.linalg.inv(H_v @ Pv @ H_v.T + R)
    y_post, P_post = yv + Kv @ (z - H_v @ yv), Pv - Kv @ H_v @ Pv
    host._condition(key, F_v, yv, Pv, y_post, P_post)
    np.testing.assert_allclose(host.mu, mu_ref, atol=1e-10)
    np.testing.assert_allclose(host.P, P_ref, atol=1e-10)


def test_detection_update_is_the_extended_kalman_update_of_the_body_frame_model(host):
    """z = R(observer)^T (p_target - c_observer): the stacked update moves the state as an EKF whose
    Jacobian is the numerical one."""
    rng = np.random.default_rng(5)
    mu, P = _joint(host, rng, [("v", "a"), ("o", 7)])
    so, st = host._sl(("v", "a")), host._sl(("o", 7))
    mu[st][:3] += np.array([8.0, 2.0, 0.5])
    host.mu = mu.copy()

    def h(x):
        from mapcontainer.geometry import rpy_to_matrix

        R = rpy_to_matrix(*x[so][3:6])
        return R.T @ (x[st][:3] - x[so][:3])

    Hn = np.zeros((3, len(mu)))
    for i in range(len(mu)):
        d = np.zeros(len(mu))
        d[i] = 1e-6
        Hn[:, i] = (h(mu + d) - h(mu - d)) / 2e-6
    cov = 0.04 * np.eye(3)
    z = h(mu) + np.array([0.1, -0.2, 0.05])
    K = P @ Hn.T @ np.linalg.inv(Hn @ P @ Hn.T + cov)
    mu_ref, P_ref = mu + K @ (z - h(mu)), P - K @ Hn @ P
    host._ekf_update(("v", "a"), [(("o", 7), z, cov)])
    np.testing.assert_allclose(host.mu, mu_ref, atol=1e-6)
    np.testing.assert_allclose(host.P, 0.5 * (P_ref + P_ref.T), atol=1e-6)


def test_blocks_come_and_go_with_their_cross_covariances(host):
    rng = np.random.default_rng(9)
    mu, P = _joint(host, rng, [("v", "a"), ("o", 1), ("o", 2)])
    host._drop(("o", 1))
    keep = np.r_[0:10, 16:22]
    np.testing.assert_array_equal(host.mu, mu[keep])
    np.testing.assert_array_equal(host.P, P[np.ix_(keep, keep)])
    assert host._sl(("o", 2)) == slice(10, 16)


def _raw(sender="cv0", seq=0, t=0.0, fleet="f"):
    cam = CameraInfo(fx=500, fy=500, cx=320, cy=240, width=640, height=480, T_body_cam=np.eye(4))
    return encode(RawObservations(fleet=fleet, sender=sender, seq=seq, t_meas=t, t_sent=t, camera=cam))


def test_raw_frames_are_screened_before_a_localizer_sees_them():
    """What the host refuses never reaches a localizer (a far-future frame would move the sender's
    localizer ahead and lock its later frames out; an unknown name would cost a localizer)."""
    box = JointHost(generate_map(load_scenario("overlap").map), FusionParams(), "f", "host", known_senders={"cv0"})
    refused = {
        _raw(t=1e6): "future",
        _raw(sender="intruder"): "unknown_sender",
        _raw(fleet="other"): "fleet",
        b"\x81\x00": "malformed",
    }
    for payload, reason in refused.items():
        assert box.ingest(payload, 0.0).reason == reason
    box.fuse(0.0)
    assert box.localizers == {}
    assert box.ingest(_raw(seq=0, t=0.0), 0.0).accepted
    assert box.ingest(_raw(seq=0, t=0.0), 0.05).reason == "duplicate"
    assert box.ingest(_raw(seq=1, t=0.1), 0.1).accepted
    box.fuse(0.1)
    assert box.localizers["cv0"].t_prev == 0.1  # the far-future frame locked nothing out
    assert box.stats()["rejected"] == {"future": 1, "unknown_sender": 1, "fleet": 1, "malformed": 1, "duplicate": 1}


def test_senders_that_went_silent_are_forgotten():
    box = JointHost(generate_map(load_scenario("overlap").map), FusionParams(), "f", "host", idle_s=5.0)
    for i in range(3):
        box.ingest(_raw(sender=f"x{i}", t=float(i)), float(i))
        box.fuse(float(i))
    assert set(box.localizers) == {"x0", "x1", "x2"}
    box.ingest(_raw(sender="x2", seq=1, t=6.5), 6.5)
    box.fuse(6.5)
    assert set(box.localizers) == {"x2"}  # x0 and x1: silent for more than 5 s


def test_a_localizer_that_starts_again_gives_nothing_to_condition_on():
    """After a gap (or any reset) the localizer's state is new: the host must re-seed the vehicle's block
    rather than condition the rest of the state on it."""
    from mapcontainer.localization import Localizer

    loc = Localizer(generate_map(load_scenario("overlap").map), initial_pose=(np.zeros(6), np.eye(6) * 0.01))
    fix = (np.zeros(3), 1.0, 2.0)
    loc.step(0.0, None, (5.0, 0.0), fix)
    assert loc.initialized and loc.conditioned is None  # initialised in this step
    loc.step(0.1, None, (5.0, 0.0), fix)
    F, y_pred, P_pred = loc.conditioned
    assert F.shape == (10, 10) and y_pred[0] == pytest.approx(0.5, abs=0.05)
    loc.step(0.1 + 2 * loc.params.max_gap_s, None, (5.0, 0.0), fix)  # a gap: it starts again
    assert loc.conditioned is None


def test_a_detection_reported_to_the_millimetre_cannot_pin_the_state(host):
    rng = np.random.default_rng(11)
    _joint(host, rng, [("v", "a"), ("o", 3)])
    before = host.P.copy()
    floored = _floored(np.eye(3)[None] * 1e-12)[0]
    np.testing.assert_allclose(np.linalg.eigvalsh(floored), _MIN_DETECTION_SIGMA_M**2)
    host._ekf_update(("v", "a"), [(("o", 3), np.zeros(3), floored)])
    st = host._sl(("o", 3))
    assert np.all(np.diag(host.P) > 0) and np.all(np.diag(host.P) <= np.diag(before) + 1e-12)
    assert np.linalg.eigvalsh(host.P[st, st][:3, :3]).min() > 1e-4  # not pinned below the floor


def _modes(host: JointHost, **modes) -> None:
    from types import SimpleNamespace

    host._results = {vid: SimpleNamespace(mode=m) for vid, m in modes.items()}


def test_a_vehicle_in_fallback_is_not_tightened_through_shared_objects(host):
    """Traced (suburban development seed 1004, centralized): a vehicle in GNSS fallback 5 m off saw the
    objects a map-matched vehicle saw; the detections of both, through the track they shared, shrank its
    sigma from 2.7 to 0.25 m with the error unchanged, and its map matching, started from that, locked on a
    wrong basin (11 m off, NEES 1,899). A vehicle whose localizer is not map matching is a consider state of
    the detection updates (Schmidt): its block does not move, the track takes its uncertainty in, and the
    covariances stay those of the update actually made."""
    rng = np.random.default_rng(13)
    _joint(host, rng, [("v", "a"), ("v", "b"), ("o", 1)])
    sa, sb, so = host._sl(("v", "a")), host._sl(("v", "b")), host._sl(("o", 1))
    host.P[sa, :] = host.P[:, sa] = 0.0
    host.P[sb, :] = host.P[:, sb] = 0.0
    host.P[sa, sa] = np.diag([4.0, 4.0, 1.0, 1e-4, 1e-4, 1e-3, 1e-4, 1e-6, 2.0, 2.0])  # fallback: GNSS-grade
    host.P[sb, sb] = np.diag([0.01, 0.01, 0.01, 1e-5, 1e-5, 1e-5, 1e-4, 1e-6, 2.0, 2.0])  # map matched
    host.mu[so][:3] = host.mu[sa][:3] + np.array([10.0, 2.0, 0.0])
    host.mu[sb][:3] = host.mu[so][:3] - np.array([12.0, -3.0, 0.0])

    def detect(obs: str, z_off=None):
        s = host._sl(("v", obs))
        x = host.mu[s]
        from mapcontainer.geometry import rpy_to_matrix

        z = rpy_to_matrix(*x[3:6]).T @ (host.mu[so][:3] - x[:3]) + (0.0 if z_off is None else z_off)
        host._ekf_update(("v", obs), [(("o", 1), z, 0.04 * np.eye(3))])

    _modes(host, a="fallback", b="map_matching")
    mu_a, P_a = host.mu[sa].copy(), host.P[sa, sa].copy()
    p_true = host.mu[so][:3].copy()
    for _ in range(20):
        detect("a", np.array([0.5, -0.3, 0.0]))
        detect("b")
    np.testing.assert_allclose(host.mu[sa], mu_a, atol=1e-12)
    np.testing.assert_allclose(host.P[sa, sa], P_a, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(host.P) > -1e-9)
    # the track is where b saw it, with b's accuracy; a's detections do not pin it
    assert np.linalg.norm(host.mu[so][:3] - p_true) < 0.15
    assert np.sqrt(host.P[so, so][0, 0]) < 0.15
    # the same detections with a map matching: a is tightened (the update is not switched off)
    _modes(host, a="map_matching", b="map_matching")
    detect("a")
    detect("b")
    assert np.trace(host.P[sa, sa][:2, :2]) < 0.5 * np.trace(P_a[:2, :2])


def test_a_fallback_frame_corrects_its_pose_only_through_sure_associations_to_shared_tracks():
    """A GNSS-grade observer's detection of a track corrects its pose only if it is that track with probability
    >= vehicle_association_probability (against objects not yet tracked too) and another vehicle saw the
    track: a track it alone saw is its own earlier view, with its own pose error."""
    from mapcontainer.fusion.association import Assignment, Detection

    host = JointHost(generate_map(load_scenario("overlap").map), FusionParams(), "f", "host")
    shared = host.tracker._new_track(Detection("b", 0.0, 0, np.zeros(3), np.eye(3), 0, np.zeros(3), np.eye(3)))
    own = host.tracker._new_track(Detection("a", 0.0, 1, np.zeros(3), np.eye(3), 0, np.ones(3), np.eye(3)))
    for k, tr in enumerate((shared, own)):
        tr.id = k + 1
        host.tracker._uid_of[tr.id] = tr.uid
    det = Detection("a", 0.1, 0, np.zeros(3), np.eye(3), 0, np.zeros(3), np.eye(3))
    p = host.params.vehicle_association_probability

    assert host._sure("a", Assignment("track", 1, det, 0.0, p + 0.01))
    assert not host._sure("a", Assignment("track", 1, det, 0.0, p - 0.01))
    assert not host._sure("a", Assignment("track", 2, det, 0.0, 0.999))  # a saw it alone


def test_the_joint_host_keeps_a_vehicle_of_the_instant_where_it_is():
    """JointHost.fuse(t, tolerance_s) publishes its vehicles by the distributed host's rule
    (hostcore.vehicle_at): a frame stamped 4 ms after t (another vehicle's clock) is not moved back by v * 4 ms,
    its covariance takes v v^T dt^2; a frame older than the tolerance is predicted by v dt."""
    from types import SimpleNamespace

    from schemas import bias_cov

    box = JointHost(generate_map(load_scenario("overlap").map), FusionParams(), "f", "host")
    pose, v = np.array([10.0, 2.0, 0.0, 0.0, 0.0, 0.3]), np.array([10.0, 0.0, 0.0])
    for t_frame, t_out in ((1.004, 1.0), (0.9, 1.0)):
        box.mu, box.P, box._keys, box._t = np.zeros(0), np.zeros((0, 0)), [], {}
        box._reindex()
        P = np.diag([0.04, 0.04, 0.01, 1e-4, 1e-4, 1e-4, 1e-3, 1e-3, 1e-2, 1e-2])
        box._set_block(("v", "a"), np.r_[pose, 1.0, 0.0, 0.0, 0.0], P, t_frame)
        box.localizers = {"a": None}
        box._results = {"a": SimpleNamespace(velocity_map=v, t=t_frame, protection_level=None)}
        out = box.fuse(t_out, tolerance_s=0.02)
        got = np.asarray(out.vehicle_pose[0], dtype=float)
        C = sym_from_upper(np.asarray(out.vehicle_pose_cov[0], dtype=float))
        C_frame = P[:6, :6] + bias_cov(box.loc_params.match_bias_sigma, pose[5])
        dt = t_out - t_frame
        if abs(dt) <= 0.02:  # the instant: where it is, the gap's motion in its covariance
            np.testing.assert_allclose(got, pose, atol=1e-5)
            np.testing.assert_allclose(C[:3, :3] - C_frame[:3, :3], np.outer(v, v) * dt**2, rtol=1e-4, atol=1e-9)
        else:  # a late frame: predicted
            np.testing.assert_allclose(got[:3], pose[:3] + v * dt, atol=1e-5)
            assert np.all(np.diag(C) > np.diag(C_frame) - 1e-9)
