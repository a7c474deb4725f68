"""Self-localization over time: odometry prediction, map matching, failure detection, fallback, recovery.

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
   and the tracker never leaves that basin (see ``_verify_start``);
2. ``initial_yaw`` given to the constructor or to ``reset``, with the GNSS position;
3. the course over ground (GNSS displacement over ``init_course_distance_m`` aligned with the
   dead-reckoned odometry path);
4. the HD map: the driving directions of the centre lines within 3 sigma of the GNSS fix. One
   direction (a one-way road) is the heading, with the directions' spread as its uncertainty.
   Two (a two-way road): the camera decides, by the global pose search (:mod:`.search`) over both
   directions and the GNSS region. One clear solution starts the track; otherwise its candidate
   basins are tracked as hypotheses (prediction, local match, accumulated score, distinct
   landmarks counted) until one is well constrained and beats the others by a margin. While a
   lone hypothesis has not won, the search runs again on every frame and its new basins join as
   rivals (a weakly supported wrong basin would otherwise hold the start for good). The first
   search waits for a frame that could decide (:meth:`.PoseSearch.can_accept`: enough landmark
   detections for the search's rules, were all of them inliers): the basins of a frame with one
   pole are mostly wrong, and searching such frames cost 0.2-0.6 s of CPU each.

Until then the result is the GNSS fix with a yaw variance of pi^2 / 3 (uniform), ``initialized``
False, mode "fallback". Whenever the prediction is too wide for one local solve (horizontal
1-sigma above ``search_sigma_m``, yaw above ``search_sigma_yaw_rad``: start-up, long fallback,
repeated jumps) the same search and hypotheses decide the basin; until they do, mode "fallback".
A match is never taken from a wide prediction on three constraints alone: that is how a wrong
lane, a wrong lamp post or the opposite heading used to be accepted with a confident covariance.

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
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree

from schemas import bias_cov

from ..geometry import circular_mean, wrap_angle
from ..hdmap.model import HDMap
from .matcher import CameraFrame, MapMatcher, MatcherParams, MatchResult
from .search import PoseSearch, PoseSearchParams, SearchOutcome

__all__ = ["GnssMeasurement", "LocalizationResult", "Localizer", "LocalizerParams", "OdometryMeasurement"]

log = logging.getLogger(__name__)

_UNIFORM_YAW_VAR = np.pi**2 / 3.0  # variance of a yaw uniform on [-pi, pi)
_N = 10  # state size
_SCALE, _GYRO, _GB = 6, 7, slice(8, 10)  # wheel-speed scale, gyro bias, GNSS bias (E, N)


@dataclass(frozen=True)
class OdometryMeasurement:
    """Wheel speed (m/s, forward) and gyro yaw rate (rad/s).

    :meth:`Localizer.step` also takes schemas.Odometry or a ``(speed, yaw_rate)`` tuple.
    """

    speed: float
    yaw_rate: float


@dataclass(frozen=True)
class GnssMeasurement:
    """A GNSS fix in the map frame with the receiver's reported 1-sigmas (m).

    :meth:`Localizer.step` also takes schemas.GnssFix or a ``(p_map, sigma_h, sigma_v)`` tuple.
    """

    p_map: np.ndarray
    sigma_h_m: float
    sigma_v_m: float


class LocalizerParams(BaseModel):
    """Parameters of :class:`Localizer` (SI units; random walks per square root of a second)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    matcher: MatcherParams = Field(default_factory=MatcherParams)
    search: PoseSearchParams = Field(default_factory=PoseSearchParams)
    search_sigma_m: float = Field(
        1.0,
        gt=0,
        description="a prediction whose horizontal 1-sigma exceeds this (m) is matched by the global pose "
        "search (start-up, recovery) instead of one local solve",
    )
    search_sigma_yaw_rad: float = Field(
        np.radians(3.0), gt=0, description="... or whose yaw 1-sigma exceeds this (rad)"
    )
    report: Literal["filtered", "frame"] = Field(
        "filtered",
        description="what pose/cov carry while map matching: the tracker's posterior ('filtered'), or this "
        "frame's own camera evidence ('frame', for consumers that fuse frames themselves); both are in the "
        "result as pose_filtered / pose_frame",
    )
    # Odometry (unicycle model); the wheel-speed scale and the gyro bias are estimated.
    speed_sigma_mps: float = Field(0.1, gt=0, description="1-sigma of the wheel speed, white (m/s)")
    speed_scale_sigma: float = Field(0.005, ge=0, description="relative 1-sigma of the wheel speed, white")
    yaw_rate_sigma_radps: float = Field(0.01, gt=0, description="1-sigma of the gyro yaw rate, white (rad/s)")
    lateral_sigma_mps: float = Field(0.1, ge=0, description="sideways velocity noise (slip, model error) (m/s)")
    z_sigma_mps: float = Field(0.1, ge=0, description="random walk of the height (m/sqrt(s))")
    roll_pitch_sigma_radps: float = Field(0.01, ge=0, description="random walk of roll and pitch (rad/sqrt(s))")
    scale_init_sigma: float = Field(0.02, gt=0, description="prior 1-sigma of the wheel-speed scale factor")
    scale_rw_sigma: float = Field(1e-4, ge=0, description="random walk of the scale factor (1/sqrt(s))")
    gyro_bias_init_sigma_radps: float = Field(0.005, gt=0, description="prior 1-sigma of the gyro bias (rad/s)")
    gyro_bias_rw_sigma: float = Field(1e-4, ge=0, description="random walk of the gyro bias (rad/s/sqrt(s))")
    # GNSS: fix = position + bias + white noise.
    gnss_bias_sigma_m: float = Field(1.5, gt=0, description="stationary 1-sigma of the receiver's bias per axis (m)")
    gnss_bias_tau_s: float = Field(60.0, gt=0, description="correlation time of the bias (s)")
    gnss_white_min_sigma_m: float = Field(
        0.5, gt=0, description="white part = sqrt(reported_sigma_h^2 - bias_sigma^2), at least this (m)"
    )
    gnss_gate_chi2: float = Field(13.8, gt=0, description="fixes beyond this chi^2 (2 dof, 99.9 %) are dropped")
    gnss_soft_chi2: float = Field(
        5.99,
        gt=0,
        description="fixes beyond this chi^2 (2 dof, 95 %) get their noise scaled by chi^2 / this "
        "(Huber-like): "
        "multipath jumps of several metres are common in cities",
    )
    # Map matching acceptance.
    jump_gate_chi2: float = Field(
        22.5, gt=0, description="a match farther than this chi^2 (6 dof) from the prediction is rejected"
    )
    jump_reset_after: int = Field(
        5,
        ge=1,
        description="after this many rejected jumps in a row the prediction is distrusted: its position and "
        "yaw "
        "covariance are widened and the match is tried again",
    )
    match_bias_sigma: tuple[float, float, float, float, float, float] = Field(
        (0.10, 0.10, 0.04, 0.0035, 0.0065, 0.0045),
        description="1-sigmas of the map-matching error that no frame can see, in the body frame (along, across, "
        "up (m); roll, pitch, yaw (rad)): the camera's calibration tolerance (0.25 deg per axis, 5 px principal "
        "point, 0.5 % focal length) and the map's survey drift common to the landmarks in view (5 cm, 3 cm "
        "vertical), as configs/sensors/default.yaml specifies them. Every frame repeats it, so the filter "
        "tracks the pose as the camera sees it and its reported covariance adds this (a consider term); "
        "measured on development seeds 1-5 (paper-urban, every error source on): RMS of each vehicle's mean "
        "error 0.09, 0.10, 0.04 m, 0.19, 0.37, 0.21 deg",
    )
    # Fallback ground constraint (the matcher's r_n when there is no match).
    ground_sigma_m: float = Field(0.2, gt=0, description="1-sigma of the height above the road in fallback (m)")
    ground_roll_pitch_sigma_rad: float = Field(0.02, gt=0, description="1-sigma of roll, pitch in fallback (rad)")
    # Start-up.
    init_extra_sigma_m: float = Field(
        2.5,
        ge=0,
        description="added to the initial position 1-sigma for a multipath jump in the first fix (m)",
    )
    init_yaw_sigma_rad: float = Field(0.05, gt=0, description="1-sigma of a given or map-derived initial heading")
    init_lane_search_m: float = Field(
        6.0, gt=0, description="centre lines at least this close to the GNSS fix give headings (m)"
    )
    init_heading_window_rad: float = Field(
        np.radians(6.0), ge=0, description="a vehicle's heading within this of its lane's direction (rad)"
    )
    init_course_distance_m: float = Field(12.0, gt=0, description="GNSS travel that gives a course over ground (m)")
    init_min_speed_mps: float = Field(1.0, ge=0, description="dead reckoning for the course only above this speed")
    max_gap_s: float = Field(5.0, gt=0, description="a longer gap between steps re-initialises")
    gnss_divergence_m: float = Field(
        15.0,
        gt=0,
        description="a state farther than this from the GNSS fix is in a wrong basin (m); the receiver errs at "
        "most about 3 sigma of bias (4.5 m) + 3 sigma white (2.4 m) + a multipath jump (up to 8 m)",
    )
    gnss_divergence_fixes: int = Field(
        5, ge=1, description="that many fixes in a row that far apart re-initialise from GNSS"
    )
    verify_start_frames: int = Field(
        20,
        ge=0,
        description="a known start pose (initial_pose) is verified by the global pose search over its "
        "covariance, for at most this many frames with features, before local matches are trusted "
        "(0: trust it at once)",
    )
    verify_agree_frames: int = Field(
        3,
        ge=1,
        description="... or until in this many frames the local match lay in the basin of the search's best "
        "solution (the search could not accept it alone: too few features for its start-up rules)",
    )


@dataclass(frozen=True)
class LocalizationResult:
    """One step's estimate: the body pose in the map (x y z roll pitch yaw) with its 6x6 covariance.

    ``pose``/``cov`` follow ``LocalizerParams.report``; ``pose_frame``/``cov_frame`` (map matching
    only) are this frame's camera evidence with a weak prior -- independent from frame to frame,
    as a factor graph that adds one prior per frame wants them.
    """

    t: float
    pose: np.ndarray
    cov: np.ndarray
    velocity_map: np.ndarray
    mode: Literal["map_matching", "fallback"]
    initialized: bool
    n_points: int = 0
    n_poles: int = 0
    n_lane: int = 0
    cost: float = 0.0
    iterations: int = 0
    converged: bool = False
    reason: str = ""
    gnss_used: bool = False
    pose_filtered: np.ndarray | None = None
    cov_filtered: np.ndarray | None = None
    # cov_filtered without the error every frame repeats (match_bias_sigma): of the pose as the camera sees the map
    cov_camera: np.ndarray | None = None
    pose_frame: np.ndarray | None = None
    cov_frame: np.ndarray | None = None
    bad_input: bool = False  # the step's input was refused (``reason`` says why): the state did not move

    def quality(self) -> dict[str, Any]:
        """The fields of schemas.LocalizationQuality."""
        return {
            "mode": self.mode,
            "n_points": self.n_points,
            "n_poles": self.n_poles,
            "n_lane": self.n_lane,
            "cost": float(self.cost),
        }


@dataclass
class _Init:
    """Start-up bookkeeping: the first GNSS fix and the odometry path since (in the odometry's own frame)."""

    g0: np.ndarray | None = None
    theta: float = 0.0
    p: np.ndarray = field(default_factory=lambda: np.zeros(2))


@dataclass
class _Hypothesis:
    """One candidate start-up track (a basin the pose search found), scored over the frames since.

    ``y_pred``/``P_pred``: the state predicted to the last frame, before its match ``last``. Its
    constraints count distinct map landmarks: seeing one pole ten times is still one pole.
    """

    y: np.ndarray
    P: np.ndarray
    score: float
    points: set[int]  # map landmarks matched so far (indices of the map's points, poles)
    poles: set[int]
    lanes: bool = False  # the lanes matched at least once
    misses: int = 0
    y_pred: np.ndarray | None = None
    P_pred: np.ndarray | None = None
    last: MatchResult | None = None

    def add(self, m: MatchResult) -> None:
        self.score += m.score
        self.points.update(m.point_pairs[:, 0].tolist())
        self.poles.update(m.pole_pairs[:, 0].tolist())
        self.lanes |= m.constraints > 2 * m.n_points + m.n_poles
        self.last, self.misses = m, 0

    @property
    def landmarks(self) -> int:
        return len(self.points) + len(self.poles)

    @property
    def constraints(self) -> int:
        return 2 * len(self.points) + len(self.poles) + 2 * self.lanes


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

    Prediction (unicycle; odometry v_m, w_m; v = k_v v_m, w = w_m - b_w, theta_m = yaw + w dt / 2)::

        x += v dt cos(theta_m),  y += v dt sin(theta_m),  yaw += w dt,  b_gnss *= exp(-dt / tau)
        P = F P F^T + G diag(s_v^2, s_w^2) G^T + Q dt

    with s_v^2 = speed_sigma^2 + (speed_scale_sigma v_m)^2 and Q the lateral, height, roll, pitch,
    scale, gyro-bias and GNSS-bias process noise. A match is folded in through its information
    (:meth:`_match_update`). Failure = the match did not converge (too few constraints, cost too
    high, no features) or jumped (chi^2 of its change against the prediction > jump_gate_chi2).
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
        xy, yaw = [], []
        for c in hdmap.centerlines:
            arcs = np.arange(0.0, c.polyline.length, 1.0)
            tng = c.polyline.tangent_at(arcs)
            xy.append(c.polyline.point_at(arcs)[:, :2])
            yaw.append(np.arctan2(tng[:, 1], tng[:, 0]))
        self._cl_tree = cKDTree(np.vstack(xy)) if xy else None  # centre-line samples: driving directions
        self._cl_yaw = np.concatenate(yaw) if yaw else np.zeros(0)
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
        self._initial_pose = initial_pose
        self.y: np.ndarray | None = None  # see the module doc
        self.P: np.ndarray | None = None
        self.t_prev: float | None = None
        self._odo_prev: OdometryMeasurement | None = None
        self._initial_yaw = initial_yaw
        self._init = _Init()
        self._jumps = 0
        self._far = 0  # GNSS fixes in a row farther than gnss_divergence_m from the state
        self._init_match: MatchResult | None = None
        self._hyps: list[_Hypothesis] = []
        self._last: LocalizationResult | None = None
        self._verify = 0  # frames left to verify a known start pose by the search (see _verify_start)
        self._agree = 0  # frames in which the local match was the search's best basin (see _verify_start)

    @property
    def initialized(self) -> bool:
        return self.y is not None

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
        if not self.initialized:
            dt_init = t - self.t_prev if self.t_prev is not None else 0.0
            self._advance_init(t, odometry, gnss)
            odo_prev, self.t_prev, self._odo_prev = self._odo_prev, t, odometry
            if not self._try_initialise(frame, gnss, dt_init, odo_prev, odometry):
                reason = "initialising: no heading yet" if gnss is not None else "initialising: no GNSS fix"
                self._last = self._uninitialised(t, gnss, reason)
                return self._last
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
        y_pred, P_pred = self._predict(self.y, self.P, dt, odo_prev, odometry)
        self.t_prev, self._odo_prev = t, odometry

        match, reason = None, ""
        self._attempt = None
        if self._init_match is not None:
            match, self._attempt, self._init_match = self._init_match, self._init_match, None
        elif self._wide(P_pred[:6, :6]):
            match, reason, y_pred, P_pred = self._recover(frame, y_pred, P_pred, dt, odo_prev, odometry)
        elif frame is None:
            reason = "no camera frame"
        elif frame.is_empty():
            reason = "no features"
        elif self._verify > 0:
            match, reason, y_pred, P_pred = self._verify_start(frame, y_pred, P_pred, dt, odo_prev, odometry)
        else:
            self._hyps = []
            match, reason = self._match(frame, y_pred, P_pred)
            if match is None and self._jumps >= p.jump_reset_after:
                # The prediction keeps disagreeing with converged matches: distrust it and search.
                self._count("jump_reset")
                self._jumps = 0
                match, reason, y_pred, P_pred = self._recover(
                    frame, y_pred, self._widen(P_pred, gnss), 0.0, odo_prev, odometry
                )
        if match is not None:
            self._jumps = 0
            y, P = self._match_update(y_pred, P_pred, match)
            mode = "map_matching"
        else:
            self._count("fallback")
            y, P = y_pred, P_pred
            mode = "fallback"
        y, P, gnss_used = self._gnss_update(y, P, gnss)
        if gnss is not None:
            self._far = self._far + 1 if np.hypot(*(gnss.p_map[:2] - y[:2])) > p.gnss_divergence_m else 0
            if self._far >= p.gnss_divergence_fixes:
                self._count("gnss_divergence_reset")
                log.warning("%d GNSS fixes in a row > %.0f m away: re-initialising", self._far, p.gnss_divergence_m)
                self.reset(None)
                return self.step(t, frame, odometry, gnss)
        if mode == "fallback":
            y, P = self._ground_update(y, P)
        self.y, self.P = y, P
        self._last = self._result(t, mode, odometry, match, self._attempt, reason, gnss_used)
        return self._last

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

    # ------------------------------------------------------------------ prediction and updates

    def _predict(self, y, P, dt: float, odo_a, odo_b) -> tuple[np.ndarray, np.ndarray]:
        """Unicycle prediction of the state (y, P) over dt with the mean of the two odometry readings."""
        p = self.params
        y, P = y.copy(), P.copy()
        if dt <= 0.0:
            return y, P
        odos = [o for o in (odo_a, odo_b) if o is not None]
        if odos:
            vm = float(np.mean([o.speed for o in odos]))
            wm = float(np.mean([o.yaw_rate for o in odos]))
            sv2 = p.speed_sigma_mps**2 + (p.speed_scale_sigma * vm) ** 2
            sw2 = p.yaw_rate_sigma_radps**2
        else:  # no odometry: stand still, with wide noise
            vm, wm = 0.0, 0.0
            sv2, sw2 = 10.0**2, 0.5**2
        k, b = y[_SCALE], y[_GYRO]
        v, w = k * vm, wm - b
        th = y[5] + 0.5 * w * dt
        c, s = np.cos(th), np.sin(th)
        phi = np.exp(-dt / p.gnss_bias_tau_s)
        y[0] += v * dt * c
        y[1] += v * dt * s
        y[5] = wrap_angle(y[5] + w * dt)
        y[_GB] *= phi
        F = np.eye(_N)
        F[0, 5], F[1, 5] = -v * dt * s, v * dt * c
        F[0, _SCALE], F[1, _SCALE] = vm * dt * c, vm * dt * s
        F[0, _GYRO], F[1, _GYRO] = 0.5 * v * dt * dt * s, -0.5 * v * dt * dt * c
        F[5, _GYRO] = -dt
        F[8, 8] = F[9, 9] = phi
        G = np.zeros((_N, 2))  # d state / d (speed noise, yaw-rate noise)
        G[0, 0], G[1, 0] = k * dt * c, k * dt * s
        G[0, 1], G[1, 1] = -0.5 * v * dt * dt * s, 0.5 * v * dt * dt * c
        G[5, 1] = dt
        Q = G @ np.diag([sv2, sw2]) @ G.T
        lat = np.array([-s, c])
        Q[:2, :2] += np.outer(lat, lat) * p.lateral_sigma_mps**2 * dt**2 + np.eye(2) * 1e-6 * dt
        Q[2, 2] += p.z_sigma_mps**2 * dt
        Q[3, 3] += p.roll_pitch_sigma_radps**2 * dt
        Q[4, 4] += p.roll_pitch_sigma_radps**2 * dt
        Q[_SCALE, _SCALE] += p.scale_rw_sigma**2 * dt
        Q[_GYRO, _GYRO] += p.gyro_bias_rw_sigma**2 * dt
        Q[8, 8] += p.gnss_bias_sigma_m**2 * (1.0 - phi**2)
        Q[9, 9] += p.gnss_bias_sigma_m**2 * (1.0 - phi**2)
        P = F @ P @ F.T + Q
        return y, 0.5 * (P + P.T)

    def _match(self, frame: CameraFrame, y, P) -> tuple[MatchResult | None, str]:
        """One local solve from the predicted pose; the result if accepted, else None and the reason.

        Rejected if it did not converge or jumped against the prediction. The attempt (accepted or
        not) is kept in ``self._attempt`` for the quality figures.
        """
        p = self.params
        x_pred, Pxx = y[:6], P[:6, :6]
        try:
            match = self.matcher.match(frame, x_pred, Pxx, None)
            self._attempt = match
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
            self._jumps += 1
            return None, f"jump: chi2 {chi2:.1f} > {p.jump_gate_chi2}"
        return match, ""

    def _recover(self, frame, y_pred, P_pred, dt: float, odo_a, odo_b):
        """Match a wide prediction (start-up, recovery): the global pose search, then its candidate
        basins tracked as hypotheses until one wins (see :meth:`_try_initialise`).

        Returns (match or None, reason, y_pred, P_pred): a winning hypothesis brings its own prediction.
        """
        if self._hyps:
            win = self._advance_hypotheses(
                frame, dt, odo_a, odo_b, lambda: (y_pred, P_pred, self._search(frame, y_pred[:6], P_pred[:6, :6]))
            )
            if win is not None:
                self._attempt = win.last
                return win.last, "", win.y_pred, win.P_pred
            if self._hyps:
                return None, f"searching: {len(self._hyps)} hypotheses", y_pred, P_pred
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
        self._attempt = out.match
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

        * the search accepts a solution (the strict start-up rules: min_constraints, min_landmarks,
          margin): it is taken, the start is verified;
        * a distinct solution of the search beats the local one by the margin: the local one is a
          wrong basin; the search's basins are tracked as hypotheses (fallback until one wins);
        * otherwise (too few features for the search to decide alone): the local match as usual; when it
          lies in the basin of the search's best converged solution in ``verify_agree_frames`` frames,
          the start is verified (the search found nothing better over the whole 3-sigma region).

        After ``verify_start_frames`` frames the local matches are trusted as before.
        Returns (match or None, reason, y_pred, P_pred) like :meth:`_recover`.
        """
        self._verify -= 1
        if self._hyps:  # basins of an earlier frame: tracked until one wins
            match, reason, y_pred, P_pred = self._recover(frame, y_pred, P_pred, dt, odo_a, odo_b)
            if match is not None:
                self._start_verified()
            elif self._verify == 0:
                self._hyps = []
            return match, reason and f"verifying start: {reason}", y_pred, P_pred
        try:
            out = self._search(frame, y_pred[:6], P_pred[:6, :6])
        except ValueError as exc:
            self._count("frame invalid")
            return None, f"frame invalid: {exc}", y_pred, P_pred
        if out.match is not None:
            self._start_verified()
            self._attempt = out.match
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
                self._agree += 1
                if self._agree >= self.params.verify_agree_frames:
                    self._start_verified()
        return match, reason, y_pred, P_pred

    def _start_verified(self) -> None:
        self._count("start verified")
        self._verify = 0

    def _wide(self, Pxx) -> bool:
        """The prediction is too uncertain for one local solve."""
        p = self.params
        return _sigma_h(Pxx) > p.search_sigma_m or float(np.sqrt(max(Pxx[5, 5], 0.0))) > p.search_sigma_yaw_rad

    def _search(self, frame: CameraFrame, x_pred, Pxx):
        """The global pose search around the prediction: 3-sigma in position and heading.

        Beyond +-30 degrees of heading the candidates are the map's driving directions nearby.
        """
        step = self.params.search.yaw_step_rad
        radius = 3.0 * _sigma_h(Pxx)
        half = 3.0 * float(np.sqrt(max(Pxx[5, 5], 0.0)))
        yaws = None
        if half > np.radians(30.0):
            yaws = self._map_yaws(x_pred[:2], radius)
        if yaws is None or len(yaws) == 0:
            k = int(np.ceil(min(half, np.pi) / step))
            yaws = wrap_angle(x_pred[5] + np.arange(-k, k + 1) * step)
        return self.search.search(frame, x_pred, Pxx, yaws, radius)

    def _widen(self, P, gnss: GnssMeasurement | None) -> np.ndarray:
        """P with the position and yaw variance raised to what GNSS alone would give."""
        p = self.params
        P = P.copy()
        var_h = p.gnss_bias_sigma_m**2 + self._gnss_white_var(gnss) + p.init_extra_sigma_m**2
        P[0, 0] += var_h
        P[1, 1] += var_h
        P[5, 5] += p.init_yaw_sigma_rad**2
        return P

    def _match_update(self, y, P, match: MatchResult) -> tuple[np.ndarray, np.ndarray]:
        """Fold the matcher's posterior on the pose into the whole state (information form).

        The matcher solved with the pose marginal (x_pred, P_xx) as its prior and returned the
        posterior (x_f, P_f); its measurement information is Lambda = P_f^-1 - P_xx^-1 with the
        information vector P_f^-1 (x_f - x_pred). Adding both to the state's information gives the
        pose posterior (x_f, P_f) again and updates the odometry and GNSS biases through their
        correlation with the pose.
        """
        Pxx = P[:6, :6]
        I_f = np.linalg.inv(match.cov_filtered)
        Lam = I_f - np.linalg.inv(Pxx)
        d = match.pose_filtered - y[:6]
        d[5] = wrap_angle(d[5])
        Y = np.linalg.inv(P)
        Y[:6, :6] += 0.5 * (Lam + Lam.T)
        P_new = np.linalg.inv(Y)
        eta = np.zeros(_N)
        eta[:6] = I_f @ d
        dy = P_new @ eta  # the prior is centred on y: delta form
        y = y.copy()
        y[:6] = match.pose_filtered  # the exact nonlinear solution for the pose block
        y[6:] += dy[6:]
        return y, 0.5 * (P_new + P_new.T)

    def _gnss_white_var(self, gnss: GnssMeasurement | None) -> float:
        p = self.params
        if gnss is None:
            return p.gnss_white_min_sigma_m**2
        return max(gnss.sigma_h_m**2 - p.gnss_bias_sigma_m**2, p.gnss_white_min_sigma_m**2)

    def _gnss_update(self, y, P, gnss: GnssMeasurement | None):
        """EKF update with the horizontal fix, z = p_xy + b + white; dropped (counted) beyond the gate."""
        if gnss is None:
            return y, P, False
        H = np.zeros((2, _N))
        H[:, :2] = np.eye(2)
        H[:, _GB] = np.eye(2)
        R = np.eye(2) * self._gnss_white_var(gnss)
        r = gnss.p_map[:2] - H @ y
        S = H @ P @ H.T + R
        chi2 = float(r @ np.linalg.solve(S, r))
        if chi2 > self.params.gnss_gate_chi2:
            self._count("gnss rejected")
            return y, P, False
        if chi2 > self.params.gnss_soft_chi2:
            R = R * (chi2 / self.params.gnss_soft_chi2)
        y, P = _kf_update(y, P, H, r, R)
        return y, P, True

    def _ground_update(self, y, P):
        """Pseudo-measurements in fallback: height on the road, roll and pitch at their nominal values."""
        p = self.params
        rows, res, var = [], [], []
        z_ground = self._ground_height(y)
        if z_ground is not None:
            rows.append(np.eye(_N)[2])
            res.append(z_ground + p.matcher.body_height_m - y[2])
            var.append(p.ground_sigma_m**2)
        for i, nominal in zip((3, 4), p.matcher.nominal_roll_pitch_rad, strict=True):
            rows.append(np.eye(_N)[i])
            res.append(nominal - y[i])
            var.append(p.ground_roll_pitch_sigma_rad**2)
        return _kf_update(y, P, np.array(rows), np.array(res), np.diag(var))

    def _ground_height(self, x) -> float | None:
        tree = self.matcher._lane_tree
        if tree is None:
            return None
        d, i = tree.query(np.asarray(x)[:2])
        return float(self.matcher._lane_xyz[i, 2]) if d < 30.0 else None

    # ------------------------------------------------------------------ start-up

    def _advance_init(self, t, odometry, gnss) -> None:
        """Dead-reckon the path since the first GNSS fix (for the course over ground)."""
        p = self.params
        it = self._init
        if gnss is None:
            return
        if it.g0 is None:
            it.g0 = gnss.p_map[:2].copy()
            return
        if self.t_prev is None or odometry is None:
            return
        dt = t - self.t_prev
        if dt <= 0 or dt > p.max_gap_s:
            return
        v, w = odometry.speed, odometry.yaw_rate
        th = it.theta + 0.5 * w * dt
        if abs(v) >= p.init_min_speed_mps:
            it.p = it.p + v * dt * np.array([np.cos(th), np.sin(th)])
        it.theta += w * dt

    def _course(self, gnss: GnssMeasurement | None) -> tuple[float, float] | None:
        """Yaw from the GNSS displacement aligned with the dead-reckoned path, and its 1-sigma."""
        it = self._init
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

    def _init_state(self, gnss: GnssMeasurement, yaw: float, sigma_yaw: float) -> None:
        """State at the GNSS fix with heading yaw; position error = -(bias + white): tied to the bias."""
        p = self.params
        z0 = self._ground_height(gnss.p_map)
        x = np.array(
            [
                gnss.p_map[0],
                gnss.p_map[1],
                gnss.p_map[2] if z0 is None else z0 + p.matcher.body_height_m,
                *p.matcher.nominal_roll_pitch_rad,
                wrap_angle(yaw),
            ]
        )
        vb = p.gnss_bias_sigma_m**2
        vh = vb + self._gnss_white_var(gnss) + p.init_extra_sigma_m**2
        vz = gnss.sigma_v_m**2 if z0 is None else p.ground_sigma_m**2
        self.y = np.concatenate([x, [1.0, 0.0, 0.0, 0.0]])
        self.P = np.diag(
            [
                vh,
                vh,
                vz,
                p.ground_roll_pitch_sigma_rad**2,
                p.ground_roll_pitch_sigma_rad**2,
                sigma_yaw**2,
                p.scale_init_sigma**2,
                p.gyro_bias_init_sigma_radps**2,
                vb,
                vb,
            ]
        )
        self.P[0, 8] = self.P[8, 0] = self.P[1, 9] = self.P[9, 1] = -vb

    def _try_initialise(self, frame, gnss: GnssMeasurement | None, dt: float, odo_a, odo_b) -> bool:
        """Set the state from GNSS and a heading if one is available now (see the module doc).

        On a two-way road the camera decides. The global pose search over both directions either
        finds one clear solution, or a few candidate basins: those are tracked as hypotheses over
        the next frames (odometry prediction, local match, accumulated score) until one of them
        is well constrained and beats every other by the search's margin. The winning match of
        this frame is kept in ``self._init_match``, with the state set to its prediction.
        """
        p = self.params
        self._init_match = None
        if gnss is None:
            return False
        if self._initial_pose is not None:
            pose0, cov0 = self._initial_pose
            self._init_state(gnss, pose0[5], 1.0)
            self.y[:6] = pose0
            self.P[:6, :] = self.P[:, :6] = 0.0
            self.P[:6, :6] = cov0
            self._initial_pose = None  # used once: a later reset starts from GNSS
            self._verify, self._agree = p.verify_start_frames, 0
            return True
        if self._initial_yaw is not None:
            self._init_state(gnss, self._initial_yaw, p.init_yaw_sigma_rad)
            return True
        course = self._course(gnss)
        if course is not None:
            self._hyps = []
            self._init_state(gnss, course[0], max(course[1], p.init_yaw_sigma_rad))
            return True
        radius = 3.0 * float(np.sqrt(p.gnss_bias_sigma_m**2 + self._gnss_white_var(gnss) + p.init_extra_sigma_m**2))
        yaws = self._map_yaws(gnss.p_map[:2], radius)
        if self._hyps:
            win = self._advance_hypotheses(
                frame, dt, odo_a, odo_b, lambda: self._gnss_search(frame, gnss, yaws, radius)
            )
            if win is not None:
                self.y, self.P, self._init_match = win.y_pred, win.P_pred, win.last
            return win is not None
        if len(yaws) == 0:
            return False
        centre = circular_mean(yaws)
        spread = float(np.max(np.abs(wrap_angle(yaws - centre))))
        if spread < np.radians(45.0):  # one driving direction (a one-way road): that is the heading
            self._init_state(gnss, centre, max(spread, p.init_yaw_sigma_rad))
            return True
        if frame is None or frame.is_empty():
            return False
        if not self.search.can_accept(frame):
            self._count("initialising: too few features to search")
            return False
        try:
            y0, P0, out = self._gnss_search(frame, gnss, yaws, radius)
        except ValueError:
            self._count("frame invalid")
            return False
        if out.match is not None:
            self.y, self.P, self._init_match = y0, P0, out.match
            return True
        self._count("initialising: " + out.reason.split(":")[0])
        self._spawn(y0, P0, out)
        return False

    def _gnss_search(self, frame, gnss: GnssMeasurement, yaws, radius: float):
        """The global pose search at start-up: over ``radius`` of the GNSS fix and the headings ``yaws``, from
        the GNSS state with a uniform heading. Returns (y0, P0, outcome) with that state; None without headings.
        Raises ValueError on a malformed frame."""
        if len(yaws) == 0:
            return None
        self._init_state(gnss, circular_mean(yaws), np.sqrt(_UNIFORM_YAW_VAR))
        y0, P0 = self.y, self.P
        self.y = self.P = None
        return y0, P0, self.search.search(frame, y0[:6], P0[:6, :6], yaws, radius)

    def _spawn(self, y0, P0, out: SearchOutcome) -> None:
        """Start-up hypotheses from the search's converged solutions (each folded into (y0, P0))."""
        self._hyps = []
        for sol in out.solutions:
            if sol.converged:
                h = _Hypothesis(*self._match_update(y0, P0, sol), 0.0, set(), set())
                h.add(sol)
                self._hyps.append(h)

    def _advance_hypotheses(self, frame, dt: float, odo_a, odo_b, search) -> _Hypothesis | None:
        """Predict and match every hypothesis with this frame; the winner, if one has won (it ends the search).

        ``search()`` runs the global pose search on this frame: (y0, P0, outcome) or None (see
        :meth:`_rivals`, for a lone hypothesis that has not won).
        """
        p, sp = self.params, self.params.search
        n_det = 0 if frame is None or frame.is_empty() else len(frame.points_uv) + len(frame.poles_uv)
        for h in self._hyps:
            h.y_pred, h.P_pred = self._predict(h.y, h.P, dt, odo_a, odo_b)
            h.y, h.P, h.last = h.y_pred, h.P_pred, None
            if n_det == 0:
                continue
            try:
                res = self.matcher.match(frame, h.y_pred[:6], h.P_pred[:6, :6], None)
            except ValueError:
                self._count("frame invalid")
                return None
            if res.converged:
                h.y, h.P = self._match_update(h.y_pred, h.P_pred, res)
                h.add(res)
            else:  # nothing explained: every detection costs like an outlier
                h.score += p.matcher.inlier_chi2 * n_det
                h.misses += 1
        # Merge hypotheses that reached one basin; drop the hopeless and the lost.
        self._hyps.sort(key=lambda h: h.score)
        kept: list[_Hypothesis] = []
        for h in self._hyps:
            if h.misses >= 3 or h.score > self._hyps[0].score + 5.0 * sp.margin:
                continue
            if all(self.search.distinct(h.y, k.y) for k in kept):
                kept.append(h)
        self._hyps = kept
        if not kept:
            return None
        best = kept[0]
        runner = kept[1].score if len(kept) > 1 else np.inf
        if (
            best.last is None
            or best.constraints < sp.min_constraints
            or best.landmarks < sp.min_landmarks
            or runner - best.score < sp.margin
        ):
            if len(kept) == 1 and n_det:
                return self._rivals(search, n_det)
            return None
        self._hyps = []
        return best

    def _rivals(self, search, n_det: int) -> _Hypothesis | None:
        """Search again while a lone hypothesis has not won; the winner if the search accepts a solution.

        A lone hypothesis has no rival to beat, only too few constraints: a wrong basin from a frame
        that showed one pole (urban seed 0: 7 m across, 10 degrees off, one pole and the lanes) keeps
        converging on its pole and the lanes frame after frame, never wins, and held the vehicle in
        fallback for the whole episode while the true basin came into view. So the search runs on
        every such frame: a solution it accepts wins at once (as at a cold start); its other converged
        solutions distinct from the hypothesis join it as rivals, scored as if they had explained the
        earlier frames as well as it did (only this frame's evidence tells them apart).
        """
        lone = self._hyps[0]
        self._count("search")
        try:
            found = search()
        except ValueError:
            self._count("frame invalid")
            return None
        if found is None:
            return None
        y0, P0, out = found
        if out.match is not None:
            self._hyps = []
            return _Hypothesis(y0, P0, out.match.score, set(), set(), y_pred=y0, P_pred=P0, last=out.match)
        earlier = lone.score - (lone.last.score if lone.last is not None else self.params.matcher.inlier_chi2 * n_det)
        for sol in out.solutions:
            if sol.converged and self.search.distinct(sol.pose_filtered, lone.y):
                h = _Hypothesis(*self._match_update(y0, P0, sol), earlier, set(), set())
                h.add(sol)
                self._hyps.append(h)
        return None

    # ------------------------------------------------------------------ results

    def _uninitialised(self, t: float, gnss: GnssMeasurement | None, reason: str) -> LocalizationResult:
        """The GNSS position with an unknown heading (or nothing at all)."""
        p = self.params
        pose = np.zeros(6)
        cov = np.diag([1e6, 1e6, 1e6, 1.0, 1.0, _UNIFORM_YAW_VAR])
        if gnss is not None:
            pose[:3] = gnss.p_map
            cov[0, 0] = cov[1, 1] = p.gnss_bias_sigma_m**2 + self._gnss_white_var(gnss)
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
        speed = float(self.y[_SCALE]) * (odometry.speed if odometry is not None else 0.0)
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
        cov_f = cov_cam + self._match_bias_cov(pose_f[5])
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

    def _match_bias_cov(self, yaw: float) -> np.ndarray:
        """The covariance of the map-matching error no frame sees (``match_bias_sigma``), in the map frame."""
        return bias_cov(self.params.match_bias_sigma, yaw)


def _sigma_h(P) -> float:
    """The largest horizontal 1-sigma of a pose covariance (m)."""
    return float(np.sqrt(max(np.linalg.eigvalsh(P[:2, :2])[-1], 0.0)))


def _kf_update(y, P, H, r, R):
    """Kalman update with residual r = z - H y (Joseph form); yaw wrapped."""
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    y = y + K @ r
    y[5] = wrap_angle(y[5])
    I_KH = np.eye(len(y)) - K @ H
    P = I_KH @ P @ I_KH.T + K @ R @ K.T
    return y, 0.5 * (P + P.T)
