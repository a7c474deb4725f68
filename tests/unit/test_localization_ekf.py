"""The localizer's EKF (mapcontainer.localization.ekf) alone: closed forms, a hand-computed Kalman update, the
information-form match update against a linear Kalman update, and the prediction's Jacobian numerically."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mapcontainer.localization import GnssMeasurement, LocalizerParams, MapMatcher, OdometryMeasurement, ekf
from mapcontainer.localization.matcher_types import MatchLinearization

from .test_localization import HDMAP, P_TRACK, pose_on, synth_frame

PARAMS = LocalizerParams()


def _spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T / n + np.eye(n))


def _matched(seed: int):
    """A state, its covariance, and a matcher posterior (x_f, P_f) that adds information Lam on the pose."""
    rng = np.random.default_rng(seed)
    y0, P0 = _state(), _spd(rng, 10, 0.2)
    Lam = _spd(rng, 6, 5.0)
    P_f = np.linalg.inv(np.linalg.inv(P0[:6, :6]) + Lam)
    return y0, P0, Lam, y0[:6] + rng.normal(0, 0.05, 6), P_f


def _state(yaw=0.3, scale=1.0, gyro_bias=0.0, gnss_bias=(0.5, -0.4)):
    return np.array([10.0, -5.0, 1.2, 0.0, 0.0, yaw, scale, gyro_bias, *gnss_bias])


def test_state_layout():
    assert ekf.N == 10 and ekf.SCALE == 6 and ekf.GYRO == 7 and ekf.GB == slice(8, 10)


def test_predict_straight_line_at_constant_speed_is_the_closed_form():
    """From an exact state (P = 0), yaw theta, speed v, no turn: x += v dt (cos, sin) theta, the GNSS bias decays
    by exp(-dt / tau); the covariance is the process noise: along the track s_v^2 dt^2 (+1e-6 dt), across it
    (v dt^2 / 2)^2 s_w^2 + lateral^2 dt^2 (+1e-6 dt), yaw s_w^2 dt^2, their cross term v dt^3 / 2 s_w^2."""
    p, v, dt, th = PARAMS, 12.0, 0.1, 0.3
    y0 = _state(yaw=th)
    odo = OdometryMeasurement(v, 0.0)
    y, P = ekf.predict(y0, np.zeros((10, 10)), dt, odo, odo, p)
    u, n = np.array([np.cos(th), np.sin(th)]), np.array([-np.sin(th), np.cos(th)])
    np.testing.assert_allclose(y[:2], y0[:2] + v * dt * u, rtol=0, atol=1e-12)
    assert y[5] == pytest.approx(th, abs=1e-15)
    np.testing.assert_allclose(y[8:], y0[8:] * np.exp(-dt / p.gnss_bias_tau_s), rtol=1e-14)
    np.testing.assert_array_equal(y[[2, 3, 4, 6, 7]], y0[[2, 3, 4, 6, 7]])

    sv2 = p.speed_sigma_mps**2 + (p.speed_scale_sigma * v) ** 2
    sw2 = p.yaw_rate_sigma_radps**2
    Pxy = P[:2, :2]
    assert u @ Pxy @ u == pytest.approx(sv2 * dt**2 + 1e-6 * dt, rel=1e-12)
    cross = (0.5 * v * dt**2) ** 2 * sw2 + p.lateral_sigma_mps**2 * dt**2 + 1e-6 * dt
    assert n @ Pxy @ n == pytest.approx(cross, rel=1e-12)
    assert u @ Pxy @ n == pytest.approx(0.0, abs=1e-15)
    assert P[5, 5] == pytest.approx(sw2 * dt**2, rel=1e-12)
    assert n @ P[:2, 5] == pytest.approx(0.5 * v * dt**3 * sw2, rel=1e-12)
    assert P[2, 2] == pytest.approx(p.z_sigma_mps**2 * dt, rel=1e-12)
    assert P[8, 8] == pytest.approx(p.gnss_bias_sigma_m**2 * (1 - np.exp(-2 * dt / p.gnss_bias_tau_s)), rel=1e-12)


def test_predict_many_steps_on_a_straight_line():
    y, P = _state(yaw=-2.0), np.diag([0.1] * 6 + [1e-4, 1e-6, 1.0, 1.0])
    odo = OdometryMeasurement(8.0, 0.0)
    for _ in range(50):
        y, P = ekf.predict(y, P, 0.1, odo, odo, PARAMS)
    np.testing.assert_allclose(y[:2], _state()[:2] + 40.0 * np.array([np.cos(-2.0), np.sin(-2.0)]), atol=1e-10)
    np.testing.assert_array_equal(P, P.T)
    assert np.all(np.linalg.eigvalsh(P) > 0)


def test_predict_covariance_uses_the_jacobian_of_its_mean():
    """P' - Q = F P F^T with F the numerical Jacobian of the mean (a turn, a scale error, gyro and GNSS biases)."""
    rng = np.random.default_rng(0)
    y0 = _state(yaw=1.0, scale=1.03, gyro_bias=0.004)
    a, b = OdometryMeasurement(9.0, 0.2), OdometryMeasurement(11.0, 0.3)
    dt = 0.2
    P0 = _spd(rng, 10, 0.01)
    _, Q = ekf.predict(y0, np.zeros((10, 10)), dt, a, b, PARAMS)
    _, P1 = ekf.predict(y0, P0, dt, a, b, PARAMS)
    F, eps = np.zeros((10, 10)), 1e-6
    for i in range(10):
        d = np.zeros(10)
        d[i] = eps
        F[:, i] = (ekf.predict(y0 + d, P0, dt, a, b, PARAMS)[0] - ekf.predict(y0 - d, P0, dt, a, b, PARAMS)[0]) / (
            2 * eps
        )
    np.testing.assert_allclose(P1 - Q, F @ P0 @ F.T, rtol=1e-6, atol=1e-10)


def test_predict_without_time_or_odometry():
    y0, P0 = _state(), np.eye(10)
    y, P = ekf.predict(y0, P0, 0.0, None, None, PARAMS)
    np.testing.assert_array_equal(y, y0)
    np.testing.assert_array_equal(P, P0)
    assert y is not y0 and P is not P0
    y, P = ekf.predict(y0, np.zeros((10, 10)), 0.1, None, None, PARAMS)  # blind: standing still, 10 m/s noise
    np.testing.assert_array_equal(y[:2], y0[:2])
    assert P[0, 0] + P[1, 1] == pytest.approx(10.0**2 * 0.1**2 + PARAMS.lateral_sigma_mps**2 * 0.01 + 2e-7, rel=1e-9)


def _hand_kalman(y, P, r, R):
    H = np.zeros((2, 10))
    H[:, :2] = H[:, 8:] = np.eye(2)
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    return y + K @ r, (np.eye(10) - K @ H) @ P, float(r @ np.linalg.inv(S) @ r)


@pytest.mark.parametrize(
    "offset_m, outcome, inflate", [(0.5, "used", False), (5.0, "used", True), (30.0, "rejected", None)]
)
def test_gnss_update_is_the_hand_computed_kalman_update(offset_m, outcome, inflate):
    """z = p_xy + b_gnss + white, R = (sigma_h^2 - bias^2) I; Huber-scaled beyond the soft gate, dropped beyond
    the hard one."""
    rng = np.random.default_rng(1)
    y0, P0 = _state(), _spd(rng, 10, 0.5)
    fix = GnssMeasurement(np.r_[y0[:2] + y0[8:] + [offset_m, 0.3 * offset_m], 0.0], 2.0, 3.0)
    white = 2.0**2 - PARAMS.gnss_bias_sigma_m**2
    assert ekf.gnss_white_var(fix, PARAMS) == pytest.approx(white)
    r = fix.p_map[:2] - y0[:2] - y0[8:]
    _, _, chi2 = _hand_kalman(y0, P0, r, white * np.eye(2))
    y, P, got = ekf.gnss_update(y0, P0, fix, PARAMS)
    assert got == outcome
    if outcome == "rejected":
        assert chi2 > PARAMS.gnss_gate_chi2
        assert y is y0 and P is P0
        return
    assert (chi2 > PARAMS.gnss_soft_chi2) is inflate
    R = white * np.eye(2) * (chi2 / PARAMS.gnss_soft_chi2 if inflate else 1.0)
    y_ref, P_ref, _ = _hand_kalman(y0, P0, r, R)
    np.testing.assert_allclose(y, y_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(P, P_ref, rtol=1e-9, atol=1e-12)
    assert ekf.gnss_update(y0, P0, None, PARAMS) == (y0, P0, "")


def test_gnss_white_variance_has_a_floor():
    assert ekf.gnss_white_var(None, PARAMS) == PARAMS.gnss_white_min_sigma_m**2
    precise = GnssMeasurement(np.zeros(3), 0.5, 1.0)  # reports less than the bias alone
    assert ekf.gnss_white_var(precise, PARAMS) == PARAMS.gnss_white_min_sigma_m**2


def test_match_update_is_the_linear_kalman_update_of_the_pose_block():
    """A posterior (x_f, P_f) from the prior (x_pred, P_xx) means information Lambda = P_f^-1 - P_xx^-1 on the pose:
    the update equals the Kalman update with H = [I 0], R = Lambda^-1 and z = R (P_f^-1 x_f - P_xx^-1 x_pred),
    biases included; the pose block is the matcher's posterior exactly."""
    y0, P0, Lam, x_f, P_f = _matched(2)
    Pxx = P0[:6, :6]
    match = SimpleNamespace(pose_filtered=x_f, cov_filtered=P_f)
    y, P = ekf.match_update(y0, P0, match)
    np.testing.assert_array_equal(y[:6], x_f)
    np.testing.assert_allclose(P[:6, :6], P_f, rtol=1e-9, atol=1e-12)
    R = np.linalg.inv(Lam)
    z = R @ (np.linalg.solve(P_f, x_f) - np.linalg.solve(Pxx, y0[:6]))
    H = np.hstack([np.eye(6), np.zeros((6, 4))])
    y_ref, P_ref = ekf.kf_update(y0, P0, H, z - y0[:6], R)
    np.testing.assert_allclose(y, y_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(P, P_ref, rtol=1e-7, atol=1e-12)


@pytest.mark.parametrize("w", [0.0, 0.3, 1.0])
def test_a_weighted_match_update_is_the_kalman_update_with_the_noise_over_the_weight(w):
    """weight w: the same pseudo-measurement z with its noise R / w (w = 0: nothing learnt)."""
    y0, P0, Lam, x_f, P_f = _matched(5)
    Pxx = P0[:6, :6]
    y, P = ekf.match_update(y0, P0, SimpleNamespace(pose_filtered=x_f, cov_filtered=P_f), w)
    if w == 0.0:
        np.testing.assert_allclose(y, y0, atol=1e-12)
        np.testing.assert_allclose(P, P0, rtol=1e-9, atol=1e-12)
        return
    R = np.linalg.inv(Lam)
    z = R @ (np.linalg.solve(P_f, x_f) - np.linalg.solve(Pxx, y0[:6]))
    H = np.hstack([np.eye(6), np.zeros((6, 4))])
    y_ref, P_ref = ekf.kf_update(y0, P0, H, z - y0[:6], R / w)
    np.testing.assert_allclose(y, y_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(P, P_ref, rtol=1e-7, atol=1e-12)
    with pytest.raises(ValueError, match="weight"):
        ekf.match_update(y0, P0, SimpleNamespace(pose_filtered=x_f, cov_filtered=P_f), 1.5)


def _real_match():
    """A synthetic frame 0.2 m, 0.3 deg off the prediction, matched: (state, its covariance, the match)."""
    truth = pose_on(170.0)
    frame, _ = synth_frame(truth, np.random.default_rng(4))
    x_pred = truth + np.array([0.2, -0.15, 0.02, 0.002, -0.002, np.radians(0.3)])
    P0 = np.zeros((10, 10))
    P0[:6, :6] = P_TRACK
    P0[6:, 6:] = np.diag([0.02**2, 0.005**2, 1.5**2, 1.5**2])
    P0[0, 8] = P0[8, 0] = P0[1, 9] = P0[9, 1] = 0.05  # the pose correlated with the GNSS bias
    match = MapMatcher(HDMAP).match(frame, x_pred, P_TRACK, None)
    assert match.converged
    return np.r_[x_pred, 1.0, 0.0, 0.3, -0.2], P0, match


def test_match_update_reproduces_the_matchers_posterior():
    y0, P0, match = _real_match()
    y, P = ekf.match_update(y0, P0, match)
    np.testing.assert_array_equal(y[:6], match.pose_filtered)
    np.testing.assert_allclose(P[:6, :6], match.cov_filtered, rtol=1e-8, atol=1e-14)
    assert P[8, 8] < P0[8, 8] and P[9, 9] < P0[9, 9]  # the bias learns through its correlation with the pose
    assert not np.allclose(y[8:], y0[8:])


def test_kf_update_joseph_form_wraps_yaw():
    rng = np.random.default_rng(3)
    y0, P0 = _state(yaw=np.pi - 0.01), _spd(rng, 10, 0.1)
    H = np.eye(10)[[5]]
    y, P = ekf.kf_update(y0, P0, H, np.array([0.5]), np.array([[1e-6]]))
    assert -np.pi <= y[5] < -np.pi + 0.5  # pi - 0.01 + ~0.5, wrapped
    K = P0 @ H.T / (H @ P0 @ H.T + 1e-6)
    np.testing.assert_allclose(P, P0 - K @ H @ P0, atol=1e-9)
    np.testing.assert_array_equal(P, P.T)


def test_ground_update_and_initial_state():
    p = PARAMS
    gnss = GnssMeasurement(np.array([3.0, 4.0, 7.0]), 2.0, 3.0)
    y, P = ekf.initial_state(gnss, 3.5, 0.1, 0.4, p)
    assert y[2] == pytest.approx(0.4 + p.matcher.body_height_m)
    assert y[5] == pytest.approx(3.5 - 2 * np.pi)
    vb = p.gnss_bias_sigma_m**2
    assert P[0, 0] == pytest.approx(vb + ekf.gnss_white_var(gnss, p) + p.init_extra_sigma_m**2)
    assert P[0, 8] == P[1, 9] == -vb and P[5, 5] == pytest.approx(0.01)
    assert np.all(np.linalg.eigvalsh(P) > 0)
    y_nz, P_nz = ekf.initial_state(gnss, 0.0, 0.1, None, p)  # no road nearby: the fix's height
    assert y_nz[2] == 7.0 and P_nz[2, 2] == 9.0
    # Ground update: the height pulled to the road by the ratio of variances, roll and pitch to nominal.
    y[2] += 0.5
    y[3] = 0.05
    y2, P2 = ekf.ground_update(y, P, 0.4, p)
    k = P[2, 2] / (P[2, 2] + p.ground_sigma_m**2)
    assert y2[2] == pytest.approx(y[2] - k * 0.5, rel=1e-9)
    assert abs(y2[3] - p.matcher.nominal_roll_pitch_rad[0]) < abs(y[3] - p.matcher.nominal_roll_pitch_rad[0])
    assert P2[2, 2] == pytest.approx(P[2, 2] * p.ground_sigma_m**2 / (P[2, 2] + p.ground_sigma_m**2), rel=1e-9)
    Pw = ekf.widen(P, gnss, p)
    assert Pw[0, 0] - P[0, 0] == pytest.approx(P[0, 0]) and Pw[5, 5] - P[5, 5] == pytest.approx(p.init_yaw_sigma_rad**2)
    assert ekf.sigma_h(np.diag([4.0, 1.0])) == 2.0


# --------------------------------------------------------------------------- consider states


def _one_landmark(s: float) -> MatchLinearization:
    """One landmark whose 2 rows measure the vehicle's x, y (m) directly with detector noise s, residual 0."""
    J = np.zeros((1, 2, 6))
    J[0, 0, 0] = J[0, 1, 1] = 1.0 / s
    zero6 = np.zeros((6, 6))
    return MatchLinearization((("pole", 7),), J, np.zeros((1, 2)), zero6, np.zeros(6), zero6, np.zeros(6))


@pytest.mark.parametrize("n", [1, 2, 10, 50])
def test_repeated_views_of_one_landmark_are_limited_by_its_map_error(n):
    """A standing vehicle seen n times through one landmark with detector noise s and map error sigma (the same in
    every view): the estimate is the views' mean, its error m + mean(noise), so its variance is sigma^2 + s^2 / n
    (closed form, a flat prior), never below the map's sigma^2; folded in as independent, (sigma^2 + s^2) / n."""
    sigma, s = 0.05, 0.02
    y, P = _state(), np.diag([1e4, 1e4, 1e-2, 1e-4, 1e-4, 1e-4, 1e-4, 1e-6, 1.0, 1.0])
    rng = np.random.default_rng(n)
    C: dict = {}
    lin = _one_landmark(s)
    for _ in range(n):
        x_f = y[:6] + np.r_[rng.normal(0, 0.1, 2), np.zeros(4)]
        y, P, C = ekf.consider_match_update(y, P, C, lin, x_f, sigma)
    assert P[0, 0] == pytest.approx(sigma**2 + s**2 / n, rel=1e-3)
    assert P[1, 1] == pytest.approx(sigma**2 + s**2 / n, rel=1e-3)
    np.testing.assert_allclose(C[("pole", 7)][:2, :2], sigma**2 * np.eye(2), rtol=1e-3)  # Cov(x, m): x = z + m


def test_consider_update_is_the_schmidt_kalman_update_of_the_augmented_state():
    """Against the augmented state written out: [y; m] with Cov(y, m) = C, rows H_a = [J, -J_xyz]: the update of y
    and of C is the Kalman update of the augmented state (its m block left as it was: a consider state), and the
    covariance is the true error covariance of that (suboptimal) estimate, P - K_y S K_y^T."""
    rng = np.random.default_rng(5)
    y0, P0 = _state(), _spd(rng, 10, 0.2)
    sigma = 0.05
    C0 = {("point", 3): 0.01 * rng.normal(size=(10, 3))}
    J = rng.normal(size=(2, 2, 6))
    e = rng.normal(size=(2, 2))
    info_l = _spd(rng, 6, 2.0)
    grad_l = rng.normal(size=6)
    lin = MatchLinearization((("point", 3), ("pole", 1)), J, e, info_l, grad_l, np.zeros((6, 6)), np.zeros(6))
    x_f = y0[:6] + rng.normal(0, 0.05, 6)
    y, P, C = ekf.consider_match_update(y0, P0, C0, lin, x_f, sigma)
    # the augmented state and its rows, written out
    Pa = np.zeros((16, 16))
    Pa[:10, :10] = P0
    Pa[:10, 10:13], Pa[10:13, :10] = C0[("point", 3)], C0[("point", 3)].T
    Pa[10:, 10:] = sigma**2 * np.eye(6)
    d = x_f - y0[:6]
    L = np.linalg.cholesky(info_l)  # any square root of the lanes' information gives the same update
    H = np.zeros((10, 16))
    H[:6, :6] = L.T
    r = [L.T @ d - np.linalg.solve(L, grad_l)]
    for k, c0 in enumerate((10, 13)):
        H[6 + 2 * k : 8 + 2 * k, :6] = J[k]
        H[6 + 2 * k : 8 + 2 * k, c0 : c0 + 3] = -J[k][:, :3]
        r.append(J[k] @ d - e[k])
    r = np.concatenate(r)
    S = H @ Pa @ H.T + np.eye(10)
    K = Pa @ H.T @ np.linalg.inv(S)
    Pa_new = Pa - K @ S @ K.T
    np.testing.assert_allclose(y, y0 + K[:10] @ r, atol=1e-10)
    np.testing.assert_allclose(P, Pa_new[:10, :10], atol=1e-10)
    np.testing.assert_allclose(C[("point", 3)], Pa_new[:10, 10:13], atol=1e-10)
    np.testing.assert_allclose(C[("pole", 1)], Pa_new[:10, 13:16], atol=1e-10)


def test_consider_update_of_a_first_view_is_the_matchers_frame_model():
    """A real frame, every landmark seen for the first time (C empty): the matcher solved with the map error in
    each detection's noise (isotropic in the image), the consider update with it as each landmark's 3-D offset.
    The two posteriors agree to the pixel approximation's few per cent, and the state moves to the solution."""
    y0, P0, match = _real_match()
    assert match.linearization is not None and len(match.linearization.keys) >= 3
    sigma = PARAMS.matcher.landmark_map_sigma_m
    y, P, C = ekf.consider_match_update(y0, P0, {}, match.linearization, match.pose_filtered, sigma)
    assert set(C) == set(match.linearization.keys)
    sd, sd_matcher = np.sqrt(np.diag(P[:6, :6])), np.sqrt(np.diag(match.cov_filtered))
    np.testing.assert_allclose(sd, sd_matcher, rtol=0.25)
    assert np.all(np.abs(y[:6] - match.pose_filtered) < 0.5 * sd_matcher + 1e-3)
    # no map error: the detector rows alone, so at least as tight as the matcher's
    y0_, P_, _ = ekf.consider_match_update(y0, P0, {}, match.linearization, match.pose_filtered, 0.0)
    assert np.all(np.diag(P_)[:6] <= np.diag(P)[:6] + 1e-12)


def test_consider_carry_follows_a_state_update():
    """An update of the state alone (a GNSS fix) changes Cov(y, m) by (I - K H) = P_after P_before^-1."""
    rng = np.random.default_rng(6)
    y0, P0 = _state(), _spd(rng, 10, 0.2)
    C0 = {("pole", 2): 0.01 * rng.normal(size=(10, 3))}
    H = np.zeros((2, 10))
    H[:, :2] = np.eye(2)
    R = 0.3 * np.eye(2)
    _, P1 = ekf.kf_update(y0, P0, H, np.zeros(2), R)
    K = P0 @ H.T @ np.linalg.inv(H @ P0 @ H.T + R)
    C1 = ekf.consider_carry(C0, P0, P1)
    np.testing.assert_allclose(C1[("pole", 2)], (np.eye(10) - K @ H) @ C0[("pole", 2)], atol=1e-12)
    assert ekf.consider_carry({}, P0, P1) == {}


def test_the_tracker_with_consider_states_tracks_and_states_wider_along_the_road():
    """LocalizerParams.map_errors='consider' on the synthetic drive (an exact map, the map error stated 5 cm):
    it tracks as the default does (map matched, RMSE), keeps the landmarks in view as consider states, and its
    along-road sigma is no tighter than the default's, which counts every view's map error as new."""
    from .test_localization import _drive

    runs = {}
    for mode in ("independent", "consider"):
        loc, out = _drive(60, seed=1, params=LocalizerParams(map_errors=mode))
        modes = [r.mode for _, r in out]
        assert modes.count("map_matching") >= 0.9 * len(modes), (mode, modes)
        err = np.array([np.hypot(*(r.pose_filtered[:2] - truth[:2])) for truth, r in out[10:]])
        assert np.sqrt(np.mean(err**2)) < 0.15, (mode, err)
        h = np.array([np.cos(out[-1][1].pose_filtered[5]), np.sin(out[-1][1].pose_filtered[5])])
        runs[mode] = (loc, float(h @ loc.P[:2, :2] @ h))
    assert runs["independent"][0].consider == {} and runs["consider"][0].consider
    assert runs["consider"][1] >= runs["independent"][1]
