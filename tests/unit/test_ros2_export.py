"""`mapc record export --ros2`: a recording as a ROS 2 bag, read back with rosbags' own reader."""

from __future__ import annotations

import json
from pathlib import Path

import msgpack
import numpy as np
import pytest

pytest.importorskip("rosbags")  # the ros extra; CI installs it (.ci/run)

from rosbags.rosbag2 import Reader  # noqa: E402

from mapcontainer.cli import run  # noqa: E402
from mapcontainer.recording import RecordingWriter  # noqa: E402
from mapcontainer.recording.ros2 import quaternion, ros2_typestore  # noqa: E402
from schemas import FusedState, GroundTruth, encode  # noqa: E402
from schemas.arrays import cov_to_upper  # noqa: E402

EPOCH_NS = 1_700_000_000 * 10**9  # the world's clock, in each message's envelope
SCALE = 0.5
CLOCK = {"epoch_wall_ns": EPOCH_NS, "time_scale": SCALE}  # in every message's envelope, as the fleet sends


def _truth(t: float) -> GroundTruth:
    return GroundTruth(
        fleet="f",
        sender="world",
        seq=int(round(t * 10)),
        t_meas=t,
        t_sent=t,
        **CLOCK,
        vehicle_ids=["cv0", "cv1"],
        vehicle_pose=np.array([[t * 5, 0, 0, 0, 0, 0], [t * 5, 20, 0, 0, 0, 0.5]], np.float32),
        vehicle_v_map=np.array([[5, 0, 0], [5, 0, 0]], np.float32),
        obstacle_id=np.array([7, 8], np.uint32),
        obstacle_cls=np.array([1, 2], np.uint8),
        obstacle_p_map=np.array([[20 + t, 0, 0], [0, 30, 0]], np.float32),
        obstacle_v_map=np.array([[1, 0, 0], [0, 0, 0]], np.float32),
        obstacle_yaw=np.array([0, 0], np.float32),
    )


def _fused(t: float, hid: str = "host") -> FusedState:
    pose_cov = np.diag([0.04, 0.09, 0.01, 1e-4, 1e-4, 4e-4])
    pose_cov[0, 1] = pose_cov[1, 0] = 0.01
    obj_cov = np.array([[0.25, 0.05, 0], [0.05, 0.16, 0], [0, 0, 0.01]])
    return FusedState(
        fleet="f",
        sender=hid,
        seq=int(round(t * 10)),
        t_meas=t,
        t_sent=t,
        **CLOCK,
        vehicle_ids=["cv0", "cv1"],
        vehicle_pose=np.array([[t * 5 + 0.1, 0, 0, 0, 0, 0.05], [t * 5, 20.2, 0, 0, 0, 0.5]], np.float32),
        vehicle_pose_cov=np.stack([cov_to_upper(pose_cov)] * 2).astype(np.float32),
        object_id=np.array([3], np.uint32),
        object_cls=np.array([1], np.uint8),
        object_p_map=np.array([[20.3 + t, 0.2, 0]], np.float32),
        object_v_map=np.array([[1, 0, 0]], np.float32),
        object_cov=np.array([cov_to_upper(obj_cov)], np.float32),
    )


def _recording(path: Path) -> Path:
    att = msgpack.packb({"t_wall_ns": EPOCH_NS}, use_bin_type=True)  # instrumentation only: not the clock
    w = RecordingWriter(path, metadata={"fleet": "f", "scenario": "paper-urban", "seed": "0"})
    for k in range(10):
        t, ns = 0.1 * k, EPOCH_NS + int(0.2e9 * k)
        assert w.add("mc/f/sim/truth", encode(_truth(t)), att, ns)
        assert w.add("mc/f/host/host/fused", encode(_fused(t)), att, ns + 50_000_000)
    assert w.add("mc/f/host/other/fused", encode(_fused(0.5, "other")), att, EPOCH_NS + 10**9)  # another host
    assert w.add("mc/f/host/host/fused", b"\x00broken", att, EPOCH_NS + 10**9)
    w.close()
    return path


def test_a_recording_exported_as_a_ros2_bag_reads_back_with_standard_types(tmp_path, capsys) -> None:
    rec, out = _recording(tmp_path / "r.mcap"), tmp_path / "bag"
    assert run_mapc(["record", "export", "--ros2", str(rec), str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["storage"] == "mcap" and doc["host"] == "host"
    assert sum(doc["skipped"].values()) == 2  # the other host's state, the broken payload
    assert "storage_identifier: mcap" in (out / "metadata.yaml").read_text()
    store = ros2_typestore()
    with Reader(out) as reader:
        assert [p.suffix for p in out.iterdir() if p.name != "metadata.yaml"] == [".mcap"]
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {
            "/mapc/fused/vehicles/cv0": "geometry_msgs/msg/PoseWithCovarianceStamped",
            "/mapc/fused/vehicles/cv1": "geometry_msgs/msg/PoseWithCovarianceStamped",
            "/mapc/fused/objects": "vision_msgs/msg/Detection3DArray",
            "/mapc/truth/vehicles/cv0": "geometry_msgs/msg/PoseStamped",
            "/mapc/truth/vehicles/cv1": "geometry_msgs/msg/PoseStamped",
            "/mapc/truth/objects": "vision_msgs/msg/Detection3DArray",
            "/mapc/map": "visualization_msgs/msg/MarkerArray",
        }
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts == {t: (1 if t == "/mapc/map" else 10) for t in types}
        msgs: dict[str, list] = {}
        for conn, ts, raw in reader.messages():
            msgs.setdefault(conn.topic, []).append((ts, store.deserialize_cdr(raw, conn.msgtype)))

    # a fused vehicle pose: position, the quaternion of its yaw, the 6x6 covariance in ROS's order
    ts, m = msgs["/mapc/fused/vehicles/cv1"][4]
    f = _fused(0.4)
    assert m.header.frame_id == "map"
    stamp = m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
    assert stamp == pytest.approx(EPOCH_NS + 0.4 / SCALE * 1e9, abs=1e3)  # the wall time of t_meas
    assert ts == EPOCH_NS + int(0.2e9 * 4) + 50_000_000  # the bag's time: when it was received
    p = m.pose.pose.position
    assert (p.x, p.y, p.z) == pytest.approx(tuple(f.vehicle_pose[1, :3]), abs=1e-5)
    q = m.pose.pose.orientation
    assert (q.x, q.y, q.z, q.w) == pytest.approx((0, 0, np.sin(0.25), np.cos(0.25)), abs=1e-6)
    cov = np.asarray(m.pose.covariance).reshape(6, 6)
    assert cov[0, 0] == pytest.approx(0.04, rel=1e-3) and cov[0, 1] == pytest.approx(0.01, rel=1e-3)
    assert cov[5, 5] == pytest.approx(4e-4, rel=1e-3) and np.allclose(cov, cov.T)

    # fused objects: position, covariance, class and track id
    _, arr = msgs["/mapc/fused/objects"][2]
    (det,) = arr.detections
    (hyp,) = det.results
    assert det.id == "3" and hyp.hypothesis.class_id == "pedestrian" and hyp.hypothesis.score == 1.0
    pos = hyp.pose.pose.position
    assert (pos.x, pos.y) == pytest.approx((20.5, 0.2), abs=1e-5)
    c = np.asarray(hyp.pose.covariance).reshape(6, 6)
    assert c[0, 0] == pytest.approx(0.25, rel=1e-3) and c[0, 1] == pytest.approx(0.05, rel=1e-3)
    assert c[3, 3] == 1e9  # orientation not estimated
    assert det.bbox.center.position.x == pos.x and det.bbox.size.z > 0

    # the truth on its own topics
    _, tv = msgs["/mapc/truth/vehicles/cv0"][9]
    assert tv.pose.position.x == pytest.approx(4.5, abs=1e-5)
    _, to = msgs["/mapc/truth/objects"][0]
    assert [d.id for d in to.detections] == ["7", "8"]
    assert [d.results[0].hypothesis.class_id for d in to.detections] == ["pedestrian", "vehicle"]

    # the map: paper-urban's lane lines as line strips and its 22 landmarks as sphere lists
    _, markers = msgs["/mapc/map"][0]
    kinds = [(mk.ns.split("/")[0], mk.type) for mk in markers.markers]
    lane = [mk for mk in markers.markers if mk.ns == "lane_lines"]
    assert lane and all(mk.type == mk.LINE_STRIP and len(mk.points) >= 2 for mk in lane)
    marks = {mk.ns: len(mk.points) for mk in markers.markers if mk.ns.startswith("landmarks/")}
    assert marks == {"landmarks/lamp": 14, "landmarks/traffic_light": 4, "landmarks/sign": 4}
    assert ("landmarks", markers.markers[-1].SPHERE_LIST) in kinds


def test_export_refuses_an_existing_directory_and_a_missing_file(tmp_path, capsys) -> None:
    rec = _recording(tmp_path / "r.mcap")
    (tmp_path / "bag").mkdir()
    assert run_mapc(["record", "export", "--ros2", str(rec), str(tmp_path / "bag")]) == 2
    assert "exists; a ROS 2 bag is a new directory" in capsys.readouterr().err
    assert run_mapc(["record", "export", "--ros2", str(tmp_path / "none.mcap"), str(tmp_path / "b2")]) == 2
    assert "no such file" in capsys.readouterr().err


def test_the_quaternion_is_rz_ry_rx() -> None:
    from mapcontainer.geometry import rpy_to_matrix

    roll, pitch, yaw = 0.1, -0.2, 2.5
    x, y, z, w = quaternion(roll, pitch, yaw)
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    assert np.allclose(R, rpy_to_matrix(roll, pitch, yaw), atol=1e-12)


def run_mapc(argv: list[str]) -> int:
    from mapcontainer.cli import build_parser
    from services.cli import add_live_commands

    parser = build_parser()
    add_live_commands(parser)
    return run(parser, argv)
