"""Our messages as Foxglove's well-known schemas in JSON, for viewers that know nothing of ours.

Foxglove reads an MCAP channel of message encoding ``json`` whose schema (encoding ``jsonschema``) is
named ``foxglove.SceneUpdate`` or ``foxglove.PosesInFrame`` as its 3D panel's entities and poses; the
schema text here describes the fields we fill (the names are Foxglove's: ``entities[].spheres[].pose
.position.x``, ``size``, ``color.r``, ``lines[].points``, ``texts[].text`` ...). Everything is in the
frame ``map`` (local ENU, metres).

* ``/viz/map``: lane lines (solid white, dashed grey), pole landmarks (lamp posts, yellow segments),
  point landmarks (traffic lights red, signs blue spheres), written once;
* ``/viz/truth`` and ``/viz/truth/vehicles``: true vehicles (green boxes, ids) and obstacles (grey);
* ``/viz/fused/<host>`` and ``/viz/fused/<host>/vehicles``: fused vehicles (orange boxes) with their
  position covariance as an ellipsoid, fused objects as covariance ellipsoids with their track ids.

Rerun's MCAP import converts Foxglove's schemas in Protobuf only, and of them not SceneUpdate; so the
same picture goes out a second time as ``foxglove.PointCloud`` in Protobuf (schema: the message's
FileDescriptorSet, from the ``foxglove-schemas-protobuf`` package), which Rerun shows as coloured 3-D
points and Foxglove as a point cloud: ``/viz/points/map`` (lane lines sampled every metre, landmarks),
``/viz/points/truth``, ``/viz/points/fused/<host>`` (vehicles and objects, no covariances).

Ellipsoids: the eigen-decomposition C = U diag(w) U^T of a 3x3 position covariance gives the axes;
the sphere's ``size`` is the ellipsoid's diameters at ``SIGMAS`` standard deviations (2 sqrt(w) SIGMAS)
and its orientation the rotation U (made proper).
"""

from __future__ import annotations

import json
from collections.abc import Callable

import numpy as np

from schemas.arrays import cov_from_upper as sym_from_upper
from schemas.codec import Rejection, decode
from schemas.models import FusedState, GroundTruth
from schemas.topics import topic

from ..geometry import rpy_to_matrix

__all__ = [
    "POSES_IN_FRAME",
    "SCENE_UPDATE",
    "SIGMAS",
    "fused_scene",
    "map_points",
    "map_scene",
    "point_cloud",
    "point_cloud_schema",
    "truth_scene",
    "visualizer",
]

SIGMAS = 2.0  # ellipsoids drawn at 2 standard deviations
FRAME = "map"

_VEC = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_QUAT = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}
_POSE = {"type": "object", "properties": {"position": _VEC, "orientation": _QUAT}}
_COLOR = {"type": "object", "properties": {k: {"type": "number"} for k in "rgba"}}
_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_SHAPE = {"type": "object", "properties": {"pose": _POSE, "size": _VEC, "color": _COLOR}}
_LINE = {
    "type": "object",
    "properties": {
        "type": {"type": "integer", "description": "0 LINE_STRIP, 1 LINE_LOOP, 2 LINE_LIST"},
        "pose": _POSE,
        "thickness": {"type": "number"},
        "scale_invariant": {"type": "boolean"},
        "points": {"type": "array", "items": _VEC},
        "color": _COLOR,
    },
}
_TEXT = {
    "type": "object",
    "properties": {
        "pose": _POSE,
        "billboard": {"type": "boolean"},
        "font_size": {"type": "number"},
        "scale_invariant": {"type": "boolean"},
        "color": _COLOR,
        "text": {"type": "string"},
    },
}
_ENTITY = {
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "id": {"type": "string"},
        "lifetime": _TIME,
        "frame_locked": {"type": "boolean"},
        "cubes": {"type": "array", "items": _SHAPE},
        "spheres": {"type": "array", "items": _SHAPE},
        "lines": {"type": "array", "items": _LINE},
        "texts": {"type": "array", "items": _TEXT},
    },
}
SCENE_UPDATE = (
    "foxglove.SceneUpdate",
    json.dumps(
        {
            "title": "foxglove.SceneUpdate",
            "description": "An update to the entities displayed in a 3D scene (the fields Map Container fills)",
            "type": "object",
            "properties": {
                "deletions": {"type": "array", "items": {"type": "object"}},
                "entities": {"type": "array", "items": _ENTITY},
            },
        }
    ).encode(),
)
POSES_IN_FRAME = (
    "foxglove.PosesInFrame",
    json.dumps(
        {
            "title": "foxglove.PosesInFrame",
            "description": "An array of timestamped poses in a frame",
            "type": "object",
            "properties": {
                "timestamp": _TIME,
                "frame_id": {"type": "string"},
                "poses": {"type": "array", "items": _POSE},
            },
        }
    ).encode(),
)

WHITE, GREY, YELLOW = (1.0, 1.0, 1.0, 1.0), (0.6, 0.6, 0.6, 1.0), (1.0, 0.85, 0.1, 1.0)
RED, BLUE, GREEN, ORANGE = (0.9, 0.1, 0.1, 1.0), (0.2, 0.4, 1.0, 1.0), (0.1, 0.8, 0.2, 0.6), (1.0, 0.5, 0.0, 0.8)
TRUTH_OBSTACLE, FUSED_OBJECT = (0.7, 0.7, 0.7, 0.5), (1.0, 0.2, 0.8, 0.45)
VEHICLE_SIZE = (4.5, 1.8, 1.5)


def _time(ns: int) -> dict:
    return {"sec": int(ns // 1_000_000_000), "nsec": int(ns % 1_000_000_000)}


def _v(p) -> dict:
    """A Vector3/Point3 to the millimetre (the JSON stays small; nothing here is finer)."""
    return {"x": round(float(p[0]), 3), "y": round(float(p[1]), 3), "z": round(float(p[2]), 3) if len(p) > 2 else 0.0}


def _c(rgba) -> dict:
    return dict(zip("rgba", (round(float(x), 3) for x in rgba), strict=True))


def _quat(R: np.ndarray) -> dict:
    """Unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0] * 4
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
        q[3] = (R[k, j] - R[j, k]) / s
    return dict(zip("xyzw", (round(float(x), 6) for x in q), strict=True))


def _pose(p, R=None) -> dict:
    return {"position": _v(p), "orientation": _quat(np.eye(3) if R is None else R)}


def _vehicle_pose(pose) -> dict:
    pose = np.asarray(pose, dtype=float)
    return _pose(pose[:3] + [0, 0, VEHICLE_SIZE[2] / 2], rpy_to_matrix(pose[3], pose[4], pose[5]))


def ellipsoid(p, C, color) -> dict:
    """A sphere primitive drawing the 3x3 covariance ``C`` around ``p`` at SIGMAS standard deviations."""
    w, U = np.linalg.eigh(0.5 * (np.asarray(C, float) + np.asarray(C, float).T))
    if np.linalg.det(U) < 0:
        U[:, 2] = -U[:, 2]
    d = 2.0 * SIGMAS * np.sqrt(np.maximum(w, 1e-8))
    return {"pose": _pose(p, U), "size": _v(d), "color": _c(color)}


def _entity(ns: int, eid: str, **prims) -> dict:
    return {"timestamp": _time(ns), "frame_id": FRAME, "id": eid, "lifetime": _time(0), "frame_locked": False, **prims}


def _text(p, text: str, color=WHITE) -> dict:
    return {
        "pose": _pose(np.asarray(p, float) + [0, 0, 2.0]),
        "billboard": True,
        "font_size": 14.0,
        "scale_invariant": True,
        "color": _c(color),
        "text": text,
    }


def _dump(obj) -> bytes:
    return json.dumps(obj, separators=(",", ":")).encode()


def map_scene(hdmap, ns: int) -> bytes:
    """The HD map as one SceneUpdate: lane lines, pole and point landmarks."""
    lines = []
    for ln in hdmap.lane_lines:
        lines.append(
            {
                "type": 1 if ln.closed else 0,
                "pose": _pose((0, 0, 0)),
                "thickness": max(float(ln.width_m), 0.1),
                "scale_invariant": False,
                "points": [_v(p) for p in np.asarray(ln.points)],
                "color": _c(WHITE if ln.kind == "solid" else GREY),
            }
        )
    poles = [
        {
            "type": 2,
            "pose": _pose((0, 0, 0)),
            "thickness": 0.3,
            "scale_invariant": False,
            "points": [_v(f.base), _v(f.top)],
            "color": _c(YELLOW),
        }
        for f in hdmap.poles
    ]
    points = [
        {"pose": _pose(f.p_map), "size": _v((0.8, 0.8, 0.8)), "color": _c(RED if f.cls == "traffic_light" else BLUE)}
        for f in hdmap.points
    ]
    entities = [
        _entity(ns, "lane_lines", lines=lines),
        _entity(ns, "landmarks", lines=poles, spheres=points),
    ]
    return _dump({"deletions": [], "entities": entities})


def truth_scene(truth: GroundTruth, ns: int) -> tuple[bytes, bytes]:
    """(SceneUpdate, PosesInFrame) of a GroundTruth: vehicles as boxes with ids, obstacles as spheres."""
    poses = np.asarray(truth.vehicle_pose, float).reshape(-1, 6)
    cubes = [{"pose": _vehicle_pose(p), "size": _v(VEHICLE_SIZE), "color": _c(GREEN)} for p in poses]
    texts = [_text(p[:3], vid, GREEN) for vid, p in zip(truth.vehicle_ids, poses, strict=True)]
    obs = np.asarray(truth.obstacle_p_map, float).reshape(-1, 3)
    spheres = [{"pose": _pose(p + [0, 0, 0.9]), "size": _v((0.8, 0.8, 1.8)), "color": _c(TRUTH_OBSTACLE)} for p in obs]
    scene = {
        "deletions": [],
        "entities": [
            _entity(ns, "truth_vehicles", cubes=cubes, texts=texts),
            _entity(ns, "truth_obstacles", spheres=spheres),
        ],
    }
    pif = {"timestamp": _time(ns), "frame_id": FRAME, "poses": [_vehicle_pose(p) for p in poses]}
    return _dump(scene), _dump(pif)


def fused_scene(fused: FusedState, ns: int) -> tuple[bytes, bytes]:
    """(SceneUpdate, PosesInFrame) of a FusedState: vehicles as boxes with their position covariance
    ellipsoids, objects as covariance ellipsoids with their track ids."""
    poses = np.asarray(fused.vehicle_pose, float).reshape(-1, 6)
    pcov = sym_from_upper(np.asarray(fused.vehicle_pose_cov, float).reshape(-1, 21))
    cubes = [{"pose": _vehicle_pose(p), "size": _v(VEHICLE_SIZE), "color": _c(ORANGE)} for p in poses]
    vell = [ellipsoid(p[:3], C[:3, :3], ORANGE) for p, C in zip(poses, pcov, strict=True)]
    texts = [_text(p[:3], f"{vid} (fused)", ORANGE) for vid, p in zip(fused.vehicle_ids, poses, strict=True)]
    ps = np.asarray(fused.object_p_map, float).reshape(-1, 3)
    oc = sym_from_upper(np.asarray(fused.object_cov, float).reshape(-1, 6))
    oell = [ellipsoid(p, C, FUSED_OBJECT) for p, C in zip(ps, oc, strict=True)]
    otext = [_text(p, f"#{int(i)}", FUSED_OBJECT) for i, p in zip(fused.object_id, ps, strict=True)]
    scene = {
        "deletions": [],
        "entities": [
            _entity(ns, "fused_vehicles", cubes=cubes, spheres=vell, texts=texts),
            _entity(ns, "fused_objects", spheres=oell, texts=otext),
        ],
    }
    pif = {"timestamp": _time(ns), "frame_id": FRAME, "poses": [_vehicle_pose(p) for p in poses]}
    return _dump(scene), _dump(pif)


def _fds(cls) -> bytes:
    """The FileDescriptorSet of a protobuf message class and everything it imports (an MCAP protobuf schema)."""
    from google.protobuf import descriptor_pb2

    out, seen = descriptor_pb2.FileDescriptorSet(), set()

    def add(fd) -> None:
        if fd.name not in seen:
            seen.add(fd.name)
            for dep in fd.dependencies:
                add(dep)
            fd.CopyToProto(out.file.add())

    add(cls.DESCRIPTOR.file)
    return out.SerializeToString()


def point_cloud_schema() -> tuple[str, bytes]:
    """(name, FileDescriptorSet) of ``foxglove.PointCloud``, for a channel of message encoding ``protobuf``."""
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    return PointCloud.DESCRIPTOR.full_name, _fds(PointCloud)


def point_cloud(points, colors, ns: int) -> bytes:
    """A ``foxglove.PointCloud`` (Protobuf) of (N, 3) map-frame points with (N, 4) RGBA colours in [0, 1]:
    x, y, z float32 and red, green, blue, alpha uint8 per point, 16 bytes each."""
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    p = np.asarray(points, dtype="<f4").reshape(-1, 3)
    c = np.clip(np.round(np.asarray(colors, dtype=float).reshape(-1, 4) * 255), 0, 255).astype(np.uint8)
    rec = np.zeros(len(p), dtype=[("xyz", "<f4", 3), ("rgba", "u1", 4)])
    rec["xyz"], rec["rgba"] = p, c
    msg = PointCloud(frame_id=FRAME, point_stride=16, data=rec.tobytes())
    msg.timestamp.FromNanoseconds(int(ns))
    f32, u8 = PackedElementField.FLOAT32, PackedElementField.UINT8
    msg.fields.extend(
        [PackedElementField(name=n, offset=4 * i, type=f32) for i, n in enumerate("xyz")]
        + [PackedElementField(name=n, offset=12 + i, type=u8) for i, n in enumerate(("red", "green", "blue", "alpha"))]
    )
    return msg.SerializeToString()


def map_points(hdmap, ns: int) -> bytes:
    """The HD map as one PointCloud: painted lane lines every metre, pole landmarks every 0.5 m, point landmarks."""
    pts, cols = [], []
    for ln in hdmap.lane_lines:
        s = ln.painted_samples(1.0)
        pts.append(s)
        cols += [WHITE if ln.kind == "solid" else GREY] * len(s)
    for f in hdmap.poles:
        n = max(2, int(np.linalg.norm(np.asarray(f.top) - f.base) / 0.5) + 1)
        pts.append(np.linspace(f.base, f.top, n))
        cols += [YELLOW] * n
    for f in hdmap.points:
        pts.append(np.asarray(f.p_map, float).reshape(1, 3))
        cols.append(RED if f.cls == "traffic_light" else BLUE)
    return point_cloud(np.concatenate(pts) if pts else np.zeros((0, 3)), cols, ns)


def _state_points(vehicles, objects, v_color, o_color, ns: int) -> bytes:
    v = np.asarray(vehicles, float).reshape(-1, 6)[:, :3] + [0, 0, VEHICLE_SIZE[2] / 2]
    o = np.asarray(objects, float).reshape(-1, 3)
    return point_cloud(np.concatenate([v, o]), [v_color] * len(v) + [o_color] * len(o), ns)


def visualizer(verifier=None, refused: dict[str, int] | None = None) -> Callable[[str, bytes, int], list]:
    """The ``viz`` callable of :class:`~.mcapio.RecordingWriter`: truth and fused states to Foxglove
    channels (other keys give nothing; a message that does not decode gives nothing). With ``verifier``
    (the fleet's CA) only truth signed by the world and fused states signed by their host (or standby) are
    drawn; what does not verify is counted by reason in ``refused``."""
    from ..security import fused_signers, unwrap

    truth_t, fused_t = topic("truth"), topic("fused")
    su, pf, pc = SCENE_UPDATE, POSES_IN_FRAME, point_cloud_schema()
    refused = {} if refused is None else refused

    def believed(payload: bytes, ns: int, senders) -> bytes | None:
        inner = unwrap(payload, verifier, ns * 1e-9, senders)
        if isinstance(inner, Rejection):
            refused[inner.reason] = refused.get(inner.reason, 0) + 1
            return None
        return inner

    def viz(key: str, payload: bytes, ns: int) -> list[tuple[str, str, bytes, bytes]]:
        if truth_t.parse(key) is not None:
            inner = believed(payload, ns, "world")
            msg = None if inner is None else decode(inner, GroundTruth)
            if not msg:
                return []
            scene, poses = truth_scene(msg, ns)
            points = _state_points(msg.vehicle_pose, msg.obstacle_p_map, GREEN, TRUTH_OBSTACLE, ns)
            return [
                ("/viz/truth", *su, scene),
                ("/viz/truth/vehicles", *pf, poses),
                ("/viz/points/truth", *pc, points),
            ]
        where = fused_t.parse(key)
        if where is not None:
            inner = believed(payload, ns, fused_signers(where["hid"]))
            msg = None if inner is None else decode(inner, FusedState)
            if not msg:
                return []
            scene, poses = fused_scene(msg, ns)
            hid = where["hid"]
            points = _state_points(msg.vehicle_pose, msg.object_p_map, ORANGE, FUSED_OBJECT, ns)
            return [
                (f"/viz/fused/{hid}", *su, scene),
                (f"/viz/fused/{hid}/vehicles", *pf, poses),
                (f"/viz/points/fused/{hid}", *pc, points),
            ]
        return []

    return viz
