"""The host window's bookkeeping (:mod:`.graph`): each vehicle's and track's states in time order, the keys
of their GTSAM variables and the ids of the factors that hang on them."""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import gtsam
import numpy as np

from schemas import ObjectClass

from .buffer import time_key
from .marginalize import TrackPrior

__all__ = ["Chain", "PoseState", "TrackState"]


@dataclass
class PoseState:
    t: float
    key: int
    pose: np.ndarray  # reported [x, y, z, roll, pitch, yaw]
    cov: np.ndarray  # reported 6x6 over pose
    v_map: np.ndarray
    cov_xi: np.ndarray  # reported covariance in Pose3's tangent [rotation, translation]
    L_xi: np.ndarray  # its Cholesky factor, L L^T = cov_xi
    T: gtsam.Pose3  # the reported pose
    M: np.ndarray  # and its 4x4 matrix
    dets: list = field(default_factory=list)  # DetectionRecords made from this frame
    prior_lin: np.ndarray | None = None  # linearization point (4x4) of a self-localization factor with a bias
    vid: str = ""


@dataclass
class TrackState:
    t: float
    key: int  # Vector6 [p, v]
    dets: list = field(default_factory=list)  # DetectionRecords of this state


@dataclass
class Chain:
    """States of one vehicle or track, sorted by time key, and the motion factors between neighbours."""

    tkeys: list[int] = field(default_factory=list)
    states: dict[int, object] = field(default_factory=dict)
    motion: dict[int, int] = field(default_factory=dict)  # tkey of the earlier state -> factor id
    prior: TrackPrior | None = None  # tracks: on the first state
    prior_fid: int = -1
    pose_prior_fids: dict[int, int] = field(default_factory=dict)  # vehicles: tkey -> self-localization factor
    bias_key: int | None = None  # vehicles: the persistent part of the self-localization error (whitened)
    persist: tuple[float, float] = (0.0, 1.0)  # vehicles: that part's fraction a and correlation time tau (s)
    cls: int = int(ObjectClass.UNKNOWN)

    def latest(self):
        return self.states[self.tkeys[-1]]

    def nearest(self, t: float, tol: float):
        """The state closest to t if it is within tol, else None."""
        if not self.tkeys:
            return None
        tk = time_key(t)
        s = self.states.get(tk)
        if s is not None and s.t == t and tol >= 0.0:  # a state at t itself: none is nearer (the common case)
            return s
        i = bisect.bisect_left(self.tkeys, tk)
        best = None
        for j in (i - 1, i):
            if 0 <= j < len(self.tkeys):
                s = self.states[self.tkeys[j]]
                if abs(s.t - t) <= tol + 1e-9 and (best is None or abs(s.t - t) < abs(best.t - t)):
                    best = s
        return best
