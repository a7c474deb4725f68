"""The lane "domain-like" feature r^R: the lane mask's distance transform I_R, the painted samples ahead,
the lateral x yaw grid search on I_R, the choice of samples and the EDT residual block (the equations
are in :mod:`.matcher`'s module doc)."""

from __future__ import annotations

import cv2
import numpy as np

from ..geometry import project_points_grid, project_points_jac, project_points_pose, rpy_to_matrix_jac, wrap_angle
from .matcher_types import FrameData, RoundData

__all__ = ["LaneTerms", "bilinear_with_grad", "lane_distance_transform", "lane_sample_nll"]


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


def lane_sample_nll(d: np.ndarray, s: np.ndarray, outlier_fraction: float, outlier_scale: float):
    """-2 log-density of lane samples' distances d >= 0 to the nearest marking (px of the mask), and each one's
    probability of being an inlier.

    A mixture: with probability 1 - eps the sample's marking is seen, d half-normal with the sample's own
    1-sigma s (the detector's and the painted width's, before ``lane_effective_samples``' inflation); with
    probability eps it is not (occluded, dropped, off in the map), d exponential with mean ``outlier_scale``:
    ``p(d) = (1 - eps) 2 N(d; 0, s^2) + eps exp(-d / mu) / mu``. Unlike the squared capped distance the
    solver minimises (an unseen sample costs (cap / sigma)^2, about 25, and how many are unseen varies from
    pose to pose), it is a density: an unseen sample costs a few units, the same wherever it is.
    """
    d = np.asarray(d, dtype=float)
    eps, mu = outlier_fraction, outlier_scale
    log_in = np.log((1.0 - eps) * np.sqrt(2.0 / np.pi) / s) - 0.5 * (d / s) ** 2
    log_out = np.log(eps / mu) - d / mu
    log_total = np.logaddexp(log_in, log_out)
    return -2.0 * log_total, np.exp(log_in - log_total)


class LaneTerms:
    """The lane stage of :class:`.matcher.MapMatcher` (a mixin: it reads the matcher's params and lane samples)."""

    def lane_evidence(self, x, fd: FrameData) -> tuple[float, np.ndarray]:
        """The lanes' -2 log-likelihood of the frame at pose x and its information (6x6): ``n_eff mean_i rho(d_i)``
        (:func:`lane_sample_nll`, ``n_eff`` = ``lane_evidence_samples``) over the painted samples ahead that
        project into the mask away from marking ends (every line, dashed too: chosen by the pose alone, as at
        every pose, whatever the solver used), d_i the uncapped distance transform. The information is
        Gauss-Newton's, each sample weighed by its inlier probability and n_eff over the samples (and without
        its along-track part unless ``lane_along_track``). 0 without a mask; every sample unseen without one in
        view."""
        p = self.params
        if fd.dt is None:
            return 0.0, np.zeros((6, 6))
        n_eff, eps, mu = p.lane_evidence_samples, p.lane_outlier_fraction, p.lane_outlier_scale_px * fd.lane_scale
        cap = p.lane_cap_px * fd.lane_scale
        unseen = n_eff * float(lane_sample_nll(cap, p.lane_sigma_px * fd.lane_scale, eps, mu)[0])
        pts, tan, width = self._lane_ahead(x, tangents=True)
        n = len(pts)
        if n == 0:
            return unseen, np.zeros((6, 6))
        uv_l, z_l = project_points_pose(fd.intr, x, fd.T_bc, np.vstack([pts, pts + 0.5 * tan]))
        pts, w_px, _ = self._lane_select(pts, width, uv_l[:n], z_l[:n], uv_l[n:], z_l[n:], fd, cap)
        if len(pts) == 0:
            return unseen, np.zeros((6, 6))
        s = np.sqrt((p.lane_sigma_px * fd.lane_scale) ** 2 + (0.5 * w_px) ** 2 / 3.0)
        uv, _, J = project_points_jac(fd.intr, x, fd.T_bc, pts)
        d, du, dv = bilinear_with_grad(fd.dt, self._to_mask(uv, fd) - [0.0, fd.dt_row0])
        rho, inlier = lane_sample_nll(d, s, eps, mu)
        g = (du[:, None] * J[:, 0, :] + dv[:, None] * J[:, 1, :]) * fd.lane_scale
        if not p.lane_along_track:
            heading = np.array([np.cos(x[5]), np.sin(x[5])])
            g[:, :2] -= np.outer(g[:, :2] @ heading, heading)
        gw = g * (n_eff / len(pts) * inlier / s**2)[:, None]
        return n_eff * float(rho.mean()), gw.T @ g

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


def _local_minima(score: np.ndarray, n: int) -> list[tuple[int, int]]:
    """Up to n lowest local minima (8-neighbourhood) of a 2-D score grid, best first."""
    pad = np.pad(score, 1, constant_values=np.inf)
    h, w = score.shape
    neigh = np.stack([pad[1 + a : 1 + a + h, 1 + b : 1 + b + w] for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b])
    idx = np.flatnonzero((score <= neigh.min(axis=0)).reshape(-1))
    idx = idx[np.argsort(score.reshape(-1)[idx], kind="stable")][:n]
    return [(int(i // w), int(i % w)) for i in idx]
