"""The simulator: presets, determinism, visibility and occlusion, sensor statistics, bad configs."""

import hashlib

import numpy as np
import pytest

from mapcontainer import geometry as geo
from mapcontainer.config import ConfigError
from mapcontainer.hdmap.model import HDMap, PointFeature, PoleFeature
from mapcontainer.sim import World, list_scenarios, load_scenario
from mapcontainer.sim.actors import ActorState, BodyMotion
from mapcontainer.sim.config import BodyConfig, load_sensor_config
from mapcontainer.sim.sensors import Camera, ObjectDetector, occluded
from schemas import ObjectClass, encode

SITE = ("overlap", "blindspot-occluded", "blindspot-beyond")


def test_presets_load_and_paper_counts():
    assert {"paper-urban", "paper-suburban", *SITE, *(f"{n}-sparse" for n in SITE)} <= set(list_scenarios())
    paper = {"lamp": 14, "traffic_light": 4, "sign": 4}
    for name in ("paper-urban", "paper-suburban"):
        world = World(load_scenario(name), seed=0)
        assert len(world.vehicle_ids) == 4
        classes = [a.cls for a in world.obstacles]
        assert classes.count(ObjectClass.PEDESTRIAN) == 8
        assert classes.count(ObjectClass.VEHICLE) == 6
        assert world.true_map.feature_counts() == paper  # the world; the vehicles' map lacks or adds a few
    for name in SITE:  # the test site at the densified and at the paper's landmark density
        dense, sparse = World(load_scenario(name), seed=0), World(load_scenario(f"{name}-sparse"), seed=0)
        assert len(dense.vehicle_ids) == 2 and len(dense.obstacles) == 1
        assert dense.true_map.feature_counts() == {"lamp": 40, "traffic_light": 4, "sign": 16}
        assert sparse.true_map.feature_counts() == paper
        assert (
            sparse.scenario.connected == dense.scenario.connected and sparse.scenario.traffic == dense.scenario.traffic
        )


# A car's body on its suspension (1-sigmas; the profile of configs/sensors/default.yaml).
CAR_BODY = {
    "heave_static_m": 0.03,
    "heave_dynamic_m": 0.01,
    "roll_static_rad": 0.003,
    "roll_dynamic_rad": 0.004,
    "pitch_static_rad": 0.005,
    "pitch_dynamic_rad": 0.005,
}
BODY_ON = {"sensors": {"body": CAR_BODY}}


def _episode_digest(seed: int, frames: int = 15, overrides=None) -> tuple[str, str, str]:
    """Digests of the sensor frames, of the traffic (where every actor is and heads) and of the connected
    vehicles' body motion (height, roll, pitch)."""
    world = World(load_scenario("paper-urban", overrides), seed=seed)
    sensors, traffic, body = hashlib.sha256(), hashlib.sha256(), hashlib.sha256()
    for k in range(frames):
        tick = world.tick(k)
        tr = tick.truth
        traffic.update(encode(tr.model_copy(update={"vehicle_pose": tr.vehicle_pose[:, [0, 1, 5]]})))
        body.update(np.ascontiguousarray(tr.vehicle_pose[:, 2:5]).tobytes())
        for vid in world.vehicle_ids:
            sensors.update(encode(tick.frames[vid]))
    return sensors.hexdigest(), traffic.hexdigest(), body.hexdigest()


TRAFFIC_OFF = {"traffic": {"enabled": False}}


def test_same_seed_gives_identical_bytes_and_noise_depends_on_seed():
    a, b, c = _episode_digest(3), _episode_digest(3), _episode_digest(4)
    assert a == b
    assert a[0] != c[0], "sensor noise must depend on the seed"
    assert a[1] != c[1], "the traffic is drawn per run"
    a, c = _episode_digest(3, 5, TRAFFIC_OFF), _episode_digest(4, 5, TRAFFIC_OFF)
    assert a[0] != c[0] and a[1] == c[1], "traffic variation off: the traffic as listed in every run"
    a, c = _episode_digest(3, 5, {**BODY_ON, **TRAFFIC_OFF}), _episode_digest(4, 5, {**BODY_ON, **TRAFFIC_OFF})
    assert a[1] == c[1] and a[2] != c[2], "the bodies' suspension motion is drawn per run, like the sensor noise"


BODY_OFF = {"sensors": {"body": dict.fromkeys(BodyConfig.model_fields, 0.0)}}


def test_body_motion_is_per_vehicle_about_nominal_and_off_is_rigid():
    assert load_sensor_config().body == BodyConfig(**CAR_BODY), "the default profile: a car's body"
    cfg = BodyConfig(**CAR_BODY)
    static = np.array([cfg.heave_static_m, cfg.roll_static_rad, cfg.pitch_static_rad])
    dynamic = np.array([cfg.heave_dynamic_m, cfg.roll_dynamic_rad, cfg.pitch_dynamic_rad])
    t = np.arange(0.0, 60.0, 0.1)
    offsets, wobble = [], []
    for seed in range(300):
        m = BodyMotion(static, dynamic, np.random.default_rng(seed))
        x = np.array([m(ti) for ti in t])
        offsets.append(m.offset)
        wobble.append(x - m.offset)
        np.testing.assert_array_equal(m(12.3), m(12.3))  # a function of t
    np.testing.assert_allclose(np.std(offsets, axis=0), static, rtol=0.15)
    np.testing.assert_allclose(np.sqrt(np.mean(np.square(wobble), axis=(0, 1))), dynamic, rtol=0.1)
    # In the world: the camera rides on the moving body; with the body profile off, the body is rigid.
    on = World(load_scenario("paper-urban", BODY_ON), seed=1).states(2.0)["cv0"]
    off = World(load_scenario("paper-urban", BODY_OFF), seed=1).states(2.0)["cv0"]
    np.testing.assert_array_equal(on.p_map, off.p_map)
    assert on.pose[2] != on.p_map[2] and np.all(on.pose[3:5] != 0.0)
    np.testing.assert_array_equal(off.pose, [*off.p_map, 0.0, 0.0, off.yaw])


def test_the_camera_sees_from_the_pitched_body():
    """Detected points sit at their projection from the body's true (heaved, rolled, pitched) pose, through
    the true camera, of the true (world's) landmarks."""
    world = World(load_scenario("paper-urban", BODY_ON), seed=5)
    cam = world.camera("cv0")
    pts = {f.id: f.p_map for f in world.true_map.points}
    res_body, res_rigid, pitch = [], [], []
    for k in range(40):
        tick = world.tick(k)
        st = tick.states["cv0"]
        obs = tick.debug["cv0"].camera
        pitch.append(st.pose[4])
        for pose, out in ((st.pose, res_body), (np.array([*st.p_map, 0.0, 0.0, st.yaw]), res_rigid)):
            T_cam_map = geo.inverse(geo.pose_to_matrix(pose) @ cam.T_body_cam)
            for uv, pid in zip(obs.points_uv, obs.point_ids, strict=True):
                if pid >= 0:
                    out.append(uv - geo.project_points(cam.intr, T_cam_map, pts[int(pid)])[0][0])
    assert len(res_body) >= 20 and np.degrees(np.max(np.abs(pitch))) > 0.3
    rms_body = np.sqrt(np.mean(np.square(res_body)))
    assert rms_body < 2.5  # pixel noise 1.5 px per axis
    assert np.sqrt(np.mean(np.square(res_rigid))) > 2.0 * rms_body


def sure_camera_config(**overrides):
    """The default camera, detecting every landmark it sees and no clutter."""
    return load_sensor_config().camera.model_copy(
        update={
            "p_detect_near": 1.0,
            "p_detect_far": 1.0,
            "clutter_points_per_frame": 0.0,
            "clutter_poles_per_frame": 0.0,
            **overrides,
        }
    )


def _camera(**overrides) -> tuple[Camera, HDMap]:
    cfg = sure_camera_config(**overrides)
    hd = HDMap(
        name="probe",
        points=[
            PointFeature(1, "sign", np.array([20.0, 4.0, 2.0])),  # ahead, beside the truck: visible
            PointFeature(2, "sign", np.array([-20.0, 0.0, 2.0])),  # behind the camera
            PointFeature(3, "traffic_light", np.array([100.0, 0.0, 5.0])),  # beyond range (60 m)
            PointFeature(4, "sign", np.array([30.0, -0.3, 1.4])),  # behind the truck below
            PointFeature(5, "sign", np.array([10.0, 30.0, 2.0])),  # outside the field of view
        ],
        poles=[PoleFeature(6, "lamp", np.array([25.0, 5.0, 0.0]), np.array([25.0, 5.0, 8.0]))],
    )
    return Camera(cfg, hd, np.random.default_rng(0)), hd


TRUCK = ActorState(
    "9", ObjectClass.VEHICLE, np.array([15.0, 0.0, 0.0]), 0.0, np.zeros(3), 0.0, np.array([4.6, 1.9, 2.5])
)


def test_camera_never_detects_hidden_landmarks():
    cam, _ = _camera()
    seen = set()
    for _ in range(50):
        obs = cam.observe(np.zeros(6), [TRUCK])
        seen |= set(obs.point_ids.tolist()) | set(obs.pole_ids.tolist())
        assert 1 in obs.point_ids and 6 in obs.pole_ids
    assert seen == {1, 6}, f"hidden features were detected: {seen - {1, 6}}"
    # Without the truck, the point it hid is seen.
    assert 4 in cam.observe(np.zeros(6), []).point_ids


def test_detected_landmarks_are_near_their_true_projection():
    cam, hd = _camera(pixel_sigma_px=0.0)
    obs = cam.observe(np.zeros(6), [])
    T_cam_map = geo.inverse(geo.pose_to_matrix(np.zeros(6)) @ cam.T_body_cam)
    uv, _ = geo.project_points(cam.intr, T_cam_map, hd.points[0].p_map)
    np.testing.assert_allclose(obs.points_uv[obs.point_ids == 1][0], uv[0], atol=1e-9)
    # The lane mask has the image's size (no lanes on this map: empty).
    assert obs.lane_mask.shape == (720, 1280) and obs.lane_mask.max() == 0


def test_occlusion_slab_test():
    origin = np.array([0.0, 0.0, 1.0])
    targets = np.array([[30.0, 0.0, 1.0], [30.0, 10.0, 1.0], [10.0, 0.0, 1.0], [30.0, 0.0, 5.0]])
    hit = occluded(origin, targets, [TRUCK])
    # Through the truck / beside it / in front of it / over it.
    assert hit.tolist() == [True, False, False, False]


def test_detector_is_occluded_by_the_vehicle_ahead():
    world = World(load_scenario("blindspot-occluded"), seed=1)
    ego_sees, cv_sees = 0, 0
    for k in range(30):
        tick = world.tick(k)
        ego_sees += "1" in tick.debug["cv0"].object_truth_ids
        cv_sees += "1" in tick.debug["cv1"].object_truth_ids
    assert ego_sees == 0 and cv_sees > 20


def test_detector_noise_matches_its_reported_covariance():
    cfg = load_sensor_config().detector.model_copy(
        update={"p_detect_near": 1.0, "p_detect_far": 1.0, "false_alarms_per_frame": 0.0}
    )
    det = ObjectDetector(cfg, (1.5, 0.0, 1.5), np.random.default_rng(5))
    me = ActorState("cv0", ObjectClass.VEHICLE, np.zeros(3), 0.0, np.zeros(3), 0.0, np.array([4.6, 1.9, 1.5]))
    tgt = ActorState(
        "1", ObjectClass.PEDESTRIAN, np.array([25.0, 8.0, 0.0]), 0.0, np.zeros(3), 0.0, np.array([0.6, 0.6, 1.75])
    )
    nees = []
    for _ in range(400):
        p, cov, cls, ids = det.observe(me, [tgt])
        assert ids == ["1"] and cls[0] == ObjectClass.PEDESTRIAN
        e = p[0] - tgt.p_map
        nees.append(e @ np.linalg.solve(cov[0], e))
    assert 2.6 < np.mean(nees) < 3.4  # chi-square with 3 degrees of freedom


def test_gnss_error_is_metres_and_odometry_is_close():
    world = World(load_scenario("paper-urban"), seed=2)
    err, speed_err = [], []
    for k in range(100):
        tick = world.tick(k)
        for vid, f in tick.frames.items():
            err.append(np.linalg.norm(f.gnss.p_map[:2] - tick.states[vid].p_map[:2]))
            speed_err.append(f.odometry.speed - tick.states[vid].speed)
    rmse = float(np.sqrt(np.mean(np.square(err))))
    assert 0.8 < rmse < 5.0
    assert float(np.sqrt(np.mean(np.square(speed_err)))) < 0.5


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (b"name: bad\nconnected:\n  - {lane: 9}\n", "lane 9 does not exist"),
        (b"name: bad\nconnected: [{speed_mps: -1}]\n", "speed_mps"),
        (b"name: [unclosed\n", "not valid YAML"),
        (b"name: bad\nduration_s: .inf\n", "duration_s"),
        (b"name: bad\nsensors: [1, 2]\n", "sensors must be a mapping"),
        (b"name: b\xe9d\n", "not UTF-8"),
        (b"name: bad\nx: " + b"[" * 5000 + b"]" * 5000 + b"\n", "nested too deeply"),
    ],
)
def test_bad_scenario_file_is_a_clear_error(tmp_path, content, match):
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(content)
    with pytest.raises(ConfigError, match=match):
        load_scenario(bad)


def test_unknown_scenario_names_the_presets():
    with pytest.raises(ConfigError, match="unknown scenario"):
        load_scenario("no-such-scenario")


def test_a_world_runs_forward_only():
    """A second run continues where the first stopped; a frame at or before the last one is refused
    clearly (the sensors' error processes cannot run backwards: they used to give NaN GNSS fixes)."""
    world = World(load_scenario("paper-urban"), seed=0)
    first = [tick.k for tick in world.run(0.3)]
    second = [tick for tick in world.run(0.2)]
    assert first == [0, 1, 2] and [tick.k for tick in second] == [3, 4]
    assert all(np.isfinite(f.gnss.p_map).all() for tick in second for f in tick.frames.values())
    with pytest.raises(ValueError, match="frame 4 is not after its last frame 4"):
        world.tick(4)
    assert world.tick(6).k == 6  # a frame left out (dropped) is fine
