"""A recording as a ROS 2 bag with standard messages, for ROS 2 and Autoware tools (``mapc record export --ros2``).

Written with the pure-Python ``rosbags`` library (the ``ros`` extra), in rosbag2's MCAP storage, CDR
serialized, with the message definitions of ROS 2 Humble; ROS 2 itself is not needed. ``vision_msgs`` is
not among rosbags' built-in types, so its messages are registered from their ``.msg`` definitions
(vision_msgs 4, as Humble ships it).

=================================  =================================================  ==========================
topic                              type                                               from
=================================  =================================================  ==========================
``/mapc/fused/vehicles/<vid>``     ``geometry_msgs/msg/PoseWithCovarianceStamped``    the host's fused states
``/mapc/fused/objects``            ``vision_msgs/msg/Detection3DArray``               the host's fused states
``/mapc/truth/vehicles/<vid>``     ``geometry_msgs/msg/PoseStamped``                  the world's ground truth
``/mapc/truth/objects``            ``vision_msgs/msg/Detection3DArray``               the world's ground truth
``/mapc/map``                      ``visualization_msgs/msg/MarkerArray``             the scenario's map, once
=================================  =================================================  ==========================

Frame ``map`` (local ENU, as REP 103). A pose ``[x, y, z, roll, pitch, yaw]`` becomes a position and the
quaternion of ``R = Rz(yaw) Ry(pitch) Rx(roll)``; its 6x6 covariance is over ``x, y, z, roll, pitch, yaw``,
which is the order of ``PoseWithCovariance.covariance`` (rotations about x, y, z: equal to roll, pitch
and yaw to first order at small roll and pitch). A fused object's detection carries its position and
3x3 covariance in ``results[0].pose`` (orientation the identity, its variances 1e9: not estimated), its
class as ``results[0].hypothesis.class_id`` (score 1), its track id as ``id`` and a bounding box of its
class's nominal size. Stamps: the wall time at which the measurement's scenario time happened on the
world's clock (from the recorded attachment), so they agree with the bag's receive times; a message
recorded without the world's clock is stamped with its receive time.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from schemas import FusedState, GroundTruth, ObjectClass, Rejection, decode
from schemas.arrays import cov_from_upper
from schemas.topics import topic

from ..hdmap.errors import require
from .mcapio import RecordingError, read_records, read_scan

__all__ = ["FRAME_ID", "NOMINAL_SIZE_M", "export_ros2", "ros2_typestore"]

FRAME_ID = "map"
UNKNOWN_VARIANCE = 1e9  # what a covariance entry not estimated gets (orientation of a point object)
NOMINAL_SIZE_M = {  # length, width, height of a bounding box, by class (the fused state has no sizes)
    ObjectClass.UNKNOWN: (1.0, 1.0, 1.0),
    ObjectClass.PEDESTRIAN: (0.6, 0.6, 1.7),
    ObjectClass.VEHICLE: (4.5, 1.8, 1.5),
    ObjectClass.CYCLIST: (1.8, 0.6, 1.7),
}

# vision_msgs 4 (ROS 2 Humble), the message definitions as the package ships them (comments left out)
VISION_MSGS = {
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"
    ),
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": (
        "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\nvision_msgs/BoundingBox3D bbox\n"
        "string id\n"
    ),
    "vision_msgs/msg/Detection3DArray": "std_msgs/Header header\nvision_msgs/Detection3D[] detections\n",
}

POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"
POSE = "geometry_msgs/msg/PoseStamped"
DETECTIONS = "vision_msgs/msg/Detection3DArray"
MARKERS = "visualization_msgs/msg/MarkerArray"


def ros2_typestore():
    """rosbags' ROS 2 Humble type store with vision_msgs registered from :data:`VISION_MSGS`."""
    typesys = require("rosbags.typesys", "ROS 2 export")
    store = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in VISION_MSGS.items():
        types.update(typesys.get_types_from_msg(text, name))
    store.register(types)
    return store


def quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    return (
        float(sr * cp * cy - cr * sp * sy),
        float(cr * sp * cy + sr * cp * sy),
        float(cr * cp * sy - sr * sp * cy),
        float(cr * cp * cy + sr * sp * sy),
    )


class _Msgs:
    """Builders of the standard messages from our arrays, on one type store."""

    def __init__(self, store) -> None:
        self.t = store.types

    def header(self, stamp_ns: int):
        t = self.t
        stamp = t["builtin_interfaces/msg/Time"](sec=int(stamp_ns // 10**9), nanosec=int(stamp_ns % 10**9))
        return t["std_msgs/msg/Header"](stamp=stamp, frame_id=FRAME_ID)

    def pose(self, pose6) -> Any:
        t, p = self.t, np.asarray(pose6, dtype=float)
        q = quaternion(*p[3:6])
        return t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
            orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )

    def point_pose(self, p_map) -> Any:
        return self.pose([*np.asarray(p_map, dtype=float)[:3], 0.0, 0.0, 0.0])

    def pose_cov_stamped(self, stamp_ns: int, pose6, cov6) -> Any:
        t = self.t
        pwc = t["geometry_msgs/msg/PoseWithCovariance"](
            pose=self.pose(pose6), covariance=np.asarray(cov6, dtype=np.float64).reshape(36)
        )
        return t[POSE_COV](header=self.header(stamp_ns), pose=pwc)

    def pose_stamped(self, stamp_ns: int, pose6) -> Any:
        return self.t[POSE](header=self.header(stamp_ns), pose=self.pose(pose6))

    def detections(self, stamp_ns: int, ids, classes, p_map, covs3) -> Any:
        t, dets = self.t, []
        for i, (oid, cls, p) in enumerate(zip(ids, classes, p_map, strict=True)):
            cov = np.diag([0.0, 0.0, 0.0, UNKNOWN_VARIANCE, UNKNOWN_VARIANCE, UNKNOWN_VARIANCE])
            if covs3 is not None:
                cov[:3, :3] = covs3[i]
            pose = self.point_pose(p)
            size = NOMINAL_SIZE_M.get(ObjectClass(int(cls)), NOMINAL_SIZE_M[ObjectClass.UNKNOWN])
            hyp = t["vision_msgs/msg/ObjectHypothesisWithPose"](
                hypothesis=t["vision_msgs/msg/ObjectHypothesis"](
                    class_id=ObjectClass(int(cls)).name.lower(), score=1.0
                ),
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov.reshape(36)),
            )
            box = t["vision_msgs/msg/BoundingBox3D"](
                center=pose, size=t["geometry_msgs/msg/Vector3"](x=size[0], y=size[1], z=size[2])
            )
            dets.append(
                t["vision_msgs/msg/Detection3D"](header=self.header(stamp_ns), results=[hyp], bbox=box, id=str(oid))
            )
        return t[DETECTIONS](header=self.header(stamp_ns), detections=dets)

    def map_markers(self, stamp_ns: int, hdmap) -> Any:
        """Lane lines as line strips (solid white, dashed grey), landmarks as sphere lists by class."""
        t, markers = self.t, []

        def color(r, g, b):
            return t["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=1.0)

        def marker(ns: str, mid: int, kind: int, pts, scale: float, rgb) -> Any:
            m = t["visualization_msgs/msg/Marker"]
            return m(
                header=self.header(stamp_ns),
                ns=ns,
                id=mid,
                type=kind,
                action=m.ADD,
                pose=self.pose(np.zeros(6)),
                scale=t["geometry_msgs/msg/Vector3"](x=scale, y=scale, z=scale),
                color=color(*rgb),
                lifetime=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
                frame_locked=False,
                points=[t["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in pts],
                colors=[],
                texture_resource="",
                texture=t["sensor_msgs/msg/CompressedImage"](
                    header=self.header(stamp_ns), format="", data=np.zeros(0, np.uint8)
                ),
                uv_coordinates=[],
                text="",
                mesh_resource="",
                mesh_file=t["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
                mesh_use_embedded_materials=False,
            )

        m = t["visualization_msgs/msg/Marker"]
        for i, ln in enumerate(hdmap.lane_lines):
            rgb = (1.0, 1.0, 1.0) if ln.kind == "solid" else (0.6, 0.6, 0.6)
            markers.append(marker("lane_lines", i, m.LINE_STRIP, ln.points, 0.15, rgb))
        landmarks = [
            ("lamp", [f.base for f in hdmap.poles], (0.2, 0.8, 0.2)),
            ("traffic_light", [f.p_map for f in hdmap.points if f.cls == "traffic_light"], (0.9, 0.1, 0.1)),
            ("sign", [f.p_map for f in hdmap.points if f.cls == "sign"], (0.6, 0.2, 0.8)),
        ]
        for i, (name, pts, rgb) in enumerate(landmarks):
            if pts:
                markers.append(marker(f"landmarks/{name}", i, m.SPHERE_LIST, pts, 0.6, rgb))
        return t[MARKERS](markers=markers)


def export_ros2(recording: str | Path, out: str | Path, hdmap=None) -> dict[str, Any]:
    """Write ``recording`` (an MCAP recording of ours) as a ROS 2 bag in the directory ``out`` (which must
    not exist: rosbag2's layout). ``hdmap``: the map for ``/mapc/map`` (default: the recorded scenario's,
    from its config.json or metadata; None when neither says). Returns what was written: topics, types and
    message counts, and the keys that were not exported (other hosts, messages that do not decode)."""
    rosbag2 = require("rosbags.rosbag2", "ROS 2 export")
    from ..clock import SimClock
    from ..security import fused_signers, unwrap
    from .replay import _verifier, host_setup

    recording, out = Path(recording), Path(out)
    if out.exists():
        raise RecordingError(f"{out} exists; a ROS 2 bag is a new directory (rosbag2 layout)")
    setup = host_setup(recording)
    scenario = read_scan(recording).metadata.get("recording", {}).get("scenario")
    if hdmap is None and scenario:  # the recorder names the world's scenario in the recording's metadata
        from ..sim.config import load_scenario
        from ..sim.maps import world_map

        hdmap = world_map(load_scenario(scenario))
    store = ros2_typestore()
    build = _Msgs(store)
    fused_t, truth_t = topic("fused"), topic("truth")
    counts: Counter[str] = Counter()
    skipped: Counter[str] = Counter()
    types: dict[str, str] = {}
    with rosbag2.Writer(out, version=8, storage_plugin=rosbag2.StoragePlugin.MCAP) as writer:
        conns: dict[str, Any] = {}

        def put(name: str, msgtype: str, msg, ns: int) -> None:
            if name not in conns:
                conns[name] = writer.add_connection(name, msgtype, typestore=store)
                types[name] = msgtype
            writer.write(conns[name], ns, bytes(store.serialize_cdr(msg, msgtype)))
            counts[name] += 1

        clock = SimClock()  # the world's clock from the believed messages, as a service keeps it
        verifier = _verifier(recording)  # a signed fleet's recording: only what its signer signed is exported

        def believed(rec, model, senders):
            inner = unwrap(rec.payload, verifier, rec.log_time_ns * 1e-9, senders)
            return inner if isinstance(inner, Rejection) else decode(inner, model)

        def stamp(msg, rec) -> int:
            """The wall time of ``msg``'s measurement, on the clock of the messages believed so far."""
            clock.update(msg, rec.log_time_ns)
            ns = clock.wall_ns(msg.t_meas)
            return rec.log_time_ns if ns is None else ns

        for rec in read_records(recording):
            where = fused_t.parse(rec.key)
            if where is not None:
                if where["hid"] != setup.host_id:
                    skipped[f"{rec.key} (host {where['hid']}, not {setup.host_id})"] += 1
                    continue
                msg = believed(rec, FusedState, fused_signers(setup.host_id))
                if not msg:
                    skipped[f"{rec.key} ({msg.reason})"] += 1
                    continue
                ns = stamp(msg, rec)
                if "/mapc/map" not in counts and hdmap is not None:
                    put("/mapc/map", MARKERS, build.map_markers(ns, hdmap), rec.log_time_ns)
                for vid, pose, cov in zip(msg.vehicle_ids, msg.vehicle_pose, msg.vehicle_pose_cov, strict=True):
                    put(
                        f"/mapc/fused/vehicles/{vid}",
                        POSE_COV,
                        build.pose_cov_stamped(ns, pose, cov_from_upper(cov)),
                        rec.log_time_ns,
                    )
                covs = [cov_from_upper(c) for c in msg.object_cov]
                det = build.detections(ns, msg.object_id, msg.object_cls, msg.object_p_map, covs)
                put("/mapc/fused/objects", DETECTIONS, det, rec.log_time_ns)
            elif truth_t.parse(rec.key) is not None:
                msg = believed(rec, GroundTruth, "world")
                if not msg:
                    skipped[f"{rec.key} ({msg.reason})"] += 1
                    continue
                ns = stamp(msg, rec)
                for vid, pose in zip(msg.vehicle_ids, msg.vehicle_pose, strict=True):
                    put(f"/mapc/truth/vehicles/{vid}", POSE, build.pose_stamped(ns, pose), rec.log_time_ns)
                det = build.detections(ns, msg.obstacle_id, msg.obstacle_cls, msg.obstacle_p_map, None)
                put("/mapc/truth/objects", DETECTIONS, det, rec.log_time_ns)
    return {
        "bag": str(out),
        "storage": "mcap",
        "host": setup.host_id,
        "topics": [{"topic": k, "type": types[k], "messages": counts[k]} for k in sorted(counts)],
        "messages": sum(counts.values()),
        "skipped": dict(skipped),
    }
