"""The host container: validate -> reorder -> associate -> factor graph -> fused state (paper §III-D).

A pure core: no I/O, no threads, time is an argument, deterministic for a given input sequence.
The live host service and ``pipeline.py`` feed it bytes with :meth:`Container.ingest` and ask for the
fused driving environment with :meth:`Container.fuse`.

``ingest_prior`` takes an already-decoded prior. (The centralized mode's host is
:class:`~.joint.JointHost`.)
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

from schemas import FusedState, Rejection, VehiclePrior, bias_cov, decode
from schemas.models import MAX_OBJECTS

from .association import Detection, Tracker, VehicleCandidate, observations_to_map
from .buffer import ReorderBuffer
from .graph import FusionGraph
from .laps import Laps
from .misbehaviour import MisbehaviourMonitor
from .motion import accel_psd, cv_predict
from .params import FusionParams
from .poses import pose_cov_from_tangent, sym_from_upper, upper_from_sym, vector_from_pose3
from .solver import SolveReport

__all__ = ["Container", "FusionParams", "IngestResult"]


@dataclass(frozen=True)
class IngestResult:
    """Whether a payload was taken; ``reason`` says why not (decoder reasons, duplicate, stale, future,
    overflow, unknown_sender, fleet)."""

    accepted: bool
    reason: str | None = None


def _make_pd(C: np.ndarray) -> np.ndarray:
    """Symmetric (..., n, n) with eigenvalues floored (float32-safe): covariances the wire validator accepts."""
    C = np.asarray(C, dtype=float)
    if C.size == 0:
        return C
    C = 0.5 * (C + np.swapaxes(C, -1, -2))
    w, U = np.linalg.eigh(C)
    floor = np.maximum(1e-12, 1e-7 * np.max(np.abs(w), axis=-1, keepdims=True))
    return (U * np.maximum(w, floor)[..., None, :]) @ np.swapaxes(U, -1, -2)


def vehicle_at(pose, cov, v_map, dt: float, params: FusionParams) -> tuple[np.ndarray, np.ndarray]:
    """A vehicle's pose and covariance moved dt at constant velocity v_map, with the vehicle motion
    factor's noise (its newest frame is not at the output time: latency, clocks)."""
    pose, cov = np.array(pose, dtype=float), np.array(cov, dtype=float)
    if dt != 0:
        pose[:3] += np.asarray(v_map, dtype=float) * dt
        s_t2 = (params.vehicle_velocity_sigma_mps * dt) ** 2 + (0.5 * params.vehicle_accel_sigma_mps2 * dt**2) ** 2
        s_r2 = (params.vehicle_rate_sigma_radps * dt) ** 2
        cov = cov + np.diag([s_t2, s_t2, s_t2, s_r2, s_r2, s_r2])
    return pose, cov


def fused_state(
    fleet, host_id, seq, t, vids, poses, pose_covs, ids, cls, ps, vs, covs, messages_fused, flagged
) -> FusedState:
    """The FusedState message of a host's estimate at t (covariances made wire-valid by _make_pd)."""
    return FusedState(
        fleet=fleet,
        sender=host_id,
        seq=seq,
        t_meas=t,
        t_sent=t,
        vehicle_ids=vids,
        vehicle_pose=np.array(poses, dtype=np.float32).reshape(-1, 6),
        vehicle_pose_cov=upper_from_sym(_make_pd(np.array(pose_covs).reshape(-1, 6, 6))).astype(np.float32),
        object_id=np.array(ids, dtype=np.uint32),
        object_cls=np.array(cls, dtype=np.uint8),
        object_p_map=np.array(ps, dtype=np.float32).reshape(-1, 3),
        object_v_map=np.array(vs, dtype=np.float32).reshape(-1, 3),
        object_cov=upper_from_sym(_make_pd(np.array(covs).reshape(-1, 3, 3))).astype(np.float32),
        messages_fused=messages_fused,
        flagged=flagged,
    )


class Container:
    """The host's fusion core. See the module docstring; the estimator is described in :mod:`.graph`."""

    def __init__(
        self,
        params: FusionParams,
        fleet: str,
        host_id: str,
        known_senders: set[str] | None = None,
    ):
        self.params = params
        self.fleet = fleet
        self.host_id = host_id
        self.known_senders = None if known_senders is None else set(known_senders)
        self.buffer = ReorderBuffer(params.window_s, params.future_tolerance_s, params.max_pending)
        self.graph = FusionGraph(params)
        self.tracker = Tracker(params)
        self._counts: Counter[str] = Counter()
        self._cross: list = []  # (observed vehicle id, Detection) waiting for that vehicle's frame
        # vid -> body-frame 1-sigmas of the error its every frame repeats (VehiclePrior.pose_bias_sigma)
        self._bias_sigma: dict[str, np.ndarray] = {}
        self._rejected: Counter[str] = Counter()
        self._seq = 0
        self._last: SolveReport | None = None
        self._last_cycle_ms = float("nan")
        self._last_phases_ms: dict[str, float] = {}
        self._candidates: dict[float, list[VehicleCandidate]] = {}
        self._reported_at: dict[float, tuple] = {}  # _reported, per instant of the cycle
        # the confirmed tracks at the cycle's start, for the ghost check (_look): ids, states [p, v], their
        # times, and the one vehicle that reported each in the window ("" if several did)
        self._lookable = (np.zeros(0, dtype=int), np.zeros((0, 6)), np.zeros(0), np.zeros(0, dtype=str))
        self.monitor = MisbehaviourMonitor(params)

    # ------------------------------------------------------------------ input
    def ingest(self, payload: bytes, t_recv: float) -> IngestResult:
        """Decode and buffer one payload received at scenario time ``t_recv``. Never raises on bad input."""
        self._counts["received"] += 1
        msg = decode(payload, VehiclePrior)
        if isinstance(msg, Rejection):
            return self._reject(msg.reason)
        return self._take(msg, t_recv)

    def ingest_prior(self, prior: VehiclePrior, t_recv: float) -> IngestResult:
        """Buffer an already-decoded prior."""
        if not isinstance(prior, VehiclePrior):
            raise TypeError(f"ingest_prior takes a VehiclePrior, got {type(prior).__name__}")
        self._counts["received"] += 1
        return self._take(prior, t_recv)

    def _take(self, msg: VehiclePrior, t_recv: float) -> IngestResult:
        reason = self._sender_refused(msg)
        if reason is None:
            reason = self.buffer.push(msg, float(t_recv))
            if self.params.misbehaviour:
                self.monitor.message(msg.sender, float(msg.t_meas), float(t_recv), reason)
        if reason is not None:
            return self._reject(reason)
        self._counts["accepted"] += 1
        return IngestResult(True)

    def _sender_refused(self, msg: VehiclePrior) -> str | None:
        if msg.fleet != self.fleet:
            return "fleet"
        if self.known_senders is not None and msg.sender not in self.known_senders:
            return "unknown_sender"
        return None

    def _reject(self, reason: str) -> IngestResult:
        self._rejected[reason] += 1
        return IngestResult(False, reason)

    # ------------------------------------------------------------------ fusion
    def fuse(self, t: float, tolerance_s: float = 0.0) -> FusedState:
        """Fuse everything received with t_meas <= t + tolerance_s within the window; the state at time t.

        ``tolerance_s``: the frame's messages lie within this of t (``FrameGate.tolerance_s``: the vehicles'
        clocks are a few ms apart); a vehicle whose frame is stamped after t is predicted back to t.
        """
        laps = Laps()
        t = float(t)
        t_min = t - self.params.window_s
        msgs = [m for m in self.buffer.pop_until(t + tolerance_s)]
        fresh = [m for m in msgs if m.t_meas >= t_min]
        self._counts["expired"] += len(msgs) - len(fresh)
        keys = []
        for m in fresh:  # all poses first, so that detections can be matched to any vehicle of the instant
            key = self.graph.add_vehicle_prior(
                m.sender, m.t_meas, m.pose, sym_from_upper(m.pose_cov), m.v_map, filtered=m.pose_filtered
            )
            if m.pose_bias_sigma is None:
                self._bias_sigma.pop(m.sender, None)
            else:
                self._bias_sigma[m.sender] = np.asarray(m.pose_bias_sigma, dtype=float)
            if key is None:
                self._counts["duplicate_instant"] += 1
            keys.append(key)
        self._candidates: dict[float, list[VehicleCandidate]] = {}  # all poses of the cycle are in
        self._reported_at: dict[float, tuple] = {}
        if self.params.misbehaviour:  # the tracks one vehicle alone reported in the window (ghost check)
            ids, xs, ts, sole = [], [], [], []
            for tid, tr in self.tracker.confirmed().items():
                sources = {s for (s, _), ts_ in tr.frames.items() if ts_ >= t - self.params.misbehaviour_window_s}
                ids.append(tid)
                xs.append(tr.x)
                ts.append(tr.t)
                sole.append(sources.pop() if len(sources) == 1 else "")
            self._lookable = (
                np.array(ids, dtype=int),
                np.array(xs).reshape(-1, 6),
                np.array(ts),
                np.array(sole, dtype=str),
            )
        laps.mark("priors")
        batch = []
        for m, key in zip(fresh, keys, strict=True):
            if key is not None:
                self.tracker.observe(m.t_meas)
                batch += self._associate(m)
        laps.mark("associate")
        self.graph.add_detections(batch)
        self._counts["detections"] += len(batch)
        self._cross_detections(t_min)
        laps.mark("detections")
        if self.params.misbehaviour:
            self.monitor.update(t)
            for tid in self.monitor.denied:  # nobody else sees it where it should be seen
                if self.tracker.remove(tid):
                    self.graph.remove_track(tid)
                    self._counts["tracks_denied"] += 1
        laps.mark("misbehaviour")
        for tid in self.tracker.expire(t):
            self.graph.remove_track(tid)
        self.graph.prune(t_min)
        laps.mark("prune")
        self._last = self.graph.solve()
        laps.mark("solve")
        self._sync_tracker()
        gone = self.tracker.merge_duplicates(t)
        trusted = [v for v in self._vehicle_candidates(t) if v.vid not in self.monitor.flagged]
        gone += self.tracker.vehicle_shadows(t, trusted)
        for tid in gone:
            self.graph.remove_track(tid)
        self._counts["fused_cycles"] += 1
        laps.mark("tracks")
        out = self._output(t)
        laps.mark("output")
        self._last_cycle_ms = sum(laps.ms.values())
        solve = self._last.phases_ms or {}
        laps.ms["solve_other"] = laps.ms.pop("solve") - sum(solve.values())  # around the solve's own phases
        laps.add(solve)
        self._last_phases_ms = laps.ms
        return out

    def _sync_tracker(self) -> None:
        for tid in self.tracker.confirmed():
            if tid in self.graph.tracks:
                ts, p, v, C = self.graph.track_estimate(tid)
                if C is not None:
                    self.tracker.sync(tid, ts, np.concatenate([p, v]), C)

    def _associate(self, m: VehiclePrior) -> list[tuple]:
        """Associate a message's detections; returns the track detections for the graph
        (:meth:`FusionGraph.add_detections` items)."""
        objs = m.objects
        if len(objs) == 0:
            return []
        t = float(m.t_meas)
        p_body = objs.p_body
        cov_body = sym_from_upper(np.asarray(objs.cov, dtype=np.float64))
        keep = np.linalg.norm(p_body, axis=1) >= self.params.min_range_m
        self._counts["too_close"] += int((~keep).sum())
        if not keep.any():
            return []
        pose = np.asarray(m.pose, dtype=float)
        pose_cov = sym_from_upper(np.asarray(m.pose_cov, dtype=float))
        p_map, S_map = observations_to_map(pose, pose_cov, p_body[keep], cov_body[keep])
        if self.params.misbehaviour:
            self.monitor.observe(m.sender, t, p_map, S_map, np.asarray(objs.cls)[keep], self._reported(t))
            self._look(m, t, pose, p_map)
            if m.sender in self.monitor.flagged:  # its detections would carry its error into everyone's picture
                self._counts["detections_of_flagged"] += len(p_map)
                return []
        idx = np.flatnonzero(keep)
        dets = [
            Detection(m.sender, t, int(i), p_body[i], cov_body[i], int(objs.cls[i]), p_map[j], S_map[j])
            for j, i in enumerate(idx)
        ]
        mb = self.monitor
        cands, (_, where, _) = self._vehicle_candidates(t), self._reported(t)
        close = np.flatnonzero(
            np.linalg.norm(where[:, None, :] - p_map[None], axis=2).min(axis=1, initial=np.inf) <= self.params.pregate_m
        )  # the tracker's pre-gate, for the vehicles
        vehicles = [
            v
            for v in (cands[i] for i in close)
            if v.vid != m.sender and v.vid not in mb.flagged and not mb.disputes(m.sender, v.vid)
        ]
        assignments, _ = self.tracker.associate(dets, vehicles)
        batch = []
        observers: dict[tuple[str, float], object] = {}
        for a in assignments:
            det = a.det
            ok = (det.sender, det.t)
            obs = observers.get(ok, False)
            if obs is False:
                obs = observers[ok] = self.graph.vehicle_state(det.sender, det.t, 0.0)
            if obs is None:  # the observer's frame has left the window
                self._counts["observer_gone"] += 1
                continue
            R_obs = obs.M[:3, :3]
            if a.kind == "vehicle":
                if self.params.cross_localization:
                    self._cross.append((a.target, det))
                    self._counts["cross_pending"] += 1
            else:
                tr = self.tracker.by_id(a.target)
                cls = tr.cls if tr is not None else det.cls
                v0 = tr.x[3:] if tr is not None else np.zeros(3)
                state = self.graph.track_state(a.target, det.t, det.p_map, v0, cls)
                k = self.params.huber_k
                d = float(np.sqrt(a.d2))
                weight = 1.0 if k is None or d <= k else k / d
                if state is None:  # older than the track's first state: into its prior
                    self.graph.fold_detection(a.target, obs.key, det.p_body, det.cov_body, weight)
                    self._counts["detections_folded"] += 1
                    continue
                delta = det.t - state.t  # nonzero only for unsynchronised senders (time_merge_s)
                z, cov = det.p_body, det.cov_body
                if delta != 0.0 and tr is not None:
                    z = z - R_obs.T @ tr.x[3:] * delta
                    cov = cov + R_obs.T @ tr.P[3:, 3:] @ R_obs * delta**2
                batch.append((obs.key, state, z, cov, weight))
        return batch

    def _look(self, m: VehiclePrior, t: float, pose: np.ndarray, p_map: np.ndarray) -> None:
        """What ``m``'s sender should see of the tracks that one other vehicle alone reports (ghost check),
        the tracks as they were at the cycle's start, moved to ``t``. Only those within the ghost range
        (plus the occlusion corridor's width) can be looked at or hide one."""
        ids, x, ts, sole = self._lookable
        p = x[:, :2] + x[:, 3:5] * (t - ts)[:, None]
        near = np.hypot(p[:, 0] - pose[0], p[:, 1] - pose[1]) <= self.params.ghost_range_m + 2.0
        look = np.flatnonzero(near & (sole != "") & (sole != m.sender))
        if not len(look):
            return
        vids, where, _ = self._reported(t)
        occluders = np.vstack([where[vids != m.sender, :2], p[near]])
        tracks = [(int(ids[i]), str(sole[i])) for i in look]
        pose_cov = sym_from_upper(np.asarray(m.pose_cov, dtype=float))
        self.monitor.look(m.sender, t, pose, pose_cov, p_map, tracks, p[look], occluders)

    def _reported(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_vehicle_candidates` at t as arrays (ids, positions, covariances), cached with them."""
        out = self._reported_at.get(t)
        if out is None:
            cands = self._vehicle_candidates(t)
            out = self._reported_at[t] = (
                np.array([v.vid for v in cands], dtype=str),
                np.array([v.p_map for v in cands]).reshape(-1, 3),
                np.array([v.cov for v in cands]).reshape(-1, 3, 3),
            )
        return out

    def _vehicle_candidates(self, t: float) -> list[VehicleCandidate]:
        """Every connected vehicle's reported position at t (its nearest frame, moved with its v_map),
        for gating detections of connected vehicles; cached per instant within a cycle."""
        out = self._candidates.get(t)
        if out is not None:
            return out
        out = []
        for vid, chain in self.graph.vehicles.items():
            s = chain.nearest(t, self.params.vehicle_gate_max_dt_s)
            if s is None:
                continue
            dt = t - s.t
            cov = s.cov[:3, :3] + (self.params.vehicle_velocity_sigma_mps * dt) ** 2 * np.eye(3)
            out.append(VehicleCandidate(vid, s.pose[:3] + s.v_map * dt, cov))
        self._candidates[t] = out
        return out

    def _cross_detections(self, t_min: float) -> None:
        """Tie detections of connected vehicles to the observed vehicle's pose at (about) the same time.

        A detection waits (up to the window) for the observed vehicle's message of its instant, which
        may arrive later than the observer's. The observed vehicle moved v * delta between its frame and
        the detection; that is taken out of the detection and its uncertainty added.
        """
        waiting, items = [], []
        for vid, det in self._cross:
            if det.t < t_min:
                self._counts["cross_no_state"] += 1
                continue
            obs = self.graph.vehicle_state(det.sender, det.t, 0.0)
            if obs is None:
                self._counts["observer_gone"] += 1
                continue
            target = self.graph.vehicle_state(vid, det.t, self.params.cross_obs_max_dt_s)
            if target is None:
                waiting.append((vid, det))
                continue
            R_obs = obs.M[:3, :3]
            delta = det.t - target.t
            z = det.p_body - R_obs.T @ target.v_map * delta
            cov = det.cov_body + (self.params.vehicle_velocity_sigma_mps * delta) ** 2 * np.eye(3)
            if vid in self._bias_sigma:  # the detection sees the body; the graph's pose is the camera's
                S_b = bias_cov(self._bias_sigma[vid], float(target.pose[5]))[:3, :3]
                cov = cov + R_obs.T @ S_b @ R_obs
            items.append((obs.key, target.key, z, cov))
        self.graph.add_cross_detections(items)
        self._counts["cross_detections"] += len(items)
        self._cross = waiting

    def _output(self, t: float) -> FusedState:
        """The fused state at t: every vehicle's newest pose and every confirmed track's newest state,
        predicted to t with constant velocity (vehicles: the reported v_map and the motion factor's
        noise; tracks: the WNOA model), so that V2X latency does not leave them behind."""
        g = self.graph
        vids = sorted(g.vehicles)
        poses, pose_covs = [], []
        pp = self.params
        for vid in vids:
            ts, T, cov_xi = g.vehicle_estimate(vid)
            pose = vector_from_pose3(T)
            if cov_xi is None:
                cov = g.vehicles[vid].latest().cov
            else:
                cov = pose_cov_from_tangent(pose, cov_xi)
            pose, cov = vehicle_at(pose, cov, g.vehicles[vid].latest().v_map, t - ts, pp)
            if vid in self._bias_sigma:  # the body is off the pose its camera sees by this
                cov = cov + bias_cov(self._bias_sigma[vid], float(pose[5]))
            poses.append(pose)
            pose_covs.append(cov)
        ids, cls, dts, xs, Cs = [], [], [], [], []
        for tid, tr in sorted(self.tracker.confirmed().items()):
            if tid not in g.tracks or len(ids) >= MAX_OBJECTS:
                continue
            ts, p, v, C = g.track_estimate(tid)
            ids.append(tid)
            cls.append(tr.cls)
            dts.append(t - ts)
            xs.append(np.concatenate([p, v]))
            Cs.append(tr.P if C is None else C)
        ps, covs, vs = np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3))
        if ids:
            q = np.array([accel_psd(self.params, c) for c in cls])
            x, P = cv_predict(np.array(xs), np.array(Cs), np.array(dts), q)
            ps, covs, vs = x[:, :3], P[:, :3, :3], np.array(xs)[:, 3:]
        self._seq += 1
        return fused_state(
            self.fleet,
            self.host_id,
            self._seq,
            t,
            vids,
            poses,
            pose_covs,
            ids,
            cls,
            ps,
            vs,
            covs,
            sum(len(c.tkeys) for c in g.vehicles.values()),
            sorted(self.monitor.flagged),
        )

    # ------------------------------------------------------------------ health
    def stats(self) -> dict:
        """Counters and figures of the last cycle (for health status and benchmarks)."""
        last = self._last
        tracks = list(self.tracker.tracks.values())
        return {
            "received": self._counts["received"],
            "accepted": self._counts["accepted"],
            "rejected": dict(self._rejected),
            "pending": len(self.buffer),
            "expired": self._counts["expired"],
            "fused_cycles": self._counts["fused_cycles"],
            "last_iterations": last.iterations if last else 0,
            "last_error_before": last.error_before if last else float("nan"),
            "last_error_after": last.error_after if last else float("nan"),
            "last_cycle_ms": self._last_cycle_ms,
            "last_phases_ms": dict(self._last_phases_ms),
            "cliques_below_root": last.cliques_below_root if last else 0,
            "reweighted": last.reweighted if last else 0,
            "factors": self.graph.num_factors,
            "variables": self.graph.num_variables,
            "vehicles": len(self.graph.vehicles),
            "tracks_confirmed": sum(tr.confirmed for tr in tracks),
            "tracks_tentative": sum(not tr.confirmed for tr in tracks),
            "association": dict(self.tracker.counts),
            "detections": self._counts["detections"],
            "detections_folded": self._counts["detections_folded"],
            "cross_detections": self._counts["cross_detections"],
            "cross_no_state": self._counts["cross_no_state"],
            "observer_gone": self._counts["observer_gone"],
            "duplicate_instant": self._counts["duplicate_instant"],
            "too_close": self._counts["too_close"],
            "flagged": dict.fromkeys(sorted(self.monitor.flagged), 1.0),
            "flagged_why": dict(sorted(self.monitor.flagged.items())),
            "flagged_total": self.monitor.flagged_total,
            "detections_of_flagged": self._counts["detections_of_flagged"],
            "tracks_denied": self._counts["tracks_denied"],
        }
