"""Misbehaviour detection: does a vehicle's reported pose agree with what the other vehicles see of it?

Every detection of a vehicle-like object (class vehicle or unknown) by another connected vehicle, at
a map-frame position ``m`` (from the observer's pose), within ``misbehaviour_radius_m`` of vehicle V's
reported position ``p_V`` at that instant, is a sighting of V with offset ``d = m - p_V``; per
observer and instant only the nearest sighting counts, and it is none when V itself reports an object
there at that instant (within the ``misbehaviour_probability`` quantile of the two detections' covariances):
what O saw is then a vehicle beside V, not V, which O does not see (it is hidden, or out of view). On
development seed 1001 (paper-urban, every error source) an honest cv3, 0.1 m off, was flagged by cv2 alone,
which at 45 m saw the car 3.5 m beside cv3 and not cv3: its view was that car. A vehicle that is not where
it says it is reports the objects about it shifted by its own error, so none of them where others see it.
An honest V is seen where it says it is: its offsets scatter about zero by the observers' and V's pose
errors and the detector's noise (a few decimetres). A vehicle whose pose is biased by ``b`` is seen at
``-b`` from where it says it is, by every observer, instant after instant.

Over the last ``misbehaviour_window_s`` seconds, each other vehicle O with at least
``misbehaviour_min_sightings`` sightings of V has a *view* of V: the median of its offsets, with the
mean of their covariances (the detection's map covariance, which carries O's pose covariance, plus V's
reported position covariance; the mean, not the mean over the count, because the errors that matter
persist over the window: the poses' and the detector's). The view agrees when it is within
``misbehaviour_offset_m`` of zero or within the ``misbehaviour_probability`` chi-square quantile of its
covariance, and disagrees otherwise: a vehicle that says it is uncertain (on GNSS, just started) is not
accused of what its covariance admits, and the map and calibration errors of honest vehicles, which put
their views a few decimetres to a metre off at range, are inside the detector's covariance. A disagreement says
that O or V is wrong, not which: the two are *disputed*, and while they are, neither cross-localizes
the other (one lying vehicle must not pull its honest neighbours). A view that disagrees *accuses* V only
when it sees V at one place: its sightings' median distance from their median below
``misbehaviour_spread_m``, as a bias of V's would put them. In the live cold start (paper-urban, seed 0)
cv0 saw an honest cv3 twice where it said it was and, in the frames between, the car in the next lane
3.4 m beside it, 1.9 m apart along the road from one frame to the next: the median of the four, 1.9 m off
at a sigma of 0.4 m, flagged cv3. V is *flagged* as the wrong one

* when at least ``misbehaviour_min_observers`` unflagged observers accuse it and their views
  agree with each other (each within ``misbehaviour_spread_m`` of their median): they independently see
  V somewhere else; or
* when a single observer O accuses it, and O is *corroborated* while V is not: O's views agreed
  with some third vehicle now (O sees it, or is seen by it, where it says it is), V's do not. Only
  current views vouch, for the accuser as for the accused: a vehicle that agreed with a third one before
  its pose went wrong is not vouched for by that. With the agreements of the last
  10 s vouching, a 3 m bias from 5 s on was flagged 5.8-6.5 s late on
  evaluation seeds (when cv1's agreements from before its fault expired), and on development seed 1000
  a cv1 1 m off, vouched for by its agreements from before, flagged the honest cv0 it saw 1.1 m off.

The flag stays until every current view of V agrees again.

Two more kinds of misbehaviour are flagged:

* *Ghosts.* A confirmed track that only V reported in the window (its sole source) is one that any other
  vehicle O should see when it lies within ``ghost_range_m`` of O's reported position, inside
  ``ghost_fov_deg`` about its heading and hidden behind no connected vehicle or other track (a 1.5 m
  wide body on the line of sight), and O knows where it is (its reported position 1-sigma below
  ``ghost_observer_sigma_m``). Each message of such an O is a *look* at the track: O saw it when one of
  O's detections lies within ``ghost_gate_m``. A track that O looked at ``ghost_min_looks`` times in
  the window and saw at most ``ghost_max_seen`` of them is *denied*: it is not there (or not where it
  is said to be), and the container deletes it, as a multi-sensor tracker lowers the existence of a
  track that sensors covering it do not detect. Honest detectors make such tracks now and then (a
  false alarm that stays a few seconds where it appeared, a track pulled metres off by a persistent
  detection error), so one denial says little about V. V is flagged when ``ghost_min_denials`` of its
  tracks were denied within ``ghost_denial_window_s`` (a false object that outlives honest false
  alarms: V makes a new track of it each time the last one is deleted), or two within
  ``ghost_together_s`` of each other (two false objects at once). On development seeds honest
  vehicles' denied tracks came one at a time, the second one 1.7 s or more after the first, which is
  why two denials alone do not flag. Once flagged, V's detections make no tracks, so there is nothing
  left to deny: the flag holds ``ghost_hold_s`` after the last denial, then V is
  tried again.
* *A clock that repeats itself.* A message of V refused as a duplicate or as stale whose ``t_meas`` is
  not after the newest instant of V's earlier messages repeats what V sent before (a frozen clock, or V
  re-sending old messages). A network replay cannot do this in a signed fleet, because the verifier
  refuses replayed signatures before the container sees them; a late but advancing message (a vehicle
  that falls behind) is not counted. V is flagged when at least ``clock_min_repeats`` of its messages
  received in the window, and ``clock_repeat_fraction`` of them, repeat, and stays flagged until none
  in the window does.

A flagged vehicle's detections are not fused and it cannot cross-localize others or be cross-localized
(:class:`~mapcontainer.fusion.container.Container`): its error stays its own.

Pure: time is the detections' ``t_meas``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..metrics import chi2_quantile
from .params import FusionParams

__all__ = ["MisbehaviourMonitor", "Sighting"]

_SAME_INSTANT_S = 0.05  # detections this near in time are of one instant (frames are 0.1 s apart)


@dataclass(eq=False)
class Sighting:
    """Observer ``observer`` saw something ``offset`` (map x, y) from where the vehicle said it was at ``t``.

    ``checked`` and ``matched``: the newest of the observed vehicle's reports tested against the sighting and
    the newest one that reported an object there (report numbers, -1: none), so that each report is tested
    against each sighting once (:meth:`MisbehaviourMonitor._reported_there`)."""

    t: float
    observer: str
    offset: np.ndarray
    cov: np.ndarray  # (2, 2) of the offset: the detection's map covariance (with its observer's pose) and the vehicle's
    where: np.ndarray  # the detection's map (x, y)
    det_cov: np.ndarray  # (2, 2): the detection's map covariance
    checked: int = field(default=-1, repr=False)
    matched: int = field(default=-1, repr=False)


class MisbehaviourMonitor:
    """Sightings per vehicle and the flags they raise (module doc)."""

    def __init__(self, params: FusionParams):
        self.params = params
        self._gate = float(chi2_quantile(params.misbehaviour_probability, 2))
        self._sightings: dict[str, deque[Sighting]] = {}
        # vehicle -> its reports of vehicle-like objects: (t, where (N, 2), cov (N, 2, 2), report number)
        self._reports: dict[str, deque[tuple[float, np.ndarray, np.ndarray, int]]] = {}
        self._report_no = 0  # numbers the reports of every vehicle in the order they came
        self.flagged: dict[str, str] = {}  # vehicle -> why (every kind below)
        self._seen_off: dict[str, str] = {}  # vehicle -> why: the others see it elsewhere
        self._ghosts: dict[str, tuple[float, str]] = {}  # vehicle -> (time of the last denial, why)
        self._denials: dict[str, deque[tuple[float, int, str, np.ndarray]]] = {}  # vehicle -> (t, track, by, where)
        self.denied: list[int] = []  # tracks denied by the last update: the container deletes them
        self._looks: dict[tuple[str, int], deque[tuple[float, str, bool, np.ndarray]]] = {}  # (source, track) -> looks
        self._arrivals: dict[str, deque[tuple[float, bool]]] = {}  # vehicle -> (t_recv, repeats an instant)
        self._newest: dict[str, float] = {}  # vehicle -> newest t_meas of its messages so far
        self.disputed: set[frozenset[str]] = set()  # pairs whose views disagree now
        # (observer, observed) -> the observer's view of it at the last update: (median offset, covariance)
        self.views: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]] = {}
        self.flagged_total = 0  # flags raised (a vehicle flagged, cleared and flagged again counts twice)

    def observe(
        self,
        observer: str,
        t: float,
        p_map: np.ndarray,
        cov_map: np.ndarray,
        cls: np.ndarray,
        reported: tuple[np.ndarray, np.ndarray, np.ndarray],
    ):
        """One message's detections (map positions ``p_map`` (N, 3) with covariances ``cov_map`` (N, 3, 3),
        classes ``cls``) by ``observer`` at ``t``, against the connected vehicles' reported positions and
        their covariances at ``t``: ``reported`` = (ids (V,), positions (V, 3), covariances (V, 3, 3)).
        Only vehicle-like detections count; each other vehicle's nearest one within the radius is a
        sighting of it."""
        r = self.params.misbehaviour_radius_m
        cls = np.asarray(cls)
        vehicle_like = (cls == 0) | (cls == 2)  # ObjectClass.UNKNOWN, ObjectClass.VEHICLE
        p = np.asarray(p_map, dtype=float).reshape(-1, 3)[vehicle_like, :2]
        S = np.asarray(cov_map, dtype=float).reshape(-1, 3, 3)[vehicle_like, :2, :2]
        if len(p):
            self._reports.setdefault(observer, deque()).append((float(t), p, S, self._report_no))
            self._report_no += 1
        vids, pos, cov = reported
        others = np.asarray(vids) != observer
        if not len(p) or not others.any():
            return
        vids, pos, cov = np.asarray(vids)[others], np.asarray(pos, float)[others], np.asarray(cov, float)[others]
        d = p[None, :, :] - pos[:, None, :2]  # (V, N, 2)
        dist = np.hypot(d[..., 0], d[..., 1])
        k = np.argmin(dist, axis=1)
        rows = np.arange(len(vids))
        for i in np.flatnonzero(dist[rows, k] <= r):
            C = S[k[i]] + cov[i, :2, :2]
            sighting = Sighting(float(t), observer, d[i, k[i]], C, p[k[i]], S[k[i]])
            self._sightings.setdefault(str(vids[i]), deque()).append(sighting)

    def message(self, sender: str, t_meas: float, t_recv: float, refused: str | None) -> None:
        """One message of ``sender`` received at ``t_recv``, taken (``refused`` None) or refused with a reason."""
        newest = self._newest.get(sender, float("-inf"))
        repeat = refused in ("duplicate", "stale") and t_meas <= newest
        self._arrivals.setdefault(sender, deque()).append((float(t_recv), repeat))
        if refused != "future":
            self._newest[sender] = max(newest, float(t_meas))

    def look(
        self,
        observer: str,
        t: float,
        pose: np.ndarray,
        pose_cov: np.ndarray,
        p_map: np.ndarray,
        tracks: list[tuple[int, str]],
        track_p: np.ndarray,
        occluders: np.ndarray,
    ) -> None:
        """``observer`` at ``pose`` (map [x, y, z, roll, pitch, yaw], covariance ``pose_cov``) detected
        ``p_map`` (N, 3) at ``t``;
        ``tracks`` are (track id, its sole source) at map positions ``track_p`` (M, 2) at ``t``, and
        ``occluders`` (K, 2) the connected vehicles' and tracks' positions that can hide a track."""
        pp = self.params
        if not tracks or np.linalg.eigvalsh(np.asarray(pose_cov, float)[:2, :2])[-1] > pp.ghost_observer_sigma_m**2:
            return
        o = np.asarray(pose, dtype=float)
        rel = np.asarray(track_p, dtype=float).reshape(-1, 2) - o[:2]
        r = np.hypot(rel[:, 0], rel[:, 1])
        bearing = np.arctan2(rel[:, 1], rel[:, 0]) - o[5]
        bearing = np.abs((bearing + np.pi) % (2 * np.pi) - np.pi)
        inview = (r <= pp.ghost_range_m) & (r >= 3.0) & (bearing <= np.radians(pp.ghost_fov_deg) / 2)
        if not inview.any():
            return
        det = np.asarray(p_map, dtype=float).reshape(-1, 3)[:, :2]
        occ = np.asarray(occluders, dtype=float).reshape(-1, 2) - o[:2]
        for i in np.flatnonzero(inview):
            u = rel[i] / r[i]
            along = occ @ u
            perp = np.abs(occ[:, 0] * u[1] - occ[:, 1] * u[0])
            between = (along > 1.0) & (along < r[i] - 1.0) & (perp < 1.5)
            if between.any():
                continue
            saw = bool(len(det)) and float(np.min(np.hypot(*(det - track_p[i]).T))) <= pp.ghost_gate_m
            tid, source = tracks[i]
            self._looks.setdefault((source, tid), deque()).append((float(t), observer, saw, track_p[i]))

    def disputes(self, a: str, b: str) -> bool:
        """Whether a and b see each other elsewhere than they say (cross-localization between them is off)."""
        return frozenset((a, b)) in self.disputed

    def update(self, t: float) -> dict[str, str]:
        """Drop evidence older than the window before ``t`` and decide every kind of flag (module doc)."""
        before = set(self.flagged)
        self._update_seen_off(t)
        self._update_ghosts(t)
        repeats = self._repeats(t)
        flagged: dict[str, list[str]] = {}
        for kind in (self._seen_off, {v: why for v, (_, why) in self._ghosts.items()}, repeats):
            for v, why in kind.items():
                flagged.setdefault(v, []).append(why)
        self.flagged = {v: "; ".join(why) for v, why in sorted(flagged.items())}
        self.flagged_total += len(set(self.flagged) - before)
        return dict(self.flagged)

    def _update_ghosts(self, t: float) -> None:
        pp = self.params
        t_min = t - pp.misbehaviour_window_s
        self.denied = []
        for key, q in list(self._looks.items()):
            while q and q[0][0] < t_min:
                q.popleft()
            if not q:
                del self._looks[key]
                continue
            by_observer: dict[str, list[bool]] = {}
            for _, o, saw, _ in q:
                by_observer.setdefault(o, []).append(saw)
            deniers = [
                o
                for o, saws in by_observer.items()
                if o not in self.flagged and len(saws) >= pp.ghost_min_looks and np.mean(saws) <= pp.ghost_max_seen
            ]
            if deniers:
                source, tid = key
                self.denied.append(tid)
                self._denials.setdefault(source, deque()).append((t, tid, min(deniers), q[-1][3]))
                del self._looks[key]
        for v, q in list(self._denials.items()):
            while q and q[0][0] < t - pp.ghost_denial_window_s:
                q.popleft()
            if not q:
                del self._denials[v]
                continue
            times = [d[0] for d in q]
            together = any(b - a <= pp.ghost_together_s for a, b in zip(times, times[1:], strict=False))
            if q[-1][0] == t and (len(q) >= pp.ghost_min_denials or together):
                which = ", ".join(f"#{tid} by {o}" for _, tid, o, _ in q)
                self._ghosts[v] = (
                    t,
                    f"reported {len(q)} objects in {pp.ghost_denial_window_s:g} s that others should see and did not "
                    f"({which})",
                )
        self._ghosts = {v: g for v, g in self._ghosts.items() if t - g[0] <= pp.ghost_hold_s}

    def _repeats(self, t: float) -> dict[str, str]:
        pp = self.params
        out = {}
        for v, q in list(self._arrivals.items()):
            while q and q[0][0] < t - pp.misbehaviour_window_s:
                q.popleft()
            if not q:
                del self._arrivals[v]
                continue
            n_rep = sum(rep for _, rep in q)
            held = n_rep and "repeat instants" in self.flagged.get(v, "")  # flagged: until it stops repeating
            if held or (n_rep >= pp.clock_min_repeats and n_rep >= pp.clock_repeat_fraction * len(q)):
                out[v] = (
                    f"{n_rep} of its {len(q)} messages in the last {pp.misbehaviour_window_s:g} s repeat instants "
                    "it had sent (a frozen clock or a replay)"
                )
        return out

    def _agrees(self, offset: np.ndarray, cov: np.ndarray) -> bool:
        """A view agrees unless it is farther off than the floor and than its covariance allows."""
        if float(np.hypot(*offset)) <= self.params.misbehaviour_offset_m:
            return True
        try:
            d2 = float(offset @ np.linalg.solve(cov, offset))
        except np.linalg.LinAlgError:
            return False
        return d2 <= self._gate

    def _reported_there(self, sightings: dict[str, deque[Sighting]]) -> None:
        """Test every report not yet tested against each sighting: did the observed vehicle itself report an
        object where the sighting saw something, at the same instant (within the ``misbehaviour_probability``
        quantile of the two detections' covariances)? Updates each sighting's ``checked`` and ``matched``.

        Exact with the test of every present report against every sighting at every update: reports
        leave their deque from its front only, in the order they came (numbers increasing), so a sighting's
        newest matching report is still there exactly when its number is at least the front's, and then
        one is. The pairs of an update are tested in one array operation."""
        where, det_cov, pts, covs, pair_of, pairs = [], [], [], [], [], []
        for vid, q in sightings.items():
            reports = self._reports.get(vid)
            if not reports:
                continue
            newest = reports[-1][3]
            for s in q:
                if s.checked >= newest:
                    continue
                for t, p, S, no in reversed(reports):
                    if no <= s.checked:
                        break
                    if abs(t - s.t) <= _SAME_INSTANT_S:
                        pair_of.append(np.full(len(p), len(pairs)))
                        pairs.append((s, no))
                        where.append(np.broadcast_to(s.where, p.shape))
                        det_cov.append(np.broadcast_to(s.det_cov, S.shape))
                        pts.append(p)
                        covs.append(S)
                s.checked = newest
        if not pairs:
            return
        d = np.concatenate(pts) - np.concatenate(where)
        C = np.concatenate(covs) + np.concatenate(det_cov)
        d2 = np.einsum("ni,ni->n", d, np.linalg.solve(C, d[..., None])[..., 0])
        hit = np.zeros(len(pairs), dtype=bool)
        hit[np.concatenate(pair_of)[d2 <= self._gate]] = True
        for (s, no), h in zip(pairs, hit, strict=True):
            if h:
                s.matched = max(s.matched, no)

    def _update_seen_off(self, t: float) -> None:
        pp = self.params
        for vid, q in list(self._reports.items()):
            while q and q[0][0] < t - pp.misbehaviour_window_s:
                q.popleft()
            if not q:
                del self._reports[vid]
        views: dict[tuple[str, str], np.ndarray] = {}  # (observer, observed) -> median offset
        covs: dict[tuple[str, str], np.ndarray] = {}  # ... -> its covariance (the sightings' mean: errors persist)
        spread: dict[tuple[str, str], float] = {}  # ... -> its sightings' median distance from their median
        for vid, q in list(self._sightings.items()):
            while q and q[0].t < t - pp.misbehaviour_window_s:
                q.popleft()
            if not q:
                del self._sightings[vid]
        self._reported_there(self._sightings)
        for vid, q in self._sightings.items():
            reports = self._reports.get(vid)
            front = reports[0][3] if reports else self._report_no  # the oldest of its reports still here
            by_observer: dict[str, list[Sighting]] = {}
            for s in q:
                if s.matched < front:  # not a vehicle it reported itself: a sighting of it
                    by_observer.setdefault(s.observer, []).append(s)
            for o, ss in by_observer.items():
                if len(ss) >= pp.misbehaviour_min_sightings:
                    offsets = np.array([s.offset for s in ss])
                    views[(o, vid)] = m = np.median(offsets, axis=0)
                    covs[(o, vid)] = np.mean([s.cov for s in ss], axis=0)
                    spread[(o, vid)] = float(np.median(np.hypot(*(offsets - m).T)))
        self.views = {k: (m, covs[k]) for k, m in views.items()}
        agrees = {k: self._agrees(m, covs[k]) for k, m in views.items()}
        # a view that disagrees accuses only when it sees V at one place: its sightings about their median
        coherent = {k: spread[k] < pp.misbehaviour_spread_m for k in views}
        self.disputed = {frozenset(k) for k, ok in agrees.items() if not ok}
        agreed_now = {frozenset(k) for k, ok in agrees.items() if ok}

        def corroborated(x: str, other: str) -> bool:
            return any(x in pair and other not in pair for pair in agreed_now)

        for v in sorted({v for _, v in views}):
            mine = {o: m for (o, vv), m in views.items() if vv == v}
            if all(agrees[(o, v)] for o in mine):
                self._seen_off.pop(v, None)
                continue
            accusers = {
                o: m for o, m in mine.items() if not agrees[(o, v)] and coherent[(o, v)] and o not in self.flagged
            }
            if not accusers:
                continue
            centre = np.median(np.array(list(accusers.values())), axis=0)
            consistent = all(float(np.hypot(*(m - centre))) < pp.misbehaviour_spread_m for m in accusers.values())
            by_many = len(accusers) >= pp.misbehaviour_min_observers and consistent
            by_trusted = [o for o in accusers if corroborated(o, v) and not corroborated(v, o)]
            if by_many or by_trusted:
                who = sorted(accusers) if by_many else by_trusted
                self._seen_off[v] = (
                    f"seen {float(np.hypot(*centre)):.1f} m from its reported position ({centre[0]:+.1f}, "
                    f"{centre[1]:+.1f}) by {', '.join(who)} in the last {pp.misbehaviour_window_s:g} s"
                )
