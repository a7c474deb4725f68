"""Spatial queries of the HD map: range, camera view, lane samples, road height."""

from __future__ import annotations

import numpy as np
import pytest

from mapcontainer.geometry import CameraIntrinsics, camera_extrinsic, pose_to_matrix, project_points
from mapcontainer.hdmap import HDMap, LaneLine, MapIndex, MapSpec, PointFeature, PoleFeature, generate_map
from mapcontainer.hdmap.query import segment_distance, segments_hit_rect

INTR = CameraIntrinsics(fx=1000.0, fy=1000.0, cx=639.5, cy=359.5, width=1280, height=720)
# Camera 1.5 m above the map origin looking along map +x (body at the origin, yaw 0).
T_MAP_CAM = pose_to_matrix([0.0, 0.0, 0.0, 0.0, 0.0, 0.0]) @ camera_extrinsic(0.0, 0.0, 1.5)


def ids(features) -> list[int]:
    return [f.id for f in features]


def view_map() -> HDMap:
    pts = {
        1: [20.0, 0.0, 2.0],  # in front, centre of the image
        2: [-20.0, 0.0, 2.0],  # behind the camera
        3: [200.0, 0.0, 2.0],  # in front but beyond max_range
        4: [20.0, 40.0, 2.0],  # in front, far outside the field of view (63 deg left)
        5: [20.0, -12.5, 1.5],  # in front, ~12 px inside the right image border
        6: [0.05, 0.0, 1.5],  # 5 cm in front of the camera centre: inside the near plane
    }
    poles = {
        11: ([30.0, 3.0, 0.0], [30.0, 3.0, 8.0]),  # an ordinary lamp in view
        12: ([-30.0, 3.0, 0.0], [-30.0, 3.0, 8.0]),  # behind
        13: ([30.0, 40.0, 0.0], [30.0, 40.0, 8.0]),  # far to the left
        14: ([3.0, 0.0, -10.0], [3.0, 0.0, 20.0]),  # both ends outside the image (below / above), crosses it
        15: ([20.0, -30.0, 1.5], [20.0, 30.0, 1.5]),  # horizontal bar, both ends outside left/right
        16: ([-5.0, 1.0, 1.5], [10.0, 1.0, 1.5]),  # starts behind the camera, ends in front: clipped
        17: ([500.0, 0.0, 0.0], [500.0, 0.0, 8.0]),  # beyond range
        18: ([2.0, -10.0, 0.0], [2.0, -10.0, 8.0]),  # beside the car, outside the image
    }
    return HDMap(
        "view",
        points=[PointFeature(i, "sign", np.array(p)) for i, p in pts.items()],
        poles=[PoleFeature(i, "lamp", np.array(a), np.array(b)) for i, (a, b) in poles.items()],
    )


def test_landmarks_in_view_keeps_only_visible_ones() -> None:
    points, poles = MapIndex(view_map()).landmarks_in_view(INTR, T_MAP_CAM, max_range=100.0)
    assert ids(points) == [1, 5]
    assert ids(poles) == [11, 14, 15, 16]


def test_margin_shrinks_the_image() -> None:
    points, _ = MapIndex(view_map()).landmarks_in_view(INTR, T_MAP_CAM, max_range=100.0, margin_px=50.0)
    assert ids(points) == [1]


def test_turning_the_camera_around_swaps_front_and_back() -> None:
    T_back = pose_to_matrix([0.0, 0.0, 0.0, 0.0, 0.0, np.pi]) @ camera_extrinsic(0.0, 0.0, 1.5)
    points, poles = MapIndex(view_map()).landmarks_in_view(INTR, T_back, max_range=100.0)
    assert ids(points) == [2]
    assert 12 in ids(poles) and 11 not in ids(poles)


def test_max_range_limits_the_view() -> None:
    points, poles = MapIndex(view_map()).landmarks_in_view(INTR, T_MAP_CAM, max_range=10.0)
    assert ids(points) == []
    assert ids(poles) == [14, 16]


def brute_force_visible_pole(a, b, T_map_cam, max_range, n=4001) -> bool:
    """Dense samples along the segment: any one in front, in the image and within range."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    pts = a + t * (b - a)
    uv, z = project_points(INTR, np.linalg.inv(T_map_cam), pts)
    near = np.linalg.norm(pts - T_map_cam[:3, 3], axis=1).min() <= max_range
    return bool(near and np.any((z > 0.1) & INTR.in_image(uv)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_view_matches_brute_force_on_a_generated_map(seed: int) -> None:
    hd = generate_map(MapSpec(seed=seed))
    index = MapIndex(hd)
    rng = np.random.default_rng(seed)
    for _ in range(20):
        s = rng.uniform(0.0, hd.centerlines[0].polyline.length)
        line = hd.centerlines[0].polyline
        p, tan = line.point_at(s), line.tangent_at(s)
        yaw = np.arctan2(tan[1], tan[0]) + rng.normal(0.0, 0.3)
        T = pose_to_matrix([p[0], p[1], 0.0, 0.0, 0.0, yaw]) @ camera_extrinsic(1.0, 0.0, 1.5, pitch=0.03)
        points, poles = index.landmarks_in_view(INTR, T, max_range=60.0)

        want_points = []
        for f in hd.points:
            uv, z = project_points(INTR, np.linalg.inv(T), f.p_map)
            in_range = np.linalg.norm(f.p_map - T[:3, 3]) <= 60.0
            if in_range and z[0] > 0.1 and INTR.in_image(uv)[0]:
                want_points.append(f.id)
        want_poles = [f.id for f in hd.poles if brute_force_visible_pole(f.base, f.top, T, 60.0)]
        assert ids(points) == want_points
        assert ids(poles) == want_poles


@pytest.mark.parametrize("radius", [5.0, 20.0, 45.0])
def test_range_query_matches_brute_force(radius: float) -> None:
    hd = generate_map(MapSpec(seed=4))
    index = MapIndex(hd)
    rng = np.random.default_rng(7)
    for p in rng.uniform([-90.0, -50.0, -2.0], [90.0, 50.0, 6.0], size=(40, 3)):
        points, poles = index.landmarks_in_range(p, radius)
        assert ids(points) == [f.id for f in hd.points if np.linalg.norm(f.p_map - p) <= radius]
        want = []
        for f in hd.poles:  # nearest point of the segment, scalar formula
            d = f.top - f.base
            t = min(max(float(np.dot(p - f.base, d) / np.dot(d, d)), 0.0), 1.0)
            if np.linalg.norm(f.base + t * d - p) <= radius:
                want.append(f.id)
        assert ids(poles) == want


def test_pole_range_uses_the_nearest_point_of_the_segment() -> None:
    hd = HDMap("p", poles=[PoleFeature(1, "lamp", np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 10.0]))])
    index = MapIndex(hd)
    assert ids(index.landmarks_in_range([1.0, 0.0, 9.0], 1.5)[1]) == [1]  # near the top, far from the mid
    assert ids(index.landmarks_in_range([1.0, 0.0, 12.0], 1.5)[1]) == []  # beyond the top: distance sqrt(5)


def test_lane_samples_in_range_match_brute_force() -> None:
    hd = generate_map(MapSpec(seed=5))
    index = MapIndex(hd)
    rng = np.random.default_rng(3)
    for spacing in (0.5, 0.25):
        every = np.vstack([line.painted_samples(spacing) for line in hd.lane_lines])
        np.testing.assert_array_equal(index.lane_samples(spacing), every)
        for p in rng.uniform([-90.0, -50.0, 0.0], [90.0, 50.0, 2.0], size=(10, 3)):
            got = index.lane_samples_in_range(p, 12.0, spacing=spacing)
            want = every[np.linalg.norm(every - p, axis=1) <= 12.0]
            assert got.shape == want.shape
            np.testing.assert_array_equal(got[np.lexsort(got.T)], want[np.lexsort(want.T)])


def test_lane_samples_are_cached_per_spacing_and_skip_dash_gaps() -> None:
    line = LaneLine(1, np.array([[0.0, 0.0, 0.0], [90.0, 0.0, 0.0]]), "dashed", dash_m=3.0, gap_m=6.0)
    index = MapIndex(HDMap("l", lane_lines=[line]))
    assert index.lane_samples(0.25) is index.lane_samples(0.25)
    got = index.lane_samples_in_range([4.5, 0.0, 0.0], 4.0, spacing=0.25)
    assert len(got) > 0 and np.all(np.mod(got[:, 0], 9.0) < 3.0)  # nothing painted in 3..6 m
    assert got[:, 0].min() >= 0.5 and got[:, 0].max() <= 8.5
    with pytest.raises(ValueError):
        index.lane_samples(0.0)


def test_nearest_lane_height() -> None:
    # A lane line climbing 10 % along x, and a flat one 50 m away.
    slope = LaneLine(1, np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 10.0]]), "dashed")
    flat = LaneLine(2, np.array([[0.0, 50.0, -1.0], [100.0, 50.0, -1.0]]), "solid")
    index = MapIndex(HDMap("h", lane_lines=[slope, flat]))
    assert index.nearest_lane_height([40.0, 2.0, 7.0]) == pytest.approx(4.0, abs=0.03)  # gaps count too
    assert index.nearest_lane_height([40.0, 48.0, 0.0]) == pytest.approx(-1.0)
    assert MapIndex(generate_map(MapSpec())).nearest_lane_height([0.0, -40.0, 1.5]) == 0.0


def test_empty_map() -> None:
    index = MapIndex(HDMap("empty"))
    assert index.landmarks_in_range([0.0, 0.0, 0.0], 100.0) == ([], [])
    assert index.landmarks_in_view(INTR, T_MAP_CAM, 100.0) == ([], [])
    assert index.lane_samples_in_range([0.0, 0.0, 0.0], 100.0).shape == (0, 3)
    with pytest.raises(ValueError, match="no lane lines"):
        index.nearest_lane_height([0.0, 0.0, 0.0])


def test_bad_arguments_raise() -> None:
    index = MapIndex(view_map())
    with pytest.raises(ValueError):
        index.landmarks_in_range([0.0, 0.0], 5.0)
    with pytest.raises(ValueError):
        index.landmarks_in_range([0.0, 0.0, np.nan], 5.0)
    with pytest.raises(ValueError):
        index.landmarks_in_range([0.0, 0.0, 0.0], -1.0)
    with pytest.raises(ValueError):
        index.landmarks_in_view(INTR, np.eye(3), 10.0)


def test_segment_helpers() -> None:
    a = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    b = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 0.0]])  # the second is degenerate (a point)
    np.testing.assert_allclose(segment_distance([3.0, 4.0, 5.0], a, b), [5.0, np.sqrt(50.0)])
    p0 = np.array([[-5.0, 5.0], [-5.0, 20.0], [5.0, 5.0], [-1.0, -1.0], [5.0, -5.0]])
    p1 = np.array([[15.0, 5.0], [15.0, 20.0], [5.0, 5.0], [-1.0, 20.0], [-5.0, 5.0]])
    # crosses; passes above; a point inside; vertical line left of the box; touches the corner (0, 0)
    assert segments_hit_rect(p0, p1, (0.0, 0.0), (10.0, 10.0)).tolist() == [True, False, True, False, True]
