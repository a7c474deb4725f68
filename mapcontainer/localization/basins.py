"""The candidate basins a start-up or recovery search leaves, tracked as hypotheses until one wins.

:class:`Hypothesis` is one candidate track with its evidence since it was found; :class:`HypothesisTracking`
is the part of :class:`.startup.StartupMachine` that keeps the set: it spawns them from a search's solutions
(with their along-road rivals, :meth:`~HypothesisTracking._aliases`), predicts and matches each with every
frame, weighs them by their posterior mass (:mod:`.hypotheses`) against *elsewhere*, merges and drops them,
searches again for rivals of a lone one (:meth:`~HypothesisTracking._rivals`) and names the winner. While none
has won, :meth:`~HypothesisTracking.mixture` is the moment-matched pose the vehicle publishes.

A base class of the machine, not a component of its own: the set, its masses and its bookkeeping
(``hyps``, ``mass``, ``null_nll``, ``odometer``, ``credited``, ``fix``, ``pending``) are the machine's state,
reset with it (:meth:`.StartupMachine.reset`), and the machine's ``params``, ``matcher``, ``search``,
``_count``, ``_pole_xy``, ``posterior`` and ``_set_hyps`` are used here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from . import ekf
from . import hypotheses as hyp
from .matcher_types import MatchResult
from .search import SearchOutcome

if TYPE_CHECKING:
    from .matcher import MapMatcher
    from .params import LocalizerParams
    from .search import PoseSearch

__all__ = ["Hypothesis", "HypothesisTracking"]


@dataclass
class Hypothesis:
    """One candidate track (a basin the pose search found), with its evidence since, kept for both start-up
    rules (``search.accept``).

    ``nll`` (rule 'posterior', and the published mixture): the camera's -2 log-likelihood of the frames
    since it was found (its first frame without the search's prior, the later ones with its own odometry
    prediction as the prior, so that the prior rows score how well it follows the motion; see
    :mod:`.hypotheses`). ``score``, ``points``, ``poles``, ``lanes`` (rule 'landmarks'): the matcher's
    scores summed, and the distinct map landmarks matched: seeing one pole ten times is still one pole.
    ``y_pred``/``P_pred``: the state predicted to the last frame, before its match ``last`` (``last_nll``
    that match's share of ``nll``), folded in with the information weight ``weight``.
    """

    y: np.ndarray
    P: np.ndarray
    nll: float
    score: float = 0.0
    points: set[int] = field(default_factory=set)  # map landmarks matched so far (indices of the map's points, poles)
    poles: set[int] = field(default_factory=set)
    lanes: bool = False  # the lanes matched at least once
    misses: int = 0
    y_pred: np.ndarray | None = None
    P_pred: np.ndarray | None = None
    last: MatchResult | None = None
    last_nll: float = 0.0
    odo: float = 0.0  # the odometer (StartupMachine.odometer) at its last view folded in
    alias: bool = False  # an along-road copy of a one-pole basin (StartupMachine._aliases), not a search's solution
    weight: float = 1.0  # that view's information weight (see StartupMachine._view_weight)

    def add(self, m: MatchResult, nll: float) -> None:
        """Fold in a converged match and its share of the camera's -2 log-likelihood."""
        self.nll += nll
        self.score += m.score
        self.points.update(m.point_pairs[:, 0].tolist())
        self.poles.update(m.pole_pairs[:, 0].tolist())
        self.lanes |= m.constraints > 2 * m.n_points + m.n_poles
        self.last, self.last_nll, self.misses = m, nll, 0

    @property
    def landmarks(self) -> int:
        return len(self.points) + len(self.poles)

    @property
    def constraints(self) -> int:
        return 2 * len(self.points) + len(self.poles) + 2 * self.lanes


class HypothesisTracking:
    """The hypothesis set of :class:`.startup.StartupMachine` (see the module doc)."""

    params: LocalizerParams
    matcher: MapMatcher
    search: PoseSearch
    hyps: list[Hypothesis]
    mass: np.ndarray
    null_nll: float
    odometer: float
    credited: dict[tuple[str, int], float]
    pending: list[np.ndarray]
    _pole_xy: np.ndarray

    def _spawn(self, y0, P0, out: SearchOutcome) -> None:
        """Hypotheses from the search's converged solutions (each folded into (y0, P0)), with the camera's
        evidence of the search's frame; *elsewhere* starts with its own."""
        self._set_hyps([])
        hyps = []
        for sol, nll in zip(out.solutions, out.nll, strict=False):
            if sol.converged and np.isfinite(nll):
                h = Hypothesis(*ekf.match_update(y0, P0, sol), 0.0, odo=self.odometer)
                h.add(sol, nll)
                hyps.append(h)
        if hyps:
            hyps += self._aliases(min(hyps, key=lambda h: h.nll), hyps)
        self._set_hyps(hyps)
        if hyps:
            self.null_nll = out.null_nll
            best = out.solutions[int(np.argmin(out.nll))]
            self.credited = {k: 0.0 for k, _ in best.inliers(self.params.matcher.inlier_chi2)}
            self.mass = self._masses()

    def _aliases(self, h: Hypothesis, others: list[Hypothesis]) -> list[Hypothesis]:
        """Rule 'posterior': the along-road copies of a basin that one pole holds (its only landmark inlier), moved
        so that the neighbouring poles of the same row (one ahead, one behind along its heading) sit where that pole
        is seen; the copies distinct from ``others``, with its evidence so far (the frames could not tell them
        apart: the lane lines are the same along the road).

        One pole with the lanes fixes the pose along the road only up to which pole it is: the search returns
        the basins within its radius of the fix, and a neighbour one lamp spacing away along a straight road is
        the same picture. Without the copies *elsewhere* was the basin's only rival there, and a pole seen over
        a baseline of travel outweighed it (paper-suburban, evaluation seeds: locks 1-14 m off along the road).
        With them, the newest GNSS fix (heavy-tailed) and the next frames' landmarks decide."""
        if not self.posterior or h.last is None or len(self._pole_xy) < 2:
            return []
        inl = h.last.inliers(self.params.matcher.inlier_chi2)
        if len(inl) != 1 or inl[0][0][0] != "pole":
            return []
        j = inl[0][0][1]
        heading = np.array([np.cos(h.y[5]), np.sin(h.y[5])])
        d = self._pole_xy - self._pole_xy[j]
        along, across = d @ heading, d @ np.array([-heading[1], heading[0]])
        row = (np.abs(across) <= self.params.search.distinct_m) & (np.abs(along) > self.params.search.distinct_m)
        out: list[Hypothesis] = []
        for side in (1.0, -1.0):
            c = np.flatnonzero(row & (side * along > 0))
            if len(c) == 0:
                continue
            y = h.y.copy()
            y[:2] += along[c[np.argmin(np.abs(along[c]))]] * heading
            if all(self.search.distinct(y, o.y) for o in [*others, *out]):
                out.append(Hypothesis(y, h.P.copy(), h.nll, h.score, odo=h.odo, weight=h.weight, alias=True))
        return out

    def _view_weight(self, h: Hypothesis) -> float:
        """The information weight of a hypothesis' view of this frame: the distance travelled since its last view
        folded in, over ``search.view_baseline_m``, at most 1 (and that view's odometer noted).

        Views from nearly one place repeat their errors: a landmark's own map error (``landmark_map_sigma_m``,
        which the matcher adds to each detection's sigma as if it were new in every frame) and the lane lines'.
        Folded in at full weight at 10 frames a second, one pole seen over a few metres shrank a basin's
        along-road sigma to 0.4 m while it was 1.8 m off along the road (development seed 10, paper-suburban,
        cv0), and the tracker then took the pole's correction as a wheel-speed scale error (4 %) and drifted
        1.5 m with an along-road sigma of 0.19 m. As for *elsewhere* (:mod:`.hypotheses`), a baseline of
        travel is worth one view. Rule 'posterior' only: under rule 'landmarks' (main's decisions, kept as they
        were) every view weighs 1; weighted there too, its suburban NEES on evaluation seeds was 8.8 (5.9
        unweighted)."""
        if not self.posterior:  # rule 'landmarks' keeps main's decisions: every frame at full weight
            return 1.0
        w = float(np.clip((self.odometer - h.odo) / self.params.search.view_baseline_m, 0.0, 1.0))
        h.odo = self.odometer
        return w

    def _null_increment(self, best_nll: float, best: MatchResult, weight: float) -> float:
        """This frame's evidence of *elsewhere* against the best match (``best_nll``: its -2 log-likelihood, already
        times its view's information ``weight``): its landmark inliers count, each once per
        ``search.view_baseline_m`` of travel (see :mod:`.hypotheses`)."""
        inlier_chi2, baseline = self.params.matcher.inlier_chi2, self.params.search.view_baseline_m
        new = []
        for key, chi2 in best.inliers(inlier_chi2):
            if key not in self.credited or self.odometer - self.credited[key] >= baseline:
                self.credited[key] = self.odometer
                new.append(chi2)
        # Elsewhere follows the odometry exactly: a lone basin that explains its landmarks only by drifting
        # against the odometry (a wrong lane sliding along a pole) loses to it.
        return hyp.null_increment(best_nll - weight * best.prior_chi2, new, inlier_chi2)

    def _gnss_nll(self, xy) -> float:
        """-2 log of the newest fix given the position xy (None: at the fix's expected spread, for *elsewhere*):
        a Student-t (``search.prior_t_dof``) over the receiver's whole error (bias, white, a multipath margin).
        Only the newest fix counts: its errors are correlated for a minute. 0 without a fix."""
        g, p = self.fix, self.params
        if g is None:
            return 0.0
        S = np.eye(2) * (p.gnss_bias_sigma_m**2 + ekf.gnss_white_var(g, p) + p.init_extra_sigma_m**2)
        return self.search.prior_nll(None if xy is None else g.p_map[:2] - np.asarray(xy)[:2], S)

    def _masses(self) -> np.ndarray:
        """The posterior masses of the hypotheses and of *elsewhere* (last): camera evidence + the newest fix."""
        nll = [h.nll + self._gnss_nll(h.y) for h in self.hyps]
        return hyp.masses([*nll, self.null_nll + self._gnss_nll(None)])

    def mixture(self, y: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """While searching: the moment-matched Gaussian (pose, 6x6) of the hypotheses and of *elsewhere*,
        the latter as (y, P) (the GNSS + odometry estimate), each by its mass; None without hypotheses."""
        if not self.hyps or len(self.mass) != len(self.hyps) + 1:
            return None
        means = [h.y[:6] for h in self.hyps] + [y[:6]]
        covs = [h.P[:6, :6] for h in self.hyps] + [P[:6, :6]]
        return hyp.mixture(means, covs, self.mass)

    def _advance_hypotheses(self, frame, dt: float, odo_a, odo_b, search) -> Hypothesis | None:
        """Predict and match every hypothesis with this frame; the winner, if one has won (it ends the search):
        it holds at least 1 - ``search.accept_epsilon`` of the posterior mass (see :mod:`.hypotheses`).

        ``search()`` runs the global pose search on this frame: (y0, P0, outcome) or None (see
        :meth:`_rivals`, for a lone hypothesis that has not won).
        """
        p, sp = self.params, self.params.search
        n_det = 0 if frame is None or frame.is_empty() else len(frame.points_uv) + len(frame.poles_uv)
        speeds = [abs(o.speed) for o in (odo_a, odo_b) if o is not None]
        self.odometer += float(np.mean(speeds)) * max(dt, 0.0) if speeds else 0.0
        # Elsewhere's evidence rides on the leading hypothesis' (the most probable so far, if it matched this
        # frame; else the best match of the frame): riding on whichever fits a frame best would hand it the
        # frame-to-frame noise of the lanes' cost between basins.
        lead = self.hyps[int(np.argmax(self.mass[:-1]))] if len(self.mass) == len(self.hyps) + 1 else None
        best: tuple[float, MatchResult, float] | None = None
        w_frame = 0.0
        for h in self.hyps:
            h.y_pred, h.P_pred = ekf.predict(h.y, h.P, dt, odo_a, odo_b, p)
            h.y, h.P, h.last = h.y_pred, h.P_pred, None
            if n_det == 0:
                continue
            try:
                res = self.matcher.match(frame, h.y_pred[:6], h.P_pred[:6, :6], None)
            except ValueError:
                self._count("frame invalid")
                return None
            w = h.weight = self._view_weight(h)  # views within a baseline of travel repeat their errors
            w_frame = max(w_frame, w)
            if res.converged:
                h.y, h.P = ekf.match_update(h.y_pred, h.P_pred, res, w)
                h.add(res, w * (res.evidence + res.prior_chi2))
                if best is None or h.last_nll < best[0]:
                    best = (h.last_nll, res, w)
            else:  # nothing explained: every detection costs like an outlier, at full weight (a basin that explains
                # nothing is no repeated view; tempered, a leading basin kept its mass through three misses, and
                # when it was dropped a weakly supported rival won at once: ideal paper-urban seed 0, cv2)
                h.nll += p.matcher.inlier_chi2 * n_det
                h.score += p.matcher.inlier_chi2 * n_det
                h.misses += 1
        if lead is not None and lead.last is not None:
            best = (lead.last_nll, lead.last, lead.weight)
        if n_det:
            self.null_nll += w_frame * p.matcher.inlier_chi2 * n_det if best is None else self._null_increment(*best)
        # Merge hypotheses that reached one basin; drop the hopeless and the lost. Rule 'posterior': their masses
        # add, the states moment-match (both places stay in the covariance); rule 'landmarks': the better one
        # stays, by the matcher's summed score.
        posterior = self.posterior
        rank = (lambda h: h.nll) if posterior else (lambda h: h.score)
        self.hyps.sort(key=rank)
        kept: list[Hypothesis] = []
        for h in self.hyps:
            if h.misses >= 3 or rank(h) > rank(self.hyps[0]) + 5.0 * sp.margin:
                continue
            same = next((k for k in kept if not self.search.distinct(h.y, k.y)), None)
            if same is None:
                kept.append(h)
            elif posterior:
                w = hyp.masses([same.nll, h.nll])
                same.y, same.P = hyp.mixture([same.y, h.y], [same.P, h.P], w)
                same.nll = -2.0 * np.logaddexp(-0.5 * same.nll, -0.5 * h.nll)
        self._set_hyps(kept)
        if not kept:
            return None
        self.mass = self._masses()
        if posterior:
            i = int(np.argmax(self.mass[:-1]))
            won = self.mass[i] >= 1.0 - sp.accept_epsilon
        else:  # well constrained by distinct landmarks, and better than every rival by the margin
            i = 0
            runner = kept[1].score if len(kept) > 1 else np.inf
            won = (
                kept[0].constraints >= sp.min_constraints
                and kept[0].landmarks >= sp.min_landmarks
                and runner - kept[0].score >= sp.margin
            )
        win = kept[i]
        if win.last is None or not won:
            if (sum(not h.alias for h in kept) == 1 or self.pending) and n_det:
                return self._rivals(search, n_det)
            return None
        self._count("hypothesis accepted")
        self._set_hyps([])
        self.pending = []
        return win

    def _rivals(self, search, n_det: int) -> Hypothesis | None:
        """Search again while a lone hypothesis has not won; the winner if the search accepts a solution.

        A lone hypothesis has no rival but *elsewhere*: a wrong basin from a frame that showed one pole
        (urban seed 0: 7 m across, 10 degrees off, one pole and the lanes) keeps converging on its pole
        and the lanes frame after frame while the true basin comes into view. So the search runs on
        every such frame: a solution it accepts wins at once (as at a cold start); its other converged
        solutions distinct from the hypothesis join it as rivals, scored as if they had explained the
        earlier frames as well as it did (only this frame's evidence tells them apart). With the anytime budget
        (``search.solves_per_frame``) it also runs while an earlier search's starts are pending, whatever the
        number of hypotheses: their solutions join as rivals of the leading one.
        """
        lone = next((h for h in self.hyps if not h.alias), self.hyps[0])  # the leading one (sorted by rank)
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
            self._set_hyps([])
            return Hypothesis(y0, P0, 0.0, out.match.score, y_pred=y0, P_pred=P0, last=out.match)
        # This frame's evidence compares solutions of one search (one prior): a rival's is its own relative to
        # the lone hypothesis' basin (to the best solution if the search did not reach that basin).
        found = [(sol, nll) for sol, nll in zip(out.solutions, out.nll, strict=False) if np.isfinite(nll)]
        if not found:
            return None
        ref = next((nll for sol, nll in found if not self.search.distinct(sol.pose_filtered, lone.y)), None)
        ref = min(nll for _, nll in found) if ref is None else ref
        earlier = lone.score - (lone.last.score if lone.last is not None else self.params.matcher.inlier_chi2 * n_det)
        for sol, nll in found:
            if all(self.search.distinct(sol.pose_filtered, h.y) for h in self.hyps):
                h = Hypothesis(*ekf.match_update(y0, P0, sol), lone.nll - ref, earlier, odo=self.odometer)
                h.add(sol, nll)
                h.last_nll = nll - ref
                self.hyps += [h, *self._aliases(h, self.hyps)]
        if len(self.hyps) > 1:
            self.mass = self._masses()
        return None
