"""The localizer's types and parameters: what :mod:`.localizer`, :mod:`.ekf` and :mod:`.startup` share.

Kept apart from the localizer so that the filter (:mod:`.ekf`) and the state machine (:mod:`.startup`)
import their inputs and parameters from here, not from the module that uses them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .matcher_types import MatcherParams
from .search import PoseSearchParams

__all__ = ["GnssMeasurement", "LocalizationResult", "LocalizerParams", "OdometryMeasurement"]


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
    map_errors: Literal["independent", "consider"] = Field(
        "independent",
        description="how the tracker folds a match in: 'independent' (the default) takes the matcher's posterior, "
        "every view's landmark map error (MatcherParams.landmark_map_sigma_m) counted as new; 'consider' (opt-in) "
        "keeps each landmark's map error as a consider state shared by its views (ekf.consider_match_update): on "
        "development seeds 10-15 HMI 77 -> 19 frames urban, 124 -> 54 suburban, but urban map-matched RMSE 0.195 -> "
        "0.222 m and more rejected jumps (docs/localization.md, Along-road rivals)",
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
    integrity_risk: float = Field(
        1e-3,
        gt=0,
        lt=0.5,
        description="probability per axis that the true error exceeds the protection level the vehicle states "
        "(lateral, longitudinal: K sigma of the filtered covariance with K the two-sided Gaussian quantile)",
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
    # A pose predicted over a longer gap from the odometry at its two ends is no start for a local match:
    # live, a vehicle frozen 3.1 s resumed 12-16 m and 17-39 deg off in 4 of 5 runs, once map-matched in the
    # wrong basin for 3.5 s; starting again relocalized it. Frames come every 0.1 s, with their odometry.
    max_gap_s: float = Field(1.0, gt=0, description="a longer gap between steps re-initialises (s)")
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
    # (lateral, longitudinal) protection levels (m) at LocalizerParams.integrity_risk, in the vehicle frame; None
    # while the vehicle does not claim integrity (not map matching, or a fault detected: ``reason``)
    protection_level: np.ndarray | None = None

    @property
    def lock(self) -> Literal["full", "lateral"] | None:
        """While map matching, what the camera fixed: 'full' (a landmark inlier with the lanes: the whole pose) or
        'lateral' (the lanes alone: lateral position and heading; along the road, GNSS and odometry); else None."""
        if self.mode != "map_matching":
            return None
        return "full" if self.n_points + self.n_poles > 0 else "lateral"

    def quality(self) -> dict[str, Any]:
        """The fields of schemas.LocalizationQuality."""
        return {
            "mode": self.mode,
            "n_points": self.n_points,
            "n_poles": self.n_poles,
            "n_lane": self.n_lane,
            "cost": float(self.cost),
            "lock": self.lock,
        }
