"""The solve of one frame: association rounds, Levenberg-Marquardt with IRLS weights, and the two estimates
(filtered and per-frame) with their acceptance (see :mod:`.matcher`'s module doc)."""

from __future__ import annotations

import numpy as np

from ..geometry import wrap_angle
from . import hypotheses as hyp
from .matcher_types import FrameData, MatchLinearization, MatchResult, RoundData
from .residuals import _Eval

__all__ = ["LevenbergMarquardt"]


class LevenbergMarquardt:
    """The solver stage of :class:`.matcher.MapMatcher` (a mixin: it calls the association and residual stages)."""

    def _solve(self, x, P, fd: FrameData, anchor=None):
        """Association rounds from (x, P): associate, LM, until the association repeats (counted in ``solves``)."""
        p = self.params
        self.solves += 1
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
            evidence=self.evidence(x, ev, rd, fd, landmarks),
            linearization=self._linearization(ev, rd),
        )

    def _linearization(self, ev: _Eval, rd: RoundData) -> MatchLinearization:
        """The measurement rows at the solution (see :class:`.MatchLinearization`): each landmark's rows
        re-whitened by the detector's noise alone (points: by sigma_total / point_sigma_px; poles: by
        W_det W^-1), the rest as information and gradient."""
        m = len(ev.e) - 6
        sw = np.sqrt(ev.w[:m])
        Jw, ew = ev.J_info[:m] * sw[:, None], ev.e[:m] * sw
        n_pt, n_pl = len(rd.pt_map), len(rd.pole_map)
        n_lm = n_pt + n_pl
        J, e = Jw[: 2 * n_lm].reshape(n_lm, 2, 6).copy(), ew[: 2 * n_lm].reshape(n_lm, 2).copy()
        k = rd.pt_sigma / self.params.point_sigma_px
        J[:n_pt] *= k[:, None, None]
        e[:n_pt] *= k[:, None]
        if n_pl:
            T = rd.pole_W_det @ np.linalg.inv(rd.pole_W)
            J[n_pt:] = T @ J[n_pt:]
            e[n_pt:] = np.einsum("kij,kj->ki", T, e[n_pt:])
        keys = tuple(("point", int(i)) for i in rd.pt_map) + tuple(("pole", int(i)) for i in rd.pole_map)
        lanes = np.zeros(m, bool)
        lanes[ev.lane_rows] = True
        Jl, el = Jw[lanes], ew[lanes]
        rest = ~lanes
        rest[: 2 * n_lm] = False
        Jr, er = Jw[rest], ew[rest]
        return MatchLinearization(keys, J, e, Jl.T @ Jl, Jl.T @ el, Jr.T @ Jr, Jr.T @ er)

    def evidence(self, x, ev: _Eval, rd: RoundData, fd: FrameData, landmarks: int) -> float:
        """The camera's -2 log marginal likelihood of the frame at the solution x (Laplace), without the prediction
        prior's rows: what basins of one frame, or hypotheses tracked over frames, are weighed by (:mod:`.hypotheses`).

        ``peak + log det(H_ev + I_prior) - log det(I_prior)`` (:func:`.hypotheses.frame_nll`), with ``peak`` = the
        landmarks' robust chi^2 + ``inlier_chi2`` per detection left unexplained + the ground (and GNSS) rows + the
        lanes' calibrated evidence at x (:meth:`.lanes.LaneTerms.lane_evidence`), and H_ev the information of the
        same terms. Not the solver's lane rows (their cost is not a likelihood, and whether a solve used the lanes
        depends on its start's covariance), nor the lane-search anchor (a pseudo-measurement).
        """
        p = self.params
        m = len(ev.e) - 6
        n_lm = 2 * (len(ev.pt_chi2) + len(ev.pole_chi2))
        keep = np.ones(m, bool)
        keep[ev.lane_rows] = False
        keep[m - (0 if rd.anchor is None else len(rd.anchor[0])) : m] = False
        e = ev.e[:m]
        landmark_rho = ev.cost - float(e[n_lm:] @ e[n_lm:]) - float(ev.e[m:] @ ev.e[m:])
        other = keep.copy()
        other[:n_lm] = False
        lanes, H_lanes = self.lane_evidence(x, fd)
        unexplained = p.inlier_chi2 * (len(fd.pt_uv) + len(fd.pole_M1) - landmarks)
        peak = landmark_rho + float(e[other] @ e[other]) + lanes + unexplained
        Jw = ev.J_info[:m][keep] * ev.w[:m][keep, None]
        H_ev = Jw.T @ ev.J_info[:m][keep] + H_lanes
        return hyp.frame_nll(peak, _safe_inv(H_ev + fd.I_prior), _safe_inv(fd.I_prior))


def _safe_inv(H: np.ndarray) -> np.ndarray:
    H = 0.5 * (H + H.T)
    try:
        return np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(H)


def _sym(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + P.T)
