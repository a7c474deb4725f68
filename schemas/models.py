"""The wire contract: every message Map Container puts on the bus or the V2X link.

All values are SI (metres, seconds, radians, m/s, rad/s) unless a field's name says otherwise.
Frames: ``*_map`` local ENU of the HD map, ``*_body`` vehicle body (x forward, y left, z up).
A pose is ``[x, y, z, roll, pitch, yaw]`` of the body in the map frame with
R_map_body = Rz(yaw) Ry(pitch) Rx(roll); pose covariances are over those six numbers in that order.
Covariances travel as the row-major upper triangle of the symmetric matrix (21 values for 6x6,
6 values for 3x3: xx, xy, xz, yy, yz, zz).

On the wire (schemas.codec) every field travels under its integer tag from schemas/tags.py, not
its name: a new field needs a new tag there.

Evolution rule: add optional fields only (with a default), never change a field's meaning or
units; readers ignore fields (tags) they do not know. A breaking change bumps SCHEMA_VERSION.
"""

from __future__ import annotations

from enum import IntEnum
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from .arrays import F16, F32, I16, U8, U32, Cov, cov_from_upper, cov_to_upper

__all__ = [
    "READABLE_VERSIONS",
    "SCHEMA_VERSION",
    "bias_cov",
    "body_pose_cov",
    "CameraInfo",
    "Certificate",
    "Envelope",
    "EvalMetrics",
    "FusedState",
    "GnssFix",
    "GroundTruth",
    "HealthStatus",
    "LandmarkClass",
    "LocalizationQuality",
    "ObjectClass",
    "ObjectObservations",
    "Odometry",
    "PoseDownlink",
    "RawObservations",
    "SecuredMessage",
    "SensorFrame",
    "VehiclePrior",
]

SCHEMA_VERSION = 4  # 2: compact V2X covariances; 3: fields keyed by integer tag (schemas/tags.py); 4: filtered priors
# Versions a reader decodes: a version 3 message is a version 4 one without the fields 4 added (their defaults).
READABLE_VERSIONS = (3, 4)

# Limits that keep a hostile payload from allocating without bound.
MAX_OBJECTS = 1024
MAX_LANDMARKS = 4096
MAX_MASK_BYTES = 4 * 1024 * 1024
NAME_PATTERN = r"^[A-Za-z0-9_\-]{1,64}$"

# Physical limits: finite values beyond these are a broken sensor or sender, not a measurement. One
# vehicle prior with v_map = 1e6 m/s put the fused vehicle and an object kilometres off for over a
# second; odometry of -1e308 m/s overflowed the host-side localizer.
MAX_TIME_S = 1e10  # seconds, either sign: scenario time, or Unix time in HealthStatus (the year 2286)
MAX_COORD_M = 1e6  # map-frame coordinates, either sign (the map is a local frame)
MAX_SPEED_MPS = 100.0  # any road user's speed, either sign
MAX_YAW_RATE_RADPS = 10.0
MIN_TIME_SCALE, MAX_TIME_SCALE = 1e-3, 100.0  # a live fleet's clock: scenario seconds per wall second

# Signed messages (SecuredMessage, Certificate; mapcontainer/security.py signs and verifies them).
DIGEST_BYTES = 8  # HashedId8 of IEEE 1609.2: the first 8 bytes of the SHA-256 of a certificate's encoding
PUBLIC_KEY_BYTES = 33  # a P-256 point, SEC 1 compressed: 0x02 or 0x03 (parity of y), then x (32 bytes)
SIGNATURE_BYTES = 64  # ECDSA P-256: r then s, 32 bytes each, big-endian (not DER)
MAX_CERT_TIME_S = 2**32 - 1  # certificate validity: Unix seconds as an unsigned 32-bit int (to the year 2106)
MAX_TIME_US = int(MAX_TIME_S * 1e6)  # a generation time in microseconds, either sign


class ObjectClass(IntEnum):
    """Class codes of detected objects (uint8 on the wire)."""

    UNKNOWN = 0
    PEDESTRIAN = 1
    VEHICLE = 2
    CYCLIST = 3


class LandmarkClass(IntEnum):
    """Class codes of camera landmark detections (uint8 on the wire)."""

    TRAFFIC_LIGHT = 1
    SIGN = 2
    LAMP = 3


def _check_pd(name: str, upper: np.ndarray) -> None:
    """Raise ValueError unless every matrix given by its upper triangle is positive definite."""
    if upper.size == 0:
        return
    try:
        np.linalg.cholesky(cov_from_upper(upper))  # one batched factorisation, float64
    except np.linalg.LinAlgError:
        raise ValueError(f"{name} is not positive definite") from None


def _check_bound(name: str, values: np.ndarray, bound: float) -> None:
    """Raise ValueError unless every value lies within [-bound, bound]."""
    worst = float(np.max(np.abs(values), initial=0.0))
    if worst > bound:
        raise ValueError(f"{name} beyond the physical limit of {bound:g} ({worst:g})")


class _Model(BaseModel):
    # strict: a wrong scalar type is invalid, never converted ("1.5" or true for a time, 7.0 for a seq)
    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False, ser_json_bytes="base64", strict=True)


class Envelope(_Model):
    """Fields every message carries."""

    schema_version: int = Field(SCHEMA_VERSION, description="wire contract version; readers reject others")
    fleet: str = Field(pattern=NAME_PATTERN, description="name of the run; every key is namespaced by it")
    sender: str = Field(pattern=NAME_PATTERN, description="id of the producing vehicle or service")
    seq: int = Field(ge=0, lt=2**63, description="per-sender sequence number, +1 per message")
    t_meas: float = Field(ge=-MAX_TIME_S, le=MAX_TIME_S, description="scenario time the content is valid for (s)")
    t_sent: float = Field(
        ge=-MAX_TIME_S, le=MAX_TIME_S, description="scenario time the sender published the message (s)"
    )
    # The world's clock on a live fleet (a simulated run leaves them out): scenario time t happened at wall
    # time epoch_wall_ns + t / time_scale * 1e9. Inside the message, so that a signature covers them.
    epoch_wall_ns: int | None = Field(
        None, gt=0, lt=2**63, description="live fleets: Unix time (ns) at which scenario time 0 happened"
    )
    time_scale: float | None = Field(
        None, ge=MIN_TIME_SCALE, le=MAX_TIME_SCALE, description="live fleets: scenario seconds per wall second"
    )
    t_next: float | None = Field(
        None,
        ge=-MAX_TIME_S,
        le=MAX_TIME_S,
        description="live fleets on the adaptive clock: scenario time of the world's next frame (clocks stop there)",
    )


# --------------------------------------------------------------------------------- parts


class CameraInfo(_Model):
    """Pinhole intrinsics (pixels) and the camera's mounting on the body."""

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    width: int = Field(gt=0, le=16384)
    height: int = Field(gt=0, le=16384)
    T_body_cam: F32(4, 4) = Field(description="maps camera-frame points to the body frame")


class GnssFix(_Model):
    """A GNSS position fix converted to the map frame."""

    p_map: F32(3) = Field(description="antenna position, map frame (m)")
    sigma_h_m: float = Field(gt=0, description="receiver-reported horizontal 1-sigma (m)")
    sigma_v_m: float = Field(gt=0, description="receiver-reported vertical 1-sigma (m)")

    @model_validator(mode="after")
    def _plausible(self):
        _check_bound("p_map", self.p_map, MAX_COORD_M)
        return self


class Odometry(_Model):
    """Wheel odometry and gyro."""

    speed: float = Field(ge=-MAX_SPEED_MPS, le=MAX_SPEED_MPS, description="forward speed (m/s)")
    yaw_rate: float = Field(ge=-MAX_YAW_RATE_RADPS, le=MAX_YAW_RATE_RADPS, description="yaw rate about body z (rad/s)")


class ObjectObservations(_Model):
    """One frame's object detections in the observer's body frame (not tracks)."""

    p_body_cm: I16(None, 3) = Field(
        default_factory=lambda: np.zeros((0, 3), np.int16),
        description="position in the body frame, centimetres (int16: +-327 m at 1 cm, as in the ETSI CPM)",
    )
    cov: Cov(3, many=True) = Field(
        default_factory=lambda: np.zeros((0, 6), np.float32),
        description="3x3 position covariance per object, upper triangle (m^2); on the wire standard "
        "deviations (float16) and correlations (int8), 9 bytes per object",
    )
    cls: U8(None) = Field(default_factory=lambda: np.zeros(0, np.uint8), description="ObjectClass code per object")

    @model_validator(mode="after")
    def _consistent(self):
        n = len(self.p_body_cm)
        if n > MAX_OBJECTS:
            raise ValueError(f"{n} objects exceed the limit of {MAX_OBJECTS}")
        if len(self.cov) != n or len(self.cls) != n:
            raise ValueError(f"objects: {n} positions but {len(self.cov)} covariances and {len(self.cls)} classes")
        return self  # cov is positive definite: checked by its type (Cov, schemas.arrays.CovSpec)

    def __len__(self) -> int:
        return len(self.p_body_cm)

    @property
    def p_body(self) -> np.ndarray:
        """Positions in metres (N, 3)."""
        return self.p_body_cm.astype(np.float64) / 100.0

    @classmethod
    def from_metres(cls, p_body, cov, obj_cls) -> ObjectObservations:
        """Build from positions in metres (rounded to 1 cm) and (N, 3, 3) or (N, 6) covariances."""
        p = np.asarray(p_body, dtype=float).reshape(-1, 3)
        cov = np.asarray(cov, dtype=float)
        if cov.ndim == 3:
            cov = cov_to_upper(cov)
        return cls(p_body_cm=np.round(p * 100.0), cov=cov.reshape(-1, 6), cls=np.asarray(obj_cls).reshape(-1))


class LocalizationQuality(_Model):
    """How the vehicle's self-localization went this frame."""

    mode: Literal["map_matching", "fallback"] = Field(
        description="map_matching: a converged camera/HD-map solution; fallback: GNSS + odometry only"
    )
    n_points: int = Field(0, ge=0, description="point landmark inliers")
    n_poles: int = Field(0, ge=0, description="pole landmark inliers")
    n_lane: int = Field(0, ge=0, description="lane samples within the distance cap")
    cost: float = Field(0.0, ge=0, description="final normalised cost (chi^2 per residual)")
    lock: Literal["full", "lateral"] | None = Field(
        None,
        description="while map_matching, what the camera fixed: 'full' (landmarks and lanes: the whole pose), "
        "'lateral' (the lanes alone: lateral position and heading; the along-road position is GNSS and odometry's, "
        "and pose_cov says so). Absent: not said (fallback, or an older sender)",
    )


# ------------------------------------------------------------------------------ messages


class Observations(Envelope):
    """Raw sensor content of one camera frame (shared by SensorFrame and RawObservations)."""

    camera: CameraInfo
    points_uv: F32(None, 2) = Field(
        default_factory=lambda: np.zeros((0, 2), np.float32), description="point landmark detections (px)"
    )
    points_cls: U8(None) = Field(
        default_factory=lambda: np.zeros(0, np.uint8), description="LandmarkClass code per point"
    )
    poles_uv: F32(None, 4) = Field(
        default_factory=lambda: np.zeros((0, 4), np.float32),
        description="pole segment detections u1, v1, u2, v2 (px)",
    )
    lane_mask_png: bytes = Field(
        b"",
        max_length=MAX_MASK_BYTES,
        description="greyscale PNG (1-bit or 8-bit) lane segmentation at the camera's resolution, "
        "non-zero = marking; b'' if none",
    )
    gnss: GnssFix | None = None
    odometry: Odometry | None = None
    objects: ObjectObservations = Field(default_factory=ObjectObservations)
    lane_mask_pooled_png: bytes | None = Field(
        None,
        max_length=MAX_MASK_BYTES,
        description="the lane segmentation max-pooled by an integer factor k >= 1 (a pixel is marking if any of "
        "the k x k camera pixels it covers is): a PNG of (width // k) x (height // k) pixels of the camera, as its "
        "header says; image coordinates scale by its width / the camera's width. Sent instead of lane_mask_png "
        "(then b''), pooled to the width the receiver's map matcher uses; absent if not pooled",
    )

    @model_validator(mode="after")
    def _consistent(self):
        n = len(self.points_uv)
        if n > MAX_LANDMARKS or len(self.poles_uv) > MAX_LANDMARKS:
            raise ValueError(f"more than {MAX_LANDMARKS} landmark detections")
        if len(self.points_cls) != n:
            raise ValueError(f"{n} point detections but {len(self.points_cls)} classes")
        if self.lane_mask_png and not self.lane_mask_png.startswith(_PNG_SIGNATURE):
            raise ValueError("lane_mask_png is not a PNG")
        if self.lane_mask_pooled_png is not None:
            if self.lane_mask_png:
                raise ValueError("a lane mask in both lane_mask_png and lane_mask_pooled_png")
            _check_pooled(self.lane_mask_pooled_png, self.camera.width, self.camera.height)
        return self


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _check_pooled(png: bytes, width: int, height: int) -> None:
    """Raise ValueError unless ``png`` is a PNG of (width // k) x (height // k) pixels for an integer k >= 1."""
    if not png.startswith(_PNG_SIGNATURE) or len(png) < 24 or png[12:16] != b"IHDR":
        raise ValueError("lane_mask_pooled_png is not a PNG")
    w, h = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    k = width // w if 0 < w <= width else 0  # the only k with width // k == w, if there is one
    if k < 1 or width // k != w or height // k != h:
        raise ValueError(
            f"lane_mask_pooled_png of {w}x{h} pixels is not a {width}x{height} camera pooled by an integer"
        )


class SensorFrame(Observations):
    """World -> vehicle (on-board bus): one frame of the vehicle's own sensors."""


class RawObservations(Observations):
    """Vehicle -> host in centralized mode: everything the host needs to localize the vehicle."""


class VehiclePrior(Envelope):
    """Vehicle -> host in distributed mode: self-localization and this frame's detections."""

    pose: F32(6) = Field(description="[x, y, z, roll, pitch, yaw] of the body in the map frame")
    pose_cov: Cov(6, corr="int16") = Field(
        description="6x6 pose covariance, upper triangle; on the wire standard deviations (float16) and "
        "correlations (int16), 42 bytes"
    )
    v_map: F32(3) = Field(description="body velocity in the map frame (m/s)")
    quality: LocalizationQuality
    objects: ObjectObservations = Field(default_factory=ObjectObservations)
    pose_filtered: bool = Field(
        False,
        description="what pose and pose_cov are. False (and every version 3 message): this frame's camera "
        "evidence with a weak prior, independent from frame to frame (a receiver fuses every frame). True: the "
        "vehicle's filtered estimate, all it knows so far of the pose as its camera sees the map (a receiver "
        "fuses only the newest; the body's pose is off by the error in pose_bias_sigma)",
    )
    pose_bias_sigma: F16(6) | None = Field(
        None,
        description="1-sigmas of the error every frame repeats, in the body frame (along, across, up (m); roll, "
        "pitch, yaw (rad)): camera calibration, the map's survey drift. The true body pose is off pose by it; "
        "the vehicle's detections share it with the pose, so they sit right in the map from pose. Body pose "
        "covariance = pose_cov + R(yaw) diag(sigma^2) R(yaw)^T (schemas.body_pose_cov)",
    )
    protection_level_m: F32(2) | None = Field(
        None,
        description="(lateral, longitudinal) protection levels of the body position in the vehicle frame (m): the "
        "true error exceeds each with probability at most integrity_risk. Present only while the vehicle claims "
        "integrity (map matched, no fault detected); absent: it does not",
    )
    integrity_risk: float | None = Field(
        None, gt=0, lt=1, description="the per-axis probability protection_level_m is stated at"
    )
    downlink: Literal["fused", "refused", "seeded"] | None = Field(
        None,
        description="what the host's downlink (PoseDownlink) did this frame: 'fused' into the vehicle's on-board "
        "estimate (pose here stays the vehicle's own), 'refused' by its consistency gate, 'seeded': the vehicle's "
        "localizer runs from a start the downlink proposed, so pose holds some of the others' information. Absent: "
        "none used (or an older sender)",
    )
    # pose_cov is positive definite: checked by its type (Cov, schemas.arrays.CovSpec)

    @model_validator(mode="after")
    def _plausible(self):
        _check_bound("pose position", self.pose[:3], MAX_COORD_M)
        _check_bound("pose angles", self.pose[3:], 2 * np.pi)
        _check_bound("v_map", self.v_map, MAX_SPEED_MPS)
        if self.pose_bias_sigma is not None:
            _check_bound("pose_bias_sigma", self.pose_bias_sigma, MAX_COORD_M)
            if np.any(self.pose_bias_sigma < 0):
                raise ValueError("pose_bias_sigma must be non-negative")
        if self.protection_level_m is not None:
            _check_bound("protection_level_m", self.protection_level_m, MAX_COORD_M)
            if np.any(self.protection_level_m < 0) or self.integrity_risk is None:
                raise ValueError("protection_level_m must be non-negative and come with integrity_risk")
        return self


class PoseDownlink(Envelope):
    """Host -> one vehicle (the V2X downlink): what the other vehicles know about ``target``'s pose at t_meas.

    The host's estimate of the target's pose with the target's own information taken out (its newest prior,
    subtracted in information form: a channel filter on the link of the star), so that the vehicle can fuse
    it as independent evidence. t_meas is the time of the target's frame it is about; ``sender`` the host.
    In information form because the others rarely know a whole pose (they see a position, seldom a heading):
    a direction they know nothing about has zero information, which no covariance can say.
    """

    target: str = Field(pattern=NAME_PATTERN, description="the vehicle this message is about and for")
    pose: F32(6) = Field(
        description="[x, y, z, roll, pitch, yaw] of the target's body in the map frame, as the others see it (in "
        "the directions without information, the host's own estimate: no information)"
    )
    pose_info: F32(21) = Field(
        description="6x6 information matrix (inverse covariance) of what the others know, over pose's six numbers, "
        "upper triangle; positive semi-definite"
    )

    @model_validator(mode="after")
    def _plausible(self):
        _check_bound("pose position", self.pose[:3], MAX_COORD_M)
        _check_bound("pose angles", self.pose[3:], 2 * np.pi)
        w = np.linalg.eigvalsh(cov_from_upper(np.asarray(self.pose_info, dtype=float)))
        if w[0] < -1e-5 * max(w[-1], 1.0):
            raise ValueError("pose_info is not positive semi-definite")
        return self


def body_pose_cov(prior: VehiclePrior) -> np.ndarray:
    """The 6x6 covariance of the vehicle's body pose from a VehiclePrior: ``pose_cov`` plus the error every
    frame repeats (``pose_bias_sigma``, body frame, turned into the map frame by the pose's yaw)."""
    cov = cov_from_upper(np.asarray(prior.pose_cov, dtype=float))
    if prior.pose_bias_sigma is None:
        return cov
    return cov + bias_cov(prior.pose_bias_sigma, float(prior.pose[5]))


def bias_cov(sigma_body, yaw: float) -> np.ndarray:
    """Covariance in the map frame of a pose error with 1-sigmas ``sigma_body`` (along, across, up, roll,
    pitch, yaw) in the body frame of a vehicle heading ``yaw``."""
    sd = np.asarray(sigma_body, dtype=float)
    B = np.eye(6)
    c, s = np.cos(yaw), np.sin(yaw)
    B[:2, :2] = [[c, -s], [s, c]]
    return (B * sd**2) @ B.T


class FusedState(Envelope):
    """Host -> anyone: the fused driving environment at t_meas."""

    vehicle_ids: list[str] = Field(default_factory=list, max_length=MAX_OBJECTS)
    vehicle_pose: F32(None, 6) = Field(default_factory=lambda: np.zeros((0, 6), np.float32))
    vehicle_pose_cov: F32(None, 21) = Field(default_factory=lambda: np.zeros((0, 21), np.float32))
    object_id: U32(None) = Field(default_factory=lambda: np.zeros(0, np.uint32), description="stable global ids")
    object_cls: U8(None) = Field(default_factory=lambda: np.zeros(0, np.uint8))
    object_p_map: F32(None, 3) = Field(default_factory=lambda: np.zeros((0, 3), np.float32))
    object_v_map: F32(None, 3) = Field(default_factory=lambda: np.zeros((0, 3), np.float32))
    object_cov: F32(None, 6) = Field(
        default_factory=lambda: np.zeros((0, 6), np.float32), description="position covariance, upper triangle"
    )
    messages_fused: int = Field(0, ge=0, description="messages in the window this state was solved from")
    flagged: list[Annotated[str, Field(pattern=NAME_PATTERN)]] = Field(
        default_factory=list,
        max_length=MAX_OBJECTS,
        description="vehicles flagged by misbehaviour detection: the others see them elsewhere than they say",
    )

    @model_validator(mode="after")
    def _consistent(self):
        v = len(self.vehicle_ids)
        if len(self.vehicle_pose) != v or len(self.vehicle_pose_cov) != v:
            raise ValueError(f"{v} vehicle ids but {len(self.vehicle_pose)} poses, {len(self.vehicle_pose_cov)} covs")
        n = len(self.object_id)
        if n > MAX_OBJECTS or any(
            len(a) != n for a in (self.object_cls, self.object_p_map, self.object_v_map, self.object_cov)
        ):
            raise ValueError("object arrays differ in length")
        _check_pd("vehicle pose covariance", self.vehicle_pose_cov)
        _check_pd("object covariance", self.object_cov)
        return self


class GroundTruth(Envelope):
    """World -> evaluator: the true state at t_meas (never used for estimation)."""

    vehicle_ids: list[str] = Field(default_factory=list, max_length=MAX_OBJECTS)
    vehicle_pose: F32(None, 6) = Field(default_factory=lambda: np.zeros((0, 6), np.float32))
    vehicle_v_map: F32(None, 3) = Field(default_factory=lambda: np.zeros((0, 3), np.float32))
    obstacle_id: U32(None) = Field(default_factory=lambda: np.zeros(0, np.uint32))
    obstacle_cls: U8(None) = Field(default_factory=lambda: np.zeros(0, np.uint8))
    obstacle_p_map: F32(None, 3) = Field(default_factory=lambda: np.zeros((0, 3), np.float32))
    obstacle_v_map: F32(None, 3) = Field(default_factory=lambda: np.zeros((0, 3), np.float32))
    obstacle_yaw: F32(None) = Field(default_factory=lambda: np.zeros(0, np.float32))

    @model_validator(mode="after")
    def _consistent(self):
        v = len(self.vehicle_ids)
        if len(self.vehicle_pose) != v or len(self.vehicle_v_map) != v:
            raise ValueError("vehicle arrays differ in length")
        n = len(self.obstacle_id)
        if n > MAX_OBJECTS or any(
            len(a) != n for a in (self.obstacle_cls, self.obstacle_p_map, self.obstacle_v_map, self.obstacle_yaw)
        ):
            raise ValueError("obstacle arrays differ in length")
        return self


class HealthStatus(Envelope):
    """Every service -> health CLI: periodic status and the reply to a health query."""

    role: str = Field(pattern=NAME_PATTERN)
    state: Literal["ok", "finished", "starting", "degraded", "failed"] = Field(
        description="ok; finished (its input ended with its source: the world finished, a replay ended); "
        "starting (a cold start's expected period); degraded; failed. The first three are healthy. "
        "finished and starting are new in schema_version 4's health messages (2026-12): a reader that "
        "does not know them should take them as ok"
    )
    uptime_s: float = Field(ge=0)
    msgs_in_per_s: float = Field(0.0, ge=0)
    msgs_out_per_s: float = Field(0.0, ge=0)
    bytes_in_per_s: float = Field(0.0, ge=0)
    bytes_out_per_s: float = Field(0.0, ge=0)
    latency_ms_p50: float | None = Field(None, ge=0, description="processing latency per message (ms)")
    latency_ms_p99: float | None = Field(None, ge=0)
    rejects: dict[str, int] = Field(default_factory=dict, description="rejected inputs by reason")
    last_error: str | None = None
    figures: dict[str, float] = Field(default_factory=dict, description="role figures, e.g. fused_objects")


class EvalMetrics(Envelope):
    """Evaluator -> anyone, once a second: live accuracy, latency and bandwidth of the fleet.

    ``t_meas`` is the scenario time of the newest evaluated fused state; figures are over the last
    ``window_s`` seconds of wall time unless named ``*_total``; None when nothing was measured yet.
    """

    t_wall: float = Field(description="Unix time of this snapshot (s)")
    window_s: float = Field(gt=0)
    fused_per_s: float = Field(0.0, ge=0)
    evaluated: int = Field(0, ge=0, description="fused states compared with truth so far")
    no_truth: int = Field(0, ge=0, description="fused states without ground truth at their t_meas")
    vehicle_rmse_m: float | None = Field(None, ge=0, description="horizontal, over the window")
    object_rmse_m: float | None = Field(None, ge=0, description="horizontal, matched objects, over the window")
    vehicle_rmse_total_m: float | None = Field(None, ge=0)
    object_rmse_total_m: float | None = Field(None, ge=0)
    objects_fused: int = Field(0, ge=0)
    objects_matched: int = Field(0, ge=0)
    obstacles_truth: int = Field(0, ge=0)
    e2e_latency_ms_p50: float | None = Field(None, ge=0, description="sensor t_meas -> fused output published")
    e2e_latency_ms_p99: float | None = Field(None, ge=0)
    tx_bytes_per_s: dict[str, float] = Field(default_factory=dict, description="V2X payload bytes per vehicle")
    tx_msgs_per_s: dict[str, float] = Field(default_factory=dict)
    tx_bytes_per_msg: dict[str, float] = Field(default_factory=dict)
    delivered_fraction: float | None = Field(None, ge=0, le=1)


# ----------------------------------------------------------------------------- security


class Certificate(_Model):
    """An explicit certificate, as IEEE 1609.2 / ETSI TS 103 097 send it: who holds which P-256 key, when.

    A vehicle's is issued by the fleet CA; the CA's own is self-signed (``issuer`` all zero). The
    **canonical encoding** is the msgpack map of the six fields keyed by tag in tag order (as the codec
    packs it); the issuer signs that encoding without ``signature`` (ECDSA P-256 over its SHA-256), and a
    certificate is named by its **digest**: the first 8 bytes of the SHA-256 of its whole canonical
    encoding (HashedId8). See schemas/README.md and :mod:`mapcontainer.security`.
    """

    # certificate files are JSON (bytes as base64url), read back with model_validate_json
    model_config = ConfigDict(**_Model.model_config, val_json_bytes="base64")

    subject: str = Field(pattern=NAME_PATTERN, description="id of the key's holder: a vehicle id (or the CA's name)")
    public_key: bytes = Field(
        min_length=PUBLIC_KEY_BYTES,
        max_length=PUBLIC_KEY_BYTES,
        description="the holder's P-256 public key, SEC 1 compressed point (33 bytes)",
    )
    valid_from: int = Field(ge=0, le=MAX_CERT_TIME_S, description="start of validity, Unix time (s)")
    valid_until: int = Field(ge=0, le=MAX_CERT_TIME_S, description="end of validity (inclusive), Unix time (s)")
    issuer: bytes = Field(
        min_length=DIGEST_BYTES,
        max_length=DIGEST_BYTES,
        description="digest of the issuing CA's certificate (8 bytes); all zero for a self-signed CA certificate",
    )
    signature: bytes = Field(
        min_length=SIGNATURE_BYTES,
        max_length=SIGNATURE_BYTES,
        description="the issuer's ECDSA P-256 signature (r || s, 64 bytes) over the SHA-256 of the canonical "
        "encoding without this field",
    )

    @model_validator(mode="after")
    def _consistent(self):
        if self.public_key[0] not in (2, 3):
            raise ValueError(f"public_key starts with {self.public_key[0]:#04x}, not 0x02 or 0x03 (a compressed point)")
        if self.valid_until < self.valid_from:
            raise ValueError(f"valid_until {self.valid_until} is before valid_from {self.valid_from}")
        return self


class SecuredMessage(_Model):
    """A signed message: what goes on the V2X link instead of the bare message (1609.2's SignedData).

    The signer is named by its full certificate (about once a second) or by the certificate's 8-byte
    digest, never both. ``signature`` is ECDSA P-256 over the SHA-256 of ``payload || t_gen_us
    (int64, big-endian) || digest of the signer's certificate``, whichever way the signer is named.
    """

    schema_version: int = Field(SCHEMA_VERSION, description="wire contract version; readers reject others")
    payload: bytes = Field(description="the message, msgpack-encoded as schemas/README.md says (e.g. a VehiclePrior)")
    certificate: Certificate | None = Field(None, description="the signer's full certificate; else signer_digest")
    signer_digest: bytes | None = Field(
        None,
        min_length=DIGEST_BYTES,
        max_length=DIGEST_BYTES,
        description="digest (HashedId8) of the signer's certificate, sent in its place; else certificate",
    )
    t_gen_us: int = Field(
        ge=-MAX_TIME_US, le=MAX_TIME_US, description="generation time, Unix time in microseconds (1609.2's Time64)"
    )
    signature: bytes = Field(
        min_length=SIGNATURE_BYTES,
        max_length=SIGNATURE_BYTES,
        description="the signer's ECDSA P-256 signature (r || s, 64 bytes) over the SHA-256 of "
        "payload || t_gen_us as int64 big-endian || signer's certificate digest",
    )

    @model_validator(mode="after")
    def _one_signer(self):
        if (self.certificate is None) == (self.signer_digest is None):
            raise ValueError("a SecuredMessage names its signer by certificate or by signer_digest: exactly one")
        return self
