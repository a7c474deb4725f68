"""What every host core is and shares: the :class:`HostCore` protocol and the code both cores run.

A host core is the pure estimator behind the host container: bytes in with :meth:`HostCore.ingest`
(never raises on bad input: it answers with an :class:`IngestResult`), a fused state out with
:meth:`HostCore.fuse` at a time the caller chooses, figures with :meth:`HostCore.stats`. Two implement
it: the distributed :class:`~.container.Container` (vehicle priors into a sliding-window factor graph)
and the centralized :class:`~.joint.JointHost` (raw observations into one joint filter). What they do
alike lives here, once:

* :class:`Intake`: decode, sender screening (fleet, known senders), the reorder buffer, the counters;
  the messages of a solve (:meth:`Intake.pop`) and the ones that left the window meanwhile;
* :func:`detections_in_map`: a message's body-frame detections, the too-close ones dropped, moved to
  the map frame with the sender's pose (:func:`~.mapframe.observations_to_map`);
* :func:`vehicle_candidate`: a connected vehicle's reported position at a detection's time, for gating;
* :func:`cross_observation`: a detection of a connected vehicle corrected to the observed vehicle's
  frame time;
* :func:`observer_bias` / :func:`observer_biases`: what the observers' repeated errors add to an object's
  covariance (a consider term), of one object / of many at once;
* :func:`vehicle_at` and :func:`fused_state`: the output, moved to the fuse time and made wire-valid;
* :func:`common_stats`: the figures both report under the same names.

The loop around a core (the frame gate, time as an argument) is :class:`mapcontainer.host.HostLoop`.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
from scipy.stats import norm

from schemas import FusedState, Rejection, decode

from .. import geometry as geo
from .association import Detection, Tracker, VehicleCandidate
from .buffer import ReorderBuffer
from .mapframe import observations_to_map, rotated_to_map
from .params import FusionParams
from .poses import sym_from_upper, upper_from_sym

__all__ = [
    "HostCore",
    "IngestResult",
    "Intake",
    "MappedDetections",
    "common_stats",
    "cross_observation",
    "detections_in_map",
    "fused_state",
    "make_pd",
    "observer_bias",
    "observer_biases",
    "observer_weights",
    "persistent_share",
    "vehicle_at",
    "vehicle_candidate",
]


@dataclass(frozen=True)
class IngestResult:
    """Whether a payload was taken; ``reason`` says why not (decoder reasons, duplicate, stale, future,
    overflow, unknown_sender, fleet)."""

    accepted: bool
    reason: str | None = None


@runtime_checkable
class HostCore(Protocol):
    """The host's estimator: pure, no I/O, time an argument, deterministic for a given input sequence."""

    fleet: str
    host_id: str

    def ingest(self, payload: bytes, t_recv: float) -> IngestResult:
        """Decode and buffer one payload received at scenario time ``t_recv``; bad input is refused, not raised."""
        ...

    def fuse(self, t: float, tolerance_s: float = 0.0) -> FusedState:
        """Everything buffered with t_meas <= t + tolerance_s taken in; the fused state at ``t``."""
        ...

    def stats(self) -> dict[str, Any]:
        """Counters and figures (health status, benchmarks); the names of :func:`common_stats` mean the same."""
        ...


class Intake:
    """decode -> sender screening -> reorder buffer, with the counters of both host cores.

    ``model``: the message type the core fuses (VehiclePrior, RawObservations). ``on_buffered(msg, t_recv,
    reason)``: told of every message of ours that reached the buffer, with the buffer's answer (None:
    taken), e.g. for the misbehaviour monitor's timing checks.
    """

    def __init__(
        self,
        model: type,
        params: FusionParams,
        fleet: str,
        known_senders: set[str] | None = None,
        on_buffered: Callable[[Any, float, str | None], None] | None = None,
    ):
        self.model = model
        self.fleet = fleet
        self.window_s = params.window_s
        self.known_senders = None if known_senders is None else set(known_senders)
        self.buffer = ReorderBuffer(params.window_s, params.future_tolerance_s, params.max_pending)
        self.on_buffered = on_buffered
        self.counts: Counter[str] = Counter()  # received, accepted, expired
        self.rejected: Counter[str] = Counter()

    def ingest(self, payload: bytes, t_recv: float) -> IngestResult:
        """Decode and buffer one payload. Never raises on bad input."""
        self.counts["received"] += 1
        msg = decode(payload, self.model)
        if isinstance(msg, Rejection):
            return self.reject(msg.reason)
        return self._take(msg, t_recv)

    def take(self, msg, t_recv: float) -> IngestResult:
        """Buffer an already-decoded message."""
        if not isinstance(msg, self.model):
            raise TypeError(f"this host takes {self.model.__name__}, got {type(msg).__name__}")
        self.counts["received"] += 1
        return self._take(msg, t_recv)

    def _take(self, msg, t_recv: float) -> IngestResult:
        reason = self._sender_refused(msg)
        if reason is None:
            reason = self.buffer.push(msg, float(t_recv))
            if self.on_buffered is not None:
                self.on_buffered(msg, float(t_recv), reason)
        if reason is not None:
            return self.reject(reason)
        self.counts["accepted"] += 1
        return IngestResult(True)

    def _sender_refused(self, msg) -> str | None:
        if msg.fleet != self.fleet:
            return "fleet"
        if self.known_senders is not None and msg.sender not in self.known_senders:
            return "unknown_sender"
        return None

    def reject(self, reason: str) -> IngestResult:
        """Count a refusal (also of a message refused after buffering, e.g. ``out_of_order``)."""
        self.rejected[reason] += 1
        return IngestResult(False, reason)

    def pop(self, t: float, tolerance_s: float) -> list:
        """The buffered messages with t_meas <= t + tolerance_s that are still within the window at t, in
        time order; older ones are dropped and counted (``expired``)."""
        msgs = self.buffer.pop_until(t + tolerance_s)
        fresh = [m for m in msgs if m.t_meas >= t - self.window_s]
        self.counts["expired"] += len(msgs) - len(fresh)
        return fresh

    def stats(self) -> dict[str, Any]:
        return {
            "received": self.counts["received"],
            "accepted": self.counts["accepted"],
            "rejected": dict(self.rejected),
            "pending": len(self.buffer),
            "expired": self.counts["expired"],
        }


@dataclass(frozen=True)
class MappedDetections:
    """A message's detections at least ``min_range_m`` away, in the map frame (``index``: into the message's
    objects)."""

    dets: list[Detection]
    index: np.ndarray  # (N,) int
    p_map: np.ndarray  # (N, 3)
    S_map: np.ndarray  # (N, 3, 3)
    cls: np.ndarray  # (N,)


def detections_in_map(
    sender: str,
    t: float,
    objects,
    pose,
    pose_cov,
    params: FusionParams,
    counts: Counter,
    floor: Callable[[np.ndarray], np.ndarray] | None = None,
) -> MappedDetections | None:
    """``objects`` (a message's ObjectList) seen by ``sender`` at ``t`` from ``pose`` (6,) with ``pose_cov``
    (6, 6), moved to the map frame:  m = R z + t,  S_m = R S_z R^T + J S_pose J^T  (association module).
    Detections closer than ``params.min_range_m`` (the observer's own body) are dropped and counted in
    ``counts["too_close"]``; ``floor`` maps the body-frame covariances first (the joint host floors them).
    None when nothing is left."""
    if len(objects) == 0:
        return None
    p_body = np.asarray(objects.p_body, dtype=float)
    cov_body = sym_from_upper(np.asarray(objects.cov, dtype=np.float64))
    if floor is not None:
        cov_body = floor(cov_body)
    keep = np.linalg.norm(p_body, axis=1) >= params.min_range_m
    counts["too_close"] += int((~keep).sum())
    if not keep.any():
        return None
    p_map, S_map = observations_to_map(pose, pose_cov, p_body[keep], cov_body[keep])
    idx = np.flatnonzero(keep)
    cls = np.asarray(objects.cls)
    dets = [
        Detection(sender, t, int(i), p_body[i], cov_body[i], int(cls[i]), p_map[j], S_map[j]) for j, i in enumerate(idx)
    ]
    return MappedDetections(dets, idx, p_map, S_map, cls[keep])


def vehicle_candidate(
    vid: str,
    p_map,
    cov_p,
    v_map,
    dt: float,
    params: FusionParams,
    bias_p: np.ndarray | None = None,
    protection: tuple[float, np.ndarray, float] | None = None,
) -> VehicleCandidate:
    """Vehicle ``vid`` where its state says it is ``dt`` after the state's time: p + v dt, with covariance
    cov_p (3x3) [+ bias_p, the part of the body's error its every frame repeats] + (sigma_v dt)^2 I.
    ``protection``: (yaw, (lateral, longitudinal) protection levels (m), integrity risk per axis) of that
    state where the vehicle claims integrity; the levels grow by k sigma_v dt (k the risk's Gaussian
    quantile) and gate the detections of it (:func:`~.association.protection_gate`)."""
    cov = np.asarray(cov_p, dtype=float)
    if bias_p is not None:
        cov = cov + bias_p
    s_dt = params.vehicle_velocity_sigma_mps * abs(dt)
    cov = cov + s_dt**2 * np.eye(3)
    box = None
    if protection is not None:
        yaw, pl, risk = protection
        k = float(norm.isf(0.5 * risk))
        box = (float(yaw), float(pl[0]) + k * s_dt, float(pl[1]) + k * s_dt, k)
    return VehicleCandidate(vid, np.asarray(p_map, dtype=float) + np.asarray(v_map, dtype=float) * dt, cov, box)


def cross_observation(
    det: Detection, R_obs: np.ndarray, v_target, delta: float, params: FusionParams, bias_p: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """A detection of a connected vehicle, made ``delta`` seconds after that vehicle's frame, as a
    measurement of its origin at its frame time, in the observer's body frame (rotation R_obs = R_map_body):

        z = p_body - R_obs^T v delta,   cov = cov_body + (sigma_v delta)^2 I [+ R_obs^T S_b R_obs],

    ``bias_p`` (3x3, map frame) the observed body's repeated error S_b: the detection sees the body, the
    state holds the pose its camera sees."""
    z = det.p_body - R_obs.T @ np.asarray(v_target, dtype=float) * delta
    cov = det.cov_body + (params.vehicle_velocity_sigma_mps * delta) ** 2 * np.eye(3)
    if bias_p is not None:
        cov = cov + R_obs.T @ bias_p @ R_obs
    return z, cov


def observer_weights(frames: dict, t_min: float) -> dict[str, float]:
    """Each observer's share w_v of a track's detections since ``t_min`` (``Track.frames``: (sender, time key)
    -> t), the weight its errors have in the track's estimate (every detection counted alike)."""
    n: Counter[str] = Counter(sender for (sender, _), t in frames.items() if t >= t_min)
    total = sum(n.values())
    return {v: k / total for v, k in n.items()} if total else {}


def persistent_share(params: FusionParams) -> float:
    """The share of a detection's variance that one observer's detections of an object in the window repeat:
    f g(T / tau), f = ``detection_persistent_fraction``, tau = ``detection_persistence_s``, T = ``window_s``,
    g(x) = 2 (x - 1 + exp(-x)) / x^2 the variance of the mean of a unit first-order Gauss-Markov process over T
    (1 for T << tau: the whole persistent part; -> 0 for T >> tau: it averages out)."""
    x = params.window_s / params.detection_persistence_s
    return params.detection_persistent_fraction * 2.0 * (x - 1.0 + float(np.exp(-x))) / (x * x)


def observer_bias(p_map, observers: list[tuple]) -> np.ndarray:
    """What the observers' repeated errors add to the covariance of an object at ``p_map`` (3,) that they saw:

        C = sum_v w_v^2 (J_v S_v J_v^T + R_v D_v R_v^T),   J_v = d (t_v + R_v z_v) / d pose_v,   z_v = R_v^T (p - t_v),

    ``observers``: (pose_v (6,) [x, y, z, roll, pitch, yaw], S_v (6, 6) the map-frame covariance of the error
    every frame of v repeats (its calibration, the map's survey drift: VehiclePrior.pose_bias_sigma), w_v its
    share of the detections[, D_v (3, 3) the persistent part of v's detection error in its body frame, or
    None: :func:`persistent_share` of its newest detection's covariance]). Such errors do not average out over
    v's detections, so the estimator, which takes them as independent, leaves them out of the object's
    covariance; errors of different observers are independent, so the weighted mean's covariance is the sum
    of the w_v^2 terms. A consider term: the host does not estimate these errors, it states what they do to
    the estimate. One object; :func:`observer_biases` does many at once (the same numbers)."""
    table = {i: (ob[0], ob[1]) for i, ob in enumerate(observers)}
    seen = [(i, ob[2], ob[3] if len(ob) > 3 else None) for i, ob in enumerate(observers)]
    return observer_biases(np.asarray(p_map, dtype=float)[None], [seen], table)[0]


def observer_biases(p_map, seen: list[list[tuple]], observers: dict) -> np.ndarray:
    """:func:`observer_bias` of K objects at ``p_map`` (K, 3) at once: (K, 3, 3).

    ``seen[k]``: object k's observers as (key into ``observers``, w_v, D_v (3, 3) or None), in the order
    their terms are summed; ``observers``: key -> (pose_v (6,), S_v (6, 6)). Each observer's rotation and
    its derivatives are computed once, and its terms for every object it saw in one array operation
    (:func:`~.mapframe.rotated_to_map`), instead of once per object and observer."""
    p = np.asarray(p_map, dtype=float).reshape(-1, 3)
    if len(seen) != len(p):
        raise ValueError(f"{len(p)} objects but {len(seen)} lists of observers")
    C = np.zeros((len(p), 3, 3))
    pairs: dict = {}  # observer -> ([object], [rank in the object's sum], [w], [D])
    for k, obs in enumerate(seen):
        for rank, (o, w, D) in enumerate(obs):
            col = pairs.get(o)
            if col is None:
                col = pairs[o] = ([], [], [], [])
            col[0].append(k)
            col[1].append(rank)
            col[2].append(w)
            col[3].append(_NO_BIAS if D is None else D)
    if not pairs:
        return C
    objs, ranks, terms = [], [], []
    for o, (ks, rs, ws, Ds) in pairs.items():
        pose = np.asarray(observers[o][0], dtype=float)
        jac = geo.rpy_to_matrix_jac(*pose[3:6])  # R once, for z and for the propagation
        z = (p[ks] - pose[:3]) @ jac[0]  # z_v = R_v^T (p - t_v), row by row
        w = np.array(ws, dtype=float)
        S = rotated_to_map(pose, jac, observers[o][1], z, np.array(Ds, dtype=float), rowwise=True)[1]
        objs += ks
        ranks += rs
        terms.append((w * w)[:, None, None] * S)
    obj, rank, term = np.array(objs), np.array(ranks), np.concatenate(terms)
    for r in range(int(rank.max()) + 1):  # each object's terms summed in its observers' order
        at = rank == r
        C[obj[at]] += term[at]
    return C


_NO_BIAS = np.zeros((3, 3))


def vehicle_at(
    pose, cov, v_map, dt: float, params: FusionParams, same_instant_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """A vehicle's pose and covariance moved dt at constant velocity v_map, with the vehicle motion
    factor's noise (its newest frame is not at the output time: latency). Both host cores publish their
    vehicles through it, with the frame gate's tolerance as ``same_instant_s`` (0: every gap is latency).

    A frame within ``same_instant_s`` of the output time (the frame gate's tolerance) is of the same
    instant: the fleet samples on one clock, and the stamps differ by the vehicles' clock offsets, which
    the host does not know. Moving it by v dt would turn a clock's error into a position error (v dt: 2-4 cm
    at 10 m/s); it stays where it is, and its covariance takes the motion it would be if the gap were real,
    v v^T dt^2."""
    pose, cov = np.array(pose, dtype=float), np.array(cov, dtype=float)
    if 0 < abs(dt) <= same_instant_s:
        v = np.asarray(v_map, dtype=float)
        cov[:3, :3] += np.outer(v, v) * dt**2
    elif dt != 0:
        pose[:3] += np.asarray(v_map, dtype=float) * dt
        s_t2 = (params.vehicle_velocity_sigma_mps * dt) ** 2 + (0.5 * params.vehicle_accel_sigma_mps2 * dt**2) ** 2
        s_r2 = (params.vehicle_rate_sigma_radps * dt) ** 2
        cov = cov + np.diag([s_t2, s_t2, s_t2, s_r2, s_r2, s_r2])
    return pose, cov


def make_pd(C: np.ndarray) -> np.ndarray:
    """Symmetric (..., n, n) with eigenvalues floored (float32-safe): covariances the wire validator accepts."""
    C = np.asarray(C, dtype=float)
    if C.size == 0:
        return C
    C = 0.5 * (C + np.swapaxes(C, -1, -2))
    w, U = np.linalg.eigh(C)
    floor = np.maximum(1e-12, 1e-7 * np.max(np.abs(w), axis=-1, keepdims=True))
    return (U * np.maximum(w, floor)[..., None, :]) @ np.swapaxes(U, -1, -2)


def fused_state(
    fleet, host_id, seq, t, vids, poses, pose_covs, ids, cls, ps, vs, covs, messages_fused, flagged
) -> FusedState:
    """The FusedState message of a host's estimate at t (covariances made wire-valid by :func:`make_pd`)."""
    return FusedState(
        fleet=fleet,
        sender=host_id,
        seq=seq,
        t_meas=t,
        t_sent=t,
        vehicle_ids=vids,
        vehicle_pose=np.array(poses, dtype=np.float32).reshape(-1, 6),
        vehicle_pose_cov=upper_from_sym(make_pd(np.array(pose_covs).reshape(-1, 6, 6))).astype(np.float32),
        object_id=np.array(ids, dtype=np.uint32),
        object_cls=np.array(cls, dtype=np.uint8),
        object_p_map=np.array(ps, dtype=np.float32).reshape(-1, 3),
        object_v_map=np.array(vs, dtype=np.float32).reshape(-1, 3),
        object_cov=upper_from_sym(make_pd(np.array(covs).reshape(-1, 3, 3))).astype(np.float32),
        messages_fused=messages_fused,
        flagged=flagged,
    )


_COUNTED = ("detections", "cross_detections", "cross_no_state", "too_close")


def common_stats(intake: Intake, tracker: Tracker, counts: Counter, vehicles: int, last_cycle_ms: float) -> dict:
    """The figures both host cores report, under the same names: the intake's, ``fused_cycles``,
    ``last_cycle_ms``, ``vehicles``, the tracker's and the detection counters."""
    tracks = list(tracker.tracks.values())
    return {
        **intake.stats(),
        "fused_cycles": counts["fused_cycles"],
        "last_cycle_ms": last_cycle_ms,
        "vehicles": vehicles,
        "tracks_confirmed": sum(tr.confirmed for tr in tracks),
        "tracks_tentative": sum(not tr.confirmed for tr in tracks),
        "association": dict(tracker.counts),
        **{k: counts[k] for k in _COUNTED},
    }
