"""The simulator's error sources and per-run traffic: each measurably there when on and absent when off,
drawn per seed from streams of their own, and the presets that use them."""

import numpy as np
import pytest

from mapcontainer import geometry as geo
from mapcontainer.config import ConfigError
from mapcontainer.sim import (
    ERROR_SOURCES,
    World,
    enabled_error_sources,
    list_scenarios,
    load_scenario,
    published_map,
    with_error_sources,
    with_traffic,
)
from mapcontainer.sim.actors import ActorState
from mapcontainer.sim.config import load_sensor_config
from mapcontainer.sim.sensors import ObjectDetector
from schemas import ObjectClass

URBAN = load_scenario("paper-urban")
CFG = load_sensor_config()


def _ideal(name: str = "paper-urban", *on: str, traffic: bool = False):
    return with_traffic(with_error_sources(load_scenario(name), on), traffic)


# ---------------------------------------------------------------- switches and defaults


def test_every_preset_has_every_source_and_traffic_on():
    for name in list_scenarios():
        try:
            sc = load_scenario(name)
        except ConfigError as exc:  # a SUMO preset without the roads extra: checked where it is installed (CI)
            assert "[roads]" in str(exc), exc
            continue
        assert enabled_error_sources(sc) == ERROR_SOURCES, name
        assert sc.traffic.enabled, name


def test_with_error_sources_switches_exactly_those():
    for src in ERROR_SOURCES:
        assert enabled_error_sources(with_error_sources(URBAN, [src])) == (src,)
    assert enabled_error_sources(with_error_sources(URBAN, [])) == ()
    off = with_error_sources(URBAN, [])
    assert enabled_error_sources(with_error_sources(off, ERROR_SOURCES)) == ERROR_SOURCES  # values kept when off
    assert with_error_sources(off, ERROR_SOURCES) == URBAN
    with pytest.raises(ValueError, match="unknown error source"):
        with_error_sources(URBAN, ["gremlins"])
    assert not with_traffic(URBAN, False).traffic.enabled and with_traffic(URBAN, False).connected == URBAN.connected


# ---------------------------------------------------------------- map


def _landmarks(hd) -> dict[int, np.ndarray]:
    out = {f.id: f.p_map for f in hd.points}
    out.update({f.id: f.base for f in hd.poles})
    return out


def test_map_error_displaces_landmarks_by_the_configured_spread_and_drops_and_adds_some():
    m = CFG.hdmap
    d, missing, extra, total = [], 0, 0, 0
    for seed in range(40):
        w = World(_ideal("paper-urban", "map"), seed)
        true, pub = _landmarks(w.true_map), _landmarks(w.hdmap)
        d += [pub[i] - true[i] for i in true if i in pub]
        missing += sum(i not in pub for i in true)
        extra += sum(i not in true for i in pub)
        total += len(true)
    d = np.array(d)
    expect_h = np.hypot(m.field_sigma_m[0], m.landmark_sigma_m[0])  # per horizontal axis
    rms = np.sqrt(np.mean(d**2, axis=0))
    assert 0.75 * expect_h < rms[0] < 1.25 * expect_h and 0.75 * expect_h < rms[1] < 1.25 * expect_h, rms
    assert 0.05 < expect_h < 0.1  # about 5-10 cm: the range
    assert 0.02 < missing / total < 0.09 and 0.02 < extra / total < 0.09, (missing, extra, total)
    # Off: the vehicles' map is the world's.
    w = World(_ideal("paper-urban"), 0)
    assert w.hdmap is w.true_map


def test_lane_line_error_is_smooth_along_the_line():
    sc = _ideal("paper-urban", "map")
    d_near, d_far, spread = [], [], []
    for seed in range(10):
        w = World(sc, seed)
        for a, b in zip(w.hdmap.lane_lines, w.true_map.lane_lines, strict=True):
            e = (a.points - b.points)[:, :2]
            spread.append(e)
            d_near.append(e[1:] - e[:-1])  # vertices 1 m apart
            d_far.append(e[60:] - e[:-60])  # 60 m apart
    rms = np.sqrt(np.mean(np.vstack(spread) ** 2))
    near = np.sqrt(np.mean(np.vstack(d_near) ** 2))
    far = np.sqrt(np.mean(np.vstack(d_far) ** 2))
    assert 0.04 < rms < 0.08, rms  # field 5 cm + the line's own 3 cm per axis
    assert near < 0.15 * rms, "neighbouring vertices move together (not white per vertex)"
    assert far > 1.0 * rms, "60 m apart the errors are nearly independent"


def test_the_camera_renders_the_true_map_and_the_vehicles_carry_the_published_one():
    sc = _ideal("paper-urban", "map").model_copy(
        update={
            "sensors": URBAN.sensors.model_copy(
                update={"camera": URBAN.sensors.camera.model_copy(update={"pixel_sigma_px": 0.0})}
            )
        }
    )
    sc = with_error_sources(sc, ["map"])
    w = World(sc, 3)
    cam = w.camera("cv0")
    true, pub = {f.id: f.p_map for f in w.true_map.points}, {f.id: f.p_map for f in w.hdmap.points}
    res_true, res_pub = [], []
    for k in range(60):
        tick = w.tick(k)
        T_cam_map = geo.inverse(geo.pose_to_matrix(tick.states["cv0"].pose) @ cam.T_body_cam)
        obs = tick.debug["cv0"].camera
        for uv, pid in zip(obs.points_uv, obs.point_ids, strict=True):
            if pid in pub:
                res_true.append(uv - geo.project_points(cam.intr, T_cam_map, true[int(pid)])[0][0])
                res_pub.append(uv - geo.project_points(cam.intr, T_cam_map, pub[int(pid)])[0][0])
    assert len(res_true) > 20
    np.testing.assert_allclose(res_true, 0.0, atol=1e-6)
    assert np.sqrt(np.mean(np.square(res_pub))) > 0.5  # about 7 cm at 10-60 m with f = 1000 px


def test_published_map_is_per_seed_and_the_same_for_the_live_services():
    a, b, c = published_map(URBAN, 5), published_map(URBAN, 5), published_map(URBAN, 6)
    la, lb, lc = _landmarks(a), _landmarks(b), _landmarks(c)
    assert la.keys() == lb.keys() and all(np.array_equal(la[i], lb[i]) for i in la)
    assert any(i not in lc or not np.array_equal(la[i], lc[i]) for i in la)
    w = _landmarks(World(URBAN, 5).hdmap)
    assert w.keys() == la.keys() and all(np.array_equal(la[i], w[i]) for i in la)
    # The map's stream is its own: other sources and the traffic do not move it.
    other = _landmarks(published_map(with_traffic(with_error_sources(URBAN, ["map"]), False), 5))
    assert all(np.array_equal(la[i], other[i]) for i in la)


# ---------------------------------------------------------------- calibration


def test_the_true_camera_differs_from_the_reported_one_by_the_configured_error():
    c = CFG.camera.calibration_error
    angles, shifts, focal = [], [], []
    for seed in range(60):
        w = World(_ideal("paper-urban", "calibration"), seed)
        for vid in w.vehicle_ids:
            cam = w.camera(vid)
            R = cam.T_body_cam_reported[:3, :3].T @ cam.T_body_cam[:3, :3]
            angles.append(np.linalg.norm(geo.so3_log(R)))
            shifts.append(cam.T_body_cam[:3, 3] - cam.T_body_cam_reported[:3, 3])
            focal.append(cam.intr.fx / cam.reported_intr.fx - 1)
            info = w._sensors[vid].camera_info
            assert info.fx == cam.reported_intr.fx and np.array_equal(info.T_body_cam, cam.T_body_cam_reported)
    rms_angle = np.sqrt(np.mean(np.square(angles)))
    assert 0.85 < rms_angle / (np.sqrt(3) * c.rotation_sigma_rad) < 1.15
    assert 0.3 < np.degrees(rms_angle) < 0.5  # the 0.3-0.5 deg
    assert 0.85 < np.sqrt(np.mean(np.square(shifts))) / c.translation_sigma_m < 1.15
    assert 0.8 < np.std(focal) / c.focal_sigma < 1.2
    cam = World(_ideal("paper-urban"), 0).camera("cv0")
    assert np.array_equal(cam.T_body_cam, cam.T_body_cam_reported) and cam.intr == cam.reported_intr


# ---------------------------------------------------------------- detector


ME = ActorState("cv0", ObjectClass.VEHICLE, np.zeros(3), 0.0, np.zeros(3), 0.0, np.array([4.6, 1.9, 1.5]))
PED = ActorState(
    "7", ObjectClass.PEDESTRIAN, np.array([25.0, 8.0, 0.0]), 0.0, np.zeros(3), 0.0, np.array([0.6, 0.6, 1.75])
)


def _detector(seed: int, errors: bool, confusion: bool = False, clutter: bool = False) -> ObjectDetector:
    cfg = CFG.detector.model_copy(
        update={
            "p_detect_near": 1.0,
            "p_detect_far": 1.0,
            "errors": CFG.detector.errors.model_copy(update={"enabled": errors}),
            "class_confusion": CFG.detector.class_confusion.model_copy(update={"enabled": confusion}),
        }
    )
    ss = np.random.SeedSequence(seed).spawn(3)
    return ObjectDetector(cfg, (1.5, 0.0, 1.5), *(np.random.default_rng(s) for s in ss), clutter=clutter)


def _whitened_errors(det: ObjectDetector, n: int, dt: float = 0.1) -> np.ndarray:
    """Errors of n detections of PED, one every dt, in units of the nominal sigmas (n, 3)."""
    L = np.linalg.cholesky(det.covariance(PED.p_map[None])[0])
    out = []
    for k in range(n):
        p, _, _, ids = det.observe(ME, [PED], k * dt)
        out.append(np.linalg.solve(L, p[ids.index("7")] - PED.p_map))
    return np.array(out)


def _autocorr(e: np.ndarray, lag: int) -> float:
    return float(np.mean(e[lag:] * e[:-lag]) / np.mean(e * e))


def test_detector_errors_persist_over_the_configured_time():
    c = CFG.detector.errors
    e = np.vstack([_whitened_errors(_detector(s, True), 1500) for s in range(4)])
    assert 0.85 < np.mean(e**2) < 1.15, "the total error keeps the nominal sigma"
    lag_tau = int(round(c.tau_s / 0.1))
    assert abs(_autocorr(e, 1) - c.persistent_fraction * np.exp(-0.1 / c.tau_s)) < 0.08
    assert abs(_autocorr(e, lag_tau) - c.persistent_fraction * np.exp(-1.0)) < 0.08
    assert abs(_autocorr(e, 10 * lag_tau)) < 0.08
    white = _whitened_errors(_detector(0, False), 1500)
    assert abs(_autocorr(white, 1)) < 0.08, "off: white noise"


def test_reported_covariance_is_only_approximately_right():
    scales = [_detector(s, True).sigma_scale for s in range(400)]
    assert 0.85 < np.std(np.log(scales)) / CFG.detector.errors.reported_scale_sigma < 1.15
    det = _detector(1, True)
    p, cov, _, _ = det.observe(ME, [PED], 0.0)
    np.testing.assert_allclose(cov[0], det.sigma_scale**2 * det.covariance(p)[0])  # at the measured position
    det = _detector(1, False)
    p, cov, _, _ = det.observe(ME, [PED], 0.0)
    assert det.sigma_scale == 1.0
    np.testing.assert_allclose(cov[0], det.covariance(PED.p_map[None])[0])


def test_class_confusion_rate():
    p = CFG.detector.class_confusion.p
    det = _detector(2, False, confusion=True)
    cls = np.concatenate([det.observe(ME, [PED], 0.1 * k)[2] for k in range(5000)])
    wrong = np.mean(cls != ObjectClass.PEDESTRIAN)
    assert abs(wrong - p) < 4 * np.sqrt(p * (1 - p) / len(cls)), wrong
    assert set(np.unique(cls)) <= {ObjectClass.PEDESTRIAN, ObjectClass.VEHICLE, ObjectClass.CYCLIST}
    det = _detector(2, False, confusion=False)
    assert all(det.observe(ME, [PED], 0.1 * k)[2][0] == ObjectClass.PEDESTRIAN for k in range(2000))


def test_false_objects_are_ghosts_that_stay_and_clutter_off_has_none():
    c = CFG.detector
    det = _detector(3, False, clutter=True)
    counts, runs, last = [], [], None
    for k in range(6000):
        p, _, _, ids = det.observe(ME, [], 0.1 * k)
        counts.append(len(ids))
        key = tuple(np.round(p[:, 0], -1))  # a ghost stands still: its range rounded to 10 m repeats
        runs.append(bool(last) and bool(set(key) & set(last)))
        last = key
    assert 0.6 * c.false_alarms_per_frame < np.mean(counts) < 1.4 * c.false_alarms_per_frame
    present = np.array(counts[1:]) > 0
    assert np.mean(np.array(runs[1:])[present]) > 0.5, "a ghost is seen again in the next frame"
    det = _detector(3, False, clutter=False)
    assert all(len(det.observe(ME, [], 0.1 * k)[3]) == 0 for k in range(500))
    w = World(_ideal("paper-urban"), 0)  # clutter off in a world: no false landmarks or objects
    for tick in w.run(3.0):
        for d in tick.debug.values():
            assert None not in d.object_truth_ids and -1 not in d.camera.point_ids and -1 not in d.camera.pole_ids


# ---------------------------------------------------------------- clock


def test_clock_offset_shifts_each_vehicles_time_stamps_by_a_constant():
    offsets = []
    for seed in range(20):
        w = World(_ideal("paper-urban", "clock_offset"), seed)
        ticks = list(w.run(0.3))
        for vid in w.vehicle_ids:
            d = [t.frames[vid].t_meas - t.t for t in ticks]
            np.testing.assert_allclose(d, w.clock_offset_s(vid), atol=1e-12)
            assert all(t.truth.t_meas == t.t for t in ticks)
            offsets.append(d[0])
    assert 0.8 < np.std(offsets) / CFG.clock.offset_sigma_s < 1.2
    assert all(t.frames["cv0"].t_meas == t.t for t in World(_ideal("paper-urban"), 0).run(0.3))


def test_switching_one_source_leaves_the_others_draws():
    a = World(with_error_sources(URBAN, ["calibration", "clock_offset"]), 4)
    b = World(with_error_sources(URBAN, ["calibration"]), 4)
    c = World(with_error_sources(URBAN, ["clock_offset", "map", "detector"]), 4)
    for vid in a.vehicle_ids:
        assert np.array_equal(a.camera(vid).T_body_cam, b.camera(vid).T_body_cam)
        assert a.clock_offset_s(vid) == c.clock_offset_s(vid) != 0.0


# ---------------------------------------------------------------- traffic


def _starts(w: World) -> np.ndarray:
    s = w.states(0.0)
    return np.array([s[a.id].p_map for a in [*w.connected, *w.obstacles]])


def test_traffic_differs_between_seeds_not_within_one_and_off_is_as_listed():
    a, b, c = _starts(World(URBAN, 1)), _starts(World(URBAN, 1)), _starts(World(URBAN, 2))
    np.testing.assert_array_equal(a, b)
    assert np.median(np.linalg.norm(a - c, axis=1)) > 1.0
    off1, off2 = World(with_traffic(URBAN, False), 1), World(with_traffic(URBAN, False), 2)
    np.testing.assert_array_equal(_starts(off1), _starts(off2))
    assert [v.s0_m for v in off1.traffic.connected] == [v.s0_m for v in URBAN.connected]
    w = World(URBAN, 1)
    speeds = [v.speed_mps for v in w.traffic.connected]
    assert speeds != [v.speed_mps for v in URBAN.connected]
    assert {p.direction for p in World(URBAN, 3).traffic.pedestrians} == {1, -1}


def test_traffic_leaves_the_sensor_streams_of_a_seed():
    """The random streams do not move with the traffic: the GNSS error and the gyro error of a seed are the
    same draws with traffic variation on and off (both are independent of where the vehicle is)."""
    on, off = World(URBAN, 8), World(with_traffic(URBAN, False), 8)
    for ta, tb in zip(on.run(1.0), off.run(1.0), strict=True):
        for vid in on.vehicle_ids:
            ea = ta.frames[vid].gnss.p_map - ta.states[vid].p_map
            eb = tb.frames[vid].gnss.p_map - tb.states[vid].p_map
            np.testing.assert_allclose(ea, eb, atol=1e-4)  # float32 on the wire
            ga = ta.frames[vid].odometry.yaw_rate - ta.states[vid].yaw_rate
            gb = tb.frames[vid].odometry.yaw_rate - tb.states[vid].yaw_rate
            np.testing.assert_allclose(ga, gb, atol=1e-6)
            assert ta.frames[vid].t_meas == tb.frames[vid].t_meas


def test_vehicles_in_a_lane_keep_their_gap():
    gap = URBAN.traffic.min_gap_m
    for seed in range(8):
        w = World(URBAN, seed)
        lanes = {
            a.id: sp.lane
            for a, sp in zip(
                [*w.connected, *w.obstacles], [*w.traffic.connected, *w.traffic.obstacle_vehicles], strict=False
            )
        }
        for t in np.arange(0.0, 30.0, 0.5):
            st = w.states(t)
            for i in lanes:
                for j in lanes:
                    if i < j and lanes[i] == lanes[j]:
                        assert np.linalg.norm(st[i].p_map - st[j].p_map) > gap - 0.5, (seed, t, i, j)


@pytest.mark.parametrize("name", ["overlap", "blindspot-occluded", "blindspot-beyond"])
def test_test_site_platoons_keep_their_order_turn_and_change_speed(name):
    base = load_scenario(name)
    for seed in range(6):
        w = World(base, seed)
        s0 = [v.s0_m for v in [*w.traffic.connected, *w.traffic.obstacle_vehicles]]
        listed = [v.s0_m for v in [*base.connected, *base.obstacle_vehicles]]
        assert np.argsort(s0).tolist() == np.argsort(listed).tolist()
        assert np.max(np.abs(np.diff(s0) - np.diff(listed))) <= 2 * 2 * base.traffic.gap_sigma_m + 1e-9
    w = World(base, 0)
    states = [w.states(t) for t in np.arange(0.0, base.duration_s, 0.1)]
    speed = [s["cv0"].speed for s in states]
    turn = abs(np.degrees(np.angle(np.exp(1j * (states[-1]["cv0"].yaw - states[0]["cv0"].yaw)))))
    assert max(speed) - min(speed) > 2.0 and turn > 60.0


def test_blindspot_scenarios_keep_their_point():
    w = World(load_scenario("blindspot-beyond"), 0)
    for tick in w.run(20.0):
        assert not {"cv1", "1"} & set(tick.debug["cv0"].object_truth_ids), tick.t
    w = World(load_scenario("blindspot-occluded"), 0)
    seen = [
        ("1" in tick.debug["cv0"].object_truth_ids, "1" in tick.debug["cv1"].object_truth_ids) for tick in w.run(20.0)
    ]
    ego, cv1 = np.array(seen).T
    assert not ego[:50].any(), "on the straight the car ahead hides the obstacle"
    assert ego.mean() < 0.35 and cv1.mean() > 0.9
