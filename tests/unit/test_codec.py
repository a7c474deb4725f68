"""The msgpack codec: field tags, round trips for every message, rejections with their reason, evolution rule."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import cv2
import msgpack
import numpy as np
import pytest
from pydantic import BaseModel, ValidationError

from mapcontainer.geometry import camera_extrinsic
from schemas import (
    REASONS,
    SCHEMA_VERSION,
    CameraInfo,
    Certificate,
    EvalMetrics,
    FusedState,
    GnssFix,
    GroundTruth,
    HealthStatus,
    LandmarkClass,
    LocalizationQuality,
    ObjectClass,
    ObjectObservations,
    Odometry,
    PoseDownlink,
    RawObservations,
    Rejection,
    SecuredMessage,
    SensorFrame,
    VehiclePrior,
    decode,
    encode,
)
from schemas.arrays import CovSpec, cov_from_upper, cov_to_upper
from schemas.codec import MAX_MESSAGE_BYTES, peek, tag_map, untag_map
from schemas.models import MAX_LANDMARKS, MAX_MASK_BYTES, body_pose_cov
from schemas.tags import NAMES, TAGS, check_table

README = Path(__file__).resolve().parents[2] / "schemas" / "README.md"

# ------------------------------------------------------------------------------- builders


def spd_upper(rng: np.random.Generator, n: int, count: int, scale: float = 0.1) -> np.ndarray:
    """``count`` random symmetric positive-definite n x n matrices as (count, n(n+1)/2) upper triangles."""
    a = rng.normal(size=(count, n, n)) * scale
    cov = a @ np.swapaxes(a, 1, 2) + np.eye(n) * scale
    return cov_to_upper(cov)


def envelope(sender: str = "veh-1", seq: int = 7) -> dict[str, Any]:
    return dict(fleet="test_fleet", sender=sender, seq=seq, t_meas=12.3, t_sent=12.345)


def camera() -> CameraInfo:
    return CameraInfo(
        fx=1000.0,
        fy=1001.5,
        cx=639.5,
        cy=359.5,
        width=1280,
        height=720,
        T_body_cam=camera_extrinsic(1.2, 0.0, 1.5, pitch=0.05),
    )


def objects(rng: np.random.Generator, n: int = 4) -> ObjectObservations:
    p = rng.uniform(-40.0, 40.0, size=(n, 3))
    return ObjectObservations.from_metres(p, spd_upper(rng, 3, n), rng.integers(0, 4, n))


def lane_png() -> bytes:
    mask = np.zeros((36, 64), np.uint8)
    mask[20:, 10:12] = 255
    ok, buf = cv2.imencode(".png", mask)
    assert ok
    return buf.tobytes()


def observations(model: type, full: bool) -> SensorFrame | RawObservations:
    rng = np.random.default_rng(1)
    if not full:
        return model(**envelope(), camera=camera())
    return model(
        **envelope(),
        camera=camera(),
        points_uv=rng.uniform(0, 720, size=(3, 2)),
        points_cls=[LandmarkClass.TRAFFIC_LIGHT, LandmarkClass.SIGN, LandmarkClass.SIGN],
        poles_uv=rng.uniform(0, 720, size=(2, 4)),
        lane_mask_png=lane_png(),
        gnss=GnssFix(p_map=[10.5, -3.25, 0.4], sigma_h_m=2.0, sigma_v_m=3.5),
        odometry=Odometry(speed=8.3, yaw_rate=-0.02),
        objects=objects(rng),
    )


def vehicle_prior(full: bool) -> VehiclePrior:
    rng = np.random.default_rng(2)
    return VehiclePrior(
        **envelope(),
        pose=[10.0, -20.5, 0.1, 0.01, -0.02, 1.5],
        pose_cov=spd_upper(rng, 6, 1)[0],
        v_map=[5.0, 1.0, 0.0],
        quality=LocalizationQuality(mode="map_matching", n_points=3, n_poles=2, n_lane=140, cost=0.8)
        if full
        else LocalizationQuality(mode="fallback"),
        objects=objects(rng, 5) if full else ObjectObservations(),
    )


def fused_state(full: bool) -> FusedState:
    rng = np.random.default_rng(3)
    if not full:
        return FusedState(**envelope("host-0"))
    v, n = 3, 6
    return FusedState(
        **envelope("host-0"),
        vehicle_ids=["veh-1", "veh-2", "veh-3"],
        vehicle_pose=rng.normal(size=(v, 6)),
        vehicle_pose_cov=spd_upper(rng, 6, v),
        object_id=np.arange(100, 100 + n),
        object_cls=rng.integers(0, 4, n),
        object_p_map=rng.normal(size=(n, 3)) * 30,
        object_v_map=rng.normal(size=(n, 3)),
        object_cov=spd_upper(rng, 3, n),
        messages_fused=40,
    )


def ground_truth(full: bool) -> GroundTruth:
    rng = np.random.default_rng(4)
    if not full:
        return GroundTruth(**envelope("world"))
    v, n = 4, 14
    return GroundTruth(
        **envelope("world"),
        vehicle_ids=[f"veh-{i}" for i in range(v)],
        vehicle_pose=rng.normal(size=(v, 6)),
        vehicle_v_map=rng.normal(size=(v, 3)),
        obstacle_id=np.arange(n),
        obstacle_cls=[ObjectClass.PEDESTRIAN] * 8 + [ObjectClass.VEHICLE] * 6,
        obstacle_p_map=rng.normal(size=(n, 3)) * 50,
        obstacle_v_map=rng.normal(size=(n, 3)),
        obstacle_yaw=rng.uniform(-np.pi, np.pi, n),
    )


def health(full: bool) -> HealthStatus:
    if not full:
        return HealthStatus(**envelope("host-0"), role="host", state="ok", uptime_s=3.0)
    return HealthStatus(
        **envelope("host-0"),
        role="host",
        state="degraded",
        uptime_s=120.5,
        msgs_in_per_s=40.0,
        msgs_out_per_s=10.0,
        bytes_in_per_s=2.1e4,
        bytes_out_per_s=5e3,
        latency_ms_p50=4.5,
        latency_ms_p99=31.0,
        rejects={"non_finite": 2, "malformed": 1},
        last_error="veh-3: schema_version 2",
        figures={"fused_objects": 14.0, "window_s": 1.0},
    )


def eval_metrics(full: bool) -> EvalMetrics:
    if not full:
        return EvalMetrics(**envelope("evaluator"), t_wall=1.7e9, window_s=5.0)
    return EvalMetrics(
        **envelope("evaluator"),
        t_wall=1.7e9,
        window_s=5.0,
        fused_per_s=9.8,
        evaluated=120,
        vehicle_rmse_m=0.12,
        object_rmse_m=0.31,
        e2e_latency_ms_p50=42.0,
        tx_bytes_per_s={"veh-1": 1900.0, "veh-2": 2100.0},
        tx_msgs_per_s={"veh-1": 10.0},
        tx_bytes_per_msg={"veh-1": 190.0},
        delivered_fraction=0.97,
    )


def certificate() -> Certificate:
    return Certificate(
        subject="veh-1",
        public_key=b"\x02" + bytes(range(32)),
        valid_from=1_790_000_000,
        valid_until=1_800_000_000,
        issuer=b"\x11" * 8,
        signature=bytes(range(64)),
    )


def secured_message(full: bool) -> SecuredMessage:
    """A SecuredMessage with its certificate (full) or the digest; the signature is not a real one."""
    signer = {"certificate": certificate()} if full else {"signer_digest": b"\x22" * 8}
    return SecuredMessage(
        payload=encode(vehicle_prior(False)), t_gen_us=1_795_000_000_123_456, signature=bytes(64), **signer
    )


def pose_downlink() -> PoseDownlink:
    """What the others know of cv1: a position, no heading (no information on the angles)."""
    info = np.zeros((6, 6))
    info[:3, :3] = np.linalg.inv(np.array([[0.09, 0.05, 0], [0.05, 0.16, 0], [0, 0, 0.25]]))
    return PoseDownlink(
        fleet="run1", sender="host", seq=7, t_meas=12.3, t_sent=12.41, target="cv1",
        pose=np.array([10.5, -3.25, 0.5, 0.0, 0.01, 1.2], np.float32), pose_info=cov_to_upper(info),
    )  # fmt: skip


CASES = {
    "pose_downlink": pose_downlink,
    "sensor_frame_full": lambda: observations(SensorFrame, True),
    "sensor_frame_min": lambda: observations(SensorFrame, False),
    "raw_observations_full": lambda: observations(RawObservations, True),
    "raw_observations_min": lambda: observations(RawObservations, False),
    "vehicle_prior_full": lambda: vehicle_prior(True),
    "vehicle_prior_min": lambda: vehicle_prior(False),
    "fused_state_full": lambda: fused_state(True),
    "fused_state_min": lambda: fused_state(False),
    "ground_truth_full": lambda: ground_truth(True),
    "ground_truth_min": lambda: ground_truth(False),
    "health_full": lambda: health(True),
    "health_min": lambda: health(False),
    "eval_metrics_full": lambda: eval_metrics(True),
    "eval_metrics_min": lambda: eval_metrics(False),
    "secured_message_full": lambda: secured_message(True),
    "secured_message_digest": lambda: secured_message(False),
}

# Every wire model: the messages and the parts nested in them.
WIRE_MODELS = [
    SensorFrame, RawObservations, VehiclePrior, FusedState, GroundTruth, HealthStatus, EvalMetrics, PoseDownlink,
    CameraInfo, GnssFix, Odometry, ObjectObservations, LocalizationQuality, SecuredMessage, Certificate,
]  # fmt: skip


def assert_same(a: Any, b: Any, where: str = "msg") -> None:
    """Field-by-field equality; arrays must agree in dtype, shape and every value -- but compact
    covariances (CovSpec) only to their quantisation: float16 sigmas, int8/int16 correlations."""
    assert type(a) is type(b), f"{where}: {type(a).__name__} != {type(b).__name__}"
    if isinstance(a, BaseModel):
        for name, info in type(a).model_fields.items():
            if any(isinstance(m, CovSpec) for m in info.metadata):
                assert_cov_close(getattr(a, name), getattr(b, name), f"{where}.{name}")
            else:
                assert_same(getattr(a, name), getattr(b, name), f"{where}.{name}")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, f"{where}: {a.dtype}{a.shape} != {b.dtype}{b.shape}"
        assert np.array_equal(a, b), f"{where}: values differ"
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            assert_same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def assert_cov_close(a: np.ndarray, b: np.ndarray, where: str) -> None:
    """Covariances equal up to the wire's quantisation: per element within 1 % of sigma_i sigma_j."""
    assert a.dtype == b.dtype and a.shape == b.shape, f"{where}: {a.dtype}{a.shape} != {b.dtype}{b.shape}"
    A, B = cov_from_upper(a.reshape(-1, a.shape[-1])), cov_from_upper(b.reshape(-1, b.shape[-1]))
    s = np.sqrt(np.diagonal(A, axis1=1, axis2=2))
    assert np.all(np.abs(A - B) <= 0.01 * s[:, :, None] * s[:, None, :] + 1e-12), f"{where}: values differ"


def tagged(msg: BaseModel) -> dict[int, Any]:
    """The encoded msgpack map as it is on the wire: keyed by integer tag."""
    return msgpack.unpackb(encode(msg), raw=False, strict_map_key=False)


def as_map(msg: BaseModel) -> dict[str, Any]:
    """The encoded msgpack map with tags turned back into names (nested parts too), for reading."""
    return untag_map(type(msg), tagged(msg))


def pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


# ------------------------------------------------------------------------------ field tags


def test_tags_are_unique_small_ints_appended_in_order() -> None:
    assert check_table(TAGS) == NAMES
    assert len(set(TAGS.values())) == len(TAGS)
    # Append-only: the table is dense and in tag order, so a new field can only go at the end.
    assert list(TAGS.values()) == list(range(len(TAGS)))
    assert max(TAGS.values()) <= 127, "past 127 a tag costs 2 bytes (msgpack uint8): fine, but on purpose"
    with pytest.raises(ValueError, match="used by both"):
        check_table({"a": 0, "b": 0})
    with pytest.raises(ValueError, match="non-negative"):
        check_table({"a": -1})


@pytest.mark.parametrize("model", WIRE_MODELS, ids=lambda m: m.__name__)
def test_every_field_of_every_wire_model_has_a_tag(model: type[BaseModel]) -> None:
    missing = [name for name in model.model_fields if name not in TAGS]
    assert not missing, f"{model.__name__}: no tag for {missing}: add them at the end of schemas/tags.py"


def test_every_tag_names_a_field_of_some_wire_model() -> None:
    used = {name for m in WIRE_MODELS for name in m.model_fields}
    assert set(TAGS) == used, f"tags without a field: {sorted(set(TAGS) - used)}"


def test_tags_are_stable() -> None:
    """A few tags pinned: renumbering any tag is a breaking wire change (see schemas/tags.py)."""
    pinned = {"schema_version": 0, "seq": 3, "t_meas": 4, "pose": 6, "pose_cov": 7, "objects": 10, "cov": 17}
    assert {k: TAGS[k] for k in pinned} == pinned
    msg = vehicle_prior(False)
    assert encode(msg)[:3] == bytes([0x80 | 12, 0, SCHEMA_VERSION])  # fixmap of 12 fields, tag 0 = version


@pytest.mark.parametrize("case", sorted(CASES))
def test_wire_map_is_keyed_by_tag_at_every_level(case: str) -> None:
    msg = CASES[case]()

    def check(obj: BaseModel, node: dict) -> None:
        for key, value in node.items():
            assert type(key) is int, f"{type(obj).__name__}: key {key!r}"
            assert NAMES.get(key) in type(obj).model_fields, f"{type(obj).__name__} has no field with tag {key}"
            inner = getattr(obj, NAMES[key])
            if isinstance(inner, BaseModel):
                check(inner, value)

    check(msg, tagged(msg))
    assert b"\xaet_meas" not in encode(msg)  # the name (fixstr of 6) is nowhere on the wire


def test_tag_map_and_untag_map_are_inverse() -> None:
    msg = observations(RawObservations, True)
    fields = msg.model_dump(mode="python", exclude_none=True)
    assert untag_map(RawObservations, tag_map(RawObservations, fields)) == fields
    assert set(tag_map(RawObservations, fields)[TAGS["gnss"]]) == {TAGS["p_map"], TAGS["sigma_h_m"], TAGS["sigma_v_m"]}
    with pytest.raises(KeyError):
        tag_map(RawObservations, {"no_such_field": 1})


def test_peek_reads_the_envelope_by_name() -> None:
    msg = vehicle_prior(True)
    head = peek(encode(msg))
    assert (head["sender"], head["seq"], head["t_meas"]) == (msg.sender, msg.seq, msg.t_meas)
    assert head["schema_version"] == SCHEMA_VERSION
    assert peek(b"\xc1 not msgpack") == {} and peek(pack([1, 2])) == {} and peek("text") == {}  # type: ignore[arg-type]


# ------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("case", sorted(CASES))
def test_round_trip(case: str) -> None:
    msg = CASES[case]()
    data = encode(msg)
    back = decode(data, type(msg))
    assert not isinstance(back, Rejection), back
    assert_same(msg, back)
    assert encode(back) == data


@pytest.mark.parametrize("case", ["sensor_frame_full", "vehicle_prior_full", "fused_state_full"])
def test_arrays_are_little_endian_row_major_bin(case: str) -> None:
    msg = CASES[case]()
    raw = as_map(msg)
    for name in type(msg).model_fields:
        value = getattr(msg, name)
        if isinstance(value, np.ndarray):
            assert isinstance(raw[name], bytes), name
            spec = next((m for m in type(msg).model_fields[name].metadata if isinstance(m, CovSpec)), None)
            if spec is not None:  # compact covariances have their own layout (test_compact_covariance_layout)
                assert len(raw[name]) == spec.row_bytes * max(1, len(value) if value.ndim == 2 else 1), name
                continue
            want = np.ascontiguousarray(value, dtype=value.dtype.newbyteorder("<")).tobytes(order="C")
            assert raw[name] == want, name
    assert "gnss" not in raw or isinstance(raw["gnss"], dict)


def test_none_fields_are_left_out() -> None:
    raw = as_map(observations(SensorFrame, full=False))
    assert "gnss" not in raw and "odometry" not in raw
    raw = as_map(health(full=False))
    assert "latency_ms_p50" not in raw and "last_error" not in raw


def compact(sigma, rho_codes, corr: str = "i1") -> bytes:
    """One compact covariance on the wire: float16 sigmas, then integer correlation codes."""
    return np.asarray(sigma, "<f2").tobytes() + np.asarray(rho_codes, np.dtype(corr).newbyteorder("<")).tobytes()


def test_objects_are_centimetres_int16_and_compact_cov() -> None:
    cov = np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.0], [0.0, 0.0, 0.0025]])
    obs = ObjectObservations.from_metres([[1.234, -5.0, 0.5]], cov[None], [ObjectClass.PEDESTRIAN])
    assert obs.p_body_cm.dtype == np.int16 and obs.p_body_cm.tolist() == [[123, -500, 50]]
    np.testing.assert_allclose(obs.p_body, [[1.23, -5.0, 0.5]])
    raw = as_map(VehiclePrior(**{**vehicle_prior(True).model_dump(), "objects": obs}))["objects"]["cov"]
    # sigma_x sigma_y sigma_z, then rho_xy rho_xz rho_yz in 1/127: 0.01 / (0.2 * 0.3) = 0.1667 -> 21
    assert raw == compact([0.2, 0.3, 0.05], [21, 0, 0])


def test_compact_covariance_layout() -> None:
    msg = vehicle_prior(True)
    raw = as_map(msg)["pose_cov"]
    C = cov_from_upper(msg.pose_cov)
    sigma = np.sqrt(np.diag(C))
    iu = np.triu_indices(6, 1)
    rho = (C / np.outer(sigma, sigma))[iu]
    assert len(raw) == 42
    assert raw == compact(sigma, np.rint(rho * 32767), "<i2")


def test_compact_covariance_stays_positive_definite_after_rounding() -> None:
    """A nearly singular pose covariance (x, y correlated 0.99999) must not round into an indefinite one."""
    C = np.eye(6) * 1e-4
    C[:2, :2] = [[1.0, 0.99999], [0.99999, 1.0]]
    msg = VehiclePrior(**{**vehicle_prior(True).model_dump(), "pose_cov": cov_to_upper(C)})
    back = decode(encode(msg), VehiclePrior)
    assert not isinstance(back, Rejection), back
    assert np.all(np.linalg.eigvalsh(cov_from_upper(back.pose_cov)) > 0)


def test_covariance_upper_triangle_order() -> None:
    cov = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 5.0], [3.0, 5.0, 6.0]])
    assert cov_to_upper(cov).tolist() == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]  # xx xy xz yy yz zz
    assert np.array_equal(cov_from_upper(cov_to_upper(cov)), cov)


# ------------------------------------------------------------------------------ rejections


def assert_rejected(data: Any, model: type[BaseModel], reason: str) -> Rejection:
    out = decode(data, model)
    assert isinstance(out, Rejection), f"expected a rejection ({reason}), decoded {type(out).__name__}"
    assert out.reason in REASONS
    assert out.reason == reason, out
    assert not out
    return out


def with_changes(msg: BaseModel, *path_and_value: tuple[tuple[str, ...], Any]) -> bytes:
    """Encoded ``msg`` with the msgpack map changed at the given field-name paths (value ``...`` deletes),
    re-keyed by tag."""
    raw = as_map(msg)
    for path, value in path_and_value:
        node = raw
        for key in path[:-1]:
            node = node[key]
        if value is ...:
            del node[path[-1]]
        else:
            node[path[-1]] = value
    return pack(tag_map(type(msg), raw))


@pytest.mark.parametrize("case", sorted(CASES))
def test_truncated_bytes_are_malformed(case: str) -> None:
    msg = CASES[case]()
    data = encode(msg)
    for cut in (0, 1, len(data) // 3, len(data) // 2, len(data) - 1):
        assert_rejected(data[:cut], type(msg), "malformed")


MODELS = [SensorFrame, RawObservations, VehiclePrior, FusedState, GroundTruth, HealthStatus]


@pytest.mark.parametrize("model", MODELS)
def test_random_bytes_are_malformed(model: type[BaseModel]) -> None:
    rng = np.random.default_rng(5)
    for _ in range(50):
        assert_rejected(rng.bytes(int(rng.integers(1, 200))), model, "malformed")


DEEP = b"\x91" * 1000 + b"\xc0"  # a list nested 1,000 deep


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"\x81\x00" + DEEP, "schema_version"),  # as schema_version: its repr raised RecursionError
        (b"\x81" + DEEP + b"\x01", "malformed"),  # as a map key
        (b"\x82\x00" + msgpack.packb(SCHEMA_VERSION) + msgpack.packb(TAGS["sender"]) + DEEP, "invalid"),
    ],
    ids=["version", "key", "field"],
)
def test_deeply_nested_values_are_refused_not_raised(model: type[BaseModel], payload: bytes, reason: str) -> None:
    out = assert_rejected(payload, model, reason)
    assert len(out.detail) <= 200
    assert isinstance(peek(payload), dict)


@pytest.mark.parametrize("top", [[1, 2, 3], 5, "fused", b"\x00", None, 1.5])
def test_non_map_top_level_is_malformed(top: Any) -> None:
    assert_rejected(pack(top), FusedState, "malformed")


@pytest.mark.parametrize("case", ["vehicle_prior_full", "raw_observations_full", "fused_state_full"])
@pytest.mark.parametrize("version", [2, SCHEMA_VERSION])
def test_payload_keyed_by_names_is_rejected(case: str, version: int) -> None:
    """A schema_version 2 writer keyed its maps by field name: rejected, with a detail that says so."""
    msg = CASES[case]()
    old = msg.model_dump(mode="python", exclude_none=True) | {"schema_version": version}
    out = assert_rejected(pack(old), type(msg), "malformed")
    assert "field name" in out.detail and "tag" in out.detail, out.detail


def test_not_bytes_is_malformed() -> None:
    assert_rejected("not bytes", FusedState, "malformed")  # type: ignore[arg-type]


@pytest.mark.parametrize("key", ["fleet", "future", b"\x01", 1.5, None])
def test_map_with_non_int_keys_is_malformed(key: Any) -> None:
    raw = tagged(fused_state(True))
    raw[key] = 1
    out = assert_rejected(pack(raw), FusedState, "malformed")
    assert "integer" in out.detail
    raw = tagged(vehicle_prior(True))
    raw[TAGS["quality"]][key] = 1  # in a nested part too
    out = assert_rejected(pack(raw), VehiclePrior, "malformed")
    assert "quality" in out.detail and "integer" in out.detail


def test_bool_map_key_is_malformed() -> None:  # msgpack true is not the tag 1, though True == 1 in Python
    assert_rejected(pack({0: SCHEMA_VERSION, True: "f"}), FusedState, "malformed")


@pytest.mark.parametrize("version", [0, 1, SCHEMA_VERSION + 1, -1, "2", 2.0, True, None, [2], ...])
def test_wrong_or_missing_schema_version(version: Any) -> None:
    assert_rejected(with_changes(fused_state(True), (("schema_version",), version)), FusedState, "schema_version")


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_float_field(bad: float) -> None:
    assert_rejected(with_changes(vehicle_prior(True), (("t_meas",), bad)), VehiclePrior, "non_finite")
    frame = observations(SensorFrame, True)
    assert_rejected(with_changes(frame, (("gnss", "sigma_h_m"), bad)), SensorFrame, "non_finite")
    assert_rejected(with_changes(health(True), (("figures", "fused_objects"), bad)), HealthStatus, "non_finite")


@pytest.mark.parametrize(
    ("path", "value"),
    [
        (("t_meas",), "1.5"),  # a number as text
        (("t_meas",), True),
        (("seq",), 7.0),
        (("seq",), "7"),
        (("seq",), False),
    ],
)
def test_a_scalar_of_the_wrong_type_is_invalid_not_converted(path: tuple[str, ...], value: Any) -> None:
    assert_rejected(with_changes(vehicle_prior(True), (path, value)), VehiclePrior, "invalid")


def test_physically_impossible_values_are_invalid() -> None:
    """Finite but impossible: one prior with v_map = 1e6 m/s put the fused picture kilometres off, and
    odometry of -1e308 m/s overflowed the host-side localizer."""
    prior = vehicle_prior(True)
    for name, bad in [
        ("v_map", [1e6, 0, 0]),
        ("pose", [1.0, 2e6, 0.0, 0.0, 0.0, 0.0]),
        ("pose", [1.0, 2.0, 0.0, 0.0, 0.0, 1e30]),
    ]:
        out = assert_rejected(with_changes(prior, ((name,), np.array(bad, "<f4").tobytes())), VehiclePrior, "invalid")
        assert "physical limit" in out.detail
    assert_rejected(with_changes(prior, (("t_meas",), 1e306)), VehiclePrior, "invalid")
    frame = observations(SensorFrame, True)
    assert_rejected(with_changes(frame, (("odometry", "speed"), -1e308)), SensorFrame, "invalid")
    assert_rejected(with_changes(frame, (("odometry", "yaw_rate"), 50.0)), SensorFrame, "invalid")
    far = np.array([3e6, 0, 0], "<f4").tobytes()
    assert_rejected(with_changes(frame, (("gnss", "p_map"), far)), SensorFrame, "invalid")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_array(bad: float) -> None:
    pose = np.array([1, 2, 3, 0, 0, bad], "<f4").tobytes()
    assert_rejected(with_changes(vehicle_prior(True), (("pose",), pose)), VehiclePrior, "non_finite")
    msg = fused_state(True)
    p = msg.object_p_map.copy()
    p[2, 1] = bad
    assert_rejected(with_changes(msg, (("object_p_map",), p.astype("<f4").tobytes())), FusedState, "non_finite")
    assert_rejected(
        with_changes(observations(SensorFrame, True), (("objects", "cov"), compact([0.1, bad, 0.1], [0, 0, 0]))),
        SensorFrame,
        "non_finite",
    )


def test_non_positive_definite_covariances() -> None:
    npd = "not_positive_definite"
    bad6 = compact([1.0, 1.0, 1.0, 1.0, 1.0, -0.1], np.zeros(15), "<i2")  # a negative standard deviation
    assert_rejected(with_changes(vehicle_prior(True), (("pose_cov",), bad6)), VehiclePrior, npd)
    singular = compact(np.ones(6), np.full(15, 32767), "<i2")  # every correlation 1
    assert_rejected(with_changes(vehicle_prior(True), (("pose_cov",), singular)), VehiclePrior, npd)

    msg = vehicle_prior(True)
    n = len(msg.objects)
    covs = [compact([1.0, 1.0, 1.0], [0, 0, 0])] * n
    covs[1] = compact([1.0, 1.0, 1.0], [-120, -120, -120])  # rho = -0.94 all round: eigenvalue < 0
    assert_rejected(with_changes(msg, (("objects", "cov"), b"".join(covs))), VehiclePrior, npd)
    covs[1] = compact([1.0, 1.0, 1.0], [-128, 0, 0])  # the unused code
    assert_rejected(with_changes(msg, (("objects", "cov"), b"".join(covs))), VehiclePrior, "invalid")

    msg = fused_state(True)
    cov = msg.object_cov.copy()
    cov[0] = -cov[0]
    assert_rejected(with_changes(msg, (("object_cov",), cov.tobytes())), FusedState, npd)


def test_mismatched_array_lengths() -> None:
    msg = vehicle_prior(True)
    assert_rejected(with_changes(msg, (("objects", "cls"), msg.objects.cls[:-1].tobytes())), VehiclePrior, "invalid")
    msg = fused_state(True)
    assert_rejected(with_changes(msg, (("object_v_map",), msg.object_v_map[:-1].tobytes())), FusedState, "invalid")
    assert_rejected(with_changes(msg, (("vehicle_ids",), ["veh-1"])), FusedState, "invalid")
    msg = observations(SensorFrame, True)
    assert_rejected(with_changes(msg, (("points_cls",), b"\x01")), SensorFrame, "invalid")
    msg = ground_truth(True)
    assert_rejected(with_changes(msg, (("obstacle_yaw",), msg.obstacle_yaw[:3].tobytes())), GroundTruth, "invalid")


def test_wrong_bin_length() -> None:
    msg = vehicle_prior(True)
    assert_rejected(with_changes(msg, (("pose",), np.zeros(5, "<f4").tobytes())), VehiclePrior, "invalid")  # 5 of 6
    assert_rejected(with_changes(msg, (("pose",), b"\x00" * 7)), VehiclePrior, "invalid")  # not whole float32s
    assert_rejected(with_changes(msg, (("objects", "p_body_cm"), b"\x00" * 10)), VehiclePrior, "invalid")  # 5 int16s
    assert_rejected(with_changes(fused_state(True), (("vehicle_pose_cov",), b"")), FusedState, "invalid")


def test_out_of_range_int16_positions() -> None:
    msg = vehicle_prior(True)
    n = len(msg.objects)
    too_far = [[40000, 0, 0]] + [[0, 0, 0]] * (n - 1)  # 400 m does not fit int16 centimetres
    assert_rejected(with_changes(msg, (("objects", "p_body_cm"), too_far)), VehiclePrior, "invalid")
    with pytest.raises(ValidationError):
        ObjectObservations.from_metres([[400.0, 0.0, 0.0]], np.eye(3)[None], [1])


def test_missing_required_and_wrong_types() -> None:
    assert_rejected(with_changes(vehicle_prior(True), (("pose",), ...)), VehiclePrior, "invalid")
    assert_rejected(with_changes(vehicle_prior(True), (("quality",), "good")), VehiclePrior, "invalid")
    assert_rejected(with_changes(vehicle_prior(True), (("sender",), "veh/1")), VehiclePrior, "invalid")
    assert_rejected(with_changes(vehicle_prior(True), (("seq",), -1)), VehiclePrior, "invalid")
    assert_rejected(with_changes(health(True), (("state",), "sleepy")), HealthStatus, "invalid")
    frame = observations(SensorFrame, True)
    assert_rejected(with_changes(frame, (("lane_mask_png",), b"GIF89a")), SensorFrame, "invalid")


def test_oversize_payloads() -> None:
    assert_rejected(b"\x80" + b"\x00" * MAX_MESSAGE_BYTES, FusedState, "too_large")
    msg = observations(SensorFrame, True)
    big_png = b"\x89PNG\r\n\x1a\n" + b"\x00" * MAX_MASK_BYTES
    assert_rejected(with_changes(msg, (("lane_mask_png",), big_png)), SensorFrame, "invalid")
    many = MAX_LANDMARKS + 1
    assert_rejected(
        with_changes(
            msg,
            (("points_uv",), np.zeros((many, 2), "<f4").tobytes()),
            (("points_cls",), np.ones(many, "u1").tobytes()),
        ),
        SensorFrame,
        "invalid",
    )


# ------------------------------------------------------------------------------- evolution


@pytest.mark.parametrize("case", sorted(CASES))
def test_reader_ignores_unknown_tags(case: str) -> None:
    """Evolution rule: a newer writer adds optional fields under new tags; this reader ignores them."""
    msg = CASES[case]()
    raw = tagged(msg)
    future = max(NAMES) + 1
    raw[future] = {"nested": [1, 2, 3], 5: b"\x00\x01"}  # whatever a future field holds, keys included
    raw[future + 1] = np.arange(4, dtype="<f4").tobytes()
    raw[1000] = "a tag beyond one byte"
    if TAGS["objects"] in raw:
        raw[TAGS["objects"]][future + 2] = b"\x00" * 6
    back = decode(pack(raw), type(msg))
    assert not isinstance(back, Rejection), back
    assert_same(msg, back)
    assert encode(back) == encode(msg)


def test_reader_fills_defaults_of_optional_fields_an_older_writer_omits() -> None:
    msg = vehicle_prior(True)
    old = with_changes(msg, (("quality", "n_lane"), ...), (("quality", "cost"), ...), (("objects",), ...))
    back = decode(old, VehiclePrior)
    assert isinstance(back, VehiclePrior), back
    assert back.quality.n_lane == 0 and back.quality.cost == 0.0 and len(back.objects) == 0
    assert_same(back.pose, msg.pose)


# ------------------------------------------------------------------- README decoding recipe

# Copied verbatim from schemas/README.md ("Decoding without our code"); the test below checks
# that the README still contains exactly this code and that it decodes our encoder's bytes.
RECIPE = """
import msgpack
import numpy as np


# FusedState's fields by tag (the tag table above, schemas/tags.py)
FUSED_STATE = {
    0: "schema_version", 1: "fleet", 2: "sender", 3: "seq", 4: "t_meas", 5: "t_sent",
    38: "vehicle_ids", 39: "vehicle_pose", 40: "vehicle_pose_cov", 41: "object_id", 42: "object_cls",
    43: "object_p_map", 44: "object_v_map", 45: "object_cov", 46: "messages_fused", 93: "flagged",
    97: "epoch_wall_ns", 98: "time_scale", 99: "t_next",
}


def decode_fused_state(data: bytes) -> dict:
    raw = msgpack.unpackb(data, raw=False, strict_map_key=False)  # a map keyed by integer tag
    msg = {FUSED_STATE[k]: v for k, v in raw.items() if k in FUSED_STATE}  # unknown tags: ignore
    if msg.get("schema_version") not in (3, 4):  # 4 only added fields to VehiclePrior
        raise ValueError(f"unsupported schema_version {msg.get('schema_version')!r}")

    def arr(name, dtype, cols=None):  # msgpack bin -> little-endian, row-major array
        a = np.frombuffer(msg.get(name, b""), dtype=np.dtype(dtype).newbyteorder("<"))
        return a if cols is None else a.reshape(-1, cols)

    def full_cov(upper, n):  # row-major upper triangle -> symmetric (N, n, n)
        iu = np.triu_indices(n)
        cov = np.zeros((len(upper), n, n))
        cov[:, iu[0], iu[1]] = upper
        cov[:, iu[1], iu[0]] = upper
        return cov

    return {
        "t_meas": msg["t_meas"],
        "vehicle_ids": msg.get("vehicle_ids", []),
        "vehicle_pose": arr("vehicle_pose", "f4", 6),  # x, y, z (m), roll, pitch, yaw (rad)
        "vehicle_pose_cov": full_cov(arr("vehicle_pose_cov", "f4", 21), 6),
        "object_id": arr("object_id", "u4"),
        "object_cls": arr("object_cls", "u1"),  # ObjectClass codes
        "object_p_map": arr("object_p_map", "f4", 3),  # m, map frame (ENU)
        "object_v_map": arr("object_v_map", "f4", 3),  # m/s, map frame
        "object_cov": full_cov(arr("object_cov", "f4", 6), 3),  # m^2
    }
"""


def test_readme_recipe_tags_match_the_table() -> None:
    namespace: dict[str, Any] = {}
    exec(RECIPE, namespace)  # noqa: S102 - the README's own code
    table = namespace["FUSED_STATE"]
    assert sorted(table.values()) == sorted(FusedState.model_fields)
    assert all(TAGS[name] == tag for tag, name in table.items())


def test_readme_tag_table_is_the_table() -> None:
    text = README.read_text(encoding="utf-8")
    for name, tag in TAGS.items():
        assert f"{tag} `{name}`" in text, f"schemas/README.md lacks tag {tag} of {name}"
    assert f"({len(TAGS)} next)" in text


def test_readme_recipe_is_in_the_readme() -> None:
    text = README.read_text(encoding="utf-8")
    assert RECIPE.strip() in text, "schemas/README.md and the RECIPE copy in this test differ"


@pytest.mark.parametrize("full", [True, False])
def test_readme_recipe_decodes_our_fused_state(full: bool) -> None:
    namespace: dict[str, Any] = {}
    exec(RECIPE, namespace)  # noqa: S102 - the README's own code, run as a reader would
    msg = fused_state(full)
    out = namespace["decode_fused_state"](encode(msg))
    assert out["t_meas"] == msg.t_meas
    assert out["vehicle_ids"] == msg.vehicle_ids
    for name in ("vehicle_pose", "object_id", "object_cls", "object_p_map", "object_v_map"):
        assert np.array_equal(out[name], getattr(msg, name)), name
        assert out[name].shape == getattr(msg, name).shape, name
    assert np.array_equal(out["vehicle_pose_cov"], cov_from_upper(msg.vehicle_pose_cov))
    assert np.array_equal(out["object_cov"], cov_from_upper(msg.object_cov))
    if full:
        assert np.all(np.linalg.eigvalsh(out["object_cov"]) > 0)


def test_readme_compact_cov_recipe_decodes_our_prior() -> None:
    text = README.read_text(encoding="utf-8")
    code = next(b.split("```")[0] for b in text.split("```python")[1:] if "def compact_cov" in b)
    namespace: dict = {"np": np}
    exec(code, namespace)  # noqa: S102 - the README's own code, run as a reader would
    msg = vehicle_prior(True)
    raw, back = as_map(msg), decode(encode(msg), VehiclePrior)
    pose = namespace["compact_cov"](raw["pose_cov"], 6, "<i2")
    objects = namespace["compact_cov"](raw["objects"]["cov"], 3, "i1")
    np.testing.assert_allclose(pose[0], cov_from_upper(back.pose_cov), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(objects, cov_from_upper(back.objects.cov), rtol=1e-6, atol=1e-12)


# ------------------------------------------------------------------------------ schema_version 4


def test_a_version_3_vehicle_prior_still_decodes_as_per_frame_evidence() -> None:
    raw = tagged(vehicle_prior(True))
    raw[TAGS["schema_version"]] = 3
    for name in ("pose_filtered", "pose_bias_sigma"):  # what a version 3 writer never wrote
        raw.pop(TAGS[name], None)
    out = decode(pack(raw), VehiclePrior)
    assert isinstance(out, VehiclePrior), out
    assert out.schema_version == 3 and out.pose_filtered is False and out.pose_bias_sigma is None
    np.testing.assert_array_equal(body_pose_cov(out), cov_from_upper(np.asarray(out.pose_cov, float)))


def test_a_filtered_prior_with_its_bias_round_trips_and_adds_the_bias_in_the_body_frame() -> None:
    sigma = np.array([0.1, 0.05, 0.04, 0.0035, 0.0065, 0.0045])
    msg = vehicle_prior(True).model_copy(update={"pose_filtered": True, "pose_bias_sigma": sigma.astype(np.float16)})
    out = decode(encode(msg), VehiclePrior)
    assert isinstance(out, VehiclePrior) and out.pose_filtered and out.schema_version == SCHEMA_VERSION == 4
    np.testing.assert_allclose(out.pose_bias_sigma, sigma, rtol=1e-3)
    extra = body_pose_cov(out) - cov_from_upper(np.asarray(out.pose_cov, float))
    yaw = float(out.pose[5])  # 1.5 rad: "along" is mostly +y in the map
    along = np.array([np.cos(yaw), np.sin(yaw)])
    assert along @ extra[:2, :2] @ along == pytest.approx(float(out.pose_bias_sigma[0]) ** 2, rel=1e-6)
    np.testing.assert_allclose(np.diag(extra)[2:], np.asarray(out.pose_bias_sigma[2:], float) ** 2, rtol=1e-6)


@pytest.mark.parametrize("bad", [[-0.1, 0, 0, 0, 0, 0], [0.1, 0.1, 0.1, 0.1, 0.1]])
def test_a_negative_or_short_bias_sigma_is_invalid(bad: list) -> None:
    raw = tagged(vehicle_prior(True))
    raw[TAGS["pose_bias_sigma"]] = np.asarray(bad, np.float16).tobytes()
    assert_rejected(pack(raw), VehiclePrior, "invalid")
