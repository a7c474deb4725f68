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

from dataclasses import replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from schemas.models import LandmarkClass

from .. import lanemask
from ..geometry import rpy_to_matrix_jac
from ..hdmap.model import HDMap
from .association import Association
from .lanes import LaneTerms, lane_distance_transform
from .lm import LevenbergMarquardt, _safe_inv
from .matcher_types import CameraFrame, FrameData, MatcherParams, MatchResult
from .residuals import Residuals

__all__ = ["MapMatcher"]

_POINT_CODES = {"traffic_light": int(LandmarkClass.TRAFFIC_LIGHT), "sign": int(LandmarkClass.SIGN)}


class MapMatcher(LaneTerms, Association, Residuals, LevenbergMarquardt):
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
        self.solves = 0  # association-round solves so far (:meth:`_solve`): the unit of the search's CPU budget
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
