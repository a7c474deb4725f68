"""Map-matching localization of one camera frame (the paper's section "Map-matching Localization").

The HD map's landmarks are projected into the image with a supposed pose, associated with the
detections, and the pose is found by Levenberg-Marquardt on the residuals below. Every residual
is whitened (divided by its standard deviation), so the cost is a chi^2:

* D_P, point landmarks (traffic lights, signs), 2 residuals each:
  ``e = (pi_P(p_m, x) - M) / sigma_point``.
* D_L, pole landmarks (lamp posts, base and top), 2 residuals each: the signed distances of the
  projected map endpoints m_1, m_2 to the infinite line through the detected segment M_1, M_2,
  ``d_k = (M_2 - M_1) x (m_k - M_1) / ||M_2 - M_1||`` (geometry.point_line_distance), whitened by
  the covariance the detected endpoints' noise induces on (d_1, d_2) (:meth:`MapMatcher.pole_whitening`).
* r^R, the lane "domain-like" feature (the EDT residual): painted lane-line samples 3-40 m ahead are
  projected and the distance transform I_R of the lane mask is read at the projection,
  ``e = min(I_R(pi(p, x)), cap) / sigma_lane`` (bilinear; capped samples have no gradient). I_R is
  0 across the painted width w, so sigma_lane^2 = sigma^2 + (w/2)^2 / 3 per sample; samples where
  the marking ends in the mask (dash ends, dropouts, occlusion) are left out (``_lane_select``).
* r_n, the paper's soft constraint on roll, pitch and camera height, weighted by lambda_n = 1/sigma:
  ``(roll - roll_0, pitch - pitch_0, C_z - (z_lane + H))``.
* The GNSS prior ``(p + R l - p_gnss) / sigma`` (l: the antenna's lever arm in the body), if given
  (the Localizer keeps GNSS in its own filter, with the receiver's bias, and passes None).
* The prediction prior ``L^T (x - x_pred)`` with ``L L^T = P_pred^-1``.

The pose is the body's ``x = [x, y, z, roll, pitch, yaw]`` (geometry.py); every Jacobian is
analytic, chained from :func:`geometry.project_points_jac` (one projection of all map points per
evaluation).

Two estimates come out of one solve. The LM runs with the prediction prior at full weight
(robust association, a well-posed problem): that is the filtered posterior ``pose_filtered``,
``cov_filtered``, what a tracker carries to the next frame. What this frame says on its own
(camera + GNSS), for a consumer that fuses frames itself -- the host's factor graph adds one prior
per frame plus motion factors, so a filtered prior would be counted many times -- is the same
problem with the prediction's information divided by ``prior_inflation`` k (a weak prior that
only keeps unobservable directions finite): ``pose``, ``cov``. It follows from the solution by one
Newton step, ``x_w = x_f - H_w^-1 (g_meas + I_p (x_f - x_pred) / k)``, ``H_w = H_meas + I_p / k``,
``cov = H_w^-1`` (g_meas, H_meas: gradient and information of the camera residuals; at the
solution g_meas = -I_p (x_f - x_pred) when they use the full Jacobian). Neither is to be fused with
the prediction again.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from schemas.models import LandmarkClass

from .. import lanemask
from ..geometry import (
    CameraIntrinsics,
    project_points_grid,
    project_points_jac,
    project_points_pose,
    rpy_to_matrix_jac,
    wrap_angle,
)
from ..hdmap.model import HDMap

__all__ = ["CameraFrame", "MapMatcher", "MatchResult", "MatcherParams", "lane_distance_transform"]

_POINT_CODES = {"traffic_light": int(LandmarkClass.TRAFFIC_LIGHT), "sign": int(LandmarkClass.SIGN)}
_BIG = 1e12


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
class MatchResult:
    """The outcome of one :meth:`MapMatcher.match` (see the module doc for the two estimates).

    ``cost`` is the robust chi^2 per residual of the camera residuals (points, poles, lane samples
    within the cap); ``score`` is the whole robust objective (prior included) plus ``inlier_chi2``
    for every detection left unexplained -- what competing solutions of one frame are ranked by;
    ``reason`` says why ``converged`` is False.
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

    def inliers(self, inlier_chi2: float) -> list[tuple[tuple[str, int], float]]:
        """((kind 'point' or 'pole', map index), chi^2) of every landmark inlier."""
        keys = [("point", int(i)) for i in self.point_pairs[:, 0]] + [("pole", int(i)) for i in self.pole_pairs[:, 0]]
        return [(k, float(c)) for k, c in zip(keys, self.pair_chi2, strict=False) if c <= inlier_chi2]


def lane_distance_transform(mask: np.ndarray) -> np.ndarray | None:
    """I_R: per pixel the Euclidean distance (px, float32) to the nearest marking pixel (mask >= 128).

    ``cv2.distanceTransform(DIST_L2, DIST_MASK_PRECISE)`` measures the distance to the nearest zero
    pixel, so markings become 0. None when the mask has no marking pixel.
    """
    mask = np.asarray(mask)
    if mask.dtype != np.uint8:
        mask = np.clip(mask, 0, 255).astype(np.uint8)
    src = cv2.threshold(np.ascontiguousarray(mask), 127, 255, cv2.THRESH_BINARY_INV)[1]
    if cv2.countNonZero(src) == src.size:
        return None
    return cv2.distanceTransform(src, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def bilinear_with_grad(img: np.ndarray, uv: np.ndarray):
    """Bilinear interpolation of img at uv (N, 2) (inside [0, W-1) x [0, H-1)) and its exact gradient.

    With the cell's corners d_00, d_01 (right), d_10 (below), d_11 and fractions f_u, f_v:
    ``top = d_00 + f_u (d_01 - d_00)``, ``bot = d_10 + f_u (d_11 - d_10)``, value ``top + f_v (bot - top)``,
    d/du ``(1 - f_v)(d_01 - d_00) + f_v (d_11 - d_10)``, d/dv ``bot - top``.
    """
    u, v = uv[:, 0], uv[:, 1]
    u0 = np.floor(u)
    v0 = np.floor(v)
    fu, fv = u - u0, v - v0
    w = img.shape[1]
    corner = v0.astype(np.intp) * w + u0.astype(np.intp)  # the flat index of d_00
    flat = img.reshape(-1)
    d00 = flat[corner].astype(np.float64)
    d01 = flat[corner + 1]
    d10 = flat[corner + w]
    d11 = flat[corner + (w + 1)]
    du_top, du_bot = d01 - d00, d11 - d10
    top = d00 + fu * du_top
    bot = d10 + fu * du_bot
    dv = bot - top
    return top + fv * dv, (1.0 - fv) * du_top + fv * du_bot, dv


def _huber(norms: np.ndarray, k: float):
    """Huber rho of residual norms (chi^2-like: norm^2 inside k) and the IRLS weights."""
    rho = np.where(norms <= k, norms**2, 2.0 * k * norms - k * k)
    w = np.where(norms <= k, 1.0, k / np.maximum(norms, 1e-12))
    return rho, w


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
    pt_sigma: np.ndarray = field(default_factory=lambda: np.ones(0))  # per point landmark, px
    lane_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    lane_sigma: np.ndarray = field(default_factory=lambda: np.ones(0))  # per sample, mask px
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


@dataclass
class _Eval:
    e: np.ndarray  # whitened residuals (m,); the last 6 rows are the prediction prior
    J: np.ndarray  # (m, 6)
    w: np.ndarray  # IRLS weights (m,)
    cost: float  # robust cost of all rows (the LM objective)
    meas_rho: float  # robust cost of landmark rows + lane rows within the cap
    n_meas: int
    pt_chi2: np.ndarray
    pole_chi2: np.ndarray
    n_lane_in: int
    lane_rows: slice  # the lane samples' rows
    yaw: float  # of the pose evaluated
    lane_along_track: bool = True

    @cached_property
    def J_info(self) -> np.ndarray:
        """J for the information matrix (see MatcherParams.lane_along_track): without it, the lane rows'
        position columns lose their component along the heading h, ``J_xy - (J_xy h) h^T``. Only the
        covariances need it, so it is made when first asked for."""
        rows = self.lane_rows
        if rows.stop == rows.start or self.lane_along_track:
            return self.J
        J_info = self.J.copy()
        heading = np.array([np.cos(self.yaw), np.sin(self.yaw)])
        J_info[rows, :2] -= np.outer(J_info[rows, :2] @ heading, heading)
        return J_info


class MapMatcher:
    """Pose of the body from one camera frame, the HD map, GNSS and a predicted pose (see the module doc).

    Association: map landmarks are projected with the current estimate; detections of the same
    class are assigned by the Hungarian method on the Mahalanobis distance
    ``d^2 = e^T (J P J^T + s^2 I)^-1 e`` (P: the current pose covariance), gated by ``gate_chi2``
    and by a pixel gate that shrinks from round to round; poles likewise on the distance of the
    detected endpoints to the projected pole's line, if the segments overlap along it. After each
    round's LM the associations are redone with the new estimate and covariance, until they repeat.

    Lanes join once the lateral position and yaw are within the capped residual's basin; with a
    wider prediction (start-up, recovery) a grid search over lateral offset and yaw on the lane
    distance transform gives a few start poses, each solved in full, and the best is kept.
    """

    def __init__(self, hdmap: HDMap, params: MatcherParams | None = None):
        self.params = params or MatcherParams()
        self.hdmap = hdmap
        self._pt_xyz = np.array([f.p_map for f in hdmap.points], dtype=float).reshape(-1, 3)
        self._pt_cls = np.array([_POINT_CODES[f.cls] for f in hdmap.points], dtype=int)
        self._pole_base = np.array([f.base for f in hdmap.poles], dtype=float).reshape(-1, 3)
        self._pole_top = np.array([f.top for f in hdmap.poles], dtype=float).reshape(-1, 3)
        samples, solid, tangents, widths = [], [], [], []
        for ln in hdmap.lane_lines:
            line = ln.polyline
            arcs = ln.painted_arcs(self.params.lane_spacing_m)
            s = line.point_at(arcs)
            samples.append(s)
            solid.append(np.full(len(s), ln.kind == "solid"))
            widths.append(np.full(len(s), ln.width_m))
            tangents.append(line.tangent_at(arcs))
        self._lane_xyz = np.vstack(samples) if samples else np.zeros((0, 3))
        self._lane_tan = np.vstack(tangents) if tangents else np.zeros((0, 3))
        self._lane_solid = np.concatenate(solid) if solid else np.zeros(0, bool)
        self._lane_width = np.concatenate(widths) if widths else np.zeros(0)
        self._lane_tree = cKDTree(self._lane_xyz[:, :2]) if len(self._lane_xyz) else None
        self._lever = np.array(self.params.gnss_lever_arm_m, dtype=float)
        self._ground_J_attitude = np.eye(6)[3:5] / self.params.sigma_roll_pitch_rad  # r_n's roll, pitch rows
        self._ground_J_attitude.flags.writeable = False

    # ------------------------------------------------------------------ public API

    def match(self, frame: CameraFrame, pose_init, cov_init, gnss: Any | None = None) -> MatchResult:
        """Estimate the pose for ``frame`` from the prediction (``pose_init`` (6,), ``cov_init`` 6x6).

        ``gnss``: an object with ``p_map`` (3,), ``sigma_h_m`` and ``sigma_v_m`` (schemas.GnssFix,
        localizer.GnssMeasurement), or None. Raises ValueError on malformed arguments; detections
        that are not finite are dropped.
        """
        fd = self.prepare(frame, pose_init, cov_init, gnss)
        P = _safe_inv(fd.I_prior)
        best = self.solve_from(fd, fd.x_prior, P)
        nominal = np.asarray(self.params.nominal_roll_pitch_rad, dtype=float)
        if np.any(np.abs(fd.x_prior[3:5] - nominal) > self.params.attitude_restart_rad):
            # The camera cost has local minima in pitch: a tracked pitch a degree off fits the lanes and
            # the landmarks' heights with a few px everywhere and a solve from it stays there. Also
            # solve from the r_n prior's centre; the better score wins.
            x = fd.x_prior.copy()
            x[3:5] = nominal
            alt = self.solve_from(fd, x, P)
            if alt.score < best.score:
                best = replace(alt, iterations=alt.iterations + best.iterations)
        return best

    def solve_from(self, fd: FrameData, x, P) -> MatchResult:
        """The best solution from start pose x with association covariance P (the prior stays fd's).

        If P is too wide for the lanes' basin, the lane search gives a few start poses, each solved.
        """
        starts = [(np.asarray(x, dtype=float).copy(), P)]
        if fd.dt is not None and not self._lanes_allowed(x, P):
            hyps = self._lane_search(x, P, fd)
            if hyps:
                starts = [(h, self._condition_lateral_yaw(h, P), self._anchor(h)) for h in hyps]
        results = [self._result(*self._solve(x, P, fd, anchor[0] if anchor else None), fd) for x, P, *anchor in starts]
        best = min(results, key=lambda r: r.score)
        return replace(best, iterations=sum(r.iterations for r in results))

    def polish(self, fd: FrameData, res: MatchResult) -> MatchResult:
        """A converged solution solved once more from itself, with its own covariance; the better score is kept.

        A solve from a start far from its basin's minimum ends when its landmark associations repeat, but
        its lane samples and their weights were chosen at the start, up to a metre off: the minimum is not
        reached and the score does not compare with that of a solution that started close (urban seed 0:
        the true basin at 0.21 m scored 531 against a wrong basin's 385, and 314 once solved again).
        """
        if not res.converged:
            return res
        again = self.solve_from(fd, res.pose_filtered, res.cov_filtered)
        if again.score < res.score:
            return replace(again, iterations=again.iterations + res.iterations)
        return res

    def prepare(self, frame: CameraFrame, pose_init, cov_init, gnss: Any | None = None) -> FrameData:
        """Validate the inputs, drop non-finite detections and compute the lane distance transform."""
        p = self.params
        x0 = np.asarray(pose_init, dtype=float).reshape(-1)
        if x0.shape != (6,) or not np.all(np.isfinite(x0)):
            raise ValueError(f"pose_init must be a finite (6,) vector, got {pose_init!r}")
        P0 = np.asarray(cov_init, dtype=float)
        if P0.shape != (6, 6) or not np.all(np.isfinite(P0)):
            raise ValueError(f"cov_init must be a finite 6x6 matrix, got shape {P0.shape}")
        try:
            I0 = np.linalg.inv(0.5 * (P0 + P0.T))
            L0 = np.linalg.cholesky(0.5 * (I0 + I0.T))
        except np.linalg.LinAlgError:
            raise ValueError("cov_init is not positive definite") from None
        T_bc = np.asarray(frame.T_body_cam, dtype=float)
        if T_bc.shape != (4, 4):
            raise ValueError(f"T_body_cam must be 4x4, got {T_bc.shape}")
        pts = np.asarray(frame.points_uv, dtype=float).reshape(-1, 2)
        cls = np.asarray(frame.points_cls).reshape(-1).astype(int)
        if len(cls) != len(pts):
            raise ValueError(f"{len(pts)} point detections but {len(cls)} classes")
        ok = np.all(np.isfinite(pts), axis=1)
        pts, cls = pts[ok], cls[ok]
        poles = np.asarray(frame.poles_uv, dtype=float).reshape(-1, 4)
        poles = poles[np.all(np.isfinite(poles), axis=1)]
        poles = poles[np.hypot(poles[:, 2] - poles[:, 0], poles[:, 3] - poles[:, 1]) >= p.min_pole_length_px]
        intr = frame.intr
        dt, scale, row0 = None, 1.0, 0
        if frame.lane_mask is not None:
            mask = np.asarray(frame.lane_mask)
            if mask.ndim != 2:
                raise ValueError(f"lane_mask must be 2-D, got shape {mask.shape}")
            scale = mask.shape[1] / intr.width
            if abs(mask.shape[0] - intr.height * scale) > 1.0:
                raise ValueError(f"lane_mask shape {mask.shape} does not match the image {intr.width}x{intr.height}")
            mask = lanemask.pool(mask, p.lane_dt_max_width_px)  # the vehicle pools with it before sending
            scale = mask.shape[1] / intr.width
            top = self._road_top_row(x0, P0, T_bc, intr, scale, mask.shape[0])
            if top is not None:
                row0 = top
                dt = lane_distance_transform(mask[row0:])
        g = None
        if gnss is not None:
            gp = np.asarray(gnss.p_map, dtype=float).reshape(3)
            sig = np.array([gnss.sigma_h_m, gnss.sigma_h_m, gnss.sigma_v_m], dtype=float)
            if np.all(np.isfinite(gp)) and np.all(np.isfinite(sig)) and np.all(sig > 0):
                g = (gp, sig)
        return FrameData(intr, T_bc, pts, cls, poles[:, :2], poles[:, 2:], dt, row0, scale, g, x0, L0, I0)

    # ------------------------------------------------------------------ helpers on the pose covariance

    def _sigmas(self, x, P, R=None) -> tuple[float, float, float]:
        """1-sigma across (lateral) and along the heading (m), and of yaw (rad)."""
        R = rpy_to_matrix_jac(*x[3:])[0] if R is None else R
        lat, lon = R[:2, 1], R[:2, 0]
        return (
            float(np.sqrt(max(lat @ P[:2, :2] @ lat, 0.0))),
            float(np.sqrt(max(lon @ P[:2, :2] @ lon, 0.0))),
            float(np.sqrt(max(P[5, 5], 0.0))),
        )

    def _lanes_allowed(self, x, P) -> bool:
        """Lateral position and yaw known well enough for the capped lane residual's basin."""
        sig_lat, _, sig_yaw = self._sigmas(x, P)
        return sig_lat <= self.params.lane_enable_sigma_m and sig_yaw <= self.params.lane_enable_sigma_yaw_rad

    def _anchor(self, h) -> tuple[np.ndarray, np.ndarray]:
        """The lane search's finding as a pseudo-measurement: rows A (2, 6) (lateral, yaw; whitened), pose h.

        Residual ``A (x - h)`` (yaw wrapped); used instead of the lanes in rounds where the lanes
        cannot be used yet (longitudinal position still too uncertain).
        """
        p = self.params
        lat = rpy_to_matrix_jac(*h[3:])[0][:2, 1]
        A = np.zeros((2, 6))
        A[0, :2] = lat / (2.0 * p.search_lateral_step_m)
        A[1, 5] = 1.0 / (2.0 * p.search_yaw_step_rad)
        return A, np.asarray(h, dtype=float).copy()

    def _condition_lateral_yaw(self, x, P) -> np.ndarray:
        """P after learning the lateral offset and yaw to the lane search's resolution."""
        A, _ = self._anchor(x)
        return _safe_inv(_safe_inv(P) + A.T @ A)

    # ------------------------------------------------------------------ lanes

    def _lane_ahead(self, x, lo: float | None = None, solid_only: bool = False, tangents: bool = False):
        """Painted lane samples from lane_range_m[0] (or lo) to lane_range_m[1] ahead of the body (body x).

        With ``tangents``, also the lines' unit directions and painted widths at the samples.
        """
        p = self.params
        if self._lane_tree is None:
            return (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)) if tangents else np.zeros((0, 3))
        lo_m, hi_m = p.lane_range_m
        lo_m = lo_m if lo is None else lo
        idx = np.asarray(self._lane_tree.query_ball_point(x[:2], hi_m + 2.0), dtype=int)
        if solid_only:
            idx = idx[self._lane_solid[idx]]
        pts = self._lane_xyz[idx]
        R = rpy_to_matrix_jac(*x[3:])[0]
        xb = (pts - x[:3]) @ R[:, 0]
        keep = (xb >= lo_m) & (xb <= hi_m)
        if tangents:
            return pts[keep], self._lane_tan[idx][keep], self._lane_width[idx][keep]
        return pts[keep]

    def _road_top_row(self, x, P, T_bc, intr, scale: float, mask_h: int) -> int | None:
        """First mask row lane samples ahead can reach (with a margin for the pose uncertainty), or None."""
        p = self.params
        pts = self._lane_ahead(x)[::4]
        if len(pts) == 0:
            return None
        uv, z, _ = project_points_jac(intr, x, T_bc, pts)
        v = uv[z > p.min_depth_m, 1]
        if len(v) == 0:
            return None
        sig_tilt = float(np.sqrt(max(P[3, 3], 0.0) + max(P[4, 4], 0.0)))
        margin = p.lane_cap_px + 20.0 + 3.0 * intr.fy * sig_tilt + 0.5 * intr.width * min(3.0 * sig_tilt, 0.2)
        row = (v.min() - margin + 0.5) * scale - 0.5
        return int(np.clip(np.floor(row), 0, mask_h - 2))

    def _in_mask(self, uv_l, z, fd: FrameData) -> np.ndarray:
        """Projections (mask px) that fall inside the cropped distance transform."""
        h, w = fd.dt.shape
        return (
            (z > self.params.min_depth_m)
            & (uv_l[:, 0] >= 0)
            & (uv_l[:, 0] < w - 1)
            & (uv_l[:, 1] >= fd.dt_row0)
            & (uv_l[:, 1] < fd.dt_row0 + h - 1)
        )

    def _to_mask(self, uv, fd: FrameData) -> np.ndarray:
        """Image px -> mask px (CameraIntrinsics.scaled)."""
        return uv if fd.lane_scale == 1.0 else (uv + 0.5) * fd.lane_scale - 0.5

    def _lane_search(self, x, P, fd: FrameData) -> list[np.ndarray]:
        """Start poses when the prediction is too uncertain for the lane basin: a lateral x yaw grid search.

        Score of a shift (delta along the body's y axis, psi in yaw) =
        n_eff mean(min(I_R, cap)^2) / sigma^2 + (delta / sigma_lat)^2 + (psi / sigma_yaw)^2,
        on a coarse grid with a wide cap, refined around its best local minima (the lane pattern
        repeats every lane width; the landmarks and the full cost decide between candidates).
        """
        p = self.params
        sig_lat, sig_lon, sig_yaw = self._sigmas(x, P)
        pts = self._lane_ahead(x, lo=max(p.lane_range_m[0], 6.0), solid_only=sig_lon > p.lane_dashed_sigma_m)
        if len(pts) < 10:
            return []
        if len(pts) > 150:
            pts = pts[np.linspace(0, len(pts) - 1, 150).astype(int)]
        lat = rpy_to_matrix_jac(*x[3:])[0][:2, 1]
        sig_lat, sig_yaw = max(sig_lat, 1e-3), max(sig_yaw, 1e-4)
        dmax = min(3.0 * sig_lat, p.search_lateral_max_m)
        ymax = min(3.0 * sig_yaw, p.search_yaw_max_rad)
        step_d, step_y = 4.0 * p.search_lateral_step_m, 4.0 * p.search_yaw_step_rad
        deltas = np.arange(-np.ceil(dmax / step_d), np.ceil(dmax / step_d) + 1) * step_d
        yaws = np.arange(-np.ceil(ymax / step_y), np.ceil(ymax / step_y) + 1) * step_y
        cap = p.lane_cap_px * fd.lane_scale
        coarse = self._lane_scores(x, pts, fd, deltas, yaws, 3.0 * cap, sig_lat, sig_yaw)
        starts = []
        for i, j in _local_minima(coarse, p.search_candidates):
            d_f = deltas[i] + np.arange(-4, 5) * p.search_lateral_step_m
            y_f = yaws[j] + np.arange(-4, 5) * p.search_yaw_step_rad
            fine = self._lane_scores(x, pts, fd, d_f, y_f, 1.5 * cap, sig_lat, sig_yaw)
            a, b = np.unravel_index(int(np.argmin(fine)), fine.shape)
            h = x.copy()
            h[:2] += d_f[a] * lat
            h[5] = wrap_angle(h[5] + y_f[b])
            starts.append(h)
        return starts

    def _lane_scores(self, x, pts, fd: FrameData, deltas, yaws, cap, sig_lat, sig_yaw) -> np.ndarray:
        """Chamfer score of the lane samples per (lateral, yaw) shift: shape (len(deltas), len(yaws))."""
        p = self.params
        lat = rpy_to_matrix_jac(*x[3:])[0][:2, 1]
        u, v, Z = project_points_grid(fd.intr, x, fd.T_bc, deltas[:, None] * lat, x[5] + yaws, pts)
        k = fd.lane_scale
        u = (u + 0.5) * k - 0.5  # image px -> mask px (rows from dt_row0)
        v = (v + 0.5) * k - 0.5 - fd.dt_row0
        h, w = fd.dt.shape
        ok = (Z > p.min_depth_m) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        ui = np.rint(np.where(ok, u, 0)).astype(np.intp)
        vi = np.rint(np.where(ok, v, 0)).astype(np.intp)
        val = np.where(ok, np.minimum(fd.dt[vi, ui], cap), cap)
        sigma = p.lane_sigma_px * k
        score = p.lane_effective_samples * np.mean(val**2, axis=2) / sigma**2
        return score + (deltas[:, None] / sig_lat) ** 2 + (yaws[None, :] / sig_yaw) ** 2

    # ------------------------------------------------------------------ association

    def associate(self, x, P, fd: FrameData, rnd: int = 0, anchor=None) -> RoundData:
        """Associations and per-round constants at pose x, covariance P (round ``rnd`` sets the pixel gate).

        With an ``anchor`` (from the lane search), the lanes wait until the landmarks have fixed the
        longitudinal position to lane_dashed_sigma_m (on curves a longitudinal error bends the lanes
        into a wrong minimum); the anchor stands in for them until then.
        """
        p = self.params
        x = np.asarray(x, dtype=float)
        gate_px = p.gate_px[min(rnd, len(p.gate_px) - 1)]
        floor2 = p.gate_floor_px**2 if rnd > 0 else 0.0
        rd = RoundData()
        R = rpy_to_matrix_jac(*x[3:])[0]
        cam_c = x[:3] + R @ fd.T_bc[:3, 3]
        sig_lat, sig_lon, sig_yaw = self._sigmas(x, P, R)
        # Nearest depth a landmark may have to be associated this round (see near_sigmas).
        near_z = max(p.min_depth_m, p.near_sigmas * np.sqrt(max(np.linalg.eigvalsh(P[:2, :2])[-1], 0.0)))

        # One projection of everything that may be used this round.
        near_pt = np.zeros(0, int)
        if len(fd.pt_uv) and len(self._pt_xyz):
            near_pt = np.flatnonzero(np.linalg.norm(self._pt_xyz - cam_c, axis=1) <= p.range_m)
        near_pl = np.zeros(0, int)
        if len(fd.pole_M1) and len(self._pole_base):
            near_pl = np.flatnonzero(np.linalg.norm(self._pole_base[:, :2] - cam_c[:2], axis=1) <= p.range_m)
        lanes = fd.dt is not None and sig_lat <= p.lane_enable_sigma_m and sig_yaw <= p.lane_enable_sigma_yaw_rad
        lane_pts, lane_tan, lane_w = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
        if lanes:
            lane_pts, lane_tan, lane_w = self._lane_ahead(x, solid_only=sig_lon > p.lane_dashed_sigma_m, tangents=True)
        nP, nL, nS = len(near_pt), len(near_pl), len(lane_pts)
        batch = np.vstack([self._pt_xyz[near_pt], self._pole_base[near_pl], self._pole_top[near_pl]])
        uv, z, J = project_points_jac(fd.intr, x, fd.T_bc, batch)

        # Points (D_P): Mahalanobis distance, same class only, Hungarian.
        vis = z[:nP] > near_z
        if vis.any():
            near, uvp, Jp = near_pt[vis], uv[:nP][vis], J[:nP][vis]
            var_det = p.point_sigma_px**2 + self._map_var_px(fd, z[:nP][vis])
            S = Jp @ P @ Jp.transpose(0, 2, 1) + (var_det + floor2)[:, None, None] * np.eye(2)
            diff = fd.pt_uv[None, :, :] - uvp[:, None, :]  # (K, D, 2)
            d2 = np.einsum("kdi,kij,kdj->kd", diff, np.linalg.inv(S), diff)
            ok = (
                (self._pt_cls[near][:, None] == fd.pt_cls[None, :])
                & (d2 <= p.gate_chi2)
                & (np.linalg.norm(diff, axis=2) <= gate_px)
            )
            r, c = _assign(d2, ok)
            rd.pt_map, rd.pt_det = near[r], c
            rd.pt_xyz, rd.pt_uv = self._pt_xyz[rd.pt_map], fd.pt_uv[rd.pt_det]
            rd.pt_sigma = np.sqrt(var_det[r])

        # Poles (D_L): distance of the detected endpoints to the projected pole's line, with overlap.
        if nL:
            a, b = slice(nP, nP + nL), slice(nP + nL, nP + 2 * nL)
            A, B = self._pole_base[near_pl].copy(), self._pole_top[near_pl].copy()
            m1, m2, JA, JB = uv[a].copy(), uv[b].copy(), J[a].copy(), J[b].copy()
            za, zb = z[a], z[b]
            keep = (za > near_z) | (zb > near_z)
            clip = keep & ((za <= p.min_depth_m) | (zb <= p.min_depth_m))
            if clip.any():  # the part in front of the camera (rare: poles beside the camera)
                t = (p.min_depth_m + 1e-6 - za[clip]) / (zb[clip] - za[clip])
                P_clip = A[clip] + t[:, None] * (B[clip] - A[clip])
                ca = clip & (za <= p.min_depth_m)
                cb = clip & (zb <= p.min_depth_m)
                A[ca], B[cb] = P_clip[ca[clip]], P_clip[cb[clip]]
                uvc, _, Jc = project_points_jac(fd.intr, x, fd.T_bc, P_clip)
                m1[ca], JA[ca] = uvc[ca[clip]], Jc[ca[clip]]
                m2[cb], JB[cb] = uvc[cb[clip]], Jc[cb[clip]]
            near, A, B, m1, m2, JA, JB = (v[keep] for v in (near_pl, A, B, m1, m2, JA, JB))
            if len(near):
                dm = m2 - m1
                Lp = np.maximum(np.linalg.norm(dm, axis=1), 1e-9)
                n = np.stack([-dm[:, 1], dm[:, 0]], axis=1) / Lp[:, None]
                r1 = fd.pole_M1[None] - m1[:, None]  # (K, D, 2)
                r2 = fd.pole_M2[None] - m1[:, None]
                e1, e2 = np.einsum("kdi,ki->kd", r1, n), np.einsum("kdi,ki->kd", r2, n)
                t1 = np.einsum("kdi,ki->kd", r1, dm) / Lp[:, None] ** 2
                t2 = np.einsum("kdi,ki->kd", r2, dm) / Lp[:, None] ** 2
                tol = p.pole_overlap_tol
                overlap = (np.maximum(t1, t2) >= -tol) & (np.minimum(t1, t2) <= 1.0 + tol)
                # Pose uncertainty across the pole under the detected segment's middle (J interpolated).
                tm = np.clip(0.5 * (t1 + t2), 0.0, 1.0)
                jnA, jnB = np.einsum("ki,kij->kj", n, JA), np.einsum("ki,kij->kj", n, JB)
                jn = (1.0 - tm)[:, :, None] * jnA[:, None, :] + tm[:, :, None] * jnB[:, None, :]
                map_sd = np.sqrt(self._map_var_px(fd, np.stack([za[keep], zb[keep]], axis=1)))  # (K, 2)
                var = np.einsum("kdi,ij,kdj->kd", jn, P, jn) + p.pole_sigma_px**2 + floor2
                var = var + (map_sd.mean(axis=1) ** 2)[:, None]
                mean_sq = 0.5 * (e1**2 + e2**2)
                d2 = mean_sq / var
                ok = (
                    (Lp >= p.min_pole_length_px)[:, None]
                    & overlap
                    & (d2 <= p.gate_chi2)
                    & (np.sqrt(mean_sq) <= gate_px)
                )
                r, c = _assign(d2, ok)
                rd.pole_map, rd.pole_det = near[r], c
                rd.pole_A, rd.pole_B = A[r], B[r]
                rd.pole_M1 = fd.pole_M1[c]
                dM = fd.pole_M2[c] - rd.pole_M1
                rd.pole_n = np.stack([-dM[:, 1], dM[:, 0]], axis=1) / np.linalg.norm(dM, axis=1)[:, None]
                rd.pole_W = self.pole_whitening(m1[r], m2[r], rd.pole_M1, fd.pole_M2[c], map_sd[r])

        # Lanes (EDT): once within the basin of the cap; dashes once the longitudinal error cannot alias.
        if anchor is not None and (len(rd.pt_map) + len(rd.pole_map)) and sig_lon > p.lane_dashed_sigma_m:
            rd.anchor = anchor
        elif lanes and nS:
            # The samples and points 0.5 m along their lines (no Jacobian needed).
            uv_l, z_l = project_points_pose(fd.intr, x, fd.T_bc, np.vstack([lane_pts, lane_pts + 0.5 * lane_tan]))
            rd.lane_cap = p.lane_cap_px * fd.lane_scale
            rd.lane_xyz, w_px, n_in = self._lane_select(
                lane_pts, lane_w, uv_l[:nS], z_l[:nS], uv_l[nS:], z_l[nS:], fd, rd.lane_cap
            )
            var = (p.lane_sigma_px * fd.lane_scale) ** 2 + (0.5 * w_px) ** 2 / 3.0
            rd.lane_sigma = np.sqrt(var * max(1.0, n_in / p.lane_effective_samples))
        if self._lane_tree is not None:
            dist, i = self._lane_tree.query(x[:2])
            if dist < 30.0:
                rd.z_ground = float(self._lane_xyz[i, 2])
        return rd.finalize()

    def _lane_select(self, pts, width, uv, z, uv_t, z_t, fd: FrameData, cap: float):
        """Lane samples to use (projecting into the mask, away from marking ends), their painted width in
        mask px, and how many are under the cap.

        ``uv``/``z``: projections (image px) of the samples, ``uv_t``/``z_t`` of points 0.5 m along
        the line. Samples where the distance transform's gradient is farther than
        ``lane_end_angle_deg`` from the line's normal are left out: the marking ends there in the
        mask -- a dash end, a dropped run, an occluding vehicle, the segmentation's range -- and
        the transform would pull the sample along the line to where the marking stops being seen.
        """
        p = self.params
        uv, uv_t = self._to_mask(uv, fd), self._to_mask(uv_t, fd)
        ok = self._in_mask(uv, z, fd) & (z_t > p.min_depth_m)
        w_px = width[ok] * fd.intr.fx * fd.lane_scale / z[ok]
        pts, uv, uv_t = pts[ok], uv[ok], uv_t[ok]
        if len(pts) == 0:
            return pts, w_px, 0
        val, du, dv = bilinear_with_grad(fd.dt, uv - [0.0, fd.dt_row0])
        t_img = uv_t - uv
        t_img /= np.maximum(np.linalg.norm(t_img, axis=1, keepdims=True), 1e-9)
        g = np.hypot(du, dv)
        along = np.abs(du * t_img[:, 0] + dv * t_img[:, 1])
        keep = (val >= cap) | (g < 1e-6) | (along <= np.sin(np.radians(p.lane_end_angle_deg)) * g)
        pts, val, w_px = pts[keep], val[keep], w_px[keep]
        if len(pts) > p.lane_max_samples:
            sel = np.linspace(0, len(pts) - 1, p.lane_max_samples).astype(int)
            pts, val, w_px = pts[sel], val[sel], w_px[sel]
        return pts, w_px, int(np.count_nonzero(val < cap))

    def _map_var_px(self, fd: FrameData, depth: np.ndarray) -> np.ndarray:
        """Pixel variance of a landmark's projection at ``depth`` (m) from its own map error."""
        f = 0.5 * (fd.intr.fx + fd.intr.fy)
        return (f * self.params.landmark_map_sigma_m / np.maximum(depth, self.params.min_depth_m)) ** 2

    def pole_whitening(self, m1, m2, M1, M2, map_sd=None) -> np.ndarray:
        """W (K, 2, 2) with W^T W = C^-1, C the covariance of D_L's (d_1, d_2) from the detection noise
        and the map pole's own position error (``map_sd`` (K, 2): its 1-sigma at each endpoint in px).

        The line through the detected endpoints is displaced at position s along M1 -> M2 (s = 0
        at M1, 1 at M2) by (1 - s) n_1 + s n_2, with n_1, n_2 ~ N(0, sigma^2) the endpoints' noise
        across the line, so ``C = sigma^2 A A^T + floor^2 I`` with ``A = [[1-s_1, s_1], [1-s_2, s_2]]``
        and s_k the position of the projected map endpoint m_k. A short or partial detection thus
        weighs less where the map pole extends beyond it. A map pole off its true place moves both
        endpoints' projections the same way: ``C += s s^T``, s = map_sd.
        """
        p = self.params
        d = M2 - M1
        L2 = np.maximum(np.einsum("ki,ki->k", d, d), 1e-9)
        s1 = np.einsum("ki,ki->k", m1 - M1, d) / L2
        s2 = np.einsum("ki,ki->k", m2 - M1, d) / L2
        A = np.stack([np.stack([1 - s1, s1], axis=1), np.stack([1 - s2, s2], axis=1)], axis=1)
        C = p.pole_sigma_px**2 * A @ A.transpose(0, 2, 1) + max(p.pole_floor_px, 1e-3) ** 2 * np.eye(2)
        if map_sd is not None:
            C = C + map_sd[:, :, None] * map_sd[:, None, :]
        return np.linalg.inv(np.linalg.cholesky(C))

    # ------------------------------------------------------------------ residuals

    def residual_blocks(self, x, fd: FrameData, rd: RoundData) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Every whitened residual block at x with its Jacobian (rows, 6), before robust weighting.

        Keys: ``points`` (D_P, 2 rows per landmark), ``poles`` (D_L, 2 rows per pole), ``lanes`` (EDT,
        1 row per sample), ``ground`` (r_n), ``gnss``, ``anchor``, ``prior``. Also ``depth``: (min depth
        of each point landmark, of each pole) to detect landmarks that moved behind the camera, and
        ``lanes_under_cap``. One rotation and one projection of all the round's map points serve every block.
        """
        x = np.asarray(x, dtype=float)
        rot = rpy_to_matrix_jac(*x[3:])
        out: dict[str, Any] = {}
        nP, nL, nS = len(rd.pt_xyz), len(rd.pole_A), len(rd.lane_xyz)
        if len(rd.xyz):
            uv, z, J = project_points_jac(fd.intr, x, fd.T_bc, rd.xyz, rot)
        else:
            uv, z, J = np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2, 6))
        # D_P
        s = np.repeat(rd.pt_sigma, 2)
        out["points"] = ((uv[:nP] - rd.pt_uv).reshape(-1) / s, J[:nP].reshape(-1, 6) / s[:, None])
        # D_L: d_k = n . (m_k - M_1), d d_k / dx = n^T dm_k/dx, whitened by W.
        if nL:
            a, b = slice(nP, nP + nL), slice(nP + nL, nP + 2 * nL)
            n = rd.pole_n
            dist = np.stack(
                [np.einsum("ki,ki->k", uv[a] - rd.pole_M1, n), np.einsum("ki,ki->k", uv[b] - rd.pole_M1, n)],
                axis=1,
            )
            Jd = np.stack([np.einsum("ki,kij->kj", n, J[a]), np.einsum("ki,kij->kj", n, J[b])], axis=1)
            out["poles"] = (np.einsum("kij,kj->ki", rd.pole_W, dist).reshape(-1), (rd.pole_W @ Jd).reshape(-1, 6))
            out["depth"] = (z[:nP], np.minimum(z[a], z[b]))
        else:
            out["poles"] = (np.zeros(0), np.zeros((0, 6)))
            out["depth"] = (z[:nP], np.zeros(0))
        # EDT lane residual.
        if nS:
            out["lanes"], out["lanes_under_cap"] = self._lane_residuals(uv, z, J, slice(nP + 2 * nL, None), fd, rd)
        else:
            out["lanes"], out["lanes_under_cap"] = (np.zeros(0), np.zeros((0, 6))), np.zeros(0, bool)
        out["ground"] = self._ground_residuals(x, rot, fd, rd)
        # GNSS
        if fd.gnss is not None:
            g, sig = fd.gnss
            R, dRr, dRp, dRy = rot
            lv = self._lever
            Jg = np.zeros((3, 6))
            Jg[:, :3] = np.eye(3)
            Jg[:, 3], Jg[:, 4], Jg[:, 5] = dRr @ lv, dRp @ lv, dRy @ lv
            out["gnss"] = ((x[:3] + R @ lv - g) / sig, Jg / sig[:, None])
        else:
            out["gnss"] = (np.zeros(0), np.zeros((0, 6)))
        # Lane-search anchor.
        if rd.anchor is not None:
            A, h = rd.anchor
            da = x - h
            da[5] = wrap_angle(da[5])
            out["anchor"] = (A @ da, A)
        else:
            out["anchor"] = (np.zeros(0), np.zeros((0, 6)))
        # Prediction prior.
        dx = x - fd.x_prior
        dx[5] = wrap_angle(dx[5])
        out["prior"] = (fd.L_prior.T @ dx, fd.L_prior.T)
        return out

    def _lane_residuals(self, uv, z, J, rows: slice, fd: FrameData, rd: RoundData):
        """The EDT block (residuals, Jacobian) from the projections' ``rows``, and which samples are under the cap."""
        uvl = self._to_mask(uv[rows], fd)
        inside = self._in_mask(uvl, z[rows], fd)
        if inside.all():
            val, du, dv = bilinear_with_grad(fd.dt, uvl - [0.0, fd.dt_row0])
        else:
            n = len(uvl)
            val, du, dv = np.full(n, rd.lane_cap), np.zeros(n), np.zeros(n)
            if inside.any():
                val[inside], du[inside], dv[inside] = bilinear_with_grad(fd.dt, uvl[inside] - [0.0, fd.dt_row0])
        under = val < rd.lane_cap
        val = np.minimum(val, rd.lane_cap)
        du = np.where(under, du, 0.0)  # capped samples have no gradient
        dv = np.where(under, dv, 0.0)
        Jl = (du[:, None] * J[rows, 0, :] + dv[:, None] * J[rows, 1, :]) * fd.lane_scale
        return (val / rd.lane_sigma, Jl / rd.lane_sigma[:, None]), under

    def _ground_residuals(self, x, rot, fd: FrameData, rd: RoundData):
        """r_n: ``(roll - roll_0, pitch - pitch_0, C_z - (z_lane + H)) / sigma`` (the last row if the lane height
        is known) with its Jacobian."""
        p = self.params
        sig_rp = p.sigma_roll_pitch_rad
        rows_e = [(x[3] - p.nominal_roll_pitch_rad[0]) / sig_rp, (x[4] - p.nominal_roll_pitch_rad[1]) / sig_rp]
        if rd.z_ground is None:
            return np.array(rows_e), self._ground_J_attitude
        R, dRr, dRp, dRy = rot
        t = fd.T_bc[:3, 3]
        H = p.body_height_m + t[2]
        rows_e.append((x[2] + R[2] @ t - rd.z_ground - H) / p.sigma_height_m)
        J = np.empty((3, 6))
        J[:2] = self._ground_J_attitude
        J[2] = np.array([0.0, 0.0, 1.0, dRr[2] @ t, dRp[2] @ t, dRy[2] @ t]) / p.sigma_height_m
        return np.array(rows_e), J

    def _evaluate(self, x, fd: FrameData, rd: RoundData) -> _Eval | None:
        """Residuals, Jacobian, IRLS weights and costs at x; None if a landmark went behind the camera.

        Rows: landmarks (points, poles; Huber-weighted per landmark on its 2-row norm), lanes, then
        ground, GNSS, anchor, and the prediction prior last.
        """
        p = self.params
        b = self.residual_blocks(x, fd, rd)
        z_pt, z_pole = b["depth"]
        if np.any(z_pt <= 0.5 * p.min_depth_m) or np.any(z_pole <= 0.5 * p.min_depth_m):
            return None
        e_pt, J_pt = b["points"]
        e_pl, J_pl = b["poles"]
        e_ln, J_ln = b["lanes"]
        under = b["lanes_under_cap"]
        blocks = [b["points"], b["poles"], b["lanes"], b["ground"], b["gnss"], b["anchor"], b["prior"]]
        e = np.concatenate([blk[0] for blk in blocks])
        J = np.concatenate([blk[1] for blk in blocks])
        n_pt, n_lm = len(e_pt) // 2, (len(e_pt) + len(e_pl)) // 2  # landmarks
        e_lm = e[: 2 * n_lm].reshape(-1, 2)
        chi2 = np.einsum("ki,ki->k", e_lm, e_lm)
        rho, w_lm = _huber(np.sqrt(chi2), p.huber_k)
        w = np.ones(len(e))
        w[: 2 * n_lm] = np.repeat(w_lm, 2)
        landmark_rho = float(rho[:n_pt].sum() + rho[n_pt:].sum())
        cost = landmark_rho + float(e[2 * n_lm :] @ e[2 * n_lm :])
        lane_in = float(e_ln[under] @ e_ln[under])
        n_under = int(np.count_nonzero(under))
        lane_rows = slice(2 * n_lm, 2 * n_lm + len(e_ln))
        return _Eval(
            e,
            J,
            w,
            cost,
            landmark_rho + lane_in,
            2 * n_lm + n_under,
            chi2[:n_pt],
            chi2[n_pt:],
            n_under,
            lane_rows,
            float(x[5]),
            p.lane_along_track,
        )

    # ------------------------------------------------------------------ solver

    def _solve(self, x, P, fd: FrameData, anchor=None):
        """Association rounds from (x, P): associate, LM, until the association repeats."""
        p = self.params
        key_prev, ev, lm_ok, iterations = None, None, True, 0
        rd = RoundData().finalize()
        for rnd in range(p.rounds):
            rd_new = self.associate(x, P, fd, rnd, anchor)
            key = rd_new.key()
            if key == key_prev and lm_ok:
                break
            rd, key_prev = rd_new, key
            x_start = x
            x, ev, it, lm_ok = self._lm(x, fd, rd)
            iterations += it
            P = _safe_inv(self._info(ev))
            moved = np.abs(x - x_start)
            if rnd > 0 and lm_ok and moved[:3].max() < p.settle_m and moved[3:].max() < p.settle_rad:
                break  # projections moved by well under a pixel: the association cannot change
        return x, ev, rd, iterations, lm_ok

    def _lm(self, x, fd: FrameData, rd: RoundData):
        """Levenberg-Marquardt (Nielsen's damping update), IRLS weights; returns x, eval, iterations, ok."""
        p = self.params
        ev = self._evaluate(x, fd, rd)
        if ev is None:  # cannot happen: associations are made with depth checks at this x
            raise RuntimeError("an associated landmark is behind the camera at the association pose")
        mu, nu = 1e-3, 2.0
        it = 0
        while it < p.max_iterations:
            it += 1
            Jw = ev.J * ev.w[:, None]
            H = Jw.T @ ev.J
            g = Jw.T @ ev.e
            D = np.diag(np.maximum(np.diag(H), 1e-9))
            while True:
                try:
                    step = np.linalg.solve(H + mu * D, -g)
                except np.linalg.LinAlgError:
                    step = None
                if step is not None:
                    pred = -(2.0 * g @ step + step @ H @ step)  # predicted decrease of sum w e^2
                    if pred <= p.tol_cost * max(ev.cost, 1e-9) or np.max(np.abs(step)) < p.tol_step:
                        return x, ev, it, True
                    xn = x + step
                    xn[5] = wrap_angle(xn[5])
                    evn = self._evaluate(xn, fd, rd)
                    gain = (ev.cost - evn.cost) / pred if evn is not None else -1.0
                    if gain > 0:
                        x, ev = xn, evn
                        mu *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
                        nu = 2.0
                        break
                mu *= nu
                nu *= 2.0
                if mu > 1e8:
                    return x, ev, it, True  # no descent left: at a (possibly non-smooth) minimum
        return x, ev, it, False

    def _info(self, ev: _Eval, prior: bool = True) -> np.ndarray:
        """J^T W J with or without the prediction prior's rows (the last 6)."""
        m = len(ev.e) if prior else len(ev.e) - 6
        Jw = ev.J_info[:m] * ev.w[:m, None]
        return Jw.T @ ev.J_info[:m]

    def _result(self, x, ev: _Eval, rd: RoundData, iterations: int, lm_ok: bool, fd: FrameData) -> MatchResult:
        p = self.params
        H_meas = self._info(ev, prior=False)
        P_f = _safe_inv(H_meas + fd.I_prior)
        k = p.prior_inflation
        P_w = _safe_inv(H_meas + fd.I_prior / k)
        dx = x - fd.x_prior
        dx[5] = wrap_angle(dx[5])
        # One Newton step of the weak-prior problem from x, with the gradient of the same information
        # model as H_meas (J_info): where the lanes' along-track part is left out, the weak prior keeps
        # the along-track position instead of extrapolating the solve's pull k times.
        m = len(ev.e) - 6
        g_meas = (ev.J_info[:m] * ev.w[:m, None]).T @ ev.e[:m]
        x_w = x - P_w @ (g_meas + (fd.I_prior / k) @ dx)
        x_w[5] = wrap_angle(x_w[5])
        n_pts = int(np.count_nonzero(ev.pt_chi2 <= p.inlier_chi2))
        n_poles = int(np.count_nonzero(ev.pole_chi2 <= p.inlier_chi2))
        cost = ev.meas_rho / ev.n_meas if ev.n_meas else 0.0
        sig_lat, _, sig_yaw = self._sigmas(fd.x_prior, _safe_inv(fd.I_prior))
        tracked = sig_lat <= p.tracked_sigma_m and sig_yaw <= p.lane_enable_sigma_yaw_rad
        landmarks = n_pts + n_poles
        constraints = 2 * n_pts + n_poles + 2 * (ev.n_lane_in >= p.min_lane_samples)
        enough = constraints >= (p.min_constraints_tracked if tracked else p.min_constraints)
        reason = ""
        if not enough:
            reason = "too few features" if landmarks or ev.n_lane_in else "no features"
        elif not lm_ok:
            reason = "max iterations"
        elif cost > p.max_cost:
            reason = f"cost {cost:.2f} > {p.max_cost}"
        return MatchResult(
            pose=x_w,
            cov=_sym(P_w),
            pose_filtered=x.copy(),
            cov_filtered=_sym(P_f),
            n_points=n_pts,
            n_poles=n_poles,
            n_lane=ev.n_lane_in,
            cost=float(cost),
            iterations=iterations,
            converged=not reason,
            reason=reason,
            constraints=constraints,
            score=float(ev.cost + p.inlier_chi2 * (len(fd.pt_uv) + len(fd.pole_M1) - landmarks)),
            gnss_used=fd.gnss is not None,
            point_pairs=np.column_stack([rd.pt_map, rd.pt_det]).astype(int).reshape(-1, 2),
            pole_pairs=np.column_stack([rd.pole_map, rd.pole_det]).astype(int).reshape(-1, 2),
            prior_chi2=float(ev.e[-6:] @ ev.e[-6:]),
            pair_chi2=np.concatenate([ev.pt_chi2, ev.pole_chi2]),
        )


def _assign(cost: np.ndarray, ok: np.ndarray):
    """Hungarian assignment on ``cost`` restricted to ``ok``; returns matched (rows, cols)."""
    if not ok.any():
        return np.zeros(0, int), np.zeros(0, int)
    rows = np.flatnonzero(ok.any(axis=1))
    cols = np.flatnonzero(ok.any(axis=0))
    c = np.where(ok[np.ix_(rows, cols)], cost[np.ix_(rows, cols)], _BIG)
    r, k = linear_sum_assignment(c)
    good = ok[rows[r], cols[k]]
    return rows[r][good], cols[k][good]


def _local_minima(score: np.ndarray, n: int) -> list[tuple[int, int]]:
    """Up to n lowest local minima (8-neighbourhood) of a 2-D score grid, best first."""
    pad = np.pad(score, 1, constant_values=np.inf)
    h, w = score.shape
    neigh = np.stack([pad[1 + a : 1 + a + h, 1 + b : 1 + b + w] for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b])
    idx = np.flatnonzero((score <= neigh.min(axis=0)).reshape(-1))
    idx = idx[np.argsort(score.reshape(-1)[idx], kind="stable")][:n]
    return [(int(i // w), int(i % w)) for i in idx]


def _safe_inv(H: np.ndarray) -> np.ndarray:
    H = 0.5 * (H + H.T)
    try:
        return np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(H)


def _sym(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + P.T)
