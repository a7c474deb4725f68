"""Hostile payloads never crash the decoder: it returns a model or a Rejection, never raises.

Maps on the wire are keyed by integer field tag (schemas/tags.py); the generators mostly use real
tags, so that payloads get past the key and version checks into validation.

Whatever the decoder accepts must also survive a re-encode/decode round trip unchanged.
"""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel

from schemas import (
    REASONS,
    SCHEMA_VERSION,
    CameraInfo,
    FusedState,
    GnssFix,
    GroundTruth,
    HealthStatus,
    LocalizationQuality,
    ObjectObservations,
    Odometry,
    RawObservations,
    Rejection,
    SensorFrame,
    VehiclePrior,
    decode,
    encode,
)
from schemas.tags import TAGS

VERSION_TAG = TAGS["schema_version"]

MODELS: tuple[type[BaseModel], ...] = (
    SensorFrame, RawObservations, VehiclePrior, FusedState, GroundTruth, HealthStatus
)
FAST = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])

ENV = dict(fleet="f", sender="veh-1", seq=3, t_meas=1.5, t_sent=1.55)
OBJECTS = ObjectObservations.from_metres(
    [[5.0, 1.0, 0.0], [20.0, -3.0, 0.5]], np.stack([np.eye(3) * 0.1, np.eye(3) * 0.5]), [1, 2]
)
CAMERA = CameraInfo(fx=1000, fy=1000, cx=639.5, cy=359.5, width=1280, height=720, T_body_cam=np.eye(4))

VALID: tuple[BaseModel, ...] = (
    SensorFrame(
        **ENV, camera=CAMERA, points_uv=[[10, 20], [30, 40]], points_cls=[1, 2], poles_uv=[[1, 2, 3, 4]],
        lane_mask_png=b"\x89PNG\r\n\x1a\n", gnss=GnssFix(p_map=[1, 2, 3], sigma_h_m=2, sigma_v_m=3),
        odometry=Odometry(speed=5, yaw_rate=0.1), objects=OBJECTS,
    ),
    RawObservations(**ENV, camera=CAMERA, objects=OBJECTS),
    VehiclePrior(
        **ENV, pose=[1, 2, 0, 0, 0, 1], pose_cov=np.eye(6)[np.triu_indices(6)], v_map=[1, 0, 0],
        quality=LocalizationQuality(mode="map_matching", n_points=2), objects=OBJECTS,
    ),
    FusedState(
        **ENV, vehicle_ids=["a", "b"], vehicle_pose=np.zeros((2, 6)),
        vehicle_pose_cov=np.tile(np.eye(6)[np.triu_indices(6)], (2, 1)), object_id=[7], object_cls=[1],
        object_p_map=[[1, 2, 3]], object_v_map=[[0, 0, 0]], object_cov=[[1, 0, 0, 1, 0, 1]],
    ),
    GroundTruth(
        **ENV, vehicle_ids=["a"], vehicle_pose=np.zeros((1, 6)), vehicle_v_map=np.zeros((1, 3)),
        obstacle_id=[1, 2], obstacle_cls=[1, 2], obstacle_p_map=np.ones((2, 3)),
        obstacle_v_map=np.ones((2, 3)), obstacle_yaw=[0.1, 0.2],
    ),
    HealthStatus(**ENV, role="host", state="ok", uptime_s=2.0, latency_ms_p50=1.0, rejects={"malformed": 1}),
)
VALID_BYTES = tuple((type(m), encode(m)) for m in VALID)

models = st.sampled_from(MODELS)
valid = st.sampled_from(VALID_BYTES)
Encoded = tuple[type[BaseModel], bytes]
byte_edits = st.lists(
    st.tuples(st.integers(min_value=0), st.integers(min_value=0, max_value=255)), min_size=1, max_size=8
)


def assert_decodes_or_rejects(data: Any, model: type[BaseModel]) -> None:
    """decode must not raise; an accepted message must round trip through the codec unchanged."""
    out = decode(data, model)
    if isinstance(out, Rejection):
        assert out.reason in REASONS, out
        assert isinstance(out.detail, str)
        return
    assert isinstance(out, model)
    again = encode(out)
    back = decode(again, model)
    assert isinstance(back, model), back
    assert encode(back) == again


# Values msgpack can carry, nested a few levels.
scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**64 - 1)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=20)
    | st.binary(max_size=64)
)
map_keys = st.integers(min_value=0, max_value=130) | st.text(max_size=10)
values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(map_keys, inner, max_size=5),
    max_leaves=20,
)


def field_tags(model: type[BaseModel]) -> list[int]:
    return sorted(TAGS[name] for name in model.model_fields)


@FAST
@given(model=models, data=st.binary(max_size=512))
def test_arbitrary_bytes_never_raise(model: type[BaseModel], data: bytes) -> None:
    assert_decodes_or_rejects(data, model)


@FAST
@given(model=models, data=st.binary(max_size=256))
def test_arbitrary_bytes_after_a_map_header_never_raise(model: type[BaseModel], data: bytes) -> None:
    assert_decodes_or_rejects(bytes([0x86, VERSION_TAG, SCHEMA_VERSION]) + data, model)


@FAST
@given(msg=valid, cut=st.integers(min_value=0, max_value=4096))
def test_truncated_valid_messages_never_raise(msg: Encoded, cut: int) -> None:
    model, data = msg
    assert_decodes_or_rejects(data[: cut % (len(data) + 1)], model)


@FAST
@given(msg=valid, edits=byte_edits)
def test_mutated_valid_messages_never_raise(msg: Encoded, edits: list[tuple[int, int]]) -> None:
    model, data = msg
    buf = bytearray(data)
    for pos, byte in edits:
        buf[pos % len(buf)] = byte
    assert_decodes_or_rejects(bytes(buf), model)


@FAST
@given(msg=valid, pos=st.integers(min_value=0), junk=st.binary(min_size=1, max_size=16), delete=st.booleans())
def test_inserted_or_deleted_bytes_never_raise(
    msg: Encoded, pos: int, junk: bytes, delete: bool
) -> None:
    model, data = msg
    i = pos % len(data)
    assert_decodes_or_rejects(data[:i] + data[i + len(junk):] if delete else data[:i] + junk + data[i:], model)


@FAST
@given(data=st.data(), model=models)
def test_random_maps_never_raise(data: st.DataObject, model: type[BaseModel]) -> None:
    keys = st.sampled_from(field_tags(model)) | st.integers(min_value=-5, max_value=200) | st.text(max_size=12)
    obj = data.draw(st.dictionaries(keys, values, max_size=12))
    if data.draw(st.booleans()):
        obj[VERSION_TAG] = SCHEMA_VERSION  # get past the version check most of the time
    assert_decodes_or_rejects(msgpack.packb(obj, use_bin_type=True), model)


@FAST
@given(data=st.data(), msg=valid)
def test_valid_map_with_fields_replaced_never_raises(data: st.DataObject, msg: Encoded) -> None:
    model, encoded = msg
    obj = msgpack.unpackb(encoded, raw=False, strict_map_key=False)
    for _ in range(data.draw(st.integers(min_value=1, max_value=3))):
        node = obj
        # Walk into a nested map now and then (camera, objects, gnss, quality, ...).
        nested = [k for k, v in node.items() if isinstance(v, dict) and v]
        if nested and data.draw(st.booleans()):
            node = node[data.draw(st.sampled_from(sorted(nested, key=repr)))]
        key = data.draw(st.sampled_from(sorted(node, key=repr)) | map_keys)
        node[key] = data.draw(values)
    assert_decodes_or_rejects(msgpack.packb(obj, use_bin_type=True), model)


@FAST
@given(data=st.data(), msg=valid)
def test_valid_map_with_arrays_resized_never_raises(data: st.DataObject, msg: Encoded) -> None:
    """Arrays (bin) of random lengths and contents, including NaN/inf bit patterns."""
    model, encoded = msg
    obj = msgpack.unpackb(encoded, raw=False, strict_map_key=False)
    parts = [obj] + [v for v in obj.values() if isinstance(v, dict)]
    node = data.draw(st.sampled_from(parts))
    bins = sorted(k for k, v in node.items() if isinstance(v, bytes))
    if bins:
        node[data.draw(st.sampled_from(bins))] = data.draw(st.binary(max_size=200))
    assert_decodes_or_rejects(msgpack.packb(obj, use_bin_type=True), model)
