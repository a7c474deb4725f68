"""The simulator: presets, determinism, visibility and occlusion, sensor statistics, bad configs."""

import hashlib

import numpy as np
import pytest

from mapcontainer import geometry as geo
from mapcontainer.config import ConfigError
from mapcontainer.hdmap.model import HDMap, PointFeature, PoleFeature
from mapcontainer.sim import World, list_scenarios, load_scenario
from mapcontainer.sim.actors import ActorState
from mapcontainer.sim.config import load_sensor_config
from mapcontainer.sim.sensors import Camera, ObjectDetector, occluded
from schemas import ObjectClass, encode


def test_presets_load_and_paper_counts():
    assert {"paper-urban", "paper-suburban", "overlap", "blindspot-occluded", "blindspot-beyond"} <= set(
        list_scenarios()
    )
    for name in ("paper-urban", "paper-suburban"):
        world = World(load_scenario(name), seed=0)
        assert len(world.vehicle_ids) == 4
        classes = [a.cls for a in world.obstacles]
        assert classes.count(ObjectClass.PEDESTRIAN) == 8
        assert classes.count(ObjectClass.VEHICLE) == 6
        assert world.hdmap.feature_counts() == {"lamp": 14, "traffic_light": 4, "sign": 4}
    for name in ("overlap", "blindspot-occluded", "blindspot-beyond"):
        world = World(load_scenario(name), seed=0)
        assert len(world.vehicle_ids) == 2 and len(world.obstacles) == 1


def _episode_digest(seed: int, frames: int = 15) -> tuple[str, str]:
    world = World(load_scenario("paper-urban"), seed=seed)
    sensors, truth = hashlib.sha256(), hashlib.sha256()
    for k in range(frames):
        tick = world.tick(k)
        truth.update(encode(tick.truth))
        for vid in world.vehicle_ids:
            sensors.update(encode(tick.frames[vid]))
    return sensors.hexdigest(), truth.hexdigest()


def test_same_seed_gives_identical_bytes_and_noise_depends_on_seed():
    a, b, c = _episode_digest(3), _episode_digest(3), _episode_digest(4)
    assert a == b
    assert a[0] != c[0], "sensor noise must depend on the seed"
    assert a[1] == c[1], "the traffic (ground truth) is the same in every Monte Carlo run"


def _camera(**overrides) -> tuple[Camera, HDMap]:
    cfg = load_sensor_config().camera.model_copy(
        update={
            "p_detect_near": 1.0,
            "p_detect_far": 1.0,
            "clutter_points_per_frame": 0.0,
            "clutter_poles_per_frame": 0.0,
            **overrides,
        }
    )
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
        p, cov, cls, ids = det.observe(me, [tgt], [me, tgt])
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


def test_bad_scenario_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: bad\nconnected:\n  - {lane: 9}\n")
    with pytest.raises(ConfigError, match="lane 9 does not exist"):
        load_scenario(bad)
    bad.write_text("name: bad\nconnected: [{speed_mps: -1}]\n")
    with pytest.raises(ConfigError, match="speed_mps"):
        load_scenario(bad)
    bad.write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_scenario(bad)
    with pytest.raises(ConfigError, match="unknown scenario"):
        load_scenario("no-such-scenario")
