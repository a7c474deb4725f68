"""The centralized host: one joint estimator over every vehicle's raw observations (the paper's centralized
architecture, the accuracy reference the distributed one is measured against).

Vehicles send RawObservations (camera features, lane mask, GNSS, odometry, object detections). The host
holds one Gaussian over everything: each vehicle's localizer state y_v (10: the pose as its camera sees
the map, wheel-speed scale, gyro bias, GNSS receiver bias; :mod:`mapcontainer.localization.ekf`) and
each confirmed track's [p, v], one mean and one covariance with every cross-covariance. A frame of
vehicle v is processed in two steps, in time order:

1. Self-localization, by the same :class:`~mapcontainer.localization.Localizer` a vehicle runs, started
   from the joint marginal of y_v (so its matcher associates and solves from everything the host knows,
   the other vehicles' observations included). Its updates (camera, GNSS, ground constraint) involve y_v
   only, so the joint posterior is exact given its result: with the prediction (F, y_pred, P_pred) the
   localizer conditioned on (``Localizer.conditioned``) and its posterior (y+, P+), every other block o
   moves with the prior's conditional: K = P_ov P_pred^-1, mu_o += K (y+ - y_pred),
   P_oo += K (P+ - P_pred) K^T, P_ov = K P+ (no information is counted twice, none is dropped). When the
   localizer did not condition on that prediction (start-up, a reset, a search hypothesis) its state
   replaces the block, uncorrelated with the rest.
2. Detections: associated by the distributed host's :class:`~.association.Tracker` (same gates, births,
   confirmation, merging and expiry) from the joint estimates; each detection of a confirmed track and
   each cross-observation of another vehicle is an extended Kalman update of the exact Cartesian model
   z = R_v^T (p - c_v) in the observer's body frame, on the observer's pose and the target jointly.

So every measurement enters once, linearized at the current joint estimate, and the vehicles' poses gain
what the objects and the other vehicles tell about them from then on (the distributed vehicle's filter
never sees that).

A vehicle whose localizer is not map matching (GNSS fallback, searching) is a *consider* state of the
detection updates (Schmidt-Kalman: its rows of the gain are zero, the covariance update is Joseph's, exact
for that gain): its detections and the detections of the tracks it saw move the tracks, with its
uncertainty in their covariance and cross-covariance, but never its own block. Traced (suburban
development seed 1004): a vehicle in fallback 5 m off (GNSS multipath) saw the parked cars the other
vehicles saw; through the tracks they shared, their GNSS fixes and detections shrank its sigma from 2.7 to
1.25 m and then, once another vehicle map-matched, to 0.25 m, error unchanged (its detections were of the
neighbouring cars, 5-6 m apart); its localizer, re-seeded from that block, locked its map matching on a
wrong basin (11 m off, NEES 1,899). A GNSS-grade pose is not one to resolve detection associations with,
unless the association is sure: a frame of such a vehicle updates its pose as any other only if each of its
detections of a track is of that track with probability at least ``vehicle_association_probability`` (the
tracker's JPDA marginal against the other gated candidates, false alarms and objects not yet tracked,
:meth:`~.association.Tracker.untracked_density`) and another vehicle saw the track (counted otherwise as
``detections_ambiguous``). A lone track in the gate is not enough: traced (suburban development seed 1006),
a vehicle 0.9 m off with sigma 1.9 m saw, in its first frame with detections, an object nobody tracked yet
7.5 m from a confirmed track alone in its gate (d2 1.5); that one update moved it 3.6 m onto the wrong
object with sigma 0.6 m, and its localizer, started from that, locked 10 m off (RMSE 8.2 m, NEES 1,337).
With the density of objects around it that no track explains, that detection is the track's with
probability 0.3. So its block holds what its own localizer measured and what its sure detections add, and
the localizer started from it is not re-seeded tighter than that evidence; from its first map-matched frame
it gains from everything again. Suburban development seeds (centralized, vehicle RMSE m / ANEES):
see docs/host.md, "The centralized reference".

Approximations, each stated: a filter, not a smoother (a measurement is linearized once);
a newly confirmed track starts from the frame's detection of it, correlated with its observer as a
landmark in EKF-SLAM (the earlier held detections give only its velocity), and a merged track's
information goes with it; a frame older than its vehicle's newest is refused (``out_of_order``), one older
than another vehicle's is taken, the tracks predicted back to it; a cross-observation uses the observed
vehicle's newest state moved by its velocity. The error every frame of a vehicle repeats
(``LocalizerParams.match_bias_sigma``) is added to its output pose's covariance as the vehicle does, and
to cross-observations of it.

Bad input: a detection's covariance is floored at 5 cm, detections far from their prediction are
down-weighted (Huber, ``FusionParams.huber_k``, as the distributed graph), an update that fails
numerically is refused (the state stays as it was before it) and counted, a localizer that fails starts
that vehicle again. The distributed host's misbehaviour monitor is not run here: a vehicle forging its raw
observations is not contained.

Cost (docs/host.md, "Centralized speed"): each update touches the columns its Jacobian is nonzero on; the
covariance is dense, so a frame's update is one rank-2m change of it, O(n^2 m) for a state of size n and
m detection rows.
"""

from __future__ import annotations

import time
from collections import Counter

import numpy as np

from schemas import FusedState, RawObservations, bias_cov
from schemas.models import MAX_OBJECTS

from .. import geometry as geo
from ..hdmap.model import HDMap
from ..localization import Localizer, LocalizerParams
from ..vehicle import camera_frame
from .association import Detection, Tracker, VehicleCandidate
from .buffer import time_key
from .hostcore import (
    IngestResult,
    Intake,
    common_stats,
    cross_observation,
    detections_in_map,
    fused_state,
    observer_bias,
    observer_weights,
    persistent_share,
    vehicle_at,
    vehicle_candidate,
)
from .motion import accel_psd, cv_model, cv_predict
from .params import FusionParams
from .symupdate import sym_rank_update

__all__ = ["JointHost"]

_V = 10  # a vehicle's block: the localizer's state
_O = 6  # a track's block: [p, v]
# A detection's covariance is floored at this 1-sigma (m) in every direction: a sender reporting
# millimetres cannot pin the joint state (no detector of ours is better than a few centimetres).
_MIN_DETECTION_SIGMA_M = 0.05


def _floored(C: np.ndarray) -> np.ndarray:
    """Covariances (..., 3, 3) with eigenvalues at least _MIN_DETECTION_SIGMA_M^2."""
    w, U = np.linalg.eigh(0.5 * (C + np.swapaxes(C, -1, -2)))
    return (U * np.maximum(w, _MIN_DETECTION_SIGMA_M**2)[..., None, :]) @ np.swapaxes(U, -1, -2)


class JointHost:
    """The centralized host's core (module docstring): ``ingest`` RawObservations bytes, ``fuse`` at t."""

    def __init__(
        self,
        hdmap: HDMap,
        params: FusionParams,
        fleet: str,
        host_id: str,
        known_senders: set[str] | None = None,
        localizer_params: LocalizerParams | None = None,
        idle_s: float = 30.0,
    ):
        """``idle_s``: a sender silent for this long (scenario time) is forgotten, its localizer and state
        with it (a host without a list of known senders would otherwise keep one for every name it saw);
        if it comes back it starts afresh."""
        self.hdmap = hdmap
        self.params = params
        self.fleet = fleet
        self.host_id = host_id
        self.loc_params = localizer_params or LocalizerParams()
        self.idle_s = idle_s
        self.intake = Intake(RawObservations, params, fleet, known_senders)
        self.tracker = Tracker(params)
        self.localizers: dict[str, Localizer] = {}
        self._results: dict = {}  # vid -> its localizer's last LocalizationResult
        self.mu = np.zeros(0)
        self.P = np.zeros((0, 0))
        self._keys: list[tuple[str, object]] = []  # blocks in state order: ("v", vid) or ("o", track id)
        self._t: dict[tuple[str, object], float] = {}  # each block's time
        self._off: dict[tuple[str, object], int] = {}
        self._counts: Counter[str] = Counter()
        self._seq = 0
        self._cycle_frames = 0
        self._last_cycle_ms = float("nan")
        self._phases: Counter[str] = Counter()  # this cycle's wall time (ms) by phase

    # ------------------------------------------------------------------ input
    def ingest(self, payload: bytes, t_recv: float) -> IngestResult:
        """Decode and buffer one RawObservations payload received at ``t_recv``. Never raises on bad input."""
        return self.intake.ingest(payload, t_recv)

    # ------------------------------------------------------------------ state blocks
    def _size(self, key) -> int:
        return _V if key[0] == "v" else _O

    def _reindex(self) -> None:
        off = 0
        self._off = {}
        for k in self._keys:
            self._off[k] = off
            off += self._size(k)

    def _sl(self, key) -> slice:
        o = self._off[key]
        return slice(o, o + self._size(key))

    def _set_block(self, key, x: np.ndarray, C: np.ndarray, t: float) -> None:
        """Put a block (new or replaced) with mean x and covariance C, uncorrelated with the rest."""
        if key in self._off:
            s = self._sl(key)
            self.P[s, :] = 0.0
            self.P[:, s] = 0.0
        else:
            n = len(self.mu)
            self._keys.append(key)
            self._off[key] = n
            m = self._size(key)
            self.mu = np.concatenate([self.mu, np.zeros(m)])
            P = np.zeros((n + m, n + m))
            P[:n, :n] = self.P
            self.P = P
            s = self._sl(key)
        self.mu[s] = x
        self.P[s, s] = 0.5 * (C + C.T)
        self._t[key] = float(t)

    def _drop(self, *keys) -> None:
        """Remove blocks (those not held are skipped): one copy of the state for all of them."""
        keys = [k for k in keys if k in self._off]
        if not keys:
            return
        keep = np.ones(len(self.mu), dtype=bool)
        for k in keys:
            keep[self._sl(k)] = False
            self._keys.remove(k)
            del self._t[k]
        self.mu = self.mu[keep]
        self.P = self.P[keep][:, keep]
        self._reindex()

    # ------------------------------------------------------------------ fusion
    def fuse(self, t: float, tolerance_s: float = 0.0) -> FusedState:
        """Process every frame received with t_meas <= t + tolerance_s (in time order); the state at t."""
        t_start = time.perf_counter()
        self._phases = Counter()
        t = float(t)
        fresh = self.intake.pop(t, tolerance_s)
        by_instant: dict[int, list[RawObservations]] = {}
        for m in fresh:
            by_instant.setdefault(time_key(m.t_meas), []).append(m)
        self._cycle_frames = 0
        for tk in sorted(by_instant):
            frames = [m for m in by_instant[tk] if self._localize(m)]
            self._cycle_frames += len(frames)
            cross: list[tuple[str, Detection]] = []
            for m in frames:
                self.tracker.observe(m.t_meas)
                cross += self._detections(m)
            t1 = time.process_time()
            self._cross_updates(cross)
            self._lap("cross", t1)
        t1 = time.process_time()
        self._sync_tracker()
        gone = self.tracker.expire(t) + self.tracker.merge_duplicates(t)
        gone += self.tracker.vehicle_shadows(t, self._vehicle_candidates(t))  # as the distributed host
        self._drop(*(("o", tid) for tid in gone))
        self._counts["fused_cycles"] += 1
        self._lap("upkeep", t1)
        t1 = time.process_time()
        out = self._output(t, tolerance_s)
        self._lap("output", t1)
        self._last_cycle_ms = (time.perf_counter() - t_start) * 1e3
        return out

    def _lap(self, phase: str, c0: float) -> None:
        """Add the CPU time since ``c0`` (time.process_time) to this cycle's ``phase``: CPU, not wall, so
        that the shares hold on a loaded machine."""
        self._phases[phase] += (time.process_time() - c0) * 1e3

    def _failed(self) -> bool:
        """Count an update refused for failing numerically (a singular innovation, a gain that is not
        finite): the state stays as it was before it."""
        self._counts["numerical_failure"] += 1
        return False

    def _wrap_yaws(self) -> None:
        for key in self._keys:
            if key[0] == "v":
                i = self._off[key] + 5
                self.mu[i] = geo.wrap_angle(self.mu[i])

    def _localize(self, raw: RawObservations) -> bool:
        """Step 1 of the module docstring for one frame; False if the frame is refused."""
        vid, t = raw.sender, float(raw.t_meas)
        for gone in [v for v, lc in self.localizers.items() if lc.t_prev is None or lc.t_prev < t - self.idle_s]:
            del self.localizers[gone]
            self._results.pop(gone, None)
            self._drop(("v", gone))
        try:
            frame = camera_frame(raw)
        except ValueError:  # e.g. a lane mask that is not an image
            self.intake.reject("invalid")
            return False
        loc = self.localizers.get(vid)
        if loc is None:
            loc = self.localizers[vid] = Localizer(self.hdmap, self.loc_params)
        if loc.t_prev is not None and t <= loc.t_prev:
            self.intake.reject("out_of_order")
            return False
        key = ("v", vid)
        held = key in self._off and loc.initialized
        if held:  # the localizer starts from everything the host knows of this vehicle
            s = self._sl(key)
            loc.y, loc.P = self.mu[s].copy(), self.P[s, s].copy()
        t0 = time.process_time()
        try:
            res = loc.step(t, frame, raw.odometry, raw.gnss)
        except (ValueError, np.linalg.LinAlgError):  # numerically broken: that vehicle starts again
            loc.reset()
            self._drop(key)
            self._counts["localizer_failure"] += 1
            return False
        finally:
            self._lap("localize", t0)
        t0 = time.process_time()
        if res.bad_input:
            self.intake.reject("bad_input")
            return False
        self._results[vid] = res
        self._counts["frames"] += 1
        if not loc.initialized:
            self._drop(key)
        elif held and loc.conditioned is not None and self._condition(key, *loc.conditioned, loc.y, loc.P):
            self._t[key] = t
        else:
            self._set_block(key, loc.y, loc.P, t)
            self._counts["vehicle_reseeded"] += 1
        self._lap("condition", t0)
        return True

    def _condition(self, key, F, y_pred, P_pred, y_post, P_post) -> bool:
        """The joint posterior of a vehicle's prediction F and its localizer's update (module docstring);
        False (counted, the state unchanged) if it fails numerically.

        With K = P_ov F^T P_pred^-1 over every row (zero on the vehicle's own): mu += K d,
        P += K (P_post - P_pred) K^T, then the vehicle's rows and columns K P_post and P_post: one rank-10
        update of the covariance, O(n^2) for a state of size n."""
        s = self._sl(key)
        P = self.P
        G = P[:, s] @ F.T  # (n, 10): P_ov F^T on the other rows
        G[s] = 0.0
        try:
            K = np.linalg.solve(P_pred, G.T).T  # P_pred symmetric
        except np.linalg.LinAlgError:
            return self._failed()
        d = y_post - y_pred
        d[5] = geo.wrap_angle(d[5])
        P_ov = K @ P_post
        finite = (np.all(np.isfinite(a)) for a in (K, P_ov, y_post, P_post))
        if not all(finite):
            return self._failed()
        self.mu += K @ d
        self.mu[s] = y_post
        P += (K @ (P_post - P_pred)) @ K.T
        P[:, s] = P_ov
        P[s, :] = P_ov.T
        P[s, s] = 0.5 * (P_post + P_post.T)
        self._wrap_yaws()
        return True

    def _predict_tracks(self, t: float) -> None:
        """Every track block to time t (constant velocity, white acceleration), with its cross-covariances.

        F = I + dt E (E moves a track's velocity onto its position) on all the tracks at once, per lag dt:
        the position rows of F P are R = P[p] + dt P[v]; those of F P F^T are R with R[:, p] += dt R[:, v],
        and its position columns their transpose (P symmetric); then Q on each track's block. O(n) per track,
        in contiguous rows."""
        keys = [k for k in self._keys if k[0] == "o" and self._t[k] != t]
        if not keys:
            return
        dts = np.array([t - self._t[k] for k in keys])
        off = np.array([self._off[k] for k in keys])
        q = np.array([accel_psd(self.params, tr.cls if (tr := self.tracker.by_id(k[1])) else 0) for k in keys])
        _, Q = cv_model(dts, q)
        P, mu = self.P, self.mu
        for dt in np.unique(dts):
            o = off[dts == dt]
            ip = (o[:, None] + np.arange(3)).ravel()
            iv = ip + 3
            mu[ip] += dt * mu[iv]
            R = P[ip] + dt * P[iv]
            R[:, ip] += dt * R[:, iv]
            P[ip] = R
            P[:, ip] = R.T
        for o, Qk in zip(off, Q, strict=True):
            P[o : o + _O, o : o + _O] += Qk
        for k in keys:
            self._t[k] = t

    def _vehicle_candidates(self, t: float, observer: str | None = None) -> list[VehicleCandidate]:
        """Every connected vehicle but ``observer`` (None: every one) as a candidate at t for association."""
        out = []
        for key in self._keys:
            if key[0] != "v" or key[1] == observer:
                continue
            s, dt = self._sl(key), t - self._t[key]
            if abs(dt) > self.params.vehicle_gate_max_dt_s:
                continue
            x = self.mu[s]
            S_b = bias_cov(self.loc_params.match_bias_sigma, float(x[5]))[:3, :3]
            res = self._results[key[1]]
            pl = res.protection_level
            prot = None if pl is None or res.t != self._t[key] else (x[5], pl, self.loc_params.integrity_risk)
            out.append(
                vehicle_candidate(key[1], x[:3], self.P[s, s][:3, :3], res.velocity_map, dt, self.params, S_b, prot)
            )
        return out

    def _detections(self, raw: RawObservations) -> list[tuple[str, Detection]]:
        """Step 2 for one frame's object detections; returns its cross-observations (target vid, detection)."""
        vid, t = raw.sender, float(raw.t_meas)
        key = ("v", vid)
        if len(raw.objects) == 0:
            return []
        if key not in self._off:
            self._counts["detections_unlocalized"] += len(raw.objects)
            return []
        s = self._sl(key)
        pose, pose_cov = self.mu[s][:6], self.P[s, s][:6, :6]
        mapped = detections_in_map(vid, t, raw.objects, pose, pose_cov, self.params, self._counts, _floored)
        if mapped is None:
            return []
        t0 = time.process_time()
        self._predict_tracks(t)
        self._sync_tracker()
        self._lap("predict", t0)
        t0 = time.process_time()
        dets = mapped.dets
        assignments, born = self.tracker.associate(dets, self._vehicle_candidates(t, vid))
        self._lap("associate", t0)
        t0 = time.process_time()
        for tid in born:
            det = next((a.det for a in assignments if a.target == tid and a.det.sender == vid and a.det.t == t), None)
            if det is not None:  # confirmed by this frame's detection (always, as the tracker works)
                self._birth(key, tid, det)
        rows, cross, sure = [], [], True
        for a in assignments:
            if a.kind == "vehicle":
                if self.params.cross_localization:
                    cross.append((a.target, a.det))
            elif a.target not in born and ("o", a.target) in self._off:
                rows.append((("o", a.target), a.det.p_body, a.det.cov_body))
                sure &= self._sure(vid, a)
        self._lap("birth", t0)
        t0 = time.process_time()
        self._counts["detections"] += len(rows)
        if rows and not sure and (res := self._results.get(vid)) is not None and res.mode != "map_matching":
            self._counts["detections_ambiguous"] += 1
        self._ekf_update(key, rows, free=key if sure else None)
        self._lap("update", t0)
        # the tracker is synced again before it is next asked (the next frame's association, the cycle's end)
        return cross

    def _birth(self, obs_key, tid: int, det: Detection) -> None:
        """A newly confirmed track's block from this frame's detection of it, as a landmark is added in
        EKF-SLAM: p = c_v + R_v z with its covariance and its cross-covariances with everything through the
        observer's pose (a track placed from a vehicle's pose is not independent of it: counting it so let
        the vehicle's next detections of it anchor the vehicle to its own past estimate, and a vehicle in
        GNSS fallback drifted metres with a confident covariance). The velocity is the tracker's (its held
        detections), uncorrelated; the earlier detections' position information is left out."""
        so = self._sl(obs_key)
        x_o = self.mu[so]
        R, dR_r, dR_p, dR_y = geo.rpy_to_matrix_jac(*x_o[3:6])
        z = det.p_body
        J = np.zeros((3, _V))
        J[:, :3] = np.eye(3)
        J[:, 3], J[:, 4], J[:, 5] = dR_r @ z, dR_p @ z, dR_y @ z
        tr = self.tracker.by_id(tid)
        x = np.concatenate([x_o[:3] + R @ z, tr.x[3:]])
        C = np.zeros((_O, _O))
        C[:3, :3] = J @ self.P[so, so] @ J.T + R @ det.cov_body @ R.T
        C[3:, 3:] = tr.P[3:, 3:]
        cross = J @ self.P[so, :]  # (3, n) before the block exists
        key = ("o", tid)
        self._set_block(key, x, C, det.t)
        st = self._sl(key)
        n = len(cross[0])
        self.P[st.start : st.start + 3, :n] = cross
        self.P[:n, st.start : st.start + 3] = cross.T

    def _cross_updates(self, cross: list[tuple[str, Detection]]) -> None:
        """Cross-observations of this instant: the observed vehicle's origin from the observer."""
        by_observer: dict[str, list] = {}
        for target, det in cross:
            tkey = ("v", target)
            okey = ("v", det.sender)
            if tkey not in self._off or okey not in self._off:
                self._counts["cross_no_state"] += 1
                continue
            delta = det.t - self._t[tkey]
            if abs(delta) > self.params.cross_obs_max_dt_s:
                self._counts["cross_no_state"] += 1
                continue
            R_obs = geo.rpy_to_matrix(*self.mu[self._sl(okey)][3:6])
            S_b = bias_cov(self.loc_params.match_bias_sigma, float(self.mu[self._sl(tkey)][5]))[:3, :3]
            v = self._results[target].velocity_map
            z, cov = cross_observation(det, R_obs, v, delta, self.params, S_b)
            by_observer.setdefault(det.sender, []).append((tkey, z, cov))
        for observer, rows in by_observer.items():
            self._counts["cross_detections"] += len(rows)
            self._ekf_update(("v", observer), rows)

    def _sure(self, observer: str, a) -> bool:
        """Whether assignment ``a`` of a detection of ``observer`` to a track may correct the observer's pose
        when it is not map matching: the detection is of that track with probability at least
        ``vehicle_association_probability`` (its JPDA marginal against the other gated candidates, clutter
        and objects not yet tracked: ``Tracker.untracked_density``), and another vehicle saw the track (one
        the observer alone saw is its own earlier view, placed with its own pose error)."""
        tr = self.tracker.by_id(a.target)
        return tr is not None and tr.seen_by_other(observer) and a.p >= self.params.vehicle_association_probability

    def _ekf_update(self, obs_key, rows: list, free=None) -> None:
        """One stacked EKF update of detections z_k = R_v^T (c_k - c_v) + n_k, n_k ~ N(0, cov_k), made by
        vehicle ``obs_key`` of targets (track position or another vehicle's origin). An update that fails
        numerically is refused and counted (the state as it was).

        H is nonzero on the observer's pose and the targets' positions only (the columns J): P H^T =
        P[:, J] H_J^T, S = H_J (P H^T)[J] + R. With the gain K (its rows on consider states zero), Joseph's
        form P - K (P H^T)^T - (P H^T) K^T + K S K^T, valid for any gain, is P - (K C^T + C K^T) with
        C = P H^T - K S / 2: one symmetric rank-2m update (BLAS syr2k), O(n^2 m), and O(n m) besides."""
        if not rows:
            return
        m = 3 * len(rows)
        so = self._sl(obs_key)
        x_o = self.mu[so]
        R, dR_r, dR_p, dR_y = geo.rpy_to_matrix_jac(*x_o[3:6])
        tgt = np.array([self._off[tkey] for tkey, _, _ in rows])
        cols = np.concatenate([np.arange(so.start, so.start + 6), (tgt[:, None] + np.arange(3)).ravel()])
        H = np.zeros((m, len(cols)))
        r = np.zeros(m)
        Rn = np.zeros((m, m))
        for k, (_, z, cov) in enumerate(rows):
            d = self.mu[tgt[k] : tgt[k] + 3] - x_o[:3]
            i = slice(3 * k, 3 * k + 3)
            r[i] = z - R.T @ d
            H[i, :3] = -R.T
            H[i, 3] = dR_r.T @ d
            H[i, 4] = dR_p.T @ d
            H[i, 5] = dR_y.T @ d
            H[i, 6 + 3 * k : 9 + 3 * k] = R.T
            Rn[i, i] = cov
        PHt = self.P[:, cols] @ H.T  # (n, m); repeated columns (a target twice) add up as in a full H
        S = H @ PHt[cols] + Rn
        k = self.params.huber_k
        try:
            if k is not None:  # Huber, as the distributed graph: a detection far off its prediction counts less
                for j in range(len(rows)):
                    i = slice(3 * j, 3 * j + 3)
                    d = float(np.sqrt(r[i] @ np.linalg.solve(S[i, i], r[i])))
                    if d > k:
                        S[i, i] += (d / k - 1.0) * Rn[i, i]
            K = np.linalg.solve(S, PHt.T).T
        except np.linalg.LinAlgError:
            self._failed()
            return
        for idx in self._considered(free):  # Schmidt: no gain on them, covariances kept exact for that gain
            K[idx] = 0.0
        C = PHt - 0.5 * (K @ S)
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(C)) and np.all(np.isfinite(r))):
            self._failed()
            return
        P = sym_rank_update(self.P, K, C)
        if not np.all(np.diag(P) > 0):
            self._failed()
            return
        self.P = P
        self.mu += K @ r
        self._wrap_yaws()

    def _considered(self, free=None) -> list[slice]:
        """The blocks of the vehicles whose localizer is not map matching (GNSS fallback, searching), ``free``
        excepted: consider states of the detection updates (module docstring)."""
        return [
            self._sl(k)
            for k in self._keys
            if k[0] == "v" and k != free and (res := self._results.get(k[1])) is not None and res.mode != "map_matching"
        ]

    def _sync_tracker(self) -> None:
        """Hand the tracker every track block's state (it gates, confirms and merges from them)."""
        mu, P, sync = self.mu, self.P, self.tracker.sync
        for key in self._keys:
            if key[0] == "o":
                o = self._off[key]
                sync(key[1], self._t[key], mu[o : o + _O], P[o : o + _O, o : o + _O])

    # ------------------------------------------------------------------ output
    def _output(self, t: float, tolerance_s: float) -> FusedState:
        """Every vehicle and confirmed track at t (constant velocity from its newest state, as the
        distributed container); a vehicle whose localizer has not initialised: its GNSS-grade estimate. A
        vehicle's frame of the instant itself (within ``tolerance_s``: stamped by another clock) is not moved,
        as in the distributed container (:func:`.hostcore.vehicle_at`)."""
        pp = self.params
        vids, poses, covs = [], [], []
        for vid in sorted(self.localizers):
            res = self._results.get(vid)
            if res is None:
                continue
            key = ("v", vid)
            if key in self._off:
                s = self._sl(key)
                pose, cov, ts = self.mu[s][:6].copy(), self.P[s, s][:6, :6].copy(), self._t[key]
                cov += bias_cov(self.loc_params.match_bias_sigma, float(pose[5]))
            else:
                pose, cov, ts = np.asarray(res.pose, float).copy(), np.asarray(res.cov, float).copy(), res.t
            if t - ts > pp.window_s:  # silent for longer than the distributed host keeps a vehicle
                continue
            pose, cov = vehicle_at(pose, cov, res.velocity_map, t - ts, pp, tolerance_s)
            vids.append(vid)
            poses.append(pose)
            covs.append(cov)
        ids, cls, ps, vs, Ps = [], [], [], [], []
        seen_from = {  # every observer's repeated error (its camera's calibration, the map's drift)
            k[1]: (x := self.mu[self._sl(k)][:6], bias_cov(self.loc_params.match_bias_sigma, float(x[5])))
            for k in self._keys
            if k[0] == "v"
        }
        for tid, tr in sorted(self.tracker.confirmed().items()):
            key = ("o", tid)
            if key not in self._off or len(ids) >= MAX_OBJECTS:
                continue
            s = self._sl(key)
            x, C = cv_predict(self.mu[s], self.P[s, s], t - self._t[key], accel_psd(pp, tr.cls))
            w = observer_weights(tr.frames, t - pp.window_s)
            ids.append(tid)
            cls.append(tr.cls)
            ps.append(x[:3])
            vs.append(self.mu[s][3:])
            f = persistent_share(pp)
            seen = [(*seen_from[o], w[o], f * tr.det_cov[o] if o in tr.det_cov else None) for o in w if o in seen_from]
            Ps.append(C[:3, :3] + observer_bias(x[:3], seen))
        self._seq += 1
        frames = self._cycle_frames  # a filter has no window: the frames this cycle took in
        return fused_state(self.fleet, self.host_id, self._seq, t, vids, poses, covs, ids, cls, ps, vs, Ps, frames, [])

    def stats(self) -> dict:
        """Counters and figures (for health status and benchmarks)."""
        vehicles = sum(k[0] == "v" for k in self._keys)
        return {
            **common_stats(self.intake, self.tracker, self._counts, vehicles, self._last_cycle_ms),
            "state_dim": len(self.mu),
            "last_phases_cpu_ms": dict(self._phases),
            "detections_unlocalized": self._counts["detections_unlocalized"],
            "detections_ambiguous": self._counts["detections_ambiguous"],
            "vehicle_reseeded": self._counts["vehicle_reseeded"],
            "numerical_failure": self._counts["numerical_failure"],
            "localizer_failure": self._counts["localizer_failure"],
        }
