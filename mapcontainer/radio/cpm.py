r"""ETSI collective perception (CPM) object inclusion rules, applied to a vehicle's distributed prior.

ETSI TS 103 324 (Collective Perception Service) generates a CPM at most every 100 ms and includes a
perceived object in it only when the object

1. is new (not included before),
2. moved more than 4 m since it was last included,
3. changed its speed by more than 0.5 m/s since then,
4. changed its heading by more than 4 degrees since then, or
5. was last included 1 s ago or more (T_GenCpmMax);

and objects of a vulnerable class (person, animal; here pedestrian and cyclist) when last included
500 ms ago or more. (The rules as the issue states them and as the standard's inclusion management is
commonly summarised; the standard's text itself was not available for this work, so its remaining
rules — e.g. the redundancy mitigation of later versions — are not modelled.)

Our vehicles send each frame's *detections*, not tracks, so the rules need object identities and
speeds: :class:`CpmRules` keeps a sender-side track per object — detections in the map frame (through
the prior's own pose), associated to tracks by nearest neighbour within ``gate_m`` and of the same
class, each track an alpha-beta filter (gains ``alpha``, ``beta``) for its position and velocity. The
rules compare a track's filtered state with its state when last included; heading changes count only
when both speeds are at least ``min_speed_for_heading_mps`` (the heading of a standing object is
noise). An included object is sent as detected (the filter only decides inclusion). The vehicle's own
pose is in every message: the rules thin the objects, not the prior.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.optimize import linear_sum_assignment

from schemas import ObjectClass, ObjectObservations, VehiclePrior

from .. import geometry as geo

__all__ = ["CpmParams", "CpmRules"]

VRU_CLASSES = (int(ObjectClass.PEDESTRIAN), int(ObjectClass.CYCLIST))


class CpmParams(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    position_m: float = Field(4.0, gt=0)
    speed_mps: float = Field(0.5, gt=0)
    heading_deg: float = Field(4.0, gt=0)
    max_interval_s: float = Field(1.0, gt=0)
    vru_interval_s: float = Field(0.5, gt=0)
    gate_m: float = Field(2.5, gt=0, description="association gate of a detection to a sender-side track")
    alpha: float = Field(0.5, gt=0, le=1)
    beta: float = Field(0.2, gt=0, le=1)
    min_speed_for_heading_mps: float = Field(1.0, ge=0)
    track_timeout_s: float = Field(1.0, gt=0, description="a track not detected for this long is forgotten")


@dataclass
class _Track:
    cls: int
    p: np.ndarray  # map x, y
    v: np.ndarray
    t: float
    t_incl: float | None = None
    p_incl: np.ndarray | None = None
    v_incl: np.ndarray | None = None


class CpmRules:
    """One sender's CPM inclusion management: ``filter(prior)`` returns the prior with only the objects
    the rules include (counts in ``included``/``omitted``)."""

    def __init__(self, params: CpmParams | None = None) -> None:
        self.params = params or CpmParams()
        self.tracks: list[_Track] = []
        self.included = 0
        self.omitted = 0

    def _associate(self, t: float, p: np.ndarray, cls: np.ndarray) -> list[_Track]:
        prm = self.params
        self.tracks = [tr for tr in self.tracks if t - tr.t <= prm.track_timeout_s]
        out: list[_Track | None] = [None] * len(p)
        if self.tracks and len(p):
            pred = np.array([tr.p + tr.v * (t - tr.t) for tr in self.tracks])
            cost = np.linalg.norm(p[:, None, :] - pred[None, :, :], axis=2)
            cost[cls[:, None] != np.array([tr.cls for tr in self.tracks])[None, :]] = np.inf
            big = np.where(np.isfinite(cost), cost, 1e9)
            rows, cols = linear_sum_assignment(big)
            for r, c in zip(rows, cols, strict=True):
                if cost[r, c] <= prm.gate_m:
                    tr = self.tracks[c]
                    dt = max(t - tr.t, 1e-3)
                    resid = p[r] - pred[c]
                    tr.p = pred[c] + prm.alpha * resid
                    tr.v = tr.v + prm.beta * resid / dt
                    tr.t = t
                    out[r] = tr
        for i, tr in enumerate(out):
            if tr is None:
                out[i] = _Track(int(cls[i]), p[i].copy(), np.zeros(2), t)
                self.tracks.append(out[i])
        return out  # type: ignore[return-value]

    def _due(self, t: float, tr: _Track) -> bool:
        prm = self.params
        if tr.t_incl is None:
            return True
        age = t - tr.t_incl
        if age >= prm.max_interval_s - 1e-6 or (tr.cls in VRU_CLASSES and age >= prm.vru_interval_s - 1e-6):
            return True
        if np.linalg.norm(tr.p - tr.p_incl) > prm.position_m:
            return True
        s_now, s_then = float(np.linalg.norm(tr.v)), float(np.linalg.norm(tr.v_incl))
        if abs(s_now - s_then) > prm.speed_mps:
            return True
        if min(s_now, s_then) >= prm.min_speed_for_heading_mps:
            dh = geo.wrap_angle(np.arctan2(tr.v[1], tr.v[0]) - np.arctan2(tr.v_incl[1], tr.v_incl[0]))
            if abs(np.degrees(dh)) > prm.heading_deg:
                return True
        return False

    def filter(self, prior: VehiclePrior) -> VehiclePrior:
        """The prior with the objects the rules include now (at its ``t_meas``)."""
        obs = prior.objects
        n = len(obs)
        if n == 0:
            return prior
        t = float(prior.t_meas)
        T_map_body = geo.pose_to_matrix(np.asarray(prior.pose, float))
        p_map = geo.transform_points(T_map_body, obs.p_body)[:, :2]
        tracks = self._associate(t, p_map, np.asarray(obs.cls, int))
        keep = np.array([self._due(t, tr) for tr in tracks], dtype=bool)
        for tr, k in zip(tracks, keep, strict=True):
            if k:
                tr.t_incl, tr.p_incl, tr.v_incl = t, tr.p.copy(), tr.v.copy()
        self.included += int(keep.sum())
        self.omitted += int((~keep).sum())
        if keep.all():
            return prior
        kept = ObjectObservations(p_body_cm=obs.p_body_cm[keep], cov=obs.cov[keep], cls=obs.cls[keep])
        return prior.model_copy(update={"objects": kept})
