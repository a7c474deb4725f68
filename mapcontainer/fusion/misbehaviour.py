"""Misbehaviour detection: does a vehicle's reported pose agree with what the other vehicles see of it?

Every detection of a vehicle-like object (class vehicle or unknown) by another connected vehicle, at
a map-frame position ``m`` (from the observer's pose), within ``misbehaviour_radius_m`` of vehicle V's
reported position ``p_V`` at that instant, is a sighting of V with offset ``d = m - p_V``; per
observer and instant only the nearest sighting counts. An honest V is seen where it says it is:
its offsets scatter about zero by the observers' and V's pose errors and the detector's noise (a few
decimetres). A vehicle whose pose is biased by ``b`` is seen at ``-b`` from where it says it is, by every
observer, instant after instant.

Over the last ``misbehaviour_window_s`` seconds, each other vehicle O with at least
``misbehaviour_min_sightings`` sightings of V has a *view* of V: the median of its offsets. The view
agrees when it is within ``misbehaviour_offset_m`` of zero and disagrees otherwise. A disagreement says
that O or V is wrong, not which: the two are *disputed*, and while they are, neither cross-localizes
the other (one lying vehicle must not pull its honest neighbours). V is *flagged* as the wrong one

* when at least ``misbehaviour_min_observers`` unflagged observers disagree with it and their views
  agree with each other (each within ``misbehaviour_spread_m`` of their median): they independently see
  V somewhere else; or
* when a single observer O disagrees with it, and O is *corroborated* while V is not: O's views agreed
  with some third vehicle in the last ``misbehaviour_trust_s`` seconds (O saw it, or was seen by it,
  where it said it was), V's did not.

The flag stays until every current view of V agrees again.

A flagged vehicle's detections are not fused and it cannot cross-localize others or be cross-localized
(:class:`~mapcontainer.fusion.container.Container`): its error stays its own.

Pure: time is the detections' ``t_meas``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from .params import FusionParams

__all__ = ["MisbehaviourMonitor", "Sighting"]


@dataclass(frozen=True)
class Sighting:
    """Observer ``observer`` saw something ``offset`` (map x, y) from where the vehicle said it was at ``t``."""

    t: float
    observer: str
    offset: np.ndarray


class MisbehaviourMonitor:
    """Sightings per vehicle and the flags they raise (module doc)."""

    def __init__(self, params: FusionParams):
        self.params = params
        self._sightings: dict[str, deque[Sighting]] = {}
        self._agreed: dict[frozenset[str], float] = {}  # pair of vehicles -> last time a view between them agreed
        self.flagged: dict[str, str] = {}  # vehicle -> why
        self.disputed: set[frozenset[str]] = set()  # pairs whose views disagree now
        self.flagged_total = 0  # flags raised (a vehicle flagged, cleared and flagged again counts twice)

    def observe(self, observer: str, t: float, p_map: np.ndarray, cls: np.ndarray, reported: dict[str, np.ndarray]):
        """One message's vehicle-like detections (map positions ``p_map`` (N, 3), classes ``cls``) by
        ``observer`` at ``t``, against the other vehicles' reported positions at ``t`` (vid -> (3,))."""
        r = self.params.misbehaviour_radius_m
        p = np.asarray(p_map, dtype=float).reshape(-1, 3)[:, :2]
        vehicle_like = np.isin(np.asarray(cls), (0, 2))  # ObjectClass.UNKNOWN, ObjectClass.VEHICLE
        p = p[vehicle_like]
        if not len(p):
            return
        for vid, pos in reported.items():
            if vid == observer:
                continue
            d = p - np.asarray(pos, dtype=float)[:2]
            dist = np.hypot(d[:, 0], d[:, 1])
            k = int(np.argmin(dist))
            if dist[k] <= r:
                self._sightings.setdefault(vid, deque()).append(Sighting(float(t), observer, d[k]))

    def disputes(self, a: str, b: str) -> bool:
        """Whether a and b see each other elsewhere than they say (cross-localization between them is off)."""
        return frozenset((a, b)) in self.disputed

    def update(self, t: float) -> dict[str, str]:
        """Drop sightings older than the window before ``t``, form the views, decide disputes and flags."""
        pp = self.params
        views: dict[tuple[str, str], np.ndarray] = {}  # (observer, observed) -> median offset
        for vid, q in list(self._sightings.items()):
            while q and q[0].t < t - pp.misbehaviour_window_s:
                q.popleft()
            if not q:
                del self._sightings[vid]
                continue
            by_observer: dict[str, list[np.ndarray]] = {}
            for s in q:
                by_observer.setdefault(s.observer, []).append(s.offset)
            for o, d in by_observer.items():
                if len(d) >= pp.misbehaviour_min_sightings:
                    views[(o, vid)] = np.median(d, axis=0)
        agrees = {k: float(np.hypot(*m)) <= pp.misbehaviour_offset_m for k, m in views.items()}
        for (o, v), ok in agrees.items():
            if ok:
                self._agreed[frozenset((o, v))] = t
        self._agreed = {k: tk for k, tk in self._agreed.items() if t - tk <= pp.misbehaviour_trust_s}
        self.disputed = {frozenset(k) for k, ok in agrees.items() if not ok}
        for pair in self.disputed:  # what two vehicles agreed on before they disputed no longer vouches for either
            self._agreed.pop(pair, None)

        def corroborated(x: str, other: str) -> bool:
            return any(x in pair and other not in pair for pair in self._agreed)

        for v in sorted({v for _, v in views}):
            mine = {o: m for (o, vv), m in views.items() if vv == v}
            if all(agrees[(o, v)] for o in mine):
                self.flagged.pop(v, None)
                continue
            accusers = {o: m for o, m in mine.items() if not agrees[(o, v)] and o not in self.flagged}
            if not accusers:
                continue
            centre = np.median(np.array(list(accusers.values())), axis=0)
            consistent = all(float(np.hypot(*(m - centre))) < pp.misbehaviour_spread_m for m in accusers.values())
            by_many = len(accusers) >= pp.misbehaviour_min_observers and consistent
            by_trusted = [o for o in accusers if corroborated(o, v) and not corroborated(v, o)]
            if by_many or by_trusted:
                if v not in self.flagged:
                    self.flagged_total += 1
                who = sorted(accusers) if by_many else by_trusted
                self.flagged[v] = (
                    f"seen {float(np.hypot(*centre)):.1f} m from its reported position ({centre[0]:+.1f}, "
                    f"{centre[1]:+.1f}) by {', '.join(who)} in the last {pp.misbehaviour_window_s:g} s"
                )
        return dict(self.flagged)
