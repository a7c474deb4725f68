"""Global pose search for start-up and recovery: which basin of the map-matching cost is the right one.

The map matcher (:mod:`.matcher`) converges from within about a metre and a few degrees. A GNSS
fix is metres off and a two-way road leaves the heading open, so at start-up (and when a track is
lost) the prediction is too wide for one local solve: a solve from the fix can settle in a wrong
basin -- one lane over, one lamp post along, or facing backwards -- and with only three constraints
fit it exactly. The search makes that choice explicit:

1. **Grid.** Hypotheses on a grid of positions within ``radius`` of the prediction (step
   ``grid_step_m``) times the candidate headings, at the prediction's height, roll and pitch. Each is
   scored by how well the map's landmarks explain the detections: per detection, the squared pixel
   distance to the nearest projected landmark of its class (points) or to the projected pole at the
   detection's mid-height (poles), truncated at ``gate_px``, plus the prediction prior on position
   and heading. Vectorised over the whole grid; no lanes (they repeat every lane width).
2. **Refine.** The best ``n_starts`` hypotheses that lie apart from each other are solved in full by
   the matcher (association rounds, LM, lanes once the basin is reached), each from the hypothesis,
   with the real prediction as the prior; each converged solution is solved once more from itself
   with its own covariance (lane samples and weights chosen at the solution, not at a start up to a
   metre off), so that the scores of different basins compare like with like.
3. **Decide** (``accept``). Rule ``"landmarks"`` (the default): each solution's score is the matcher's
   (its robust cost plus ``inlier_chi2`` for every detection it leaves unexplained); the best is
   accepted if it is well constrained (``min_constraints`` on x, y, yaw: 2 per point inlier, 1 per
   pole inlier, 2 for the lanes; ``min_landmarks``) and no distinct solution (farther than
   ``distinct_m`` or ``distinct_rad``) scores within ``margin`` of it. Rule ``"posterior"`` (opt-in):
   each converged solution is a basin; its -2 log-likelihood (:mod:`.hypotheses`) is the
   matcher's score without the prediction prior, with the Laplace volume term, plus a heavy-tailed
   (Student-t, ``prior_t_dof``) prior on its position around the prediction's: a GNSS fix several
   metres off under multipath must not decide between basins. Beside them stands *elsewhere* (a basin
   the search did not reach, which explains none of the best one's landmarks). The best is accepted if
   it holds at least ``1 - accept_epsilon`` of the posterior mass. Otherwise the result says why
   ("ambiguous", with the mass) and the caller tracks the basins over the next frames
   (:mod:`.startup`), where the evidence of a pole seen over a baseline of travel accumulates.

Everything here is pure and deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ..geometry import project_points_grid, wrap_angle
from . import hypotheses as hyp
from .matcher import MapMatcher
from .matcher_types import CameraFrame, FrameData, MatchResult

__all__ = ["PoseSearch", "PoseSearchParams", "SearchOutcome"]


class PoseSearchParams(BaseModel):
    """Parameters of :class:`PoseSearch` (pixels at the camera's full resolution, SI units otherwise)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    grid_step_m: float = Field(0.75, gt=0, description="position grid step (m)")
    yaw_step_rad: float = Field(np.radians(1.5), gt=0, description="heading grid step (rad)")
    max_radius_m: float = Field(9.0, gt=0, description="the position grid reaches at most this far (m)")
    gate_px: float = Field(50.0, gt=0, description="a detection's grid residual is truncated here (px)")
    n_starts: int = Field(4, ge=1, description="at most this many hypotheses are solved in full ...")
    start_window: float = Field(
        1.5, ge=0, description="... those with a grid score within this many gate_px^2 of the best one"
    )
    start_sigma_m: float = Field(0.75, gt=0, description="position 1-sigma of a start (association gate)")
    start_sigma_rad: float = Field(np.radians(2.0), gt=0, description="heading 1-sigma of a start")
    distinct_m: float = Field(1.0, gt=0, description="solutions this far apart are different basins (m)")
    distinct_rad: float = Field(np.radians(5.0), gt=0, description="... or this far apart in heading (rad)")
    margin: float = Field(
        9.0,
        ge=0,
        description="rule 'landmarks': the best solution's score must beat every distinct one by this much; "
        "either rule: a distinct solution that scores this much better than a verified start's local match "
        "rejects it (about one detection explained better)",
    )
    accept: Literal["landmarks", "posterior"] = Field(
        "landmarks",
        description="how the start-up accepts a basin: 'landmarks' (the default) when it is well constrained "
        "(min_constraints, min_landmarks: distinct map landmarks counted over its frames) and beats every "
        "distinct one by the margin; 'posterior' (opt-in) when it holds 1 - accept_epsilon of the posterior "
        "mass (see localization/hypotheses.py; on suburban evaluation seeds it accepts lone-pole starts "
        "1-2 m off along the road: docs/localization.md). Either way the basins' posterior is tracked",
    )
    min_constraints: int = Field(
        5, ge=3, description="rule 'landmarks': constraints on (x, y, yaw) a solution needs: the 3 unknowns and 2 more"
    )
    min_landmarks: int = Field(2, ge=1, description="... of which at least this many landmark inliers")
    accept_epsilon: float = Field(
        1e-3,
        gt=0,
        lt=0.5,
        description="rule 'posterior': a basin is accepted once it holds at least 1 - this of the posterior "
        "mass (the other basins found and 'elsewhere')",
    )
    view_baseline_m: float = Field(
        5.0,
        gt=0,
        description="a landmark explained again counts as new evidence against 'elsewhere' once the vehicle has "
        "travelled this far since it last counted (views from nearly one place are not independent)",
    )
    prior_t_dof: float = Field(
        4.0,
        gt=0,
        description="degrees of freedom of the Student-t position prior (GNSS, a widened prediction) that "
        "weighs basins: heavy tails for multipath jumps of several metres",
    )
    solves_per_frame: int | None = Field(
        6,
        ge=1,
        description="anytime budget: a search solves starts until it has used this many of the matcher's "
        "solves (association rounds + LM from one start pose; the lane search and the polish count) in the step, "
        "the hypotheses' matches included; the starts left are returned as pending and solved on the next frames "
        "(carried by the odometry), and nothing is accepted while any is pending. None: every start in the frame "
        "(unbounded frame time; see docs/localization.md for the figures of both)",
    )
    grid_detections: int = Field(
        64,
        ge=2,
        description="the grid scores at most this many detections (points first, then poles): its memory "
        "and time grow with detections x landmarks x hypotheses, and a frame of 4,096 took 6 GB",
    )


@dataclass(frozen=True)
class SearchOutcome:
    """The accepted solution (None if none), why not, and the distinct solutions it found."""

    match: MatchResult | None
    reason: str
    hypotheses: int
    solutions: tuple[MatchResult, ...] = ()  # the distinct solutions, best first
    best_score: float = np.inf
    runner_up_score: float = np.inf
    nll: tuple[float, ...] = ()  # the camera's -2 log-likelihood of each solution (see PoseSearch.camera_nll)
    null_nll: float = np.inf  # ... and of 'elsewhere'
    pending: tuple[np.ndarray, ...] = ()  # start poses not solved within the frame's budget, best first


class PoseSearch:
    """Grid search + full solves over the basins of the map-matching cost (see the module doc)."""

    def __init__(self, matcher: MapMatcher, params: PoseSearchParams | None = None):
        self.matcher = matcher
        self.params = params or PoseSearchParams()

    def search(
        self, frame: CameraFrame, pose_pred, cov_pred, yaws, radius_m: float, starts=None, budget: int | None = None
    ) -> SearchOutcome:
        """Search around the prediction (pose_pred, cov_pred: its prior) over positions within
        ``radius_m`` and the headings ``yaws`` (absolute, rad). ``starts``: instead of the grid, solve these
        start poses (an earlier search's ``pending``, carried to this frame; nothing is accepted then: the
        earlier search's basins are not among these solutions). ``budget``: at most about this many of the
        matcher's solves in this call (None: ``solves_per_frame``); the starts left are returned as ``pending``
        and nothing is accepted. Raises ValueError on malformed input."""
        p = self.params
        fd = self.matcher.prepare(frame, pose_pred, cov_pred, None)
        n_det = len(fd.pt_uv) + len(fd.pole_M1)
        if n_det == 0:
            return SearchOutcome(None, "no landmark detections", 0, pending=tuple(starts or ()))
        budget = p.solves_per_frame if budget is None else budget
        x0 = fd.x_prior
        P0 = np.linalg.inv(fd.I_prior)
        if starts is not None:
            return self._decide(fd, P0, list(starts), 0, budget, resumed=True)
        yaws = np.unique(np.round(np.asarray(yaws, dtype=float) / 1e-6) * 1e-6)
        radius = min(float(radius_m), p.max_radius_m)
        k = int(np.ceil(radius / p.grid_step_m))
        g = np.arange(-k, k + 1) * p.grid_step_m
        off = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
        off = off[np.hypot(off[:, 0], off[:, 1]) <= radius + 1e-9]
        scores = self._grid_scores(fd, x0, off, yaws)
        # Prediction prior on (x, y, yaw) for every hypothesis.
        idx3 = [0, 1, 5]
        I3 = np.linalg.inv(P0[np.ix_(idx3, idx3)])
        dyaw = wrap_angle(yaws - x0[5])
        D = np.zeros((len(off), len(yaws), 3))
        D[..., :2] = off[:, None, :]
        D[..., 2] = dyaw[None, :]
        scores = scores + np.einsum("pyi,ij,pyj->py", D, I3, D)

        return self._decide(fd, P0, self._starts(scores, off, yaws, x0), scores.size, budget)

    def _decide(
        self, fd: FrameData, P0, starts: list[np.ndarray], hypotheses: int, budget: int | None, resumed: bool = False
    ):
        """Solve the starts (within the budget), merge those that fell into one basin, and decide (module doc, 2-3).
        ``resumed``: the starts are an earlier search's pending ones, whose other basins are not among these
        solutions (the caller tracks them): nothing is accepted, the solutions join the caller's hypotheses."""
        p = self.params
        P_start = np.diag([p.start_sigma_m**2, p.start_sigma_m**2, P0[2, 2], P0[3, 3], P0[4, 4], p.start_sigma_rad**2])
        sols: list[MatchResult] = []
        used0, pending = self.matcher.solves, ()
        for k, h in enumerate(starts):
            if budget is not None and k and self.matcher.solves - used0 >= budget:
                pending = tuple(starts[k:])
                break
            res = self.matcher.polish(fd, self.matcher.solve_from(fd, h, P_start))
            if all(self.distinct(res.pose_filtered, o.pose_filtered) for o in sols):
                sols.append(res)
            else:  # two starts fell into one basin: keep its better solution
                i = next(i for i, o in enumerate(sols) if not self.distinct(res.pose_filtered, o.pose_filtered))
                sols[i] = min(sols[i], res, key=lambda r: r.score)
        sols.sort(key=lambda r: r.score)
        best, best_score = sols[0], sols[0].score
        runner = sols[1].score if len(sols) > 1 else np.inf
        out = dict(
            hypotheses=hypotheses, solutions=tuple(sols), best_score=best_score, runner_up_score=runner, pending=pending
        )
        if not any(r.converged for r in sols):
            return SearchOutcome(None, best.reason, **out)
        nll, null = self.camera_nll(sols)
        out.update(nll=tuple(nll), null_nll=null)
        if pending or resumed:
            return SearchOutcome(None, f"searching: {len(pending)} starts pending", **out)
        if p.accept == "landmarks":
            if not best.converged:
                return SearchOutcome(None, best.reason, **out)
            if best.constraints < p.min_constraints or best.n_points + best.n_poles < p.min_landmarks:
                return SearchOutcome(None, f"too few features ({best.constraints} constraints)", **out)
            if runner - best_score < p.margin:
                return SearchOutcome(None, f"ambiguous: {runner - best_score:.1f} < margin {p.margin}", **out)
            return SearchOutcome(replace(best, reason=""), "", **out)
        S = P0[:2, :2]
        prior = [self.prior_nll(r.pose_filtered[:2] - fd.x_prior[:2], S) for r in sols]
        mass = hyp.masses([*(np.add(nll, prior)), null + self.prior_nll(None, S)])
        i = int(np.argmax(mass[:-1]))
        if mass[i] < 1.0 - p.accept_epsilon:
            return SearchOutcome(None, f"ambiguous: best basin holds {mass[i]:.3f} of the mass", **out)
        return SearchOutcome(replace(sols[i], reason=""), "", **out)

    def camera_nll(self, sols) -> tuple[list[float], float]:
        """The camera's -2 log-likelihood of each solution of one frame (inf if not converged): its
        ``MatchResult.evidence`` (Laplace, against the frame's prior, without the prior's rows); and that of
        *elsewhere* (see :mod:`.hypotheses`). Needs a converged solution."""
        out = [r.evidence if r.converged else np.inf for r in sols]
        best = sols[int(np.argmin(out))]
        inlier_chi2 = self.matcher.params.inlier_chi2
        return out, hyp.null_increment(min(out), [c for _, c in best.inliers(inlier_chi2)], inlier_chi2)

    def prior_nll(self, d, S) -> float:
        """-2 log of the heavy-tailed position prior (Student-t, ``prior_t_dof``, scale S) at the offset d;
        d None: at the prior's expected spread (Mahalanobis^2 = 2), where *elsewhere* is."""
        if d is None:
            d = np.linalg.cholesky(S) @ np.ones(2)
        return hyp.student_t_nll(d, S, self.params.prior_t_dof)

    def can_accept(self, frame: CameraFrame) -> bool:
        """Whether a search of this frame could accept a solution or find a basin worth tracking (cheap: counts
        only). Rule 'landmarks': enough landmark detections for ``min_landmarks`` and, were every one an inlier
        and the lanes matched too, for ``min_constraints``. Rule 'posterior': a landmark detection (lanes alone
        repeat along the road)."""
        p = self.params
        n_points, n_poles = np.size(frame.points_uv) // 2, np.size(frame.poles_uv) // 4
        if p.accept == "posterior":
            return n_points + n_poles >= 1
        return n_points + n_poles >= p.min_landmarks and 2 * n_points + n_poles + 2 >= p.min_constraints

    def distinct(self, a, b) -> bool:
        """Poses a, b lie in different basins (farther apart than distinct_m or distinct_rad)."""
        return bool(
            np.hypot(a[0] - b[0], a[1] - b[1]) > self.params.distinct_m
            or abs(wrap_angle(a[5] - b[5])) > self.params.distinct_rad
        )

    # ------------------------------------------------------------------ internals

    def _starts(self, scores: np.ndarray, off: np.ndarray, yaws: np.ndarray, x0) -> list[np.ndarray]:
        """The best hypotheses, each distinct from the ones before: two, and up to n_starts within
        start_window of the best."""
        out: list[np.ndarray] = []
        limit = float(scores.min()) + self.params.start_window * self.params.gate_px**2
        for flat in np.argsort(scores, axis=None, kind="stable"):
            i, j = divmod(int(flat), len(yaws))
            if scores[i, j] > limit and len(out) >= 2:  # two at least: ambiguity is judged on solutions
                break
            h = x0.copy()
            h[:2] += off[i]
            h[5] = yaws[j]
            if all(self.distinct(h, o) for o in out):
                out.append(h)
                if len(out) == self.params.n_starts:
                    break
        return out

    def _grid_scores(self, fd: FrameData, x0, off: np.ndarray, yaws: np.ndarray) -> np.ndarray:
        """Truncated squared pixel residuals of the detections (at most ``grid_detections`` of them), per
        (position, heading): (len(off), len(yaws))."""
        p, m = self.params, self.matcher
        gate2 = p.gate_px**2
        total = np.zeros((len(off), len(yaws)))
        reach = m.params.range_m + float(np.max(np.hypot(off[:, 0], off[:, 1]), initial=0.0))
        pt_uv, pt_cls = fd.pt_uv[: p.grid_detections], fd.pt_cls[: p.grid_detections]
        n_poles = p.grid_detections - len(pt_uv)
        pole_M1, pole_M2 = fd.pole_M1[:n_poles], fd.pole_M2[:n_poles]
        if len(pt_uv):
            near = np.flatnonzero(np.hypot(*(m._pt_xyz[:, :2] - x0[:2]).T) <= reach)
            near = near[np.isin(m._pt_cls[near], pt_cls)]
            best = np.full((len(off), len(yaws), len(pt_uv)), gate2)
            if len(near):
                u, v, z = self._project(fd, x0, off, yaws, m._pt_xyz[near])
                vis = z > m.params.min_depth_m
                for c in np.unique(pt_cls):
                    dets = np.flatnonzero(pt_cls == c)
                    lm = m._pt_cls[near] == c
                    if not lm.any():
                        continue
                    du = u[..., lm, None] - pt_uv[dets, 0]
                    dv = v[..., lm, None] - pt_uv[dets, 1]
                    d2 = np.where(vis[..., lm, None], du * du + dv * dv, np.inf)
                    best[..., dets] = np.minimum(d2.min(axis=2), gate2)
            total += best.sum(axis=2)
        if len(pole_M1):
            near = np.flatnonzero(np.hypot(*(m._pole_base[:, :2] - x0[:2]).T) <= reach)
            mid = 0.5 * (pole_M1 + pole_M2)  # (D, 2)
            best = np.full((len(off), len(yaws), len(mid)), gate2)
            if len(near):
                ub, vb, zb = self._project(fd, x0, off, yaws, m._pole_base[near])
                ut, vt, zt = self._project(fd, x0, off, yaws, m._pole_top[near])
                vis = (zb > m.params.min_depth_m) & (zt > m.params.min_depth_m)
                dv_pole = np.where(np.abs(vb - vt) > 1e-6, vb - vt, 1e-6)
                s = (vb[..., None] - mid[:, 1]) / dv_pole[..., None]  # 0 at the base, 1 at the top
                u_at = ub[..., None] + s * (ut - ub)[..., None]
                inside = (s >= -0.3) & (s <= 1.3) & vis[..., None]
                d2 = np.where(inside, (u_at - mid[:, 0]) ** 2, np.inf)
                best = np.minimum(d2.min(axis=2), gate2)
            total += best.sum(axis=2)
        return total

    def _project(self, fd: FrameData, x0, off: np.ndarray, yaws: np.ndarray, pts: np.ndarray):
        """u, v (px), depth of map points pts (K, 3) from every hypothesis: each (len(off), len(yaws), K)."""
        return project_points_grid(fd.intr, x0, fd.T_bc, off, yaws, pts)
