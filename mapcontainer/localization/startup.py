"""The localizer's mode: start-up, verification of a known start, recovery, tracking; a state machine.

:class:`StartupMachine` holds everything the :class:`.Localizer` decides its mode by (the start-up
bookkeeping, the candidate basins tracked as hypotheses, the counters of frames left to verify, of
rejected jumps and of far GNSS fixes) and picks, every step, how the frame is matched. The EKF
state (y, P) stays with the localizer: the machine takes the prediction and returns what to fold
in. Its phases (:class:`Phase`)::

    UNINITIALISED -> VERIFYING      initial_pose used (verify_start_frames > 0)
    UNINITIALISED -> TRACKING       a heading: initial_yaw, the course over ground, a one-way road,
                                    the search's accepted solution or a winning start-up hypothesis
    VERIFYING     -> TRACKING       the search accepted a solution, verify_agree_frames agreements,
                                    or verify_start_frames frames used up
    VERIFYING     -> SEARCHING      the frames used up while a distinct better solution's basins
                                    are still tracked as hypotheses
    TRACKING      -> SEARCHING      a wide prediction (or jump_reset_after jumps): the search left
                                    candidate basins
    SEARCHING     -> TRACKING       a hypothesis won or all were dropped
    any           -> UNINITIALISED  reset: a gap > max_gap_s, GNSS divergence, Localizer.reset

Before the state exists (UNINITIALISED) on a two-way road, the candidate basins of the start-up
search are tracked as hypotheses as well (``hyps``); a winner initialises the state.

The hypotheses are kept by the machine's base class :class:`.basins.HypothesisTracking`, weighed by their
posterior mass (:mod:`.hypotheses`: the camera's evidence over the frames since they were found, the newest
GNSS fix through a heavy-tailed likelihood, and *elsewhere* for a basin the search did not reach); one wins
when it holds ``1 - search.accept_epsilon`` of it. While none does, :meth:`StartupMachine.mixture` is the
moment-matched pose the vehicle publishes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import circular_mean, wrap_angle
from ..hdmap.model import HDMap
from . import ekf
from .basins import Hypothesis, HypothesisTracking
from .matcher import MapMatcher
from .matcher_types import CameraFrame, MatchResult
from .search import PoseSearch, SearchOutcome

if TYPE_CHECKING:
    from .params import GnssMeasurement, LocalizerParams, OdometryMeasurement

__all__ = ["StartupMachine", "Phase", "UNIFORM_YAW_VAR"]

UNIFORM_YAW_VAR = np.pi**2 / 3.0  # variance of a yaw uniform on [-pi, pi)


class Phase(Enum):
    """What the localizer is doing (see the module doc for the transitions)."""

    UNINITIALISED = "uninitialised"  # no state yet: waiting for GNSS and a heading (or a start-up hypothesis)
    VERIFYING = "verifying"  # a known start pose (initial_pose), checked by the global search every frame
    SEARCHING = "searching"  # the prediction's candidate basins tracked as hypotheses until one wins
    TRACKING = "tracking"  # local matches from the prediction, gated against jumps


@dataclass
class _Course:
    """Start-up bookkeeping: the first GNSS fix and the odometry path since (in the odometry's own frame)."""

    g0: np.ndarray | None = None
    theta: float = 0.0
    p: np.ndarray = field(default_factory=lambda: np.zeros(2))


class StartupMachine(HypothesisTracking):
    """Start-up, verification, recovery and tracking of one :class:`.Localizer` (see the module doc).

    ``count(reason)`` counts an event in the localizer's ``stats``; ``ground_height(p)`` is the road's
    height under p (x, y) or None. ``attempt`` is the last step's match attempt (accepted or not),
    for the result's quality figures.
    """

    def __init__(
        self,
        hdmap: HDMap,
        params: LocalizerParams,
        matcher: MapMatcher,
        search: PoseSearch,
        count: Callable[[str], None],
        ground_height: Callable[[np.ndarray], float | None],
    ):
        self.params = params
        self.matcher = matcher
        self.search = search
        self._count = count
        self._ground_height = ground_height
        xy, yaw = [], []
        for c in hdmap.centerlines:
            arcs = np.arange(0.0, c.polyline.length, 1.0)
            tng = c.polyline.tangent_at(arcs)
            xy.append(c.polyline.point_at(arcs)[:, :2])
            yaw.append(np.arctan2(tng[:, 1], tng[:, 0]))
        self._cl_tree = cKDTree(np.vstack(xy)) if xy else None  # centre-line samples: driving directions
        self._cl_yaw = np.concatenate(yaw) if yaw else np.zeros(0)
        self._pole_xy = np.array([f.base[:2] for f in hdmap.poles], dtype=float).reshape(-1, 2)
        self.reset(None, None)

    def reset(self, initial_yaw: float | None, initial_pose: tuple[np.ndarray, np.ndarray] | None) -> None:
        """Back to UNINITIALISED; the start will use ``initial_pose`` (validated), else ``initial_yaw``, else
        GNSS and a heading from the course or the map."""
        self.phase = Phase.UNINITIALISED
        self.initial_pose = initial_pose
        self.initial_yaw = initial_yaw
        self.course = _Course()
        self.hyps: list[Hypothesis] = []
        self.null_nll = np.inf  # the camera's -2 log-likelihood of 'elsewhere' over the hypotheses' frames
        self.mass: np.ndarray = np.zeros(0)  # the hypotheses' posterior masses (and elsewhere's, last)
        self.odometer = 0.0  # distance travelled while searching (m)
        self.credited: dict[tuple[str, int], float] = {}  # landmark -> odometer when it last counted against elsewhere
        self.init_match: MatchResult | None = None  # the match that initialised the state, for the first step
        self.init_weight = 1.0  # ... and its information weight
        self.weight = 1.0  # the information weight of the match :meth:`match` returned (see _view_weight)
        self.verify_left = 0  # frames left to verify a known start pose by the search (see _verify_start)
        self.agree = 0  # frames in which the local match was the search's best basin (see _verify_start)
        self.jumps = 0  # converged matches rejected as jumps in a row
        self.far = 0  # GNSS fixes in a row farther than gnss_divergence_m from the state
        self.attempt: MatchResult | None = None
        self.fix: GnssMeasurement | None = None  # this step's GNSS fix: it weighs the hypotheses
        self.pending: list[np.ndarray] = []  # search starts not solved within a frame's budget, carried by odometry
        self._solves0 = 0  # the matcher's solve count at the start of this step (the search's budget)

    @property
    def posterior(self) -> bool:
        """The start-up accepts by posterior mass (``search.accept == 'posterior'``), not by landmarks counted."""
        return self.params.search.accept == "posterior"

    def _set_hyps(self, hyps: list[Hypothesis]) -> None:
        """Replace the hypotheses; once initialised (and not verifying), SEARCHING while there are any."""
        self.hyps = hyps
        if not hyps:
            self.null_nll, self.mass = np.inf, np.zeros(0)
            self.odometer, self.credited = 0.0, {}
        if self.phase in (Phase.TRACKING, Phase.SEARCHING):
            self.phase = Phase.SEARCHING if hyps else Phase.TRACKING

    # ------------------------------------------------------------------ one step, initialised

    def match(
        self,
        frame: CameraFrame | None,
        y_pred: np.ndarray,
        P_pred: np.ndarray,
        dt: float,
        odo_a: OdometryMeasurement | None,
        odo_b: OdometryMeasurement | None,
        gnss: GnssMeasurement | None,
    ) -> tuple[MatchResult | None, str, np.ndarray, np.ndarray]:
        """The match to fold into the prediction this step, by phase: (match or None, reason, y_pred, P_pred);
        a winning hypothesis brings its own prediction. Sets ``attempt``."""
        p = self.params
        match, reason = None, ""
        self.attempt, self.fix, self.weight = None, gnss, 1.0
        self._carry(dt, odo_a, odo_b)
        if self.init_match is not None:
            match, self.attempt, self.init_match = self.init_match, self.init_match, None
            self.weight = self.init_weight
        elif (self.hyps and self.phase is Phase.SEARCHING and self.posterior) or self._wide(P_pred[:6, :6]):
            # Rule 'posterior': hypotheses decide until one wins, even if the GNSS + odometry estimate narrows
            # meanwhile (a local match from it would pick a basin they have not told apart). Rule 'landmarks':
            # a narrow prediction ends the search with a local match.
            match, reason, y_pred, P_pred = self._recover(frame, y_pred, P_pred, dt, odo_a, odo_b)
        elif frame is None:
            reason = "no camera frame"
        elif frame.is_empty():
            reason = "no features"
        elif self.phase is Phase.VERIFYING:
            match, reason, y_pred, P_pred = self._verify_start(frame, y_pred, P_pred, dt, odo_a, odo_b)
            if self.verify_left == 0:
                self.phase = Phase.SEARCHING if self.hyps else Phase.TRACKING
        else:
            self._set_hyps([])
            self.pending = []
            match, reason = self._match(frame, y_pred, P_pred)
            if match is None and self.jumps >= p.jump_reset_after:
                # The prediction keeps disagreeing with converged matches: distrust it and search.
                self._count("jump_reset")
                self.jumps = 0
                match, reason, y_pred, P_pred = self._recover(
                    frame, y_pred, ekf.widen(P_pred, gnss, p), 0.0, odo_a, odo_b
                )
        if match is not None:
            self.jumps = 0
        return match, reason, y_pred, P_pred

    def diverged(self, gnss: GnssMeasurement | None, y: np.ndarray) -> bool:
        """Count this fix if it is farther than gnss_divergence_m from the state; True once
        gnss_divergence_fixes did so in a row (the state is in a wrong basin: start again)."""
        p = self.params
        if gnss is None:
            return False
        self.far = self.far + 1 if np.hypot(*(gnss.p_map[:2] - y[:2])) > p.gnss_divergence_m else 0
        return self.far >= p.gnss_divergence_fixes

    def _match(self, frame: CameraFrame, y, P) -> tuple[MatchResult | None, str]:
        """One local solve from the predicted pose; the result if accepted, else None and the reason.

        Rejected if it did not converge or jumped against the prediction. The attempt (accepted or
        not) is kept in ``self.attempt`` for the quality figures.
        """
        p = self.params
        x_pred, Pxx = y[:6], P[:6, :6]
        try:
            match = self.matcher.match(frame, x_pred, Pxx, None)
            self.attempt = match
        except ValueError as exc:  # a malformed frame: count it, go on without it
            self._count("frame invalid")
            return None, f"frame invalid: {exc}"
        if not match.converged:
            return None, match.reason
        d = match.pose_filtered - x_pred
        d[5] = wrap_angle(d[5])
        chi2 = float(d @ np.linalg.solve(Pxx, d))
        if chi2 > p.jump_gate_chi2:
            self._count("match_jump")
            self.jumps += 1
            return None, f"jump: chi2 {chi2:.1f} > {p.jump_gate_chi2}"
        return match, ""

    def _recover(self, frame, y_pred, P_pred, dt: float, odo_a, odo_b):
        """Match a wide prediction (start-up, recovery): the global pose search, then its candidate
        basins tracked as hypotheses until one wins (see :meth:`try_initialise`).

        Returns (match or None, reason, y_pred, P_pred): a winning hypothesis brings its own prediction.
        """
        if self.hyps:
            win = self._advance_hypotheses(
                frame, dt, odo_a, odo_b, lambda: (y_pred, P_pred, self._search(frame, y_pred[:6], P_pred[:6, :6]))
            )
            if win is not None:
                self.attempt, self.weight = win.last, win.weight
                return win.last, "", win.y_pred, win.P_pred
            if self.hyps:
                return None, f"searching: {len(self.hyps)} hypotheses", y_pred, P_pred
        if frame is None or frame.is_empty():
            return None, "no features", y_pred, P_pred
        if not self.search.can_accept(frame):
            self._count("too few features to search")
            return None, "too few features to search", y_pred, P_pred
        self._count("search")
        try:
            out = self._search(frame, y_pred[:6], P_pred[:6, :6])
        except ValueError as exc:
            self._count("frame invalid")
            return None, f"frame invalid: {exc}", y_pred, P_pred
        self.attempt = out.match
        if out.match is not None:
            return out.match, "", y_pred, P_pred
        self._spawn(y_pred, P_pred, out)
        return None, f"search: {out.reason}", y_pred, P_pred

    def _verify_start(self, frame, y_pred, P_pred, dt: float, odo_a, odo_b):
        """Match a frame while a known start pose (``initial_pose``) is not yet verified.

        A start pose is a Gaussian prior, but the map-matching cost is multimodal: from a start a few
        sigma off (a 2.6-sigma yaw puts a pole 40 m ahead 1.8 m sideways) the local solve associates a
        detection with the wrong landmark, converges on three constraints -- enough for a tracked
        prediction -- and the tracker, now confident, never sees the true basin again. So until it
        is verified, every frame is also matched by the global pose search over the prediction's own
        covariance (3 sigma in position and heading):

        * the search accepts a solution (one basin holds 1 - accept_epsilon of the posterior mass):
          it is taken, the start is verified;
        * a distinct solution of the search beats the local one by the margin: the local one is a
          wrong basin; the search's basins are tracked as hypotheses (fallback until one wins);
        * otherwise (the frame too poor for the search to decide alone): the local match as usual; when it
          lies in the basin of the search's best converged solution in ``verify_agree_frames`` frames,
          the start is verified (the search found nothing better over the whole 3-sigma region).

        After ``verify_start_frames`` frames the local matches are trusted as before.
        Returns (match or None, reason, y_pred, P_pred) like :meth:`_recover`.
        """
        self.verify_left -= 1
        if self.hyps:  # basins of an earlier frame: tracked until one wins
            match, reason, y_pred, P_pred = self._recover(frame, y_pred, P_pred, dt, odo_a, odo_b)
            if match is not None:
                self._start_verified()
            elif self.verify_left == 0:
                self._set_hyps([])
            return match, reason and f"verifying start: {reason}", y_pred, P_pred
        try:
            out = self._search(frame, y_pred[:6], P_pred[:6, :6])
        except ValueError as exc:
            self._count("frame invalid")
            return None, f"frame invalid: {exc}", y_pred, P_pred
        if out.match is not None:
            self._start_verified()
            self.attempt = out.match
            return out.match, "", y_pred, P_pred
        match, reason = self._match(frame, y_pred, P_pred)
        if match is not None:
            margin = self.params.search.margin
            better = [
                s
                for s in out.solutions
                if s.converged
                and self.search.distinct(s.pose_filtered, match.pose_filtered)
                and s.score < match.score - margin
            ]
            if better:
                self._count("start rejected")
                self._spawn(y_pred, P_pred, out)
                return None, f"verifying start: a distinct solution beats the local one by {margin}", y_pred, P_pred
            best = next((s for s in out.solutions if s.converged), None)
            if best is not None and not self.search.distinct(best.pose_filtered, match.pose_filtered):
                self.agree += 1
                if self.agree >= self.params.verify_agree_frames:
                    self._start_verified()
        return match, reason, y_pred, P_pred

    def _start_verified(self) -> None:
        self._count("start verified")
        self.verify_left = 0

    def _wide(self, Pxx) -> bool:
        """The prediction is too uncertain for one local solve."""
        p = self.params
        return ekf.sigma_h(Pxx) > p.search_sigma_m or float(np.sqrt(max(Pxx[5, 5], 0.0))) > p.search_sigma_yaw_rad

    def _search(self, frame: CameraFrame, x_pred, Pxx):
        """The global pose search around the prediction: 3-sigma in position and heading.

        Beyond +-30 degrees of heading the candidates are the map's driving directions nearby.
        """
        step = self.params.search.yaw_step_rad
        radius = 3.0 * ekf.sigma_h(Pxx)
        half = 3.0 * float(np.sqrt(max(Pxx[5, 5], 0.0)))
        yaws = None
        if half > np.radians(30.0):
            yaws = self._map_yaws(x_pred[:2], radius)
        if yaws is None or len(yaws) == 0:
            k = int(np.ceil(min(half, np.pi) / step))
            yaws = wrap_angle(x_pred[5] + np.arange(-k, k + 1) * step)
        return self._budgeted(frame, x_pred, Pxx, yaws, radius)

    def _budgeted(self, frame: CameraFrame, x_pred, Pxx, yaws, radius: float) -> SearchOutcome:
        """The search within what is left of this step's budget (``search.solves_per_frame`` less the solves the
        hypotheses' matches used; one start at least), continuing from the pending starts if there are any."""
        budget = self.params.search.solves_per_frame
        if budget is not None:
            budget = max(1, budget - (self.matcher.solves - self._solves0))
        starts = self.pending or None
        out = self.search.search(frame, x_pred, Pxx, yaws, radius, starts=starts, budget=budget)
        self.pending = list(out.pending)
        return out

    def _carry(self, dt: float, odo_a, odo_b) -> None:
        """Start of a step: the pending starts moved by the odometry (a unicycle over dt), and the budget's count."""
        if self.params.search.solves_per_frame is not None:
            self._solves0 = self.matcher.solves
        speeds = [o for o in (odo_a, odo_b) if o is not None]
        if not self.pending or not speeds or dt <= 0.0:
            return
        v = float(np.mean([o.speed for o in speeds]))
        w = float(np.mean([o.yaw_rate for o in speeds]))
        moved = []
        for h in self.pending:
            h = h.copy()
            yaw = h[5] + 0.5 * w * dt
            h[:2] += v * dt * np.array([np.cos(yaw), np.sin(yaw)])
            h[5] = wrap_angle(h[5] + w * dt)
            moved.append(h)
        self.pending = moved

    # ------------------------------------------------------------------ start-up (no state yet)

    def advance_course(self, t: float, t_prev: float | None, odometry, gnss) -> None:
        """Dead-reckon the path since the first GNSS fix (for the course over ground)."""
        p = self.params
        it = self.course
        if gnss is None:
            return
        if it.g0 is None:
            it.g0 = gnss.p_map[:2].copy()
            return
        if t_prev is None or odometry is None:
            return
        dt = t - t_prev
        if dt <= 0 or dt > p.max_gap_s:
            return
        v, w = odometry.speed, odometry.yaw_rate
        th = it.theta + 0.5 * w * dt
        if abs(v) >= p.init_min_speed_mps:
            it.p = it.p + v * dt * np.array([np.cos(th), np.sin(th)])
        it.theta += w * dt

    def _course(self, gnss: GnssMeasurement | None) -> tuple[float, float] | None:
        """Yaw from the GNSS displacement aligned with the dead-reckoned path, and its 1-sigma."""
        it = self.course
        if gnss is None or it.g0 is None:
            return None
        dg = gnss.p_map[:2] - it.g0
        dist = float(np.linalg.norm(dg))
        if dist < self.params.init_course_distance_m or np.linalg.norm(it.p) < 0.5 * dist:
            return None
        offset = np.arctan2(dg[1], dg[0]) - np.arctan2(it.p[1], it.p[0])
        sigma = float(2.0 * np.sqrt(2.0) * gnss.sigma_h_m / dist)
        return float(wrap_angle(offset + it.theta)), sigma

    def _map_yaws(self, p_xy, radius_m: float) -> np.ndarray:
        """Candidate headings: the driving directions of the centre lines within radius_m of p_xy, each
        widened by init_heading_window_rad, on the search's heading grid."""
        p = self.params
        if self._cl_tree is None:
            return np.zeros(0)
        idx = self._cl_tree.query_ball_point(np.asarray(p_xy[:2], dtype=float), max(radius_m, p.init_lane_search_m))
        if not idx:
            return np.zeros(0)
        step = p.search.yaw_step_rad
        base = np.unique(np.round(self._cl_yaw[idx] / step))
        k = int(np.ceil(p.init_heading_window_rad / step))
        grid = (base[:, None] + np.arange(-k, k + 1)[None, :]).reshape(-1) * step
        return np.unique(np.round(wrap_angle(grid), 9))

    def _init_state(self, gnss: GnssMeasurement, yaw: float, sigma_yaw: float) -> tuple[np.ndarray, np.ndarray]:
        return ekf.initial_state(gnss, yaw, sigma_yaw, self._ground_height(gnss.p_map), self.params)

    def try_initialise(
        self, frame, gnss: GnssMeasurement | None, dt: float, odo_a, odo_b
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The state (y, P) from GNSS and a heading if one is available now (see the localizer's module doc),
        else None. Leaves UNINITIALISED for VERIFYING (a known start pose) or TRACKING.

        On a two-way road the camera decides. The global pose search over both directions either
        finds one clear solution, or a few candidate basins: those are tracked as hypotheses over
        the next frames (odometry prediction, local match, accumulated score) until one of them
        is well constrained and beats every other by the search's margin. The winning match of
        this frame is kept in ``init_match``, with the state its prediction.
        """
        self._carry(dt, odo_a, odo_b)
        state = self._initialise(frame, gnss, dt, odo_a, odo_b)
        if state is not None:
            self.pending = []
            self.phase = Phase.VERIFYING if self.verify_left > 0 else Phase.TRACKING
        return state

    def _initialise(self, frame, gnss, dt, odo_a, odo_b):
        p = self.params
        self.init_match, self.init_weight, self.fix = None, 1.0, gnss
        if gnss is None:
            return None
        if self.initial_pose is not None:
            pose0, cov0 = self.initial_pose
            y, P = self._init_state(gnss, pose0[5], 1.0)
            y[:6] = pose0
            P[:6, :] = P[:, :6] = 0.0
            P[:6, :6] = cov0
            self.initial_pose = None  # used once: a later reset starts from GNSS
            self.verify_left, self.agree = p.verify_start_frames, 0
            return y, P
        if self.initial_yaw is not None:
            return self._init_state(gnss, self.initial_yaw, p.init_yaw_sigma_rad)
        course = self._course(gnss)
        if course is not None:
            self._set_hyps([])
            return self._init_state(gnss, course[0], max(course[1], p.init_yaw_sigma_rad))
        radius = 3.0 * float(np.sqrt(p.gnss_bias_sigma_m**2 + ekf.gnss_white_var(gnss, p) + p.init_extra_sigma_m**2))
        yaws = self._map_yaws(gnss.p_map[:2], radius)
        if self.hyps:
            win = self._advance_hypotheses(
                frame, dt, odo_a, odo_b, lambda: self._gnss_search(frame, gnss, yaws, radius)
            )
            if win is None:
                return None
            self.init_match, self.init_weight = win.last, win.weight
            return win.y_pred, win.P_pred
        if len(yaws) == 0:
            return None
        centre = circular_mean(yaws)
        spread = float(np.max(np.abs(wrap_angle(yaws - centre))))
        if spread < np.radians(45.0):  # one driving direction (a one-way road): that is the heading
            return self._init_state(gnss, centre, max(spread, p.init_yaw_sigma_rad))
        if frame is None or frame.is_empty():
            return None
        if not self.search.can_accept(frame):
            self._count("initialising: too few features to search")
            return None
        try:
            y0, P0, out = self._gnss_search(frame, gnss, yaws, radius)
        except ValueError:
            self._count("frame invalid")
            return None
        if out.match is not None:
            self.init_match = out.match
            return y0, P0
        self._count("initialising: " + out.reason.split(":")[0])
        self._spawn(y0, P0, out)
        return None

    def _gnss_search(self, frame, gnss: GnssMeasurement, yaws, radius: float):
        """The global pose search at start-up: over ``radius`` of the GNSS fix and the headings ``yaws``, from
        the GNSS state with a uniform heading. Returns (y0, P0, outcome) with that state; None without headings.
        Raises ValueError on a malformed frame."""
        if len(yaws) == 0:
            return None
        y0, P0 = self._init_state(gnss, circular_mean(yaws), np.sqrt(UNIFORM_YAW_VAR))
        return y0, P0, self._budgeted(frame, y0[:6], P0[:6, :6], yaws, radius)
