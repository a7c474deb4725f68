"""Self-localization over time: odometry prediction, map matching, failure detection, fallback, recovery.

The filter's equations are in :mod:`.ekf`; start-up, verification, recovery and tracking are the
phases of :class:`.startup.StartupMachine` (``Localizer.phase``).

:class:`Localizer` is pure: ``step(t, frame, odometry, gnss)`` takes the scenario time as an
argument and returns a :class:`LocalizationResult`; bad input is counted in ``stats`` and
returned as a result with a reason, never raised.

One step::

    initialise?  from GNSS and a heading (below)
    predict      the state over dt = t - t_prev with the odometry (unicycle)
    match        the camera frame from the prediction (MapMatcher)
                 -> accepted if converged and no jump against the prediction: mode "map_matching"
                 -> otherwise:                                               mode "fallback"
    GNSS         EKF update of position + GNSS bias (outlying fixes down-weighted, far ones dropped)
    fallback     + the ground constraint (height on the road, roll = pitch = 0)

If converged matches keep being rejected as jumps (``jump_reset_after`` in a row), the prediction
is distrusted: its position and yaw covariance are widened and the match is tried again. If the
state stays farther from the GNSS fixes than GNSS alone can err (``gnss_divergence_m`` for
``gnss_divergence_fixes`` fixes in a row), it is in a wrong basin that its own matches keep
confirming (the fixes are all refused by the gate): the localizer starts again from GNSS.

The state is ``[x, y, z, roll, pitch, yaw, k_v, b_w, b_E, b_N]``: the pose, the wheel-speed
scale factor, the gyro bias and the GNSS receiver's slowly drifting horizontal bias (first-order
Gauss-Markov). While map matching holds the position, the GNSS fixes teach the filter the bias; in
fallback, the fixes then pull the position towards ``fix - bias``, and their information never
accumulates below the bias' uncertainty (a low-cost receiver's errors are correlated for a minute:
treated as white they would make the fallback overconfident).

Start-up (and after :meth:`Localizer.reset`), in this order:

1. ``initial_pose`` (pose and covariance known at start, e.g. the last estimate before parking),
   verified: for up to ``verify_start_frames`` frames the global pose search over its own
   covariance also matches each frame; its accepted solution is taken, and a local match that a
   distinct search solution beats by the margin is rejected (its basins tracked as hypotheses, as
   below): a start a few sigma off in yaw otherwise lets the local solve fit a wrong pole exactly,
   and the tracker never leaves that basin (see :mod:`.startup`);
2. ``initial_yaw`` given to the constructor or to ``reset``, with the GNSS position;
3. the course over ground (GNSS displacement over ``init_course_distance_m`` aligned with the
   dead-reckoned odometry path);
4. the HD map: the driving directions of the centre lines within 3 sigma of the GNSS fix. One
   direction (a one-way road) is the heading, with the directions' spread as its uncertainty.
   Two (a two-way road): the camera decides, by the global pose search (:mod:`.search`) over both
   directions and the GNSS region. Its candidate basins are tracked as hypotheses (prediction, local
   match, accumulated evidence) until one is accepted, by the rule ``search.accept``:
   ``"landmarks"`` (the default): one is well constrained (``search.min_constraints``, distinct map
   landmarks counted, at least ``search.min_landmarks``) and beats the others by ``search.margin``;
   the first search waits for a frame that could decide (:meth:`.PoseSearch.can_accept`).
   ``"posterior"`` (opt-in; on suburban roads it accepts lone-pole starts metres off along the road,
   see docs/localization.md): one holds at least ``1 - search.accept_epsilon`` of the posterior mass
   (the newest fix through a heavy-tailed likelihood, and *elsewhere* for a basin the search did not
   reach: :mod:`.hypotheses`); a pole seen over a baseline of travel with the lanes is enough. Under
   either rule the posterior mass is tracked. While a lone hypothesis has not won, the search runs
   again on every frame and its new basins join as rivals (a weakly supported wrong basin would
   otherwise hold the start).

Until then the result is the GNSS fix with a yaw variance of pi^2 / 3 (uniform), ``initialized``
False, mode "fallback". While an initialised localizer is searching (phase SEARCHING), the result's
pose and covariance are the moment-matched Gaussian of its hypotheses and the GNSS + odometry
estimate, each by its posterior mass (wide and honest: never one basin among rivals).

Whenever the prediction is too wide for one local solve (horizontal 1-sigma above ``search_sigma_m``,
yaw above ``search_sigma_yaw_rad``: start-up, long fallback,
repeated jumps) the same search and hypotheses decide the basin; until they do, mode "fallback".
A match is never taken from a wide prediction on three constraints alone: that is how a wrong
lane, a wrong lamp post or the opposite heading used to be accepted with a confident covariance.

Integrity: a map-matched result carries ``protection_level`` (lateral, longitudinal, m): K sigma of
its filtered covariance in the vehicle frame at ``integrity_risk`` per axis. A fix that the GNSS gate
refuses while the state is map matched (its innovation chi^2 beyond ``gnss_gate_chi2``) is a detected
fault: that frame states no protection level (the vehicle does not claim integrity); detections
inconsistent with the map are excluded by the matcher's inlier gate.

What to send on: ``pose``/``cov`` are the tracker's posterior by default (``report="filtered"``),
the best estimate of the vehicle's pose now; ``cov_filtered`` includes the error every frame repeats
(``match_bias_sigma``: calibration, the map's survey drift) and ``cov_camera`` is the same without it,
the covariance of the pose as the camera sees the map. A VehiclePrior carries the filtered pose with
``cov_camera`` and the bias beside it (``pose_filtered``, ``pose_bias_sigma``): a consumer fuses only
the newest. ``pose_frame``/``cov_frame`` are this frame's camera evidence with a weak prior (see
:mod:`.matcher`), for a consumer that fuses frames itself, or ``report="frame"``.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any

import numpy as np
from scipy.stats import norm

from schemas import bias_cov

from ..hdmap.model import HDMap
from . import ekf
from .matcher import MapMatcher
from .matcher_types import CameraFrame, MatchResult
from .params import GnssMeasurement, LocalizationResult, LocalizerParams, OdometryMeasurement
from .search import PoseSearch
from .startup import UNIFORM_YAW_VAR, Phase, StartupMachine

__all__ = ["Localizer"]

log = logging.getLogger(__name__)


def _as_odometry(o) -> OdometryMeasurement | None:
    if o is None:
        return None
    if isinstance(o, tuple | list):
        return OdometryMeasurement(float(o[0]), float(o[1]))
    return OdometryMeasurement(float(o.speed), float(o.yaw_rate))


def _as_gnss(g) -> GnssMeasurement | None:
    if g is None:
        return None
    if isinstance(g, tuple | list):
        return GnssMeasurement(np.asarray(g[0], dtype=float).reshape(-1), float(g[1]), float(g[2]))
    return GnssMeasurement(np.asarray(g.p_map, dtype=float).reshape(-1), float(g.sigma_h_m), float(g.sigma_v_m))


class Localizer:
    """Tracks one vehicle's pose by HD-map matching with a GNSS + odometry fallback (see the module doc).

    Prediction (unicycle, :func:`.ekf.predict`) with the wheel speed and the gyro; a match is folded in
    through its information (:func:`.ekf.match_update`). Failure = the match did not converge (too few
    constraints, cost too high, no features) or jumped (chi^2 of its change against the prediction >
    jump_gate_chi2).
    In fallback the EKF keeps GNSS and the ground constraint; every frame with features is matched
    from the fallback estimate, whose covariance has grown, and the matcher's wide-basin search
    takes over when needed (recovery).
    """

    def __init__(
        self,
        hdmap: HDMap,
        params: LocalizerParams | None = None,
        initial_yaw: float | None = None,
        initial_pose: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        self.params = params or LocalizerParams()
        self.hdmap = hdmap
        self.matcher = MapMatcher(hdmap, self.params.matcher)
        self.search = PoseSearch(self.matcher, self.params.search)
        self.stats: dict[str, int] = {}
        self.startup = StartupMachine(hdmap, self.params, self.matcher, self.search, self._count, self._ground_height)
        self.reset(initial_yaw, initial_pose)

    # ------------------------------------------------------------------ public

    def reset(
        self, initial_yaw: float | None = None, initial_pose: tuple[np.ndarray, np.ndarray] | None = None
    ) -> None:
        """Forget the state; the next steps initialise again: from ``initial_pose`` (pose (6,), 6x6
        covariance: a pose known at start, e.g. the last estimate before the vehicle was parked) if
        given, else from GNSS and a heading."""
        if initial_pose is not None:
            pose0, cov0 = (np.asarray(a, dtype=float) for a in initial_pose)
            if (
                pose0.shape != (6,)
                or cov0.shape != (6, 6)
                or not (np.all(np.isfinite(pose0)) and np.all(np.isfinite(cov0)))
            ):
                raise ValueError("initial_pose must be a finite (pose (6,), covariance 6x6) pair")
            if np.any(np.linalg.eigvalsh(0.5 * (cov0 + cov0.T)) <= 0):
                raise ValueError("initial_pose covariance is not positive definite")
            initial_pose = (pose0, 0.5 * (cov0 + cov0.T))
        self.y: np.ndarray | None = None  # see the module doc
        self.P: np.ndarray | None = None
        self.t_prev: float | None = None
        self._odo_prev: OdometryMeasurement | None = None
        self._last: LocalizationResult | None = None
        # (F, y_pred, P_pred) of the last step if its updates (camera, GNSS, ground) were applied to the
        # prediction F y_prev of the state before the step, else None (the step initialised, possibly
        # after a reset, or a start-up hypothesis brought its own prediction): a joint estimator holding
        # this state can condition on it.
        self.conditioned: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        # Cov(y, m_k) of the map error m_k of each landmark seen (consider states, see ekf.consider_match_update),
        # and the P they are relative to (a holder that replaces P, a joint estimator, is followed by consider_carry)
        self.consider: dict[tuple[str, int], np.ndarray] = {}
        self._P_consider: np.ndarray | None = None
        self.startup.reset(initial_yaw, initial_pose)

    @property
    def initialized(self) -> bool:
        return self.y is not None

    @property
    def phase(self) -> Phase:
        """What the localizer is doing: uninitialised, verifying a known start, searching, tracking."""
        return self.startup.phase

    @property
    def pose(self) -> np.ndarray | None:
        """The current (filtered) pose estimate."""
        return None if self.y is None else self.y[:6].copy()

    def step(self, t: float, frame: CameraFrame | None, odometry: Any | None, gnss: Any | None) -> LocalizationResult:
        """Advance to time t with this frame's camera detections, odometry and GNSS fix (each may be None)."""
        p = self.params
        try:
            odometry, gnss = _as_odometry(odometry), _as_gnss(gnss)
        except (TypeError, ValueError, AttributeError, IndexError) as exc:
            return self._bad_input(t, f"input malformed: {exc}")
        bad = self._check_inputs(t, odometry, gnss)
        if bad:
            return self._bad_input(t, bad)
        self.conditioned = None
        fresh = not self.initialized  # initialised in this step: nothing to condition on
        if fresh:
            dt_init = t - self.t_prev if self.t_prev is not None else 0.0
            self.startup.advance_course(t, self.t_prev, odometry, gnss)
            odo_prev, self.t_prev, self._odo_prev = self._odo_prev, t, odometry
            state = self.startup.try_initialise(frame, gnss, dt_init, odo_prev, odometry)
            if state is None:
                reason = "initialising: no heading yet" if gnss is not None else "initialising: no GNSS fix"
                self._last = self._uninitialised(t, gnss, reason)
                return self._last
            self.y, self.P = state
            self._count("initialised")
            dt = 0.0
        else:
            dt = t - self.t_prev
            if dt > p.max_gap_s:
                self._count("gap_reset")
                log.warning("gap of %.2f s > max_gap_s: re-initialising", dt)
                self.reset(None)
                return self.step(t, frame, odometry, gnss)
        odo_prev = self._odo_prev
        y_prior = self.y
        if fresh:
            self.consider = {}
        elif self.consider and self.P is not self._P_consider:  # P replaced by its holder since the last step
            self.consider = ekf.consider_carry(self.consider, self._P_consider, self.P)
        y_pred, P_pred = ekf.predict(self.y, self.P, dt, odo_prev, odometry, p)
        F = ekf.transition(y_prior, dt, odo_prev, odometry, p)[1]
        if F is not None:
            self.consider = {k: F @ c for k, c in self.consider.items()}
        self.t_prev, self._odo_prev = t, odometry

        predicted = y_pred
        match, reason, y_pred, P_pred = self.startup.match(frame, y_pred, P_pred, dt, odo_prev, odometry, gnss)
        if y_pred is not predicted:  # a start-up hypothesis' own prediction: no cross-covariances with this state
            self.consider = {}
        elif not fresh:  # the updates apply to the prediction from the previous state
            self.conditioned = (np.eye(ekf.N) if F is None else F, y_pred, P_pred)
        if match is not None:
            y, P = self._match_update(y_pred, P_pred, match)
            mode = "map_matching"
        else:
            self._count("fallback")
            y, P = y_pred, P_pred
            mode = "fallback"
        P_before = P
        y, P, gnss_outcome = ekf.gnss_update(y, P, gnss, p)
        if gnss_outcome == "rejected":
            self._count("gnss rejected")
        if self.startup.diverged(gnss, y):
            self._count("gnss_divergence_reset")
            log.warning("%d GNSS fixes in a row > %.0f m away: re-initialising", self.startup.far, p.gnss_divergence_m)
            self.reset(None)
            return self.step(t, frame, odometry, gnss)
        if mode == "fallback":
            y, P = ekf.ground_update(y, P, self._ground_height(y), p)
        self.consider = self._in_range(ekf.consider_carry(self.consider, P_before, P), y)
        self.y, self.P = y, P
        self._P_consider = P
        self._last = self._result(t, mode, odometry, match, self.startup.attempt, reason, gnss_outcome == "used")
        if mode == "map_matching":
            if gnss_outcome == "rejected":  # the fix and the map-matched state disagree beyond the gate: a fault
                self._count("integrity fault")
                self._last = replace(self._last, reason="integrity: GNSS innovation beyond the gate")
            else:
                self._last = replace(self._last, protection_level=self.protection_level(self._last))
        return self._last

    def _match_update(self, y_pred: np.ndarray, P_pred: np.ndarray, match: MatchResult):
        """Fold the match in: under ``map_errors='consider'`` with the landmarks' map errors as consider states
        (:func:`.ekf.consider_match_update`) when it is a full view; otherwise, and for a start-up hypothesis' view
        (its information weight below 1, see :mod:`.basins`), through :func:`.ekf.match_update`, the consider
        states forgotten."""
        w = self.startup.weight
        if self.params.map_errors == "independent" or w < 1.0 or match.linearization is None:
            self.consider = {}
            return ekf.match_update(y_pred, P_pred, match, w)
        sigma_m = self.params.matcher.landmark_map_sigma_m
        y, P, self.consider = ekf.consider_match_update(
            y_pred, P_pred, self.consider, match.linearization, match.pose_filtered, sigma_m
        )
        return y, P

    def _in_range(self, C: dict[tuple[str, int], np.ndarray], y: np.ndarray) -> dict[tuple[str, int], np.ndarray]:
        """The consider states of the landmarks within the matcher's range of the vehicle (the others cannot be
        seen from here; one seen again later starts anew)."""
        if not C:
            return C
        where = {"point": self.matcher._pt_xyz, "pole": self.matcher._pole_base}
        r2 = self.params.matcher.range_m**2
        return {
            k: c for k, c in C.items() if k[0] not in where or float(np.sum((where[k[0]][k[1], :2] - y[:2]) ** 2)) <= r2
        }

    def protection_level(self, res: LocalizationResult) -> np.ndarray:
        """(lateral, longitudinal) protection levels (m) of a result: K sigma of its filtered covariance in the
        vehicle frame, K the two-sided Gaussian quantile of ``integrity_risk`` (3.29 at 1e-3)."""
        k = float(norm.isf(0.5 * self.params.integrity_risk))
        c, s = np.cos(res.pose_filtered[5]), np.sin(res.pose_filtered[5])
        along, across = np.array([c, s]), np.array([-s, c])
        C = res.cov_filtered[:2, :2]
        return k * np.sqrt(np.array([across @ C @ across, along @ C @ along]))

    # ------------------------------------------------------------------ inputs

    def _check_inputs(self, t, odometry, gnss) -> str:
        if not np.isfinite(t):
            return "time not finite"
        if self.t_prev is not None and t < self.t_prev:
            return "time went backwards"
        if odometry is not None and not (np.isfinite(odometry.speed) and np.isfinite(odometry.yaw_rate)):
            return "odometry not finite"
        if gnss is not None:
            if gnss.p_map.shape != (3,) or not np.all(np.isfinite(gnss.p_map)):
                return "GNSS fix invalid"
            if not (gnss.sigma_h_m > 0 and gnss.sigma_v_m > 0):
                return "GNSS sigmas invalid"
        return ""

    def _bad_input(self, t, reason: str) -> LocalizationResult:
        """Bad input is data: count it, log it once, return the last result with the reason and
        ``bad_input`` set (it is not an estimate at ``t``)."""
        self._count(reason.split(":")[0])
        if self._last is not None:
            return replace(self._last, reason=reason, bad_input=True)
        return replace(self._uninitialised(float(t) if np.isfinite(t) else 0.0, None, reason), bad_input=True)

    def _count(self, key: str) -> None:
        if key not in self.stats:
            log.info("localizer: first %r", key)
        self.stats[key] = self.stats.get(key, 0) + 1

    # ------------------------------------------------------------------ map

    def _ground_height(self, x) -> float | None:
        """The height of the road's nearest lane sample under x (within 30 m), else None."""
        tree = self.matcher._lane_tree
        if tree is None:
            return None
        d, i = tree.query(np.asarray(x)[:2])
        return float(self.matcher._lane_xyz[i, 2]) if d < 30.0 else None

    # ------------------------------------------------------------------ results

    def _uninitialised(self, t: float, gnss: GnssMeasurement | None, reason: str) -> LocalizationResult:
        """The GNSS position with an unknown heading (or nothing at all)."""
        p = self.params
        pose = np.zeros(6)
        cov = np.diag([1e6, 1e6, 1e6, 1.0, 1.0, UNIFORM_YAW_VAR])
        if gnss is not None:
            pose[:3] = gnss.p_map
            # as the initial state's: the bias, the white noise and a multipath jump the fix may carry
            cov[0, 0] = cov[1, 1] = p.gnss_bias_sigma_m**2 + ekf.gnss_white_var(gnss, p) + p.init_extra_sigma_m**2
            cov[2, 2] = gnss.sigma_v_m**2
            cov[3, 3] = cov[4, 4] = p.ground_roll_pitch_sigma_rad**2
        return LocalizationResult(t, pose, cov, np.zeros(3), "fallback", False, reason=reason)

    def _result(
        self,
        t,
        mode,
        odometry,
        match: MatchResult | None,
        attempt: MatchResult | None,
        reason: str,
        gnss_used: bool,
    ):
        speed = float(self.y[ekf.SCALE]) * (odometry.speed if odometry is not None else 0.0)
        yaw, pitch = self.y[5], self.y[4]
        vel = speed * np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), -np.sin(pitch)])
        q = {}
        if attempt is not None:
            q = dict(
                n_points=attempt.n_points,
                n_poles=attempt.n_poles,
                n_lane=attempt.n_lane,
                cost=attempt.cost,
                iterations=attempt.iterations,
                converged=attempt.converged,
            )
        pose_f, cov_cam = self.y[:6].copy(), self.P[:6, :6].copy()
        searching = self.startup.mixture(self.y, self.P) if mode == "fallback" else None
        if searching is not None:  # ambiguous: the hypotheses' moment-matched Gaussian, never one basin
            pose_f, cov_cam = searching
        cov_f = cov_cam + bias_cov(self.params.match_bias_sigma, pose_f[5])  # the error every frame repeats
        pose, cov = pose_f, cov_f
        frame_pose = frame_cov = None
        if mode == "map_matching":
            frame_pose, frame_cov = match.pose.copy(), match.cov.copy()
            if self.params.report == "frame":
                pose, cov = frame_pose, frame_cov
        return LocalizationResult(
            t=t,
            pose=pose,
            cov=cov,
            velocity_map=vel,
            mode=mode,
            initialized=True,
            reason=reason,
            gnss_used=gnss_used,
            pose_filtered=pose_f,
            cov_filtered=cov_f,
            cov_camera=cov_cam,
            pose_frame=frame_pose,
            cov_frame=frame_cov,
            **q,
        )
