"""Culling in the simulator: each sensor looks only at the actors within its reach, and its frames are
byte for byte those of a sensor that looks at every actor."""

import json
import math

import cv2
import numpy as np
import pytest

from mapcontainer import geometry as geo
from mapcontainer.hdmap.model import HDMap, PointFeature, PoleFeature
from mapcontainer.sim import World, load_scenario
from mapcontainer.sim.actors import ActorState, LaneFollower, box_corners
from mapcontainer.sim.bench import growth_exponent, spread_scene
from mapcontainer.sim.config import load_sensor_config, scale_scenario
from mapcontainer.sim.scene import ActorBoxes
from mapcontainer.sim.sensors import Camera, ObjectDetector, _draw_lines, _in_view
from schemas import ObjectClass, encode

from .test_sim import BODY_ON, sure_camera_config


@pytest.mark.parametrize(
    ("scenario", "vehicles", "overrides"),
    [("paper-urban", 12, BODY_ON), ("blindspot-occluded", 5, None), ("paper-suburban", 3, None)],
)
def test_culled_frames_equal_the_brute_force(scenario, vehicles, overrides):
    sc = scale_scenario(load_scenario(scenario, overrides), vehicles)
    culled, brute = World(sc, seed=3, cull=True), World(sc, seed=3, cull=False)
    left_out = detections = 0
    for k in range(12):
        a, b = culled.tick(k), brute.tick(k)
        assert encode(a.truth) == encode(b.truth)
        boxes = culled.boxes(a.states)
        for vid in culled.vehicle_ids:
            assert encode(a.frames[vid]) == encode(b.frames[vid]), f"{vid} at frame {k}"
            assert a.debug[vid].object_truth_ids == b.debug[vid].object_truth_ids
            np.testing.assert_array_equal(a.debug[vid].camera.lane_mask, b.debug[vid].camera.lane_mask)
            near = boxes.near(a.states[vid].p_map, sc.sensors.detector.range_m, boxes.index(vid))
            left_out += len(boxes) - 1 - len(near)
        detections += sum(len(a.debug[v].object_truth_ids) for v in culled.vehicle_ids)
    assert left_out > 0, "no actor was ever out of range: the comparison proved nothing about culling"
    assert detections > 0, "no detections at all"


def _actor(aid, x, y, z=0.0, yaw=0.0, size=(4.6, 1.9, 1.5)):
    return ActorState(aid, ObjectClass.VEHICLE, np.array([x, y, z]), yaw, np.zeros(3), 0.0, np.array(size, float))


def _crowd(rng, n: int, half_m: float) -> list[ActorState]:
    """n actors scattered over a square: cars, tall trucks and pedestrians."""
    sizes = np.array([(4.6, 1.9, 1.5), (9.0, 2.5, 3.8), (0.6, 0.6, 1.75)])
    cls = [ObjectClass.VEHICLE, ObjectClass.VEHICLE, ObjectClass.PEDESTRIAN]
    kinds = rng.integers(0, 3, n)
    xy = rng.uniform(-half_m, half_m, (n, 2))
    yaw = rng.uniform(-3, 3, n)
    return [
        ActorState(str(i), cls[k], np.array([*xy[i], 0.0]), yaw[i], np.zeros(3), 0.0, sizes[k])
        for i, k in enumerate(kinds)
    ]


def test_camera_and_detector_in_a_crowd_see_what_they_see_without_culling():
    """A dense crowd (every actor a possible occluder, most of them out of range) among landmarks, most of
    them out of range too: the culled sensors and the brute-force ones, from the same seeds, give the same
    frames."""
    rng = np.random.default_rng(4)
    hd = HDMap(
        name="crowd",
        points=[PointFeature(i, "sign", np.array([*rng.uniform(-150, 150, 2), rng.uniform(1, 6)])) for i in range(300)],
        poles=[  # some lean (a pole of an imported map need not stand upright)
            PoleFeature(1000 + i, "lamp", np.array([x, y, 0.0]), np.array([x + dx, y, 8.0]))
            for i, (x, y, dx) in enumerate(
                zip(*rng.uniform(-150, 150, (2, 80)), rng.choice([0.0, 6.0], 80), strict=True)
            )
        ],
    )
    crowd = _crowd(rng, 400, 150.0)
    culled, brute = ActorBoxes(crowd), ActorBoxes(crowd, index=False)
    sensors = load_sensor_config()
    cams = [
        Camera(sensors.camera, hd, np.random.default_rng(9), np.random.default_rng(8), cull=cull)
        for cull in (True, False)
    ]
    dets = [ObjectDetector(sensors.detector, (1.5, 0.0, 1.5), np.random.default_rng(7)) for _ in range(2)]
    sure = sure_camera_config()
    in_crowd, alone = (Camera(sure, hd, np.random.default_rng(0)) for _ in range(2))
    seen = hidden = 0
    for k in range(60):
        me = int(rng.integers(len(crowd)))
        pose = np.array([*crowd[me].p_map[:2], 0.0, *rng.uniform(-0.08, 0.08, 2), crowd[me].yaw])
        c = crowd[me]
        observer = ActorState(c.id, c.cls, c.p_map, c.yaw, c.v_map, 0.0, c.size, np.array([0.0, *pose[3:5]]))
        a, b = (cam.observe(pose, boxes, skip=me) for cam, boxes in zip(cams, (culled, brute), strict=True))
        for field in ("points_uv", "point_ids", "poles_uv", "pole_ids", "lane_mask"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=f"{field} at {k}")
        da, db = (d.observe(observer, boxes, 0.1 * k, skip=me) for d, boxes in zip(dets, (culled, brute), strict=True))
        for x, y in zip(da, db, strict=True):
            np.testing.assert_array_equal(np.asarray(x, dtype=object), np.asarray(y, dtype=object))
        seen += len(a.point_ids) + len(da[3])
        # What the crowd hides: landmarks a camera that detects all it sees sees only when alone.
        crowded = set(in_crowd.observe(pose, culled, skip=me).point_ids.tolist())
        hidden += len(set(alone.observe(pose, []).point_ids.tolist()) - crowded)
    assert seen > 0 and hidden > 0


def test_a_box_or_pole_centred_beyond_range_still_counts_in_range():
    sure = sure_camera_config()
    x_cam, _, z_cam = sure.mount_xyz_m
    sign = PointFeature(1, "sign", np.array([x_cam + 59.0, 0.0, z_cam]))  # 59 m ahead of the camera
    cam = Camera(sure, HDMap(name="one sign", points=[sign]), np.random.default_rng(0))
    assert 1 in cam.observe(np.zeros(6), []).point_ids
    truck = _actor("7", x_cam + 61.0, 0.0, size=(9.0, 2.5, 3.8))  # its centre out of range, its tail in it
    assert 1 not in cam.observe(np.zeros(6), ActorBoxes([truck])).point_ids
    # A leaning pole: base 70 m away, top 56 m, middle 63 m: its top is in range.
    pole = PoleFeature(2, "lamp", np.array([x_cam + 70.0, 0.0, 0.0]), np.array([x_cam + 56.0, 0.0, 8.0]))
    cam = Camera(sure, HDMap(name="one pole", poles=[pole]), np.random.default_rng(0))
    assert 2 in cam.observe(np.zeros(6), []).pole_ids


def test_near_is_a_superset_of_the_actors_in_range_and_corners_are_box_corners():
    rng = np.random.default_rng(0)
    states = [_actor(str(i), *rng.uniform(-200, 200, 2), yaw=rng.uniform(-3, 3)) for i in range(300)]
    boxes = ActorBoxes(states)
    assert boxes.reach_m == pytest.approx(np.hypot(4.6, 1.9) / 2)
    for _ in range(50):
        c, r = rng.uniform(-200, 200, 2), rng.uniform(0, 80)
        skip = int(rng.integers(300))
        d = np.linalg.norm(boxes.p_map[:, :2] - c, axis=1)
        want = set(np.flatnonzero(d <= r)) - {skip}
        got = boxes.near(c, r, skip)
        assert want <= set(got.tolist()) and skip not in got and np.all(np.diff(got) > 0)
        assert len(got) < 300  # a range query, not everything
    idx = np.array([5, 17, 299])
    np.testing.assert_array_equal(boxes.corners(idx), np.stack([box_corners(states[i]) for i in idx]))
    everything = ActorBoxes(states, index=False).near(np.zeros(2), 1.0, skip=7)
    np.testing.assert_array_equal(everything, np.delete(np.arange(300), 7))


def test_candidate_radius_covers_every_target_in_range_of_a_tilted_body():
    cfg = load_sensor_config().detector
    det = ObjectDetector(cfg, (1.5, 0.0, 1.5), np.random.default_rng(0))
    rng = np.random.default_rng(1)
    targets = [_actor(str(i), *rng.uniform(-90, 90, 2), z=rng.uniform(-3, 3)) for i in range(4000)]
    boxes = ActorBoxes(targets)
    worst = 0.0
    for roll, pitch in rng.uniform(-0.3, 0.3, (40, 2)):
        T_map_body = geo.pose_to_matrix(np.array([0.0, 0.0, 0.5, roll, pitch, rng.uniform(-3, 3)]))
        sensor = geo.transform_points(T_map_body, det.sensor_body)
        radius = det.candidate_radius(T_map_body, sensor, boxes)
        rel = geo.transform_points(geo.inverse(T_map_body), boxes.p_map)[:, :2] - det.sensor_body[:2]
        in_range = np.linalg.norm(rel, axis=1) <= cfg.range_m
        h = np.linalg.norm(boxes.p_map[:, :2] - sensor[:2], axis=1)
        assert np.all(h[in_range] <= radius)
        worst = max(worst, h[in_range].max() / radius)
        assert radius < 1.2 * cfg.range_m  # and it is a bound, not everything
    assert worst > 0.95  # the bound is about tight


def test_lines_beside_the_image_are_left_out_and_grouped_drawing_is_cv2_line():
    rng = np.random.default_rng(2)
    pa = rng.integers(-8000, 12000, (3000, 2)).astype(np.int32)
    pb = (pa + rng.integers(-400, 400, (3000, 2))).astype(np.int32)
    thick = rng.integers(1, 41, 3000)
    one_by_one = np.zeros((720, 1280), np.uint8)
    for p, q, t in zip(pa, pb, thick, strict=True):
        cv2.line(one_by_one, (int(p[0]), int(p[1])), (int(q[0]), int(q[1])), 255, int(t), cv2.LINE_8, 2)
    keep = _in_view(pa, pb, thick, 1280, 720)
    assert 0 < keep.sum() < len(keep) // 2
    culled = np.zeros_like(one_by_one)
    _draw_lines(culled, pa[keep], pb[keep], thick[keep])
    np.testing.assert_array_equal(culled, one_by_one)
    assert one_by_one.any()


def test_a_followers_remembered_arc_is_its_arc():
    line = World(load_scenario("paper-urban"), seed=0).connected[0].line

    def chain():
        cars = [LaneFollower(f"c{i}", line, 10.0 * i, 9.0 + i, 2.0, 7.0, i, (4.6, 1.9, 1.5)) for i in range(4)]
        for behind, ahead in zip(cars, cars[1:], strict=False):
            behind.leader, behind.min_gap_m = ahead, 8.0
        return cars

    ts = np.random.default_rng(3).uniform(0, 30, 40)
    remembering = chain()
    for t in [*ts, *ts[::-1], *ts]:
        fresh = chain()
        assert [c.arc(t) for c in remembering] == [c.arc(t) for c in fresh]


def test_growth_exponent():
    n = np.array([2, 4, 8, 16, 32])
    assert growth_exponent(n, 3.0 * n) == pytest.approx(1.0)
    assert growth_exponent(n, 0.5 * n**2) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="two different sizes"):
        growth_exponent([4, 4], [1.0, 2.0])


def test_bench_world_reports_every_size_and_the_growth(capsys):
    from mapcontainer.cli import main

    assert main(["bench", "world", "--vehicles", "3,1", "--ticks", "2", "--scenario", "overlap"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert [r["vehicles"] for r in result["sizes"]] == [1, 3] and result["cull"] is True
    one, three = result["sizes"]
    assert three["actors"] == one["actors"] + 2  # the vehicles added to the scenario's obstacles
    for row in result["sizes"]:
        assert row["ms_per_vehicle"] == pytest.approx(row["ms_per_tick_p50"] / row["vehicles"], abs=0.01)
        assert row["vehicle_over_yardstick"] == pytest.approx(row["tick_over_yardstick"] / row["vehicles"], abs=1e-3)
        assert row["yardstick_ms_p50"] > 0 and row["bytes_per_vehicle_mean"] > 1000  # a lane mask in every frame
    assert math.isfinite(result["growth_exponent"]) and math.isfinite(result["growth_exponent_paired"])
    with pytest.raises(SystemExit) as exc:
        main(["bench", "world", "--vehicles", "4"])
    assert exc.value.code == 2 and "two or more different sizes" in capsys.readouterr().err


def test_a_spread_scene_keeps_the_scenarios_density():
    sc = load_scenario("paper-urban")
    big = spread_scene(sc, 16)
    assert len(big.connected) == 16 and len(big.obstacle_vehicles) == 4 * len(sc.obstacle_vehicles)
    assert len(big.pedestrians) == 4 * len(sc.pedestrians)
    ring, big_ring = (2 * (s.map.length_m + s.map.width_m) for s in (sc, big))
    assert big_ring == pytest.approx(4 * ring)
    small_world, big_world = World(sc, seed=0), World(big, seed=0)
    assert big_world.true_map.feature_counts()["lamp"] == 4 * small_world.true_map.feature_counts()["lamp"]
    n_actors = [len(w.states(0.0)) for w in (small_world, big_world)]
    assert n_actors[1] == 4 * n_actors[0]
    assert spread_scene(sc, 3) == scale_scenario(sc, 3)  # no larger than the scenario: its own ring
