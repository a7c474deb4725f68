"""Association of body-frame detections to tracks and connected vehicles, and track management.

Each message's detections are moved to the map frame with the sender's reported pose
(:func:`~.mapframe.observations_to_map`) and compared with (a) the other connected vehicles' reported
positions at t_meas (extrapolated with their v_map) and (b) every live track predicted to t_meas with a
constant-velocity Kalman filter (white-noise acceleration, the same PSDs as the factor graph). The cost is
the Mahalanobis distance

    d^2 = (m - c)^T (S_m + S_c)^-1 (m - c),

gated at chi2_3(gate_probability); incompatible classes are not matched. One Hungarian assignment
(scipy.optimize.linear_sum_assignment) per message solves the frame. A detection matched to a
connected vehicle becomes a cross-localization constraint on that vehicle's pose; one matched to a
confirmed track becomes an observation of it; one matched to a tentative track is held by it; the
rest start tentative tracks. Each assignment carries the probability that the detection is of its target
(JPDA's single-detection marginal against every other gated candidate and against "none of them": false
alarms and objects not yet tracked, :meth:`Tracker.untracked_density`, the density of objects around the
sender that no connected vehicle or shared track explains). A detection of a connected vehicle constrains
that vehicle's pose only if the probability is at least ``vehicle_association_probability``; the
centralized host applies the same test before a detection corrects the pose of an observer that is not map
matching. A tentative track is confirmed (and gets the next stable global id)
once it has detections at ``birth_hits`` distinct instants; its held detections then enter the
graph. Tentative tracks die after ``tentative_timeout_s`` without a detection, counted in measurement
time: from the track's last detection to the newest ``t_meas`` the tracker has been shown
(:meth:`Tracker.observe`), so that V2X latency does not matter (measured against the fuse time, a
latency above the timeout dropped every tentative track before its second detection arrived).
Confirmed tracks die after ``death_s`` without a detection, counted in fuse time (their graph states
leave the window by fuse time); every track also dies that way, so tracks do not outlive senders
that fell silent.

The Kalman filter only gates and initialises; the estimates come from the factor graph, which
overwrites the filter state after each solve (:meth:`Tracker.sync`).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from itertools import chain

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from schemas import ObjectClass

from ..metrics import chi2_quantile
from .buffer import time_key
from .mapframe import mahalanobis_logdet, mahalanobis_matrix
from .motion import accel_psd, cv_predict, speed_prior
from .params import FusionParams

__all__ = [
    "Assignment",
    "Detection",
    "Track",
    "Tracker",
    "VehicleCandidate",
    "classes_compatible",
    "cv_predict",
    "protection_gate",
]

_INFEASIBLE = 1e12


def _match_probability(nll: np.ndarray, gated: np.ndarray, density: float) -> np.ndarray:
    """P[i, j]: the probability that detection i is of candidate j, given the gated candidates of its row and
    the hypothesis that it is of none of them (an object not yet tracked, a false alarm) with spatial density
    ``density`` (per m^3), as in JPDA's single-detection marginals:

        P[i, j] = N_ij / (lambda + sum_k N_ik),   N_ij = (2 pi)^-3/2 exp(-nll_ij / 2),   nll = d2 + ln det S.
    """
    if nll.size == 0:
        return np.zeros_like(nll)
    log_n = np.where(gated, -0.5 * nll - 1.5 * np.log(2.0 * np.pi), -np.inf)
    top = np.maximum(log_n.max(axis=1, keepdims=True, initial=np.log(density)), np.log(density))
    n = np.exp(log_n - top)
    return n / (np.exp(np.log(density) - top) + n.sum(axis=1, keepdims=True))


def classes_compatible(a: int, b: int) -> bool:
    """Same class, or one of them unknown."""
    return a == b or a == ObjectClass.UNKNOWN or b == ObjectClass.UNKNOWN


@dataclass(frozen=True)
class Detection:
    """One body-frame detection of one message, with its map-frame position from the sender's prior."""

    sender: str
    t: float
    index: int
    p_body: np.ndarray
    cov_body: np.ndarray
    cls: int
    p_map: np.ndarray
    cov_map: np.ndarray


@dataclass(frozen=True)
class VehicleCandidate:
    """A connected vehicle's reported position at a detection's time (for gating). ``protection``: where the
    vehicle claims integrity, (yaw, lateral and longitudinal protection levels (m), the Gaussian quantile k of
    their integrity risk): its body is within them of p_map but with that risk per axis."""

    vid: str
    p_map: np.ndarray
    cov: np.ndarray
    protection: tuple[float, float, float, float] | None = None


def protection_gate(m: np.ndarray, S_m: np.ndarray, vehicles: list[VehicleCandidate]) -> np.ndarray:
    """(N, V) bool: detection i (map position m (N, 3), covariance S_m (N, 3, 3)) can be of vehicle j by its
    protection levels: in the vehicle's frame (yaw), |across| <= PL_lat + k sigma_across and |along| <= PL_long +
    k sigma_along (sigma: the detection's own, k: the vehicle's integrity quantile). A vehicle that claims no
    integrity passes every detection (its covariance alone gates it)."""
    out = np.ones((len(m), len(vehicles)), dtype=bool)
    for j, v in enumerate(vehicles):
        if v.protection is None:
            continue
        yaw, pl_lat, pl_long, k = v.protection
        along, across = np.array([np.cos(yaw), np.sin(yaw), 0.0]), np.array([-np.sin(yaw), np.cos(yaw), 0.0])
        e = m - v.p_map
        for axis, pl in ((across, pl_lat), (along, pl_long)):
            sd = np.sqrt(np.einsum("i,nij,j->n", axis, S_m, axis))
            out[:, j] &= np.abs(e @ axis) <= pl + k * sd
    return out


@dataclass(frozen=True)
class Assignment:
    """What became of a detection: ``track`` (a confirmed track id) or ``vehicle`` (a connected vehicle id)."""

    kind: str
    target: int | str
    det: Detection
    d2: float = 0.0  # Mahalanobis distance squared of the match (innovation)
    p: float = 1.0  # probability that the detection is of the target (Tracker.associate)


@dataclass
class Track:
    """A track's bookkeeping and its gating filter (state [p, v] at time t)."""

    uid: int  # internal, from creation
    x: np.ndarray
    P: np.ndarray
    t: float
    t_last: float
    t_first: float
    id: int | None = None  # stable global id, from confirmation
    cls_votes: Counter = field(default_factory=Counter)
    hit_keys: set = field(default_factory=set)
    frames: dict = field(default_factory=dict)  # (sender, time key) -> t of its detections
    det_cov: dict = field(default_factory=dict)  # sender -> body-frame covariance of its newest detection
    pending: list[tuple[Detection, float]] = field(default_factory=list)  # held detections and their d2

    @property
    def confirmed(self) -> bool:
        return self.id is not None

    def seen_by_other(self, vid: str) -> bool:
        """Whether a sender other than ``vid`` has detected it (a track only ``vid`` saw is its own earlier view,
        placed with its own pose error)."""
        return any(sender != vid for sender, _ in self.frames)

    cls: int = int(ObjectClass.UNKNOWN)  # majority of cls_votes (see vote)

    def vote(self, cls: int) -> None:
        """Count a class vote; ``cls`` is the majority (ties: the class voted for first, as Counter.most_common)."""
        n = self.cls_votes[cls] = self.cls_votes[cls] + 1
        if cls == self.cls:
            return
        cur = self.cls_votes.get(self.cls, 0)
        if n > cur or (n == cur and list(self.cls_votes).index(cls) < list(self.cls_votes).index(self.cls)):
            self.cls = int(cls)


@dataclass
class _Instant:
    """The live tracks predicted to one instant t: states (K, 6) and covariances (K, 6, 6) by row;
    ``ahead``: the track's filter was already past t (not updated by detections of t)."""

    t: float
    tracks: list[Track]
    x: np.ndarray
    P: np.ndarray
    ahead: np.ndarray
    _tree: cKDTree | None = None  # over the rows' positions when it was built (lazily, by near())
    _n_tree: int = 0  # rows in the tree (later rows: tracks born at this instant)
    moved: float = 0.0  # how far any row's position moved since the tree was built (Kalman updates)

    def add(self, tr: Track) -> None:
        self.tracks.append(tr)
        self.x = np.concatenate([self.x, tr.x[None]])
        self.P = np.concatenate([self.P, tr.P[None]])
        self.ahead = np.append(self.ahead, False)

    def near(self, m: np.ndarray, radius: float) -> np.ndarray:
        """Rows whose position is within ``radius`` (Euclidean, 3-D) of any of the points m (N, 3), in
        order: candidates from a k-d tree (its radius widened by how far rows moved since it was built),
        then checked exactly."""
        if self._tree is None:
            self._tree, self._n_tree, self.moved = cKDTree(self.x[:, :3]), len(self.x), 0.0
        hits = self._tree.query_ball_point(m, radius + self.moved, return_sorted=False)
        cand = np.unique(
            np.concatenate([np.fromiter(chain.from_iterable(hits), dtype=int), np.arange(self._n_tree, len(self.x))])
        )
        if not len(cand):
            return cand
        gap = np.linalg.norm(self.x[cand, None, :3] - m[None], axis=2).min(axis=1)
        return cand[gap <= radius]


class Tracker:
    """Tracks with stable ids; associates one message's detections at a time (module docstring). The
    messages of one instant share one prediction of every track (``_at``), which their Kalman updates
    change; anything else that changes the tracks (sync, merge, expire) drops it."""

    def __init__(self, params: FusionParams):
        self.params = params
        self.gate = params.gate_chi2
        self.vehicle_gate = float(chi2_quantile(params.vehicle_gate_probability, 3))
        self.exclusion_gate = float(chi2_quantile(params.birth_exclusion_probability, 3))
        self.merge_gate = float(chi2_quantile(params.merge_probability, 3))
        self._merge_streak: dict[tuple[int, int], int] = {}
        self._shadow_streak: dict[tuple[int, str], int] = {}  # (track id, vehicle id) -> consecutive calls
        self.tracks: dict[int, Track] = {}  # by uid
        self._uid_of: dict[int, int] = {}  # global id -> uid
        self._next_uid = 1
        self._next_id = 1
        self.counts: Counter[str] = Counter()
        self.t_data = float("-inf")  # newest t_meas shown to the tracker (observe / associate)
        self._instant: _Instant | None = None  # see _at
        # each sender's recent detections (decayed over window_s of measurement time): (untracked, all, at t)
        self._recent: dict[str, tuple[float, float, float]] = {}

    def observe(self, t_meas: float) -> None:
        """A message measured at ``t_meas`` was fused (with or without detections): the tracker's data clock."""
        self.t_data = max(self.t_data, float(t_meas))

    def untracked_density(self, sender: str) -> float:
        """Spatial density (per m^3) of what a detection of ``sender`` may be of besides the candidates in its
        gate: false alarms (``clutter_density_m3``) and objects not yet tracked, ``object_density_m3`` times
        the share of the sender's recent detections (window_s, measurement time) that no connected vehicle
        and no confirmed track another sender saw took (all of them before it has detected anything). The
        new-target density of JPDA's likelihood ratio, observed around that observer: where it sees objects
        the others do not track (a cold start; a vehicle ahead of the rest), a lone track in a wide gate is
        not evidence that its detection is of it; a track it alone saw is its own earlier view, placed with
        its own pose error."""
        untracked, seen, _ = self._recent.get(sender, (0.0, 0.0, float("-inf")))
        share = untracked / seen if seen > 0 else 1.0
        return self.params.clutter_density_m3 + self.params.object_density_m3 * share

    def _count_recent(self, sender: str, t: float, n: int, untracked: int) -> None:
        """Add one message's detections (``untracked``: see untracked_density) to its sender's recent counts,
        the older ones decayed by exp(-dt / window_s)."""
        u, s, t0 = self._recent.get(sender, (0.0, 0.0, float("-inf")))
        w = float(np.exp(-max(t - t0, 0.0) / self.params.window_s)) if np.isfinite(t0) else 0.0
        self._recent[sender] = (w * u + untracked, w * s + n, max(t, t0))

    # ---------------------------------------------------------------- queries
    def confirmed(self) -> dict[int, Track]:
        """Confirmed tracks by global id."""
        return {tr.id: tr for tr in self.tracks.values() if tr.id is not None}

    def by_id(self, track_id: int) -> Track | None:
        uid = self._uid_of.get(track_id)
        return None if uid is None else self.tracks.get(uid)

    def predict_states(self, tracks: list[Track], t: float) -> tuple[np.ndarray, np.ndarray]:
        """:func:`cv_predict` of many tracks to time t at once: states (K, 6), covariances (K, 6, 6)."""
        x = np.array([tr.x for tr in tracks])
        P = np.array([tr.P for tr in tracks])
        dt = np.array([t - tr.t for tr in tracks])
        return cv_predict(x, P, dt, np.array([accel_psd(self.params, tr.cls) for tr in tracks]))

    def _at(self, t: float) -> _Instant:
        """Every live track predicted to t, kept while the messages of instant t are associated (they
        update its rows); rebuilt for another instant or after the tracks changed outside association."""
        inst = self._instant
        if inst is None or inst.t != t:
            tracks = list(self.tracks.values())
            x, P = self.predict_states(tracks, t) if tracks else (np.zeros((0, 6)), np.zeros((0, 6, 6)))
            ahead = np.array([tr.t > t for tr in tracks], dtype=bool)
            inst = self._instant = _Instant(t, tracks, x, P, ahead)
        return inst

    # ---------------------------------------------------------------- association
    def associate(self, dets: list[Detection], vehicles: list[VehicleCandidate]) -> tuple[list[Assignment], list[int]]:
        """Assign one message's detections. Returns (assignments for the graph, ids of newly confirmed tracks).

        Assignments to a newly confirmed track include its held detections (oldest first). A detection
        left unassigned starts a tentative track unless it lies within the birth-exclusion gate of a
        vehicle or track that no detection of this message took (then it is most likely that object,
        seen with an unlucky error, and a second track for it would be a duplicate).
        """
        if not dets:
            return [], []
        t = dets[0].t
        self.observe(t)
        inst = self._at(t)
        m = np.array([d.p_map for d in dets])
        # only tracks that could be near a detection (a cheap Euclidean pre-gate)
        near = inst.near(m, self.params.pregate_m) if len(inst.tracks) else np.zeros(0, dtype=int)
        live = [inst.tracks[k] for k in near]
        nv, nt = len(vehicles), len(live)
        # one Mahalanobis matrix against the vehicles' reported positions and the tracks' predictions
        c = np.concatenate([np.array([v.p_map for v in vehicles]).reshape(-1, 3), inst.x[near, :3]])
        S_c = np.concatenate([np.array([v.cov for v in vehicles]).reshape(-1, 3, 3), inst.P[near, :3, :3]])
        d2, logdet = mahalanobis_logdet(m, np.array([d.cov_map for d in dets]), c, S_c)
        dc = np.array([d.cls for d in dets])[:, None]
        tc = np.array([int(ObjectClass.VEHICLE)] * nv + [tr.cls for tr in live])[None, :]
        compat = (dc == tc) | (dc == ObjectClass.UNKNOWN) | (tc == ObjectClass.UNKNOWN)
        d2_all = np.where(compat, d2, np.inf)
        gate = np.r_[np.full(nv, self.vehicle_gate), np.full(nt, self.gate)]
        gated = d2_all <= gate
        gated[:, :nv] &= protection_gate(m, np.array([d.cov_map for d in dets]), vehicles)
        nll = d2 + logdet  # -2 ln N(m; c, S) - 3 ln 2 pi: a wide candidate pays for its width
        cost = np.where(gated, nll, _INFEASIBLE)
        rows, cols = linear_sum_assignment(cost)
        ok = gated[rows, cols]
        matched: dict[int, int] = dict(zip(rows[ok].tolist(), cols[ok].tolist(), strict=True))
        sender = dets[0].sender
        p_match = _match_probability(nll, gated, self.untracked_density(sender))
        taken = np.zeros(nv + nt, dtype=bool)
        taken[list(matched.values())] = True
        excluded = (d2_all[:, ~taken] <= self.exclusion_gate).any(axis=1)  # for the unmatched rows

        out: list[Assignment] = []
        born: list[int] = []
        kf: list[tuple[int, Detection]] = []  # (row of the instant, detection)
        for i, det in enumerate(dets):
            j = matched.get(i)
            if j is None:
                if excluded[i]:
                    self.counts["birth_suppressed"] += 1
                else:
                    tr = self._new_track(det)
                    inst.add(tr)
                    self._maybe_confirm(tr, out, born)
                    self.counts["new_tentative"] += 1
            elif j < nv:
                if p_match[i, j] < self.params.vehicle_association_probability:  # another candidate may be it
                    self.counts["vehicle_ambiguous"] += 1
                    continue
                out.append(Assignment("vehicle", vehicles[j].vid, det, float(d2[i, j]), float(p_match[i, j])))
                self.counts["matched_vehicle"] += 1
            else:
                tr = live[j - nv]
                self._record(tr, det)
                kf.append((int(near[j - nv]), det))
                if tr.confirmed:
                    out.append(Assignment("track", tr.id, det, float(d2[i, j]), float(p_match[i, j])))
                    self.counts["matched_track"] += 1
                else:
                    tr.pending.append((det, float(d2[i, j])))
                    self.counts["matched_tentative"] += 1
                    self._maybe_confirm(tr, out, born)
        self._update(inst, kf)
        shared = sum(
            a.det.t == t and (a.kind == "vehicle" or self.by_id(a.target).seen_by_other(sender))
            for a in out
        )
        self._count_recent(sender, t, len(dets), len(dets) - shared)
        return out, born

    def _maybe_confirm(self, tr: Track, out: list[Assignment], born: list[int]) -> None:
        """Confirm a tentative track with detections at birth_hits instants: next global id, held
        detections out to the graph (oldest first)."""
        if tr.confirmed or len(tr.hit_keys) < self.params.birth_hits:
            return
        tr.id = self._next_id
        self._uid_of[tr.id] = tr.uid
        self._next_id += 1
        born.append(tr.id)
        held = sorted(tr.pending, key=lambda p: p[0].t)
        out.extend(Assignment("track", tr.id, d, d2) for d, d2 in held)
        tr.pending = []
        self.counts["confirmed"] += 1

    def _new_track(self, det: Detection) -> Track:
        sv = speed_prior(self.params, det.cls)
        P = np.zeros((6, 6))
        P[:3, :3] = det.cov_map
        P[3:, 3:] = np.diag([sv**2, sv**2, 0.01])
        tr = Track(
            uid=self._next_uid, x=np.concatenate([det.p_map, np.zeros(3)]), P=P, t=det.t, t_last=det.t, t_first=det.t
        )
        self._next_uid += 1
        tr.vote(det.cls)
        tr.hit_keys.add(time_key(det.t))
        tr.frames[(det.sender, time_key(det.t))] = det.t
        tr.det_cov[det.sender] = det.cov_body
        tr.pending.append((det, 0.0))
        self.tracks[tr.uid] = tr
        return tr

    def _record(self, tr: Track, det: Detection) -> None:
        tr.vote(det.cls)
        tk = time_key(det.t)
        tr.hit_keys.add(tk)
        tr.frames[(det.sender, tk)] = det.t
        tr.t_last = max(tr.t_last, det.t)
        tr.t_first = min(tr.t_first, det.t)

    def _update(self, inst: _Instant, pairs: list[tuple[int, Detection]]) -> None:
        """Kalman updates of distinct tracks (rows of the instant) with their map-frame detections, all at
        once (tracks whose filter is already past the instant are skipped: the filter only gates and
        initialises)."""
        pairs = [(k, det) for k, det in pairs if not inst.ahead[k]]
        if not pairs:
            return
        rows = np.array([k for k, _ in pairs])
        x, P = inst.x[rows], inst.P[rows]
        m = np.array([det.p_map for _, det in pairs])
        S = P[:, :3, :3] + np.array([det.cov_map for _, det in pairs])
        K = np.linalg.solve(S, P[:, :3, :]).transpose(0, 2, 1)  # P H^T S^-1 (S symmetric)
        step = np.einsum("nij,nj->ni", K, m - x[:, :3])
        x = x + step
        P = P - K @ P[:, :3, :]
        P = 0.5 * (P + P.transpose(0, 2, 1))
        inst.x[rows], inst.P[rows] = x, P
        inst.moved += float(np.max(np.linalg.norm(step[:, :3], axis=1)))
        for k, xn, Pn in zip(rows.tolist(), x, P, strict=True):
            tr = inst.tracks[k]
            tr.x, tr.P, tr.t = xn, Pn, inst.t

    # ---------------------------------------------------------------- maintenance
    def sync(self, track_id: int, t: float, x, P) -> None:
        """Replace a confirmed track's filter state by the graph's estimate at time t."""
        tr = self.by_id(track_id)
        if tr is not None and t >= tr.t - 1e-9:
            tr.x, tr.P, tr.t = np.asarray(x, dtype=float), np.asarray(P, dtype=float), float(t)
            self._instant = None

    def merge_duplicates(self, t: float) -> list[int]:
        """Delete confirmed tracks that duplicate an older one; returns the deleted global ids.

        Two confirmed tracks of compatible classes are one object if, for ``merge_cycles`` consecutive
        calls, both their positions and their velocities at t are within the merge gate
        (Mahalanobis, chi2_3(merge_probability)) and no single sender frame ever detected both (one
        frame's detections are distinct objects). The younger track (higher id) goes.
        """
        conf = [tr for tr in self.tracks.values() if tr.confirmed]
        if len(conf) < 2:
            self._merge_streak = {}
            return []
        x, P = self.predict_states(conf, t)
        pairs = cKDTree(x[:, :3]).query_pairs(self.params.pregate_m, output_type="ndarray").reshape(-1, 2)
        d2p = d2v = np.zeros(0)
        if len(pairs):
            a_, b_ = pairs[:, 0], pairs[:, 1]
            dp, dv = x[a_, :3] - x[b_, :3], x[a_, 3:] - x[b_, 3:]
            Sp, Sv = P[a_, :3, :3] + P[b_, :3, :3], P[a_, 3:, 3:] + P[b_, 3:, 3:]
            d2p = np.einsum("ni,ni->n", dp, np.linalg.solve(Sp, dp[..., None])[..., 0])
            d2v = np.einsum("ni,ni->n", dv, np.linalg.solve(Sv, dv[..., None])[..., 0])
        close = (d2p <= self.merge_gate) & (d2v <= self.merge_gate)
        streak: dict[tuple[int, int], int] = {}
        gone: list[int] = []
        for a, b in pairs[close]:
            ta, tb = conf[a], conf[b]
            if not classes_compatible(ta.cls, tb.cls) or ta.frames.keys() & tb.frames.keys():
                continue
            pair = (min(ta.id, tb.id), max(ta.id, tb.id))
            streak[pair] = self._merge_streak.get(pair, 0) + 1
        for pair, count in sorted(streak.items()):
            if count >= self.params.merge_cycles and pair[0] not in gone and pair[1] not in gone:
                gone.append(pair[1])
        for tid in gone:
            older = self.by_id(min(p for p in streak if tid in p)[0])
            young = self.by_id(tid)
            if older is not None and young is not None:
                older.cls_votes.update(young.cls_votes)
                older.cls = int(older.cls_votes.most_common(1)[0][0])
                older.hit_keys |= young.hit_keys
            del self.tracks[self._uid_of.pop(tid)]
            self._instant = None
            self.counts["merged"] += 1
        self._merge_streak = {p: c for p, c in streak.items() if p[0] not in gone and p[1] not in gone}
        return gone

    def remove(self, track_id: int, reason: str = "denied") -> bool:
        """Delete the confirmed track ``track_id`` (others' views deny it, or it is a connected vehicle),
        counted under ``reason``; False if there is none."""
        uid = self._uid_of.pop(track_id, None)
        if uid is None:
            return False
        del self.tracks[uid]
        self._instant = None
        self.counts[reason] += 1
        return True

    def vehicle_shadows(self, t: float, vehicles: list[VehicleCandidate]) -> list[int]:
        """Delete confirmed tracks that are a connected vehicle; returns their global ids.

        A track born from detections of a connected vehicle (while its reported pose was off, during its
        cold start or while it was flagged) sits where the vehicle is and from then on takes the
        detections of it that should tie it to its pose: a second copy of the vehicle in the picture. A
        track of a vehicle-like class whose position at t is within the vehicle gate of a vehicle's
        reported position (where a detection would be taken as the vehicle: Mahalanobis,
        chi2_3(vehicle_gate_probability), both covariances) and nearer than ``vehicle_shadow_m`` (two road
        users' centres are never that close; the gate alone would reach far around a vehicle that reports
        itself uncertain) for ``merge_cycles`` consecutive calls, and that the vehicle itself never
        detected (a vehicle does not see itself), is that vehicle. ``vehicles``: the connected vehicles
        whose reported positions are trusted.
        """
        conf = [tr for tr in self.tracks.values() if tr.confirmed and classes_compatible(tr.cls, ObjectClass.VEHICLE)]
        if not conf or not vehicles:
            self._shadow_streak = {}
            return []
        x, P = self.predict_states(conf, t)
        pv = np.array([v.p_map for v in vehicles])
        d2 = mahalanobis_matrix(x[:, :3], P[:, :3, :3], pv, np.array([v.cov for v in vehicles]))
        d2[np.linalg.norm(x[:, None, :2] - pv[None, :, :2], axis=2) > self.params.vehicle_shadow_m] = np.inf
        streak: dict[tuple[int, str], int] = {}
        gone: list[int] = []
        for i, j in np.argwhere(d2 <= self.vehicle_gate):
            tr, vid = conf[i], vehicles[j].vid
            if any(sender == vid for sender, _ in tr.frames):
                continue
            key = (tr.id, vid)
            streak[key] = self._shadow_streak.get(key, 0) + 1
            if streak[key] >= self.params.merge_cycles and tr.id not in gone:
                gone.append(tr.id)
        for tid in gone:
            self.remove(tid, "vehicle_shadow")
        self._shadow_streak = {k: c for k, c in streak.items() if k[0] not in gone}
        return gone

    def expire(self, t: float) -> list[int]:
        """Drop tracks not detected for too long; returns the global ids of deleted confirmed tracks.

        Tentative tracks: ``tentative_timeout_s`` from their last detection to the newest measurement
        time observed (latency-independent); every track: ``death_s`` from its last detection to the
        fuse time ``t``.
        """
        dead = []
        horizon = t - self.params.window_s
        for tr in self.tracks.values():
            if len(tr.frames) > 64:
                tr.frames = {k: v for k, v in tr.frames.items() if v >= horizon}
        t_data = min(t, self.t_data)
        death, timeout = self.params.track_death_s, self.params.tentative_timeout_s
        for uid, tr in list(self.tracks.items()):
            if t - tr.t_last > death or (not tr.confirmed and t_data - tr.t_last > timeout):
                del self.tracks[uid]
                self._instant = None
                if tr.confirmed:
                    dead.append(tr.id)
                    del self._uid_of[tr.id]
                    self.counts["deleted"] += 1
                else:
                    self.counts["tentative_dropped"] += 1
        return dead
