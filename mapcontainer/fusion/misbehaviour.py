"""Misbehaviour detection: does a vehicle's reported pose agree with what the other vehicles see of it?

*Sightings.* Every detection of a vehicle-like object (class vehicle or unknown) by another connected
vehicle O, at a map-frame position ``m`` (from O's pose), within ``misbehaviour_radius_m`` of vehicle V's
reported position ``p_V`` at that instant, is a sighting of V with offset ``d = m - p_V``; per observer and
instant only the nearest one counts. Its weight ``w`` is the probability that it is V as the host's own
association has it (:attr:`~.association.Tracker.vehicle_matches`): the association probability where the
host matched the detection with V, one minus it where the host matched it with another connected vehicle,
1 where it matched no connected vehicle (nothing any vehicle claims explains it). It is no sighting when V
itself reports an object there at that instant (within the ``misbehaviour_probability`` quantile of the two
detections' covariances): what O saw is then a vehicle beside V, not V, which O does not see (it is hidden,
or out of view). On development seed 1001 (paper-urban, every error source) an honest cv3 was flagged by cv2
alone, which at 45 m saw the car 3.5 m beside cv3 and not cv3. A vehicle that is not where it says it is
reports the objects about it shifted by its own error, so none of them where others see it.

*The offsets and their test.* Every vehicle X's offset ``b_X`` (true minus reported position, map x, y)
is estimated from the sightings of the last ``misbehaviour_window_s`` seconds. A sighting's error has a
part that averages out over O's frames (``A``: the detector's noise), one that O's every frame repeats
through the detection's lever arm (``B``: O's attitude error, with its repeated calibration error; O's
position error is O's own offset ``b_O``) and one that every detection of V repeats, whoever makes it
(``D``: the persistent share of the detector's error, :func:`~.hostcore.persistent_share` over the
window: the object's shape and size prior and box fit). O's *view* of V is

    y_OV = (sum_k w_k A_k^-1)^-1 sum_k w_k A_k^-1 d_k,     C_OV = (sum_k w_k A_k^-1)^-1 + mean_w B_k,

    y_OV = b_V + s_V - b_O + e_OV,     e_OV ~ N(0, C_OV),     s_V ~ N(0, K_V),  K_V = mean_w D_k,

since O's detections sit where O's pose puts them: a vehicle off by ``b`` is seen off by ``b`` and sees
every other vehicle off by ``-b``. An honest X's offset is drawn from the error it states, ``P0_X``: its
reported position covariance plus the error its every frame repeats (VehiclePrior.pose_bias_sigma); where
it claims integrity, its protection levels, as the covariance whose 1-sigmas are the levels over their
integrity risk's Gaussian quantile. V is tested against every view at once (:func:`network_test`), every
other vehicle honest (b_X ~ N(0, P0_X)) and V's offset free: the joint least squares (an information
filter over the window) gives b^_V with covariance P^_V, independent of b_V, so for an honest V

    q_V = b^_V^T (P0_V + P^_V)^-1 b^_V ~ chi2(2),

and r_V, the chi-square of the n views that involve V about the joint estimate, is about chi2(2 (n - 1))
whatever b_V is. The test's false-alarm probability ``alpha`` follows from the rate one states:
``misbehaviour_false_alarms_per_hour`` per vehicle over 3600 / ``misbehaviour_test_period_s`` tests an hour
(a union bound: the tests of consecutive frames share their evidence, so the rate is at most that); V
fails when q_V exceeds the chi-square(2) quantile 1 - alpha. V is *flagged* when it fails on views that
involve it (others' views of it, its views of others) with at least ``misbehaviour_min_observers`` other
vehicles (two vehicles alone cannot tell which of them is off) and that agree with each other (r_V within
its quantile 1 - alpha), the most evident first: once a vehicle is flagged, its views are no evidence
about the others (a vehicle 3 m off sees everyone off), and they are tested again without them. Flags are
decided anew at every update; a vehicle nothing is seen of keeps its flag. Both
directions count: a vehicle 1 m off that one other vehicle sees, and that sees one other vehicle, is seen
off and sees off, and the two agree about whose offset it is. One view alone is no proof: on development
seed 1001 cv3 saw the car beside an honest cv1 (hidden) 4.3 m from it, and cv2 one beside an honest cv3,
each flagging it with nothing else against it; on development seed 1000 a cv1 1 m off flagged the honest
cv0 it saw 1.1 m off. A single view is tested against both vehicles' stated errors,
``y_OV^T (P0_V + P0_O + C_OV + K_V)^-1 y_OV``: O and V *dispute* when it fails, and while they do, neither
cross-localizes the other (one lying vehicle must not pull its honest neighbours).

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
from scipy.special import chdtri

from ..metrics import chi2_quantile
from .hostcore import persistent_share
from .mapframe import observations_to_map
from .params import FusionParams

__all__ = ["BiasTest", "MisbehaviourMonitor", "Sighting", "View", "chi2_sf_quantile", "network_test", "view_of"]

_SAME_INSTANT_S = 0.05  # detections this near in time are of one instant (frames are 0.1 s apart)


@dataclass(eq=False)
class Sighting:
    """Observer ``observer`` saw something ``offset`` (map x, y) from where the vehicle said it was at ``t``,
    with weight ``weight`` (the probability that it is that vehicle); ``white``, ``persistent`` and ``shape``:
    the (2, 2) covariances of the parts of its error that average out over the observer's frames, that the
    observer's every frame repeats (its pose error), and that every detection of the vehicle repeats,
    whoever makes it (the detector's persistent error: the object's shape and size prior).

    ``checked`` and ``matched``: the newest of the observed vehicle's reports tested against the sighting and
    the newest one that reported an object there (report numbers, -1: none), so that each report is tested
    against each sighting once (:meth:`MisbehaviourMonitor._reported_there`)."""

    t: float
    observer: str
    offset: np.ndarray
    white: np.ndarray
    persistent: np.ndarray
    shape: np.ndarray
    weight: float
    where: np.ndarray  # the detection's map (x, y)
    det_cov: np.ndarray  # (2, 2): the detection's map covariance
    checked: int = field(default=-1, repr=False)
    matched: int = field(default=-1, repr=False)


@dataclass(frozen=True)
class View:
    """An observer's view of a vehicle over the window: its offset ``y``, its covariance ``C`` and the part
    ``K`` of its error that every observer's view of the vehicle shares (module doc), and ``q``, the offset's
    chi-square against the errors stated, ``y^T (P0 + C + K)^-1 y``."""

    y: np.ndarray
    C: np.ndarray
    K: np.ndarray
    q: float


@dataclass(frozen=True)
class BiasTest:
    """Vehicle ``vid``'s offset b^ (covariance P^) from every view, its chi-square q against the error it states,
    and r, the chi-square of the ``n`` views that involve it about the joint estimate (module doc)."""

    vid: str
    b: np.ndarray
    P: np.ndarray
    q: float
    r: float
    n: int
    residuals: dict[tuple[str, str], float] = field(default_factory=dict)  # each view's (y - y^)^T C^-1 (y - y^)


def view_of(sightings: list[Sighting], P0: np.ndarray) -> View:
    """One observer's view from its sightings of a vehicle, the two stating the errors ``P0`` (2, 2) together
    (module doc): y = (sum w A^-1)^-1 sum w A^-1 d,  C = (sum w A^-1)^-1 + sum w B / sum w,  K = sum w D / sum w,
    q = y^T (P0 + C + K)^-1 y."""
    w = np.array([s.weight for s in sightings])
    Ainv = np.linalg.inv(np.array([s.white for s in sightings]))  # (K, 2, 2)
    cov_mean = np.linalg.inv(np.einsum("k,kij->ij", w, Ainv))
    y = cov_mean @ np.einsum("k,kij,kj->i", w, Ainv, np.array([s.offset for s in sightings]))
    C = cov_mean + np.einsum("k,kij->ij", w, np.array([s.persistent for s in sightings])) / w.sum()
    K = np.einsum("k,kij->ij", w, np.array([s.shape for s in sightings])) / w.sum()
    return View(y, C, K, float(y @ np.linalg.solve(P0 + C + K, y)))


def network_test(views: dict[tuple[str, str], View], stated: dict[str, np.ndarray], vid: str) -> BiasTest:
    """Test ``vid`` against every view (observer, observed) -> View, every other vehicle X honest with its stated
    error ``stated[X]`` (module doc): the joint estimate of every vehicle's offset b_X and seen-as error s_X,

        y_OV = b_V + s_V - b_O + e,   e ~ N(0, C_OV),   b_X ~ N(0, P0_X) (X != vid),   s_X ~ N(0, K_X),

    b_vid with no prior; q = b^^T (P0 + P^)^-1 b^ of vid's; r the least squares' chi-square, of the views
    ((y - y^)^T C^-1 (y - y^)) and of the priors (b^_X^T P0_X^-1 b^_X, s^_X^T K_X^-1 s^_X), with 2 (n - 1)
    degrees of freedom for n views that all involve vid; ``residuals``: each view's own and its other
    vehicle's priors'."""
    ids = sorted({x for pair in views for x in pair})
    at = {x: i for i, x in enumerate(ids)}
    n = len(ids)
    info, vec = np.zeros((4 * n, 4 * n)), np.zeros(4 * n)
    seen_as: dict[str, list[np.ndarray]] = {}
    for (_, v), view in views.items():
        seen_as.setdefault(v, []).append(view.K)
    priors = []  # (state index, information) of the priors: every offset but vid's, every seen-as error
    for x, i in at.items():
        if x != vid:
            priors.append((2 * i, np.linalg.inv(stated[x])))
        K = np.mean(seen_as[x], axis=0) if x in seen_as else np.eye(2)
        priors.append((2 * n + 2 * i, np.linalg.inv(K + 1e-9 * np.eye(2))))
    for j, W in priors:
        info[j : j + 2, j : j + 2] += W
    rows = {}
    for (o, v), view in views.items():
        H = np.zeros((2, 4 * n))
        H[:, 2 * at[v] : 2 * at[v] + 2] += np.eye(2)
        H[:, 2 * n + 2 * at[v] : 2 * n + 2 * at[v] + 2] += np.eye(2)
        H[:, 2 * at[o] : 2 * at[o] + 2] -= np.eye(2)
        G = np.linalg.inv(view.C)
        info += H.T @ G @ H
        vec += H.T @ G @ view.y
        rows[(o, v)] = (H, G)
    cov = np.linalg.inv(info)
    mean = cov @ vec
    i = 2 * at[vid]
    b, P = mean[i : i + 2], cov[i : i + 2, i : i + 2]
    e = {k: views[k].y - rows[k][0] @ mean for k in views}
    res = {k: float(e[k] @ rows[k][1] @ e[k]) for k in views}
    prior_res = {j: float(mean[j : j + 2] @ W @ mean[j : j + 2]) for j, W in priors}
    for k in views:  # each view's share: its own residual and its other vehicle's priors' (b and s)
        x = at[k[0] if k[1] == vid else k[1]]
        res[k] += prior_res.get(2 * x, 0.0) + prior_res[2 * n + 2 * x]
    r = sum(float(e[k] @ rows[k][1] @ e[k]) for k in views) + sum(prior_res.values())
    return BiasTest(vid, b, P, float(b @ np.linalg.solve(stated[vid] + P, b)), r, len(views), res)


def chi2_sf_quantile(alpha: float, dof: int) -> float:
    """x with P(X > x) = alpha for X ~ chi2(dof), exact for small alpha (no 1 - alpha rounding)."""
    return float(chdtri(dof, alpha))


class MisbehaviourMonitor:
    """Sightings per vehicle and the flags they raise (module doc)."""

    def __init__(self, params: FusionParams):
        self.params = params
        self._gate = float(chi2_quantile(params.misbehaviour_probability, 2))
        # the bias test's false-alarm probability per test, and the quantile it puts on q (2 dof)
        self.alpha = params.misbehaviour_false_alarms_per_hour * params.misbehaviour_test_period_s / 3600.0
        self.threshold = chi2_sf_quantile(self.alpha, 2)
        # the share of a detection's variance that one observer's detections repeat over the window
        self._share = persistent_share(params.model_copy(update={"window_s": params.misbehaviour_window_s}))
        self._sightings: dict[str, deque[Sighting]] = {}
        self._prior: dict[str, np.ndarray] = {}  # vehicle -> the newest (2, 2) error it states (P0)
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
        self.views: dict[tuple[str, str], View] = {}  # (observer, observed) -> the view at the last update
        self.tests: dict[str, BiasTest] = {}  # vehicle -> its bias test at the last update (if it was disputed)
        self.flagged_total = 0  # flags raised (a vehicle flagged, cleared and flagged again counts twice)

    def errors(self, pose, pose_cov, p_body, cov_body) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The map covariances (N, 3, 3) of the three parts of the error of detections ``p_body`` (N, 3)
        (body-frame covariances ``cov_body``) by an observer at ``pose``: what averages out over its frames (the
        detector's noise but its persistent share over the window), what it repeats frame after frame (its pose
        error ``pose_cov`` (6, 6), what it reports and what every frame of it repeats, through the detections'
        lever arms), and the detector's persistent share (the object's shape and size prior, which every
        observer's detections of it share)."""
        cov_body = np.asarray(cov_body, dtype=float)
        zero = np.zeros((6, 6))
        turn = np.array(pose_cov, dtype=float)  # its position error is its own offset's (b_O): the lever arms'
        turn[:3, :] = turn[:, :3] = 0.0
        white = observations_to_map(pose, zero, p_body, (1.0 - self._share) * cov_body)[1]
        shape = observations_to_map(pose, zero, p_body, self._share * cov_body)[1]
        return white, observations_to_map(pose, turn, p_body, 0.0 * cov_body)[1], shape

    def observe(
        self,
        observer: str,
        t: float,
        p_map: np.ndarray,
        cov_map: np.ndarray,
        cls: np.ndarray,
        reported: tuple[np.ndarray, np.ndarray, np.ndarray],
        errors: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
        matches: list[tuple[str, float] | None] | None = None,
        prior: dict[str, np.ndarray] | None = None,
    ):
        """One message's detections (map positions ``p_map`` (N, 3) with covariances ``cov_map`` (N, 3, 3),
        classes ``cls``) by ``observer`` at ``t``, against the connected vehicles' reported positions and
        their covariances at ``t``: ``reported`` = (ids (V,), positions (V, 3), covariances (V, 3, 3)).
        ``errors``: the (N, 3, 3) covariances of the parts of the detections' error that average out over the
        observer's frames, that it repeats and that the object's every detection repeats (:meth:`errors`; None:
        ``cov_map`` split by the detector's persistent share into the first and the last); ``matches``: the
        host's association of each detection (:attr:`~.association.Tracker.vehicle_matches`; None: none known);
        ``prior``: vehicle -> the (2, 2) covariance of its position error as it states it (P0; a vehicle not in
        it: its reported covariance).
        Only vehicle-like detections count; each other vehicle's nearest one within the radius is a sighting
        of it."""
        r = self.params.misbehaviour_radius_m
        cls = np.asarray(cls)
        vehicle_like = (cls == 0) | (cls == 2)  # ObjectClass.UNKNOWN, ObjectClass.VEHICLE
        p = np.asarray(p_map, dtype=float).reshape(-1, 3)[vehicle_like, :2]
        S = np.asarray(cov_map, dtype=float).reshape(-1, 3, 3)[vehicle_like, :2, :2]
        if errors is None:
            A, B, D = (1.0 - self._share) * S, np.zeros_like(S), self._share * S
        else:
            A, B, D = (np.asarray(e, dtype=float).reshape(-1, 3, 3)[vehicle_like, :2, :2] for e in errors)
        match = [None] * len(cls) if matches is None else list(matches)
        match = [m for m, keep in zip(match, vehicle_like, strict=True) if keep]
        if len(p):
            self._reports.setdefault(observer, deque()).append((float(t), p, S, self._report_no))
            self._report_no += 1
        vids, pos, cov = reported
        for vid, c in zip(vids, cov, strict=True):
            stated = None if prior is None else prior.get(str(vid))
            self._prior[str(vid)] = np.asarray(c, dtype=float)[:2, :2] if stated is None else stated
        others = np.asarray(vids) != observer
        if not len(p) or not others.any():
            return
        vids, pos, cov = np.asarray(vids)[others], np.asarray(pos, float)[others], np.asarray(cov, float)[others]
        d = p[None, :, :] - pos[:, None, :2]  # (V, N, 2)
        dist = np.hypot(d[..., 0], d[..., 1])
        k = np.argmin(dist, axis=1)
        rows = np.arange(len(vids))
        for i in np.flatnonzero(dist[rows, k] <= r):
            vid, j = str(vids[i]), int(k[i])
            w = 1.0 if match[j] is None else (match[j][1] if match[j][0] == vid else 1.0 - match[j][1])
            if w <= 0.0:
                continue
            # the observer's error; the observed vehicle's own is the offset under test (its P0)
            sighting = Sighting(float(t), observer, d[i, j], A[j], B[j], D[j], w, p[j], S[j])
            self._sightings.setdefault(vid, deque()).append(sighting)

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
        for vid, q in list(self._sightings.items()):
            while q and q[0].t < t - pp.misbehaviour_window_s:
                q.popleft()
            if not q:
                del self._sightings[vid]
        self._reported_there(self._sightings)
        views: dict[tuple[str, str], View] = {}
        for vid, q in self._sightings.items():
            reports = self._reports.get(vid)
            front = reports[0][3] if reports else self._report_no  # the oldest of its reports still here
            by_observer: dict[str, list[Sighting]] = {}
            for s in q:
                if s.matched < front:  # not a vehicle it reported itself: a sighting of it
                    by_observer.setdefault(s.observer, []).append(s)
            for o, ss in by_observer.items():
                if sum(s.weight for s in ss) >= pp.misbehaviour_min_sightings:
                    views[(o, vid)] = view_of(ss, self._prior[vid] + self._prior[o])
        self.views = views
        disputes = {k: v.q > self.threshold for k, v in views.items()}
        self.disputed = {frozenset(k) for k, off in disputes.items() if off}
        # the most evident offset first: once a vehicle is flagged, its views are no evidence about the others
        # (a vehicle 3 m off sees everyone off), and the others are tested again without them
        involved = {x for pair in views for x in pair}
        not_evidence = {v for v in self.flagged if v not in self._seen_off}  # flagged for ghosts or its clock
        seen_off = {v: why for v, why in self._seen_off.items() if v not in involved}  # nothing seen of it: kept
        self.tests = {}
        while True:
            best = None
            for v in sorted(involved - set(seen_off)):
                test, who = self._judge(v, views, not_evidence | set(seen_off))
                if test is not None:
                    self.tests[v] = test
                if who and (best is None or test.q > best[1].q):
                    best = (v, test, who)
            if best is None:
                break
            v, test, who = best
            b = test.b
            seen_off[v] = (
                f"seen {float(np.hypot(*b)):.1f} m from its reported position ({b[0]:+.1f}, {b[1]:+.1f}) by "
                f"{', '.join(who)} in the last {pp.misbehaviour_window_s:g} s (chi-square {test.q:.0f} > "
                f"{self.threshold:.1f})"
            )
        self._seen_off = seen_off

    def _judge(self, v: str, views: dict[tuple[str, str], View], excluded: set[str]):
        """V's test on the views that involve it and no vehicle in ``excluded``, views that disagree about it
        left out one at a time, the farthest first: (the last test or None, the other vehicles it is flagged
        on, or [] if it is not)."""
        star = {k: view for k, view in views.items() if v in k and not (set(k) - {v}) & excluded}
        test = None
        while star:
            test = network_test(star, self._prior, v)
            if test.q <= self.threshold:
                return test, []
            if test.n == 1 or test.r <= chi2_sf_quantile(self.alpha, 2 * (test.n - 1)):
                who = sorted({x for k in star for x in k} - {v})
                return test, who if len(who) >= self.params.misbehaviour_min_observers else []
            del star[max(test.residuals, key=test.residuals.get)]
        return test, []
