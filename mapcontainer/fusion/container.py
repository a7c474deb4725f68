"""The host container: validate -> reorder -> associate -> factor graph -> fused state (paper §III-D).

A pure core: no I/O, no threads, time is an argument, deterministic for a given input sequence.
The live host service and ``pipeline.py`` feed it bytes with :meth:`Container.ingest` and ask for the
fused driving environment with :meth:`Container.fuse`.

``ingest_prior`` takes an already-decoded prior. (The centralized mode's host is
:class:`~.joint.JointHost`.)
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from schemas import FusedState, VehiclePrior, bias_cov
from schemas.models import MAX_OBJECTS

from .association import Assignment, Tracker, VehicleCandidate
from .graph import FusionGraph
from .hostcore import (
    IngestResult,
    Intake,
    common_stats,
    cross_observation,
    detections_in_map,
    fused_state,
    observer_biases,
    observer_weights,
    persistent_share,
    vehicle_at,
    vehicle_candidate,
)
from .laps import Laps
from .misbehaviour import MisbehaviourMonitor
from .motion import accel_psd, cv_predict
from .params import FusionParams
from .poses import pose_cov_from_tangent, sym_from_upper, vector_from_pose3
from .solver import SolveReport

__all__ = ["Container", "FusionParams", "IngestResult"]


def _sole_source(frames: dict, since: float) -> str:
    """The one sender of a track's detections (``Track.frames``: (sender, time key) -> t) since ``since``,
    or "" if none or several did; stops at the second (most tracks are seen by several)."""
    sole = ""
    for (sender, _), t in frames.items():
        if t >= since and sender != sole:
            if sole:
                return ""
            sole = sender
    return sole


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
        self.intake = Intake(VehiclePrior, params, fleet, known_senders, self._buffered)
        self.graph = FusionGraph(params)
        self.tracker = Tracker(params)
        self._counts: Counter[str] = Counter()
        self._cross: list = []  # (observed vehicle id, Detection) waiting for that vehicle's frame
        # vid -> body-frame 1-sigmas of the error its every frame repeats (VehiclePrior.pose_bias_sigma)
        self._bias_sigma: dict[str, np.ndarray] = {}
        # (vid, t_meas) -> (protection levels, integrity risk) of the frames in the window that claim integrity
        self._protection: dict[tuple[str, float], tuple[np.ndarray, float]] = {}
        # (vid, t_meas) -> whether its heading is known within a linear model, of the frames in the window whose
        # sender was not map matching (GNSS fallback, searching)
        self._unmatched: dict[tuple[str, float], bool] = {}
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
        return self.intake.ingest(payload, t_recv)

    def ingest_prior(self, prior: VehiclePrior, t_recv: float) -> IngestResult:
        """Buffer an already-decoded prior."""
        return self.intake.take(prior, t_recv)

    def _buffered(self, msg: VehiclePrior, t_recv: float, reason: str | None) -> None:
        if self.params.misbehaviour:
            self.monitor.message(msg.sender, float(msg.t_meas), t_recv, reason)

    # ------------------------------------------------------------------ fusion
    def fuse(self, t: float, tolerance_s: float = 0.0) -> FusedState:
        """Fuse everything received with t_meas <= t + tolerance_s within the window; the state at time t.

        ``tolerance_s``: the frame's messages lie within this of t (``FrameGate.tolerance_s``: the vehicles'
        clocks are a few ms apart); a vehicle whose frame is stamped after t is predicted back to t.
        """
        laps = Laps()
        t = float(t)
        t_min = t - self.params.window_s
        fresh = self.intake.pop(t, tolerance_s)
        keys = []
        for m in fresh:  # all poses first, so that detections can be matched to any vehicle of the instant
            key = self.graph.add_vehicle_prior(
                m.sender, m.t_meas, m.pose, sym_from_upper(m.pose_cov), m.v_map, filtered=m.pose_filtered
            )
            if m.pose_bias_sigma is None:
                self._bias_sigma.pop(m.sender, None)
            else:
                self._bias_sigma[m.sender] = np.asarray(m.pose_bias_sigma, dtype=float)
            if m.protection_level_m is not None:  # the vehicle claims integrity for this frame
                self._protection[(m.sender, float(m.t_meas))] = (np.asarray(m.protection_level_m), m.integrity_risk)
            if m.quality.mode != "map_matching":
                yaw_var = sym_from_upper(np.asarray(m.pose_cov, dtype=float))[5, 5]
                self._unmatched[(m.sender, float(m.t_meas))] = yaw_var <= self.params.observer_yaw_sigma_max_rad**2
            if key is None:
                self._counts["duplicate_instant"] += 1
            keys.append(key)
        self._protection = {k: v for k, v in self._protection.items() if k[1] >= t_min}
        self._unmatched = {k: v for k, v in self._unmatched.items() if k[1] >= t_min}
        self._candidates: dict[float, list[VehicleCandidate]] = {}  # all poses of the cycle are in
        self._reported_at: dict[float, tuple] = {}
        if self.params.misbehaviour:  # the tracks one vehicle alone reported in the window (ghost check)
            ids, xs, ts, sole = [], [], [], []
            since = t - self.params.misbehaviour_window_s
            for tid, tr in self.tracker.confirmed().items():
                ids.append(tid)
                xs.append(tr.x)
                ts.append(tr.t)
                sole.append(_sole_source(tr.frames, since))
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
        out = self._output(t, tolerance_s)
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
        t = float(m.t_meas)
        pose = np.asarray(m.pose, dtype=float)
        pose_cov = sym_from_upper(np.asarray(m.pose_cov, dtype=float))
        mapped = detections_in_map(m.sender, t, m.objects, pose, pose_cov, self.params, self._counts)
        if mapped is None:
            return []
        dets, p_map = mapped.dets, mapped.p_map
        if self.params.misbehaviour:
            self.monitor.observe(m.sender, t, p_map, mapped.S_map, mapped.cls, self._reported(t))
            self._look(m, t, pose, p_map)
            if m.sender in self.monitor.flagged:  # its detections would carry its error into everyone's picture
                self._counts["detections_of_flagged"] += len(p_map)
                return []
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
        assignments, born = self.tracker.associate(dets, vehicles)
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
                share = self._observer_share(a, born)
                self._counts["detections_considered"] += share is None
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
                batch.append((obs.key, state, z, cov, weight, share))
        return batch

    def _observer_share(self, a: Assignment, born: list[int]) -> float | None:
        """How much the detection of a track in ``a`` may tell about its observer's pose: the share of its
        information the graph takes (its factor ties the observer's pose to the track, so a wrong association
        drags the observer), or None: none, a *consider* detection (:mod:`.detections`: it moves the track,
        with the observer's reported pose uncertainty in its noise, never the observer).

        A map-matched observer: all of it. An observer that is not (GNSS fallback, searching: a GNSS-grade
        pose, with which the assignment was made), the association's probability ``Assignment.p`` (its JPDA
        marginal against the other gated candidates, clutter and the objects not yet tracked): each detection
        counts for the observer's pose as much as it is of that track, as in EM data association. None where
        there is no such probability or no model for it: a detection held by the track while it was tentative
        (``born``: confirmed by this message, never tested against the track), or by an observer whose
        reported heading is too uncertain for the linear model of the factor (yaw 1-sigma above
        ``observer_yaw_sigma_max_rad``: a vehicle searching for its start does not know its heading;
        linearized there, even a small share of a detection moves it metres). (Detections of a track only the
        observer saw tie it to its own earlier placements, as for every vehicle: "a vehicle's own echo",
        docs/host.md.)

        Traced (paper-urban, seed 0, the default fleet's first run): cv2, searching with a GNSS fix 4 m off
        and a yaw sigma of 1.8 rad, had its detections placed in the map 25-60 m wide and assigned to
        whatever track was in the gate (p of a few per cent, and 1 for the held ones); taken whole, they
        fused it 10-41 m off with sigma 1-2 m (NEES up to 868) for its first 1.8 s, and cv1 9-22 m off for
        its first 0.3 s."""
        heading_known = self._unmatched.get((a.det.sender, a.det.t))
        if heading_known is None:  # map matched
            return 1.0
        tr = self.tracker.by_id(a.target)
        if not heading_known or a.target in born or tr is None:
            return None
        return a.p

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
            pl = self._protection.get((vid, float(s.t)))
            prot = None if pl is None else (float(s.pose[5]), *pl)
            out.append(
                vehicle_candidate(vid, s.pose[:3], s.cov[:3, :3], s.v_map, t - s.t, self.params, protection=prot)
            )
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
            S_b = None
            if vid in self._bias_sigma:  # the detection sees the body; the graph's pose is the camera's
                S_b = bias_cov(self._bias_sigma[vid], float(target.pose[5]))[:3, :3]
            z, cov = cross_observation(det, obs.M[:3, :3], target.v_map, det.t - target.t, self.params, S_b)
            items.append((obs.key, target.key, z, cov))
        self.graph.add_cross_detections(items)
        self._counts["cross_detections"] += len(items)
        self._cross = waiting

    def _output(self, t: float, tolerance_s: float) -> FusedState:
        """The fused state at t: every vehicle's newest pose and every confirmed track's newest state,
        predicted to t with constant velocity (vehicles: the reported v_map and the motion factor's
        noise; tracks: the WNOA model), so that V2X latency does not leave them behind. A vehicle's frame
        of the instant itself (within ``tolerance_s``: stamped by another clock) is not moved
        (:func:`.hostcore.vehicle_at`)."""
        g = self.graph
        vids = sorted(g.vehicles)
        poses, pose_covs = [], []
        pp = self.params
        seen_from: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # vid -> (pose, S_b): an observer's repeated error
        for vid in vids:
            ts, T, cov_xi = g.vehicle_estimate(vid)
            pose = vector_from_pose3(T)
            S_b = bias_cov(self._bias_sigma[vid], float(pose[5])) if vid in self._bias_sigma else np.zeros((6, 6))
            seen_from[vid] = (pose, S_b)
            if cov_xi is None:
                cov = g.vehicles[vid].latest().cov
            else:
                cov = pose_cov_from_tangent(pose, cov_xi)
            pose, cov = vehicle_at(pose, cov, g.vehicles[vid].latest().v_map, t - ts, pp, tolerance_s)
            if vid in self._bias_sigma:  # the body is off the pose its camera sees by this
                cov = cov + bias_cov(self._bias_sigma[vid], float(pose[5]))
            poses.append(pose)
            pose_covs.append(cov)
        ids, cls, dts, xs, Cs, seen = [], [], [], [], [], []
        f = persistent_share(pp)
        for tid, tr in sorted(self.tracker.confirmed().items()):
            if tid not in g.tracks or len(ids) >= MAX_OBJECTS:
                continue
            ts, p, v, C = g.track_estimate(tid)
            ids.append(tid)
            cls.append(tr.cls)
            dts.append(t - ts)
            xs.append(np.concatenate([p, v]))
            Cs.append(tr.P if C is None else C)
            w = observer_weights(tr.frames, t - pp.window_s)
            seen.append([(o, w[o], f * tr.det_cov[o] if o in tr.det_cov else None) for o in w if o in seen_from])
        ps, covs, vs = np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3))
        if ids:
            Cs = np.array(Cs, dtype=float)
            Cs[:, :3, :3] += observer_biases(np.array(xs)[:, :3], seen, seen_from)
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

    # ------------------------------------------------------------------ downlink
    def downlink(self, t_sent: float, seq0: int) -> list:
        """What the others know about each vehicle's newest frame, its own prior removed (:mod:`..downlink`):
        PoseDownlink messages numbered from ``seq0``, sent at ``t_sent``."""
        from ..downlink import downlink_messages

        return downlink_messages(self.graph, self.fleet, self.host_id, t_sent, seq0)

    # ------------------------------------------------------------------ health
    def stats(self) -> dict:
        """Counters and figures of the last cycle (for health status and benchmarks)."""
        last = self._last
        return {
            **common_stats(self.intake, self.tracker, self._counts, len(self.graph.vehicles), self._last_cycle_ms),
            "last_iterations": last.iterations if last else 0,
            "last_error_before": last.error_before if last else float("nan"),
            "last_error_after": last.error_after if last else float("nan"),
            "last_phases_ms": dict(self._last_phases_ms),
            "cliques_below_root": last.cliques_below_root if last else 0,
            "reweighted": last.reweighted if last else 0,
            "factors": self.graph.num_factors,
            "variables": self.graph.num_variables,
            "detections_folded": self._counts["detections_folded"],
            "detections_considered": self._counts["detections_considered"],
            "observer_gone": self._counts["observer_gone"],
            "duplicate_instant": self._counts["duplicate_instant"],
            "flagged": dict.fromkeys(sorted(self.monitor.flagged), 1.0),
            "flagged_why": dict(sorted(self.monitor.flagged.items())),
            "flagged_total": self.monitor.flagged_total,
            "detections_of_flagged": self._counts["detections_of_flagged"],
            "tracks_denied": self._counts["tracks_denied"],
        }
