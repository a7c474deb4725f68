"""The downlink, vehicle side: the host's "what the others know about you" fused into the on-board estimate.

A :class:`~schemas.PoseDownlink` is the others' knowledge of the vehicle's pose at one of its own frames
(t_D), its own share removed by the host (:mod:`.downlink`). The vehicle:

1. moves it to the present with its own motion since t_D (its filtered poses at t_D and now):
   z = D + (own_now - own_D) on position and angles, with the displacement's error added
   (``transport_fraction`` of its length, and its length times the own heading's sigma, per horizontal axis);
2. keeps only the directions the others inform: from the eigen-decomposition Y = U diag(lambda) U^T of the
   message's information, the eigenvalues above :data:`~.downlink.MIN_INFO`: H = U_k^T, R = diag(1 / lambda_k),
   plus the displacement's error H Q H^T;
3. checks it against its own estimate (its integrity monitor): innovation nu = H (z - x) (angles wrapped),
   S = H P H^T + R, nu^T S^-1 nu against the chi^2 quantile at ``gate_p``; beyond it the downlink is refused
   and counted, the vehicle's own estimate stays (a wrong host cannot drag a vehicle that is right);
4. fuses it. Exact (the host removed the vehicle's own share, so the two are independent): the Kalman update
   K = P H^T S^-1, x+ = x + K nu, P+ = (I - K H) P (I - K H)^T + K R K^T. Where the correlation is not
   known: covariance intersection. That is the case while the localizer runs from a start the downlink
   seeded (its estimate then holds some of the others' information, which the next downlink holds again):
   Y+ = w P^-1 + (1 - w) H^T R^-1 H, x+ = x + Y+^-1 (1 - w) H^T R^-1 nu, w in [0, 1] minimising the
   horizontal variance.

The result is the vehicle's on-board estimate; the localizer itself is left alone, and the prior the vehicle
sends is its own (so no information loops through the host). While the localizer searches for its start,
the downlink is one more hypothesis source: :meth:`DownlinkFusion.seed` proposes a start pose (the vehicle's
own estimate fused with the downlink, the downlink's covariance inflated by ``seed_inflation``: a basin to
verify, not a measurement) which the localizer verifies with its global search like any known start.
A downlink older than ``max_age_s`` is not used; only the newest is kept (each is a whole posterior, never
an increment: fusing two would count their common information twice).
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.stats import chi2

from schemas import PoseDownlink
from schemas.arrays import cov_from_upper

from .downlink import MIN_INFO
from .geometry import wrap_angle

__all__ = ["DownlinkFusion", "DownlinkParams", "Onboard"]

_OMEGAS = np.linspace(0.0, 1.0, 41)


@dataclass(frozen=True)
class DownlinkParams:
    """How a vehicle uses the host's downlink (module docstring)."""

    gate_p: float = 1e-3  # false-alarm probability of the consistency gate (chi^2 on the innovation)
    max_age_s: float = 1.0  # a downlink about a frame older than this is not used
    transport_fraction: float = 0.02  # 1-sigma error of the own displacement since t_D, per metre
    # while searching, propose a start from the downlink (the hypothesis source). Off: on development seeds 11-13
    # (urban, 10 s) the seeds cost accuracy (on-board RMSE 0.239 m with, 0.188 m without; off 0.324 m): a seed
    # resets the localizer, whose own hypotheses are lost (docs/downlink.md)
    seed_search: bool = False
    seed_max_sigma_m: float = 1.5  # a searching localizer is seeded only by a downlink at least this good (1 sigma)
    seed_max_yaw_sigma_rad: float = 0.2  # ... and only when the heading is known that well (its or the downlink's)
    seed_inflation: float = 4.0  # the seed's covariance takes the downlink's times this
    seed_interval_s: float = 3.0  # at most one seed per this many seconds (the verification takes frames)
    history_s: float = 2.0  # own poses kept for moving a downlink to the present
    always_ci: bool = False  # covariance intersection always, not only where the correlation is known to be unknown


@dataclass(frozen=True)
class Onboard:
    """The on-board estimate of one frame: ``pose``/``cov`` (6, 6x6), and what the downlink did (``status``:
    "none", "stale", "refused", "fused", "fused_ci"; ``nis``: the innovation's chi^2 when it was checked)."""

    pose: np.ndarray
    cov: np.ndarray
    status: Literal["none", "stale", "refused", "fused", "fused_ci"] = "none"
    nis: float | None = None

    @property
    def used(self) -> bool:
        return self.status in ("fused", "fused_ci")


def _delta(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a - b on [x, y, z, roll, pitch, yaw], angles wrapped."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    d[3:] = wrap_angle(d[3:])
    return d


@dataclass
class DownlinkFusion:
    """One vehicle's use of the downlink: ``receive`` messages, ``record`` its own poses, ``fuse`` each frame."""

    vehicle_id: str
    fleet: str
    params: DownlinkParams = field(default_factory=DownlinkParams)
    counts: Counter = field(default_factory=Counter)
    latest: PoseDownlink | None = None
    _history: deque = field(default_factory=deque)  # (t, pose (6,), cov (6x6)) of the own estimate
    _last_seed_t: float = -np.inf

    def receive(self, msg: PoseDownlink) -> str | None:
        """Keep the newest downlink about this vehicle; the reason (counted) when it is not taken."""
        reason = None
        if msg.fleet != self.fleet:
            reason = "fleet"
        elif msg.target != self.vehicle_id:
            reason = "not_for_us"
        elif self.latest is not None and msg.t_meas <= self.latest.t_meas:
            reason = "old"
        self.counts["received"] += 1
        if reason is not None:
            self.counts[f"rejected_{reason}"] += 1
            return reason
        self.latest = msg
        return None

    def record(self, t: float, pose: np.ndarray, cov: np.ndarray) -> None:
        """The vehicle's own filtered estimate at its frame t (what a downlink about frame t is moved from)."""
        self._history.append((float(t), np.asarray(pose, dtype=float), np.asarray(cov, dtype=float)))
        while self._history and self._history[0][0] < t - self.params.history_s:
            self._history.popleft()

    def _own_at(self, t: float) -> np.ndarray | None:
        for ts, pose, _ in reversed(self._history):
            if abs(ts - t) < 1e-6:
                return pose
        return None

    def measurement(self, t: float, pose_now: np.ndarray, cov_now: np.ndarray):
        """The newest downlink moved to ``t`` as a measurement (z, H, R) of the pose's informed directions
        (module docstring), None when there is none, it says nothing, it is older than ``max_age_s``, or the
        own pose of its frame is not in the history (counted ``stale``)."""
        d = self.latest
        if d is None:
            return None
        own_d = self._own_at(d.t_meas)
        if t - d.t_meas > self.params.max_age_s or own_d is None:
            self.counts["stale"] += 1
            return None
        step = _delta(pose_now, own_d)
        z = np.asarray(d.pose, dtype=float) + step
        z[3:] = wrap_angle(z[3:])
        Y = cov_from_upper(np.asarray(d.pose_info, dtype=float))
        w, U = np.linalg.eigh(0.5 * (Y + Y.T))
        keep = w > MIN_INFO
        if not keep.any():
            return None
        H = U[:, keep].T
        length = float(np.hypot(*step[:2]))
        Q = np.zeros((6, 6))
        Q[0, 0] = Q[1, 1] = (self.params.transport_fraction * length) ** 2 + length**2 * float(cov_now[5, 5])
        return z, H, np.diag(1.0 / w[keep]) + H @ Q @ H.T

    def fuse(self, t: float, pose: np.ndarray, cov: np.ndarray, correlated: bool = False) -> Onboard:
        """The on-board estimate at t: the own (pose, cov) with the newest downlink fused if it is fresh and
        consistent; ``correlated``: the own estimate holds downlink information (covariance intersection)."""
        pose, cov = np.asarray(pose, dtype=float), np.asarray(cov, dtype=float)
        m = self.measurement(t, pose, cov)
        if m is None:
            return Onboard(pose, cov, "none" if self.latest is None else "stale")
        out = _update(pose, cov, *m, self.params.gate_p, correlated or self.params.always_ci)
        self.counts[out.status] += 1
        return out

    def seed(self, t: float, pose: np.ndarray, cov: np.ndarray, speed: float, t_next: float):
        """A start pose for a searching localizer (module docstring), at ``t_next`` (the next frame: the own
        estimate at ``t`` moved by ``speed`` along its heading), or None: no fresh downlink good enough, the
        heading unknown, refused by the gate, or seeded within ``seed_interval_s``."""
        p = self.params
        if not p.seed_search or t - self._last_seed_t < p.seed_interval_s:
            return None
        pose, cov = np.asarray(pose, dtype=float), np.asarray(cov, dtype=float)
        m = self.measurement(t, pose, cov)
        if m is None:
            return None
        z, H, R = m
        Y = H.T @ np.linalg.solve(R, H)  # the downlink's information over the pose
        if np.linalg.eigvalsh(Y[:2, :2])[0] < p.seed_max_sigma_m**-2:
            return None
        if cov[5, 5] > p.seed_max_yaw_sigma_rad**2 and Y[5, 5] < p.seed_max_yaw_sigma_rad**-2:
            self.counts["seed_no_heading"] += 1
            return None
        out = _update(pose, cov, z, H, R * p.seed_inflation, p.gate_p, False)
        if not out.used:
            return None
        y, P = out.pose.copy(), out.cov.copy()
        step = speed * (t_next - t)
        y[:2] += step * np.array([np.cos(y[5]), np.sin(y[5])])
        P[:2, :2] += ((p.transport_fraction * step) ** 2 + step**2 * P[5, 5]) * np.eye(2)
        self._last_seed_t = t
        self.counts["seeded"] += 1
        return y, 0.5 * (P + P.T)


def _update(x, P, z, H, Rk, gate_p: float, correlated: bool) -> Onboard:
    """Gate and fuse the measurement H x = H z + N(0, Rk) into N(x, P) (module docstring)."""
    nu = H @ _delta(z, x)
    S = H @ P @ H.T + Rk
    nis = float(nu @ np.linalg.solve(S, nu))
    if nis > chi2.isf(gate_p, len(nu)):
        return Onboard(x, P, "refused", nis)
    if not correlated:
        K = np.linalg.solve(S, H @ P).T
        IKH = np.eye(len(x)) - K @ H
        x1, P1 = x + K @ nu, IKH @ P @ IKH.T + K @ Rk @ K.T
        status = "fused"
    else:
        Y_own, Y_d = np.linalg.inv(P), H.T @ np.linalg.solve(Rk, H)
        # w = 0 left out: the downlink alone leaves directions without information
        candidates = [(om, np.linalg.inv(om * Y_own + (1.0 - om) * Y_d)) for om in _OMEGAS[1:]]
        om, P1 = min(candidates, key=lambda c: np.trace(c[1][:2, :2]))
        x1 = x + P1 @ ((1.0 - om) * H.T @ np.linalg.solve(Rk, nu))
        status = "fused_ci"
    x1[3:] = wrap_angle(x1[3:])
    return Onboard(x1, 0.5 * (P1 + P1.T), status, nis)
