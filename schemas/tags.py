"""Field tags: on the wire every field travels under a small integer, not its name.

Like protobuf field numbers or the ASN.1 components of an ETSI CPM, a tag identifies a field in
every message and nested part: a name has the same tag wherever it appears (``objects`` is 10 in
a VehiclePrior and in a RawObservations, ``cov`` is 17 inside ObjectObservations). Tags 0..127
pack as one byte (msgpack positive fixint).

Rules (this table is append-only):

* never reuse or renumber a tag, even of a field that was removed (mark it retired instead);
* a new field gets the next unused tag, at the end of the table;
* every field of every wire model must have a tag (the codec refuses to start otherwise).

The exported JSON Schemas (``schemas/json/``) carry each property's tag as ``x-tag``.
"""

from __future__ import annotations

__all__ = ["NAMES", "TAGS", "check_table"]

TAGS: dict[str, int] = {
    # Envelope (every message)
    "schema_version": 0,
    "fleet": 1,
    "sender": 2,
    "seq": 3,
    "t_meas": 4,
    "t_sent": 5,
    # VehiclePrior
    "pose": 6,
    "pose_cov": 7,
    "v_map": 8,
    "quality": 9,
    "objects": 10,
    # LocalizationQuality
    "mode": 11,
    "n_points": 12,
    "n_poles": 13,
    "n_lane": 14,
    "cost": 15,
    # ObjectObservations
    "p_body_cm": 16,
    "cov": 17,
    "cls": 18,
    # SensorFrame / RawObservations
    "camera": 19,
    "points_uv": 20,
    "points_cls": 21,
    "poles_uv": 22,
    "lane_mask_png": 23,
    "gnss": 24,
    "odometry": 25,
    # CameraInfo
    "fx": 26,
    "fy": 27,
    "cx": 28,
    "cy": 29,
    "width": 30,
    "height": 31,
    "T_body_cam": 32,
    # GnssFix
    "p_map": 33,
    "sigma_h_m": 34,
    "sigma_v_m": 35,
    # Odometry
    "speed": 36,
    "yaw_rate": 37,
    # FusedState
    "vehicle_ids": 38,
    "vehicle_pose": 39,
    "vehicle_pose_cov": 40,
    "object_id": 41,
    "object_cls": 42,
    "object_p_map": 43,
    "object_v_map": 44,
    "object_cov": 45,
    "messages_fused": 46,
    # GroundTruth
    "vehicle_v_map": 47,
    "obstacle_id": 48,
    "obstacle_cls": 49,
    "obstacle_p_map": 50,
    "obstacle_v_map": 51,
    "obstacle_yaw": 52,
    # HealthStatus
    "role": 53,
    "state": 54,
    "uptime_s": 55,
    "msgs_in_per_s": 56,
    "msgs_out_per_s": 57,
    "bytes_in_per_s": 58,
    "bytes_out_per_s": 59,
    "latency_ms_p50": 60,
    "latency_ms_p99": 61,
    "rejects": 62,
    "last_error": 63,
    "figures": 64,
    # EvalMetrics
    "t_wall": 65,
    "window_s": 66,
    "fused_per_s": 67,
    "evaluated": 68,
    "no_truth": 69,
    "vehicle_rmse_m": 70,
    "object_rmse_m": 71,
    "vehicle_rmse_total_m": 72,
    "object_rmse_total_m": 73,
    "objects_fused": 74,
    "objects_matched": 75,
    "obstacles_truth": 76,
    "e2e_latency_ms_p50": 77,
    "e2e_latency_ms_p99": 78,
    "tx_bytes_per_s": 79,
    "tx_msgs_per_s": 80,
    "tx_bytes_per_msg": 81,
    "delivered_fraction": 82,
    # Certificate
    "subject": 83,
    "public_key": 84,
    "valid_from": 85,
    "valid_until": 86,
    "issuer": 87,
    "signature": 88,
    # SecuredMessage
    "payload": 89,
    "certificate": 90,
    "signer_digest": 91,
    "t_gen_us": 92,
    # FusedState (added)
    "flagged": 93,
    # SensorFrame / RawObservations (added)
    "lane_mask_pooled_png": 94,
    # VehiclePrior (added in schema_version 4)
    "pose_filtered": 95,
    "pose_bias_sigma": 96,
    # Envelope (added): the world's clock of a live fleet
    "epoch_wall_ns": 97,
    "time_scale": 98,
    "t_next": 99,
    # VehiclePrior (added, still schema_version 4: optional)
    "protection_level_m": 100,
    "integrity_risk": 101,
    # LocalizationQuality (added, optional)
    "lock": 102,
    # PoseDownlink (a new message): and pose (6) as in VehiclePrior
    "target": 103,
    "pose_info": 104,
    # VehiclePrior (added, optional)
    "downlink": 105,
    # new fields: next tag 106
}


def check_table(tags: dict[str, int]) -> dict[int, str]:
    """Tag -> name, after checking that tags are unique non-negative ints (ValueError otherwise)."""
    names: dict[int, str] = {}
    for name, tag in tags.items():
        if type(tag) is not int or tag < 0:
            raise ValueError(f"tag of {name!r} is {tag!r}, not a non-negative int")
        if tag in names:
            raise ValueError(f"tag {tag} is used by both {names[tag]!r} and {name!r}")
        names[tag] = name
    return names


NAMES: dict[int, str] = check_table(TAGS)
