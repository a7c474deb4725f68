"""The map matcher's parameters and data: what :class:`.matcher.MapMatcher` takes, keeps per frame and per
association round, and returns (the equations are in :mod:`.matcher`'s module doc)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ..geometry import CameraIntrinsics

__all__ = ["CameraFrame", "FrameData", "MatchResult", "MatcherParams", "RoundData"]


class MatcherParams(BaseModel):
    """Parameters of :class:`MapMatcher` (pixels at the camera's full resolution, SI units otherwise).

    The paper's lambda_n (0.001 with cm and degrees) is expressed as standard deviations:
    lambda_roll_pitch = 1 / sigma_roll_pitch_rad, lambda_height = 1 / sigma_height_m.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    # Measurement noise.
    point_sigma_px: float = Field(2.0, gt=0, description="1-sigma of a point detection incl. map error (px)")
    pole_sigma_px: float = Field(2.0, gt=0, description="1-sigma of a pole segment endpoint across the pole (px)")
    pole_floor_px: float = Field(1.0, ge=0, description="extra 1-sigma of D_L for model error (px)")
    landmark_map_sigma_m: float = Field(
        0.05,
        ge=0,
        description="1-sigma of a map landmark's own position error per axis (m), the map's specification: it "
        "moves the landmark's projection by f sigma / depth (px), added to the detection's sigma (a lamp post "
        "10 m ahead: 5 px against the detector's 2). The error shared by every landmark in view (the survey's "
        "drift) cannot be seen in one frame: the Localizer accounts for it (LocalizerParams.match_bias_sigma)",
    )
    lane_sigma_px: float = Field(
        2.0,
        gt=0,
        description="1-sigma of one lane EDT residual (px), before the marking's width: the residual is 0 "
        "anywhere on the painted width w, so each sample also gets (w/2)^2/3 (uniform) added to its variance",
    )
    lane_dt_max_width_px: int = Field(
        640,
        ge=16,
        description="the distance transform is computed at most this wide: a wider mask is pooled by an integer "
        "factor, a block with any marking pixel being marking (1280x720: 4.7 -> 1.4 ms here; accuracy unchanged)",
    )
    lane_cap_px: float = Field(10.0, gt=0, description="cap of the lane distance; a larger one pulls into wrong lanes")
    lane_effective_samples: float = Field(
        30.0,
        gt=0,
        description="lane residuals share the mask's correlated errors: their total information is that "
        "of at most this many independent samples (sigma_lane is inflated accordingly)",
    )
    lane_outlier_fraction: float = Field(
        0.46,
        gt=0,
        lt=1,
        description="the lane evidence (MatchResult.evidence): the fraction of lane samples whose marking the mask "
        "does not show near them at the true pose (occlusion, dropouts, map and calibration error); fitted by EM "
        "on development seeds 10-11 of both paper scenarios (docs/localization.md)",
    )
    lane_outlier_scale_px: float = Field(
        46.0,
        gt=0,
        description="... the mean distance (px, exponential) of such a sample's nearest marking (fitted likewise)",
    )
    lane_evidence_samples: float = Field(
        7.0,
        gt=0,
        description="... the lanes' evidence of one frame is worth this many independent samples (n_eff times "
        "the mean per-sample -2 log-likelihood): fitted on the same seeds so that the lateral offset the lanes "
        "alone give has a NEES of 1 at the true pose",
    )
    huber_k: float = Field(2.0, gt=0, description="Huber threshold on a landmark's whitened residual norm")
    # The soft constraint r_n and the GNSS antenna.
    sigma_roll_pitch_rad: float = Field(0.01, gt=0, description="r_n: 1/lambda_n on roll and pitch (rad)")
    sigma_height_m: float = Field(0.05, gt=0, description="r_n: 1/lambda_n on the camera height (m)")
    nominal_roll_pitch_rad: tuple[float, float] = Field((0.0, 0.0), description="roll, pitch of the body at rest")
    attitude_restart_rad: float = Field(
        0.005,
        gt=0,
        description="a prediction whose roll or pitch is farther than this from nominal is also solved from the "
        "nominal attitude; the better score wins (pitch has local minima)",
    )
    body_height_m: float = Field(0.0, description="body origin above the road; H = this + camera z in the body (m)")
    gnss_lever_arm_m: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="GNSS antenna in the body (m)")
    prior_inflation: float = Field(
        25.0, ge=1.0, description="the per-frame estimate keeps 1/this of the prediction's information"
    )
    # What is used.
    range_m: float = Field(70.0, gt=0, description="landmarks farther than this are not projected (m)")
    min_depth_m: float = Field(1.0, gt=0, description="nearest depth along the optical axis that is used (m)")
    lane_range_m: tuple[float, float] = Field((3.0, 40.0), description="lane samples this far ahead (body x, m)")
    lane_spacing_m: float = Field(1.0, gt=0, description="spacing of the precomputed painted lane samples (m)")
    lane_max_samples: int = Field(300, ge=1, description="at most this many lane samples per frame")
    lane_enable_sigma_m: float = Field(0.75, gt=0, description="lanes are used once the lateral 1-sigma is below (m)")
    lane_enable_sigma_yaw_rad: float = Field(0.02, gt=0, description="... and the yaw 1-sigma below (rad)")
    lane_dashed_sigma_m: float = Field(
        1.0,
        gt=0,
        description="dashed lines only once the longitudinal 1-sigma is below (dashes alias every 9 m)",
    )
    lane_along_track: bool = Field(
        False,
        description="count the lanes' information on the position along the heading (dash phase, "
        "curvature) in the covariance; off, the along-track part of their Jacobian is projected out of "
        "the information (the solve still uses it): the dash pattern's phase is not surveyed to that "
        "accuracy and its errors repeat from frame to frame, which made the tracker overconfident along "
        "the road (suburban 6-DoF NEES 12.4)",
    )
    lane_end_angle_deg: float = Field(
        30.0,
        ge=0,
        le=90,
        description="samples where the distance transform's gradient is farther than this from the line's "
        "normal (the marking ends there) are left out",
    )
    min_pole_length_px: float = Field(8.0, gt=0, description="shorter detected or projected poles are ignored (px)")
    # Association.
    gate_chi2: float = Field(13.8, gt=0, description="Mahalanobis association gate (2 dof, 99.9 %)")
    gate_px: tuple[float, ...] = Field(
        (1e9, 60.0, 25.0, 12.0),
        min_length=1,
        description="pixel gate per round, shrinking (the last value repeats); round 0 relies on the "
        "Mahalanobis gate with the prediction's covariance",
    )
    gate_floor_px: float = Field(
        3.0, ge=0, description="pixel 1-sigma added to the association covariance after round 0"
    )
    near_sigmas: float = Field(
        3.0,
        ge=0,
        description="a landmark nearer (depth along the optical axis) than this many horizontal position "
        "1-sigmas of the round's pose is not associated: its projection is too nonlinear in the pose for the "
        "linearised gate (a lamp post beside the car, 1.5 m deep, projects thousands of px off the image "
        "and its huge Jacobian lets a far detection pass; the LM then follows it)",
    )
    pole_overlap_tol: float = Field(
        0.3,
        ge=0,
        description="a detected segment must overlap the projected pole (tolerance, fraction of its length)",
    )
    inlier_chi2: float = Field(9.21, gt=0, description="a landmark is an inlier below this chi^2 (2 dof, 99 %)")
    # Lane search when the prediction is too uncertain for the lane basin.
    search_lateral_max_m: float = Field(7.0, gt=0, description="lane search: at most this lateral shift (m)")
    search_yaw_max_rad: float = Field(0.1, gt=0, description="lane search: at most this yaw shift (rad)")
    search_lateral_step_m: float = Field(0.125, gt=0, description="lane search: fine lateral step; coarse 4x (m)")
    search_yaw_step_rad: float = Field(0.002, gt=0, description="lane search: fine yaw step; coarse 4x (rad)")
    search_candidates: int = Field(3, ge=1, description="lane search: local minima solved as start poses")
    # Solver.
    rounds: int = Field(4, ge=1, description="association rounds (associate, then LM)")
    max_iterations: int = Field(10, ge=1, description="LM iterations per round")
    tol_cost: float = Field(1e-4, gt=0, description="relative (predicted) cost decrease that ends a round")
    tol_step: float = Field(1e-5, gt=0, description="step (m, rad) that ends a round")
    settle_m: float = Field(0.01, ge=0, description="no further round after one that moved less than this (m) ...")
    settle_rad: float = Field(5e-4, ge=0, description="... and this (rad)")
    # Acceptance.
    min_constraints: int = Field(
        3,
        ge=0,
        description="converged needs this many constraints on (x, y, yaw) -- 2 per point inlier, 1 per pole "
        "inlier (its bearing), 2 for the lanes (lateral offset and yaw): the 3 unknowns ...",
    )
    min_constraints_tracked: int = Field(
        1,
        ge=0,
        description="... or this many when the prediction is 'tracked': lateral 1-sigma below "
        "tracked_sigma_m, yaw 1-sigma below lane_enable_sigma_yaw_rad (lanes cannot lock onto a wrong lane)",
    )
    tracked_sigma_m: float = Field(0.5, gt=0, description="lateral 1-sigma of a 'tracked' prediction (m)")
    min_lane_samples: int = Field(20, ge=0, description="lane samples within the cap for a lanes-only match")
    max_cost: float = Field(4.0, gt=0, description="converged needs a cost (chi^2 per residual) below this")


@dataclass(frozen=True)
class CameraFrame:
    """One camera frame's detections, in pixels of ``intr``.

    ``lane_mask`` may have a lower resolution than ``intr`` with the same aspect (e.g. half size).
    """

    intr: CameraIntrinsics
    T_body_cam: np.ndarray  # 4x4
    points_uv: np.ndarray  # (N, 2) point landmark detections (px)
    points_cls: np.ndarray  # (N,) LandmarkClass codes
    poles_uv: np.ndarray  # (M, 4) pole segments u1, v1, u2, v2 (px), possibly partial
    lane_mask: np.ndarray | None = None  # (H, W) uint8, 255 on markings

    def is_empty(self) -> bool:
        """No detections and no lane marking pixel."""
        return (
            len(self.points_uv) == 0
            and len(self.poles_uv) == 0
            and (self.lane_mask is None or not np.any(self.lane_mask))
        )


@dataclass(frozen=True)
class MatchLinearization:
    """A match's camera rows linearised at its solution x_f, for a filter that keeps each landmark's own map
    error as a consider state (:func:`.ekf.consider_match_update`).

    Landmark k (``keys[k]``: 'point' or 'pole', map index) has 2 rows: ``J[k]`` (2, 6) and ``e[k]`` (2,),
    whitened by the detector's noise alone (without ``landmark_map_sigma_m``, which the solve adds to every
    frame as if it were new) and times the square root of their IRLS weight. Moving the landmark by m (map
    frame, m) moves its projection as moving the vehicle by -m would, so its map error's Jacobian is
    ``-J[k][:, :3]``. The lane rows are given by their information ``info_lanes`` = J^T W J (6, 6) and gradient
    ``grad_lanes`` = J^T W e (6,) at x_f, the other measurement rows (ground, GNSS, anchor; not the prediction
    prior) likewise by ``info_rest``, ``grad_rest``.
    """

    keys: tuple[tuple[str, int], ...]
    J: np.ndarray
    e: np.ndarray
    info_lanes: np.ndarray
    grad_lanes: np.ndarray
    info_rest: np.ndarray
    grad_rest: np.ndarray


@dataclass(frozen=True)
class MatchResult:
    """The outcome of one :meth:`MapMatcher.match` (see the module doc for the two estimates).

    ``cost`` is the robust chi^2 per residual of the camera residuals (points, poles, lane samples
    within the cap); ``score`` is the whole robust objective (prior included) plus ``inlier_chi2``
    for every detection left unexplained -- what competing solutions of one frame are ranked by;
    ``reason`` says why ``converged`` is False. ``evidence``: the camera's -2 log marginal likelihood of the
    frame at this solution (Laplace; without the prediction prior's rows, ``prior_chi2``): what basins are
    weighed by (see :meth:`.lm.LevenbergMarquardt.evidence`).
    """

    pose: np.ndarray
    cov: np.ndarray
    pose_filtered: np.ndarray
    cov_filtered: np.ndarray
    n_points: int
    n_poles: int
    n_lane: int
    cost: float
    iterations: int
    converged: bool
    reason: str = ""
    score: float = 0.0
    constraints: int = 0  # on (x, y, yaw): 2 per point inlier, 1 per pole inlier, 2 for the lanes
    gnss_used: bool = False
    point_pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), int))  # (map index, detection index)
    pole_pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), int))
    prior_chi2: float = 0.0  # the prediction prior's part of ``score``
    pair_chi2: np.ndarray = field(default_factory=lambda: np.zeros(0))  # chi^2 of point_pairs, then pole_pairs
    evidence: float = 0.0
    linearization: MatchLinearization | None = None  # the camera rows at pose_filtered (see MatchLinearization)

    def inliers(self, inlier_chi2: float) -> list[tuple[tuple[str, int], float]]:
        """((kind 'point' or 'pole', map index), chi^2) of every landmark inlier."""
        keys = [("point", int(i)) for i in self.point_pairs[:, 0]] + [("pole", int(i)) for i in self.pole_pairs[:, 0]]
        return [(k, float(c)) for k, c in zip(keys, self.pair_chi2, strict=False) if c <= inlier_chi2]


@dataclass
class FrameData:
    """A validated frame with its distance transform and priors (built by :meth:`MapMatcher.prepare`)."""

    intr: CameraIntrinsics
    T_bc: np.ndarray
    pt_uv: np.ndarray
    pt_cls: np.ndarray
    pole_M1: np.ndarray
    pole_M2: np.ndarray
    dt: np.ndarray | None  # I_R of mask rows dt_row0.. (rows above the road are not needed)
    dt_row0: int
    lane_scale: float  # mask px per image px
    gnss: tuple[np.ndarray, np.ndarray] | None  # (p_map, sigma (3,))
    x_prior: np.ndarray
    L_prior: np.ndarray  # e = L^T (x - x_prior)
    I_prior: np.ndarray


@dataclass
class RoundData:
    """One round's associations and constants, fixed while LM iterates (from :meth:`MapMatcher.associate`)."""

    pt_map: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    pt_det: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    pt_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    pt_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    pole_map: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    pole_det: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    pole_A: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # clipped map pole endpoints
    pole_B: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    pole_M1: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # detected endpoints
    pole_n: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # unit normal of M1 -> M2
    pole_W: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    pole_W_det: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))  # ... without the map's error
    pt_sigma: np.ndarray = field(default_factory=lambda: np.ones(0))  # per point landmark, px
    lane_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    lane_sigma: np.ndarray = field(default_factory=lambda: np.ones(0))  # per sample, mask px
    lane_s: np.ndarray = field(default_factory=lambda: np.ones(0))  # ... before lane_effective_samples' inflation
    lane_cap: float = 10.0  # mask px
    z_ground: float | None = None
    anchor: tuple[np.ndarray, np.ndarray] | None = None  # lane-search pseudo-measurement (rows, pose)
    xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # all of the above, projected at once

    def finalize(self) -> RoundData:
        self.xyz = np.vstack([self.pt_xyz, self.pole_A, self.pole_B, self.lane_xyz])
        return self

    def key(self):
        return (
            tuple(self.pt_map),
            tuple(self.pt_det),
            tuple(self.pole_map),
            tuple(self.pole_det),
            len(self.lane_xyz) > 0,
            self.anchor is None,
        )
