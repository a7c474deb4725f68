"""Data association of one round: map landmarks projected with the current estimate, detections assigned
by the Hungarian method on the Mahalanobis distance, the lane samples chosen (see
:class:`.matcher.MapMatcher`)."""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..geometry import project_points_jac, project_points_pose, rpy_to_matrix_jac
from .matcher_types import FrameData, RoundData

__all__ = ["Association"]

_BIG = 1e12


class Association:
    """The association stage of :class:`.matcher.MapMatcher` (a mixin: it reads the matcher's params and map)."""

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
                rd.pole_W_det = self.pole_whitening(m1[r], m2[r], rd.pole_M1, fd.pole_M2[c])

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
            rd.lane_s = np.sqrt(var)
            rd.lane_sigma = np.sqrt(var * max(1.0, n_in / p.lane_effective_samples))
        if self._lane_tree is not None:
            dist, i = self._lane_tree.query(x[:2])
            if dist < 30.0:
                rd.z_ground = float(self._lane_xyz[i, 2])
        return rd.finalize()

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
