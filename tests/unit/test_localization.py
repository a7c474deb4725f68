"""Map-matching localization: residual Jacobians, convergence, clutter, fallback and recovery, accuracy.

The camera frames come from a small synthetic generator below (independent of mapcontainer.sim):
the map's landmarks projected from the true pose with pixel noise, partial pole segments, optional
clutter, and a lane mask rendered from the painted lane samples like a segmentation network's output.
"""

from __future__ import annotations

import tracemalloc

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from mapcontainer import geometry as geo
from mapcontainer.hdmap import MapSpec, generate_map
from mapcontainer.localization import (
    CameraFrame,
    GnssMeasurement,
    Localizer,
    LocalizerParams,
    MapMatcher,
    MatcherParams,
    OdometryMeasurement,
)
from mapcontainer.localization.search import PoseSearch, PoseSearchParams

INTR = geo.CameraIntrinsics(1000.0, 1000.0, 639.5, 359.5, 1280, 720)
T_BC = geo.camera_extrinsic(1.5, 0.0, 1.5, pitch=0.0)
CODES = {"traffic_light": 1, "sign": 2}
HDMAP = generate_map(MapSpec())


# --------------------------------------------------------------------------- synthetic sensors


def _lane_segments(hdmap, spacing=0.5):
    """Consecutive painted samples (start, end) of every lane line: what the mask is drawn from."""
    a, b = [], []
    for ln in hdmap.lane_lines:
        line = ln.polyline
        s = np.arange(0.0, line.length, spacing)
        if ln.kind == "dashed":
            s = s[np.mod(s, ln.dash_m + ln.gap_m) < ln.dash_m - 1e-9]
        p = line.point_at(s)
        ok = np.diff(s) < 1.5 * spacing
        a.append(p[:-1][ok])
        b.append(p[1:][ok])
    return np.vstack(a), np.vstack(b)


SEGMENTS = _lane_segments(HDMAP)


def synth_frame(
    pose,
    rng,
    *,
    sigma_px=1.5,
    range_m=60.0,
    clutter=0.0,
    p_detect=1.0,
    lanes=True,
    lane_sigma_px=1.0,
    empty=False,
    T_bc=T_BC,
    intr=INTR,
) -> tuple[CameraFrame, int]:
    """A CameraFrame seen from ``pose`` and the number of true detections (clutter is appended after them).

    ``clutter`` is the fraction of all detections that are false (random pixel, random class).
    """
    if empty:
        return CameraFrame(
            intr,
            T_bc,
            np.zeros((0, 2)),
            np.zeros(0, np.uint8),
            np.zeros((0, 4)),
            np.zeros((intr.height, intr.width), np.uint8),
        ), 0
    T_map_body = geo.pose_to_matrix(pose)
    T_cam_map = geo.inverse(T_map_body @ T_bc)
    cam_c = geo.transform_points(T_map_body, T_bc[:3, 3])
    pts = np.array([f.p_map for f in HDMAP.points])
    cls = np.array([CODES[f.cls] for f in HDMAP.points])
    uv, z = geo.project_points(intr, T_cam_map, pts)
    vis = (z > 1.0) & (np.linalg.norm(pts - cam_c, axis=1) <= range_m)
    vis[vis] &= intr.in_image(uv[vis])
    vis &= rng.random(len(vis)) < p_detect
    p_uv = uv[vis] + rng.normal(0.0, sigma_px, (int(vis.sum()), 2))
    p_cls = cls[vis]
    poles = []
    f = np.linspace(0.0, 1.0, 16)
    for pl in HDMAP.poles:
        smp = pl.base + f[:, None] * (pl.top - pl.base)
        suv, sz = geo.project_points(intr, T_cam_map, smp)
        ok = (sz > 1.0) & (np.linalg.norm(smp - cam_c, axis=1) <= range_m)
        ok[ok] &= intr.in_image(suv[ok])
        idx = np.flatnonzero(ok)
        if len(idx) < 2 or rng.random() >= p_detect:
            continue
        a, b = smp[idx[0]], smp[idx[-1]]
        t0, t1 = rng.uniform(0.0, 0.35), rng.uniform(0.65, 1.0)  # partly occluded
        seg, _ = geo.project_points(intr, T_cam_map, np.stack([a + t0 * (b - a), a + t1 * (b - a)]))
        seg = seg.reshape(4)
        if np.hypot(*(seg[2:] - seg[:2])) >= 15.0:
            poles.append(seg + rng.normal(0.0, sigma_px, 4))
    poles = np.array(poles).reshape(-1, 4)
    n_true = len(p_uv) + len(poles)
    if clutter > 0:
        n_c = int(np.ceil(clutter / (1.0 - clutter) * max(n_true, 1)))
        n_cp = rng.binomial(n_c, 0.6)
        p_uv = np.vstack([p_uv, rng.uniform((0, 0), (intr.width - 1, intr.height - 1), (n_cp, 2))])
        p_cls = np.concatenate([p_cls, rng.choice([1, 2], n_cp)])
        fake = []
        for _ in range(n_c - n_cp):
            u, v = rng.uniform(0, intr.width - 1), rng.uniform(0, intr.height / 2)
            fake.append([u, v + rng.uniform(30, 200), u + rng.normal(0, 3), v])
        poles = np.vstack([poles, np.array(fake).reshape(-1, 4)])
    mask = None
    if lanes:
        mask = np.zeros((intr.height, intr.width), np.uint8)
        A, B = SEGMENTS
        near = np.linalg.norm(A[:, :2] - cam_c[:2], axis=1) <= 40.0
        ua, za = geo.project_points(intr, T_cam_map, A[near])
        ub, zb = geo.project_points(intr, T_cam_map, B[near])
        front = (za > 1.0) & (zb > 1.0)
        ua, ub, zz = ua[front], ub[front], 0.5 * (za[front] + zb[front])
        jitter = rng.normal(0.0, lane_sigma_px, (len(zz), 2))
        thick = np.clip(np.rint(intr.fx * 0.15 / zz), 1, 40).astype(int)
        pa = np.rint((ua + jitter) * 4).astype(np.int32)
        pb = np.rint((ub + jitter) * 4).astype(np.int32)
        keep = (np.abs(pa) < 40000).all(axis=1) & (np.abs(pb) < 40000).all(axis=1)
        for p, q, t in zip(pa[keep], pb[keep], thick[keep], strict=True):
            cv2.line(mask, (int(p[0]), int(p[1])), (int(q[0]), int(q[1])), 255, int(t), cv2.LINE_8, 2)
    frame = CameraFrame(intr, T_bc, p_uv.reshape(-1, 2), p_cls.astype(np.uint8), poles, mask)
    return frame, n_true


def pose_on(s, lane=0):
    """True pose at arc length s of a lane centre line (body origin on the ground, yaw from a 2 m chord)."""
    line = HDMAP.centerlines[lane].polyline
    p = line.point_at(s)
    d = line.point_at(s + 1.0) - line.point_at(s - 1.0)
    return np.array([p[0], p[1], 0.0, 0.0, 0.0, np.arctan2(d[1], d[0])])


def pose_error(est, truth):
    e = np.asarray(est, dtype=float) - truth
    e[5] = geo.wrap_angle(e[5])
    return e


def numerical_jacobian(f, x, eps=1e-6):
    f0 = np.asarray(f(x))
    J = np.zeros((f0.size, x.size))
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = eps
        J[:, i] = (np.asarray(f(x + dx)).reshape(-1) - np.asarray(f(x - dx)).reshape(-1)) / (2 * eps)
    return J


# Positions along centre line 0 where at least two landmarks are in view (checked in a test below).
RICH_S = [20.0, 170.0, 190.0, 250.0, 410.0]
P_WIDE = np.diag([3.0**2, 3.0**2, 0.3**2, 0.02**2, 0.02**2, np.radians(3.0) ** 2])
P_TRACK = np.diag([0.3**2, 0.3**2, 0.05**2, 0.005**2, 0.005**2, np.radians(0.5) ** 2])


# --------------------------------------------------------------------------- residuals


@pytest.fixture(scope="module")
def matcher():
    params = MatcherParams(gnss_lever_arm_m=(0.5, -0.2, 1.6))  # a lever arm exercises the GNSS rotation terms
    return MapMatcher(HDMAP, params)


def _round_at(matcher, s, rng):
    truth = pose_on(s)
    frame, _ = synth_frame(truth, rng)
    gnss = GnssMeasurement(truth[:3] + rng.normal(0, 1.0, 3), 2.0, 3.0)
    fd = matcher.prepare(frame, truth, P_TRACK, gnss)
    rd = matcher.associate(truth, P_TRACK, fd, 1)
    return truth, fd, rd


@pytest.mark.parametrize("block", ["points", "poles", "lanes", "ground", "gnss", "prior"])
def test_residual_jacobians_match_numerical(matcher, block):
    rng = np.random.default_rng(3)
    truth, fd, rd = _round_at(matcher, 250.0, rng)
    x = truth + np.array([0.08, -0.05, 0.02, 0.002, -0.003, 0.004])  # off the optimum, non-zero residuals
    e, J = matcher.residual_blocks(x, fd, rd)[block]
    assert len(e) > 0, f"no {block} residuals at this pose"
    Jn = numerical_jacobian(lambda q: matcher.residual_blocks(q, fd, rd)[block][0], x)
    if block == "lanes":
        # The bilinear distance transform is piecewise smooth: compare away from cell borders and the cap.
        uv, z, _ = geo.project_points_jac(fd.intr, x, fd.T_bc, rd.lane_xyz)
        frac = uv - np.floor(uv)
        smooth = np.all((frac > 0.01) & (frac < 0.99), axis=1) & matcher.residual_blocks(x, fd, rd)["lanes_under_cap"]
        assert smooth.sum() >= 10
        np.testing.assert_allclose(J[smooth], Jn[smooth], rtol=1e-3, atol=1e-3)
        assert np.abs(J).max() > 0
    else:
        np.testing.assert_allclose(J, Jn, rtol=1e-5, atol=1e-6)


def test_pole_residual_is_the_papers_line_distance(matcher):
    """D_L: signed distances of the projected map endpoints to the detected line (point_line_distance)."""
    rng = np.random.default_rng(4)
    truth, fd, rd = _round_at(matcher, 250.0, rng)
    assert len(rd.pole_A) >= 1
    x = truth + np.array([0.1, 0.1, 0.0, 0.0, 0.0, 0.01])
    e, _ = matcher.residual_blocks(x, fd, rd)["poles"]
    uv, _, _ = geo.project_points_jac(fd.intr, x, fd.T_bc, np.vstack([rd.pole_A, rd.pole_B]))
    K = len(rd.pole_A)
    for k in range(K):
        M1, M2 = fd.pole_M1[rd.pole_det[k]], fd.pole_M2[rd.pole_det[k]]
        d, _ = geo.point_line_distance(M1, M2, np.stack([uv[k], uv[K + k]]))
        np.testing.assert_allclose(e[2 * k : 2 * k + 2], rd.pole_W[k] @ d, atol=1e-9)


def test_landmarks_are_in_view_at_the_test_positions():
    rng = np.random.default_rng(0)
    for s in RICH_S:
        frame, n_true = synth_frame(pose_on(s), rng)
        assert 2 * len(frame.points_uv) + len(frame.poles_uv) >= 4, s


# --------------------------------------------------------------------------- one frame


@pytest.mark.parametrize("s", RICH_S)
def test_converges_from_3m_and_2deg(s):
    rng = np.random.default_rng(int(s))
    m = MapMatcher(HDMAP)
    truth = pose_on(s)
    frame, _ = synth_frame(truth, rng)
    d = np.array([2.1, -2.1, 0.0, 0.0, 0.0, np.radians(2.0)])  # 3 m and 2 deg off
    res = m.match(frame, truth + d, P_WIDE)
    e = pose_error(res.pose_filtered, truth)
    assert res.converged, res.reason
    # One frame, from a wide prior: the right basin (a wrong one is metres and degrees off) ...
    assert np.hypot(e[0], e[1]) < 0.4
    assert abs(np.degrees(e[5])) < 0.5
    assert res.n_lane > 0
    # ... and an honest covariance (chi^2, 6 dof, 99.9 %).
    assert e @ np.linalg.solve(res.cov_filtered, e) < 22.5


@pytest.mark.parametrize("seed", range(4))
def test_robust_to_20_percent_clutter(seed):
    rng = np.random.default_rng(100 + seed)
    m = MapMatcher(HDMAP)
    s = RICH_S[seed]
    truth = pose_on(s)
    frame, n_true = synth_frame(truth, rng, clutter=0.2)
    assert len(frame.points_uv) + len(frame.poles_uv) > n_true  # there is clutter
    for x0, P0 in [
        (truth + np.array([0.3, -0.2, 0, 0, 0, 0.005]), P_TRACK),
        (truth + np.array([2.1, -2.1, 0, 0, 0, np.radians(2.0)]), P_WIDE),
    ]:
        res = m.match(frame, x0, P0)
        e = pose_error(res.pose_filtered, truth)
        assert res.converged, res.reason
        assert np.hypot(e[0], e[1]) < 0.4, e
        assert abs(np.degrees(e[5])) < 0.5
        assert e @ np.linalg.solve(res.cov_filtered, e) < 22.5


def test_clutter_is_not_associated_when_tracking():
    m = MapMatcher(HDMAP)
    for s in RICH_S:
        truth = pose_on(s)
        clean, _ = synth_frame(truth, np.random.default_rng(int(s)))
        frame, _ = synth_frame(truth, np.random.default_rng(int(s)), clutter=0.2)
        n_pts_true, n_poles_true = len(clean.points_uv), len(clean.poles_uv)
        res = m.match(frame, truth + np.array([0.1, 0.1, 0, 0, 0, 0.002]), P_TRACK)
        assert np.all(res.point_pairs[:, 1] < n_pts_true), (s, res.point_pairs)
        assert np.all(res.pole_pairs[:, 1] < n_poles_true), (s, res.pole_pairs)


def test_no_features_is_reported_not_raised():
    m = MapMatcher(HDMAP)
    truth = pose_on(50.0)
    frame, _ = synth_frame(truth, np.random.default_rng(0), empty=True)
    res = m.match(frame, truth, P_TRACK)
    assert not res.converged and res.reason == "no features"
    np.testing.assert_allclose(res.pose_filtered, truth, atol=1e-9)  # only the prior: nothing moves


def test_half_resolution_lane_mask():
    rng = np.random.default_rng(5)
    m = MapMatcher(HDMAP)
    truth = pose_on(250.0)
    frame, _ = synth_frame(truth, rng)
    half = cv2.resize(frame.lane_mask, (640, 360), interpolation=cv2.INTER_AREA)
    frame_half = CameraFrame(
        frame.intr,
        frame.T_body_cam,
        frame.points_uv,
        frame.points_cls,
        frame.poles_uv,
        np.where(half > 0, 255, 0).astype(np.uint8),
    )
    res = m.match(frame_half, truth + np.array([0.2, -0.2, 0, 0, 0, 0.003]), P_TRACK)
    e = pose_error(res.pose_filtered, truth)
    assert res.converged and res.n_lane > 20
    assert np.hypot(e[0], e[1]) < 0.3
    assert e @ np.linalg.solve(res.cov_filtered, e) < 22.5


def test_malformed_inputs_raise_value_errors():
    m = MapMatcher(HDMAP)
    frame, _ = synth_frame(pose_on(20.0), np.random.default_rng(0))
    with pytest.raises(ValueError, match="pose_init"):
        m.match(frame, np.zeros(5), P_TRACK)
    with pytest.raises(ValueError, match="positive definite"):
        m.match(frame, pose_on(20.0), -np.eye(6))
    bad = CameraFrame(INTR, T_BC, np.zeros((3, 2)), np.zeros(2, np.uint8), np.zeros((0, 4)), None)
    with pytest.raises(ValueError, match="classes"):
        m.match(bad, pose_on(20.0), P_TRACK)
    with pytest.raises(ValidationError):
        MatcherParams(lane_cap_px=-1.0)
    with pytest.raises(ValidationError):
        LocalizerParams(no_such_field=1)


def test_non_finite_detections_are_dropped():
    m = MapMatcher(HDMAP)
    truth = pose_on(250.0)
    frame, _ = synth_frame(truth, np.random.default_rng(1))
    pts = np.vstack([frame.points_uv, [[np.nan, 3.0]]])
    cls = np.concatenate([frame.points_cls, [1]]).astype(np.uint8)
    dirty = CameraFrame(frame.intr, frame.T_body_cam, pts, cls, frame.poles_uv, frame.lane_mask)
    res = m.match(dirty, truth, P_TRACK)
    assert res.converged
    assert np.hypot(*pose_error(res.pose_filtered, truth)[:2]) < 0.2


# --------------------------------------------------------------------------- tracking


# The synthetic frames here come from the exact map through the exact camera: the localizer is told so (its
# defaults carry the realistic map and calibration specification, which these frames do not have).
EXACT = dict(match_bias_sigma=(0.0,) * 6, matcher=MatcherParams(landmark_map_sigma_m=0.0))


def _drive(n, seed, *, dark=(), clutter=0.0, initial_yaw=True, lane=0, s0=10.0, v=10.0, params=None):
    """Drive n frames at 10 Hz along a centre line; ``dark`` frames have no detections and an empty mask."""
    rng = np.random.default_rng(seed)
    loc = Localizer(
        HDMAP, params or LocalizerParams(**EXACT), initial_yaw=pose_on(s0, lane)[5] if initial_yaw else None
    )
    dt = 0.1
    bias = rng.normal(0.0, 1.5, 2)
    scale, gyro_bias = 1.0 + rng.normal(0.0, 0.01), rng.normal(0.0, 0.002)
    out = []
    for k in range(n):
        t = k * dt
        s = s0 + v * t
        truth = pose_on(s, lane)
        yaw_rate = geo.wrap_angle(pose_on(s + v * dt, lane)[5] - pose_on(s - v * dt, lane)[5]) / (2 * dt)
        odo = OdometryMeasurement(v * scale + rng.normal(0, 0.05), yaw_rate + gyro_bias + rng.normal(0, 0.005))
        phi = np.exp(-dt / 60.0)
        bias = phi * bias + np.sqrt(1 - phi**2) * 1.5 * rng.normal(size=2)
        gnss = GnssMeasurement(truth[:3] + np.r_[bias + rng.normal(0, 0.8, 2), rng.normal(0, 1.5)], 2.0, 3.0)
        frame, _ = synth_frame(truth, rng, clutter=clutter, p_detect=0.9, empty=k in dark)
        res = loc.step(t, frame, odo, gnss)
        out.append((truth, res))
    return loc, out


def _stats(out, start=0):
    errs, nees = [], []
    for truth, res in out[start:]:
        e = pose_error(res.pose, truth)
        errs.append(e)
        nees.append(e @ np.linalg.solve(res.cov, e))
    errs = np.array(errs)
    return (
        np.sqrt(np.mean(np.sum(errs[:, :2] ** 2, axis=1))),
        np.degrees(np.sqrt(np.mean(errs[:, 5] ** 2))),
        float(np.mean(nees)),
    )


def test_tracking_accuracy_and_consistency():
    loc, out = _drive(120, seed=1)
    modes = [r.mode for _, r in out]
    pos_rmse, yaw_rmse_deg, nees = _stats(out, start=5)
    assert modes.count("map_matching") >= 0.95 * len(modes)
    assert pos_rmse < 0.15, pos_rmse
    assert yaw_rmse_deg < 0.3, yaw_rmse_deg
    assert 1.0 < nees < 15.0, nees  # 6-DoF NEES: 6 expected; loose for 115 correlated frames


def test_frame_estimates_are_consistent_too():
    _, out = _drive(60, seed=2, params=LocalizerParams(report="frame", **EXACT))
    pos_rmse, yaw_rmse_deg, nees = _stats(out, start=5)
    assert pos_rmse < 0.25 and yaw_rmse_deg < 0.4
    assert nees < 15.0
    assert all(r.pose_frame is not None for _, r in out if r.mode == "map_matching")


def test_fallback_when_blind_and_recovery():
    dark = set(range(30, 60))
    loc, out = _drive(90, seed=3, dark=dark)
    modes = [r.mode for _, r in out]
    assert all(m == "map_matching" for m in modes[5:30])
    assert all(m == "fallback" for m in modes[30:60])
    sig = [np.sqrt(np.trace(r.cov[:2, :2])) for _, r in out[30:60]]
    assert sig[-1] > 2.0 * sig[0]  # dead reckoning: the covariance grows
    assert np.all(np.diff(sig) > -1e-3)
    # Honest while blind: the error stays within 3 sigma (per axis, horizontal).
    for truth, r in out[30:60]:
        e = pose_error(r.pose, truth)
        assert e[:2] @ np.linalg.solve(r.cov[:2, :2], e[:2]) < 13.8
    # Recovery: map matching again within a few frames, and accurate.
    assert all(m == "map_matching" for m in modes[65:])
    pos_rmse, yaw_rmse_deg, _ = _stats(out, start=70)
    assert pos_rmse < 0.2 and yaw_rmse_deg < 0.3
    assert loc.stats["fallback"] >= 30


def test_robust_tracking_with_clutter():
    _, out = _drive(50, seed=4, clutter=0.2)
    pos_rmse, yaw_rmse_deg, _ = _stats(out, start=5)
    assert sum(r.mode == "map_matching" for _, r in out) >= 45
    assert pos_rmse < 0.2 and yaw_rmse_deg < 0.3


def test_initialises_without_a_heading():
    """No initial yaw on a two-way road: the lane directions in the map, confirmed by the camera, decide."""
    loc, out = _drive(60, seed=5, initial_yaw=False, s0=20.0)
    first = next(k for k, (_, r) in enumerate(out) if r.mode == "map_matching")
    assert first < 10
    pos_rmse, yaw_rmse_deg, _ = _stats(out, start=first + 5)
    assert pos_rmse < 0.2 and yaw_rmse_deg < 0.3
    assert loc.stats["initialised"] == 1


def test_bad_input_is_counted_not_raised():
    loc, out = _drive(5, seed=6)
    last = out[-1][1]
    res = loc.step(0.1, None, OdometryMeasurement(10.0, 0.0), None)  # time went backwards
    assert res.reason == "time went backwards"
    np.testing.assert_allclose(res.pose, last.pose)
    res = loc.step(0.6, None, OdometryMeasurement(np.nan, 0.0), None)
    assert "odometry" in res.reason
    res = loc.step(0.6, None, (10.0, 0.0), (np.zeros(2), 2.0, 3.0))  # tuples are accepted; this fix is malformed
    assert "GNSS" in res.reason
    assert loc.stats["time went backwards"] == 1
    res = loc.step(0.6, None, (10.0, 0.0), (pose_on(16.0)[:3], 2.0, 3.0))
    assert res.initialized and res.mode == "fallback" and res.reason == "no camera frame"
    assert res.quality()["mode"] == "fallback"


def test_heading_from_the_course_over_ground_without_camera():
    """Two-way road, no camera: the GNSS course picks which lane direction the vehicle drives."""
    rng = np.random.default_rng(8)
    loc = Localizer(HDMAP)
    v, dt = 10.0, 0.1
    res = truth = None
    for k in range(40):
        s = 30.0 + v * dt * k
        truth = pose_on(s, lane=1)  # an inner lane, driven clockwise
        yaw_rate = geo.wrap_angle(pose_on(s + v * dt, 1)[5] - pose_on(s - v * dt, 1)[5]) / (2 * dt)
        gnss = GnssMeasurement(truth[:3] + np.r_[rng.normal(0, 0.8, 2), 0.0], 2.0, 3.0)
        res = loc.step(dt * k, None, OdometryMeasurement(v, yaw_rate), gnss)
        if k < 5:  # a two-way road: the heading is not known yet, and the result says so
            assert not res.initialized and res.mode == "fallback"
            assert res.cov[5, 5] == pytest.approx(np.pi**2 / 3)
    assert res.initialized and res.mode == "fallback"
    e = pose_error(res.pose, truth)
    assert abs(np.degrees(e[5])) < 5.0
    assert e[5] ** 2 < 9.0 * res.cov[5, 5]


def test_frame_estimate_without_measurements_is_the_weak_prior():
    m = MapMatcher(HDMAP)
    truth = pose_on(50.0)
    frame, _ = synth_frame(truth, np.random.default_rng(0), empty=True)
    res = m.match(frame, truth, P_TRACK)
    k = m.params.prior_inflation
    np.testing.assert_allclose(res.pose, truth, atol=1e-9)
    # Only r_n adds information (roll, pitch, height); x, y and yaw keep the weakened prior.
    for i in (0, 1, 5):
        assert res.cov[i, i] == pytest.approx(k * P_TRACK[i, i], rel=1e-6)
        assert res.cov_filtered[i, i] == pytest.approx(P_TRACK[i, i], rel=1e-6)


# --------------------------------------------------------------------------- start-up: global pose search


def _yaws_both_ways(yaw, half_deg=6.0, step_deg=1.5):
    k = np.arange(-half_deg, half_deg + 1e-9, step_deg)
    return geo.wrap_angle(np.radians(np.concatenate([k, k + 180.0])) + yaw)


WHOLE = PoseSearchParams(solves_per_frame=None)  # every start solved in the frame: the search's decision in one call


@pytest.mark.parametrize("s", [10.0, 190.0, 205.0])
def test_search_finds_the_basin_from_a_gnss_fix_facing_either_way(s):
    """The search's decision over all its starts (no budget: one call solves them all)."""
    rng = np.random.default_rng(int(s))
    m = MapMatcher(HDMAP)
    truth = pose_on(s)
    frame, _ = synth_frame(truth, rng)
    start = truth + np.array([2.5, -2.0, 0.0, 0.0, 0.0, np.pi])  # GNSS-level off and facing backwards
    cov = np.diag([9.0, 9.0, 0.04, 4e-4, 4e-4, np.pi**2 / 3])
    out = PoseSearch(m, WHOLE).search(frame, start, cov, _yaws_both_ways(truth[5]), radius_m=9.0)
    assert out.match is not None, out.reason
    e = pose_error(out.match.pose_filtered, truth)
    assert np.hypot(*e[:2]) < 0.3 and abs(np.degrees(e[5])) < 0.5
    assert out.runner_up_score - out.best_score >= PoseSearchParams().margin


@pytest.mark.parametrize("s", [10.0, 190.0, 205.0])
def test_the_budgeted_start_up_finds_the_basin_from_a_gnss_fix_over_a_few_frames(s):
    """The same start as above through the localizer, with the default anytime budget (search.solves_per_frame):
    no heading, the fix 3.2 m off, the vehicle standing still (the same frame each step, zero odometry). The search
    spreads its starts over the first frames and its basins are tracked until one wins: map matched within 4
    frames, as accurate as the whole search, never a map-matched pose before; and no step uses more than the
    budget and one start's solves (a lane search and a polish, 4 at most)."""
    rng = np.random.default_rng(int(s))
    truth = pose_on(s)
    frame, _ = synth_frame(truth, rng)
    loc = Localizer(HDMAP, LocalizerParams(**EXACT))
    fix = GnssMeasurement(truth[:3] + np.array([2.5, -2.0, 0.0]), 2.0, 3.0)
    modes, solves = [], []
    for k in range(8):
        solves0 = loc.matcher.solves
        res = loc.step(0.1 * k, frame, OdometryMeasurement(0.0, 0.0), fix)
        solves.append(loc.matcher.solves - solves0)
        modes.append(res.mode)
        if res.mode == "map_matching":
            e = pose_error(res.pose, truth)
            assert np.hypot(*e[:2]) < 0.3 and abs(np.degrees(e[5])) < 0.5, (k, e)
    assert "map_matching" in modes[:4], modes
    first = modes.index("map_matching")
    assert modes[first:] == ["map_matching"] * (8 - first), modes
    assert max(solves) <= loc.params.search.solves_per_frame + 4, solves


def test_a_budgeted_search_carries_its_starts_and_decides_once_all_are_solved():
    """The anytime search (search.solves_per_frame): a budget of 1 solve solves the first start only, accepts
    nothing and returns the others as pending; solving those (here on the same frame) finds the basin the whole
    search accepts."""
    s = 190.0
    m = MapMatcher(HDMAP)
    truth = pose_on(s)
    frame, _ = synth_frame(truth, np.random.default_rng(int(s)))
    start = truth + np.array([2.5, -2.0, 0.0, 0.0, 0.0, np.pi])
    cov = np.diag([9.0, 9.0, 0.04, 4e-4, 4e-4, np.pi**2 / 3])
    search = PoseSearch(m, WHOLE)
    whole = search.search(frame, start, cov, _yaws_both_ways(truth[5]), radius_m=9.0)
    solves = m.solves
    first = search.search(frame, start, cov, _yaws_both_ways(truth[5]), radius_m=9.0, budget=1)
    assert first.match is None and first.reason.startswith("searching") and len(first.solutions) == 1
    assert whole.match is not None and whole.pending == ()
    assert len(first.pending) >= 1 and m.solves - solves <= 4  # one start (its lane search, its polish)
    # Resumed without a budget, the carried starts are all solved; their basins join the caller's hypotheses
    # (nothing accepted: the first frame's basins are not among them), and the true one is there.
    rest = search.search(frame, start, cov, _yaws_both_ways(truth[5]), radius_m=9.0, starts=first.pending)
    assert rest.pending == () and rest.match is None and rest.solutions
    e = pose_error(rest.solutions[0].pose_filtered, truth)
    assert np.hypot(*e[:2]) < 0.3 and abs(np.degrees(e[5])) < 0.5


def test_search_does_not_guess_from_one_landmark():
    rng = np.random.default_rng(7)
    truth = pose_on(30.0)
    frame, _ = synth_frame(truth, rng, lanes=False)
    one = CameraFrame(frame.intr, frame.T_body_cam, frame.points_uv[:1], frame.points_cls[:1], np.zeros((0, 4)))
    cov = np.diag([9.0, 9.0, 0.04, 4e-4, 4e-4, np.pi**2 / 3])
    out = PoseSearch(MapMatcher(HDMAP)).search(one, truth, cov, _yaws_both_ways(truth[5]), radius_m=9.0)
    assert out.match is None
    assert out.reason  # too few features or ambiguous: said, not guessed


def test_the_grid_search_of_a_frame_with_4096_detections_stays_small():
    """A frame of MAX_LANDMARKS point detections (105 kB on the wire) took the grid over 6 GB: the grid
    scores at most grid_detections of them, so its memory does not grow with the frame."""
    rng = np.random.default_rng(7)
    truth = pose_on(30.0)
    frame, _ = synth_frame(truth, rng)
    n = 4096
    pts = np.column_stack([rng.uniform(0, 1280, n), rng.uniform(0, 720, n)])
    big = CameraFrame(frame.intr, frame.T_body_cam, pts, rng.choice(np.unique(frame.points_cls), n), frame.poles_uv)
    cov = np.diag([9.0, 9.0, 0.04, 4e-4, 4e-4, np.pi**2 / 3])
    tracemalloc.start()
    try:
        out = PoseSearch(MapMatcher(HDMAP)).search(big, truth, cov, _yaws_both_ways(truth[5]), radius_m=9.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert out.match is None and out.reason  # clutter everywhere: nothing accepted, and said why
    assert peak < 150e6, f"{peak / 1e6:.0f} MB"


@pytest.mark.parametrize(
    ("rule", "n_points", "n_poles", "decidable"),
    [
        ("landmarks", 0, 2, False),
        ("landmarks", 1, 0, False),
        ("landmarks", 2, 0, True),
        ("landmarks", 1, 1, True),
        ("landmarks", 0, 3, True),
        ("posterior", 0, 0, False),
        ("posterior", 0, 1, True),
        ("posterior", 1, 0, True),
        ("posterior", 2, 0, True),
        ("posterior", 0, 3, True),
    ],
)
def test_search_knows_which_frames_cannot_decide(rule, n_points, n_poles, decidable):
    """Rule 'landmarks' (the default): min_constraints 5 (2 per point, 1 per pole, 2 for the lanes) and min_landmarks
    2: a frame that cannot meet them even were every detection an inlier is not worth a start-up search. Rule
    'posterior': a frame with a landmark detection is (one pole with the lanes, explained frame after frame, can
    decide a start by its posterior mass); the lanes alone repeat along the road."""
    rng = np.random.default_rng(7)
    truth = pose_on(30.0)
    frame, _ = synth_frame(truth, rng)
    pts, poles = np.zeros((n_points, 2)), np.tile([[600.0, 500.0, 600.0, 300.0]], (n_poles, 1))
    some = CameraFrame(frame.intr, frame.T_body_cam, pts, np.zeros(n_points, int), poles, frame.lane_mask)
    assert PoseSearch(MapMatcher(HDMAP), PoseSearchParams(accept=rule)).can_accept(some) is decidable


@pytest.mark.parametrize(
    ("rule", "seed", "s0", "min_matched"),
    [
        ("landmarks", 11, 170.0, 30),
        ("landmarks", 12, 190.0, 30),
        ("landmarks", 13, 55.0, 0),
        ("posterior", 11, 170.0, 30),
        ("posterior", 12, 190.0, 30),
        pytest.param(
            "posterior",
            13,
            55.0,
            0,
            marks=pytest.mark.xfail(
                strict=True,
                reason="known regression of the posterior-mass start-up: one distant pole on lanes that repeat "
                "about a metre across holds the mass after a baseline of travel and locks 0.9 m across at 4 sigma "
                "(with the calibrated lane evidence too: the search does not return the true basin, and elsewhere is "
                "outweighed by the pole's views; see docs/localization.md)",
            ),
        ),
    ],
)
def test_cold_start_is_never_confidently_wrong(rule, seed, s0, min_matched):
    """No heading, GNSS metres off: until the camera settles it the result says fallback (honestly); after,
    it is right. From s = 55 m the landmarks are too sparse to settle it within 4 s: fallback throughout."""
    params = LocalizerParams(**EXACT, search=PoseSearchParams(accept=rule))
    _, out = _drive(40, seed=seed, initial_yaw=False, s0=s0, params=params)
    matched = [(truth, r) for truth, r in out if r.mode == "map_matching"]
    assert len(matched) >= min_matched
    for truth, r in matched:
        e = pose_error(r.pose, truth)
        assert np.hypot(*e[:2]) < 0.5 and abs(np.degrees(e[5])) < 1.0
    for truth, r in out:
        if r.mode == "fallback" and r.initialized:
            e = pose_error(r.pose, truth)[:2]
            assert e @ np.linalg.solve(r.cov[:2, :2], e) < 13.8  # within the 99.9 % ellipse


def test_known_start_pose_matches_from_the_first_frame():
    truth = pose_on(40.0)
    cov = np.diag([0.09, 0.09, 0.01, 1e-4, 1e-4, np.radians(1.0) ** 2])
    loc = Localizer(HDMAP, initial_pose=(truth + [0.2, -0.2, 0.0, 0.0, 0.0, 0.01], cov))
    frame, _ = synth_frame(truth, np.random.default_rng(3))
    res = loc.step(0.0, frame, OdometryMeasurement(10.0, 0.0), GnssMeasurement(truth[:3] + [2.0, 1.0, 0.0], 2.0, 3.0))
    assert res.mode == "map_matching"
    assert np.hypot(*pose_error(res.pose, truth)[:2]) < 0.2
    with pytest.raises(ValueError, match="positive definite"):
        Localizer(HDMAP, initial_pose=(truth, -np.eye(6)))


@pytest.mark.parametrize("offset_m, resets", [(20.0, 1), (10.0, 0)])
def test_a_state_far_from_every_gnss_fix_starts_again_from_gnss(offset_m, resets):
    """A wrong basin that its own matches keep confirming refuses every GNSS fix (the gate). When the
    state stays farther from the fixes than GNSS alone can err (15 m, 5 fixes in a row), the localizer
    starts again from GNSS; 10 m away (a multipath jump on a biased receiver) it keeps its state."""
    rng = np.random.default_rng(9)
    truth = pose_on(40.0)
    wrong = truth + np.r_[offset_m * np.array([np.cos(truth[5] + 1.0), np.sin(truth[5] + 1.0)]), 0, 0, 0, 0]
    cov = np.diag([0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4])
    loc = Localizer(HDMAP, LocalizerParams(verify_start_frames=0), initial_pose=(wrong, cov))
    for k in range(8):
        fix = GnssMeasurement(truth[:3] + np.r_[rng.normal(0, 0.8, 2), 0.0], 2.0, 3.0)
        res = loc.step(0.1 * k, None, OdometryMeasurement(0.0, 0.0), fix)  # standing still, camera blind
    assert loc.stats.get("gnss_divergence_reset", 0) == resets
    assert loc.stats["gnss rejected"] >= 5 - resets
    if resets:  # back to the GNSS fix, heading unknown until the course or the camera gives it
        assert not res.initialized and np.hypot(*(res.pose[:2] - truth[:2])) < 3.0
    else:
        assert res.initialized and np.hypot(*(res.pose[:2] - wrong[:2])) < 1.0
