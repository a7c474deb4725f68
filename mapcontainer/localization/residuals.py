"""The whitened residual blocks of one frame at a pose, their Jacobians and the robust cost (the equations
are in :mod:`.matcher`'s module doc)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from ..geometry import project_points_jac, rpy_to_matrix_jac, wrap_angle
from .matcher_types import FrameData, RoundData

__all__ = ["Residuals"]


def _huber(norms: np.ndarray, k: float):
    """Huber rho of residual norms (chi^2-like: norm^2 inside k) and the IRLS weights."""
    rho = np.where(norms <= k, norms**2, 2.0 * k * norms - k * k)
    w = np.where(norms <= k, 1.0, k / np.maximum(norms, 1e-12))
    return rho, w


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


class Residuals:
    """The residual stage of :class:`.matcher.MapMatcher` (a mixin: it reads the matcher's params and lever arm)."""

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
