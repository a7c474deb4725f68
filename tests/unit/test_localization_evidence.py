"""The camera's evidence that weighs basins (MatchResult.evidence, lanes.lane_sample_nll, LaneTerms.lane_evidence):
a proper per-sample density, the Laplace marginal likelihood where there are no lanes, and lanes that prefer the
true lateral position by a bounded amount (an unseen sample costs a few units, not (cap / sigma)^2)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad

from mapcontainer.localization import MapMatcher, MatcherParams
from mapcontainer.localization import hypotheses as hyp
from mapcontainer.localization.lanes import lane_sample_nll

from .test_localization import HDMAP, P_TRACK, pose_on, synth_frame


@pytest.mark.parametrize("s", [0.7, 1.5, 4.0])
def test_lane_sample_nll_is_a_density_with_inlier_probabilities(s):
    p = MatcherParams()
    eps, mu = p.lane_outlier_fraction, p.lane_outlier_scale_px

    def density(d):
        return float(np.exp(-0.5 * lane_sample_nll(d, s, eps, mu)[0]))

    mass = quad(density, 0.0, 20.0 * s, points=[s, 3 * s])[0] + quad(density, 20.0 * s, np.inf)[0]
    assert mass == pytest.approx(1.0, abs=1e-6)
    d = np.linspace(0.0, 50.0, 101)
    _, inlier = lane_sample_nll(d, s, eps, mu)
    assert np.all((inlier >= 0) & (inlier <= 1)) and inlier[0] > 0.5 and inlier[-1] < 1e-6
    # Far out, a sample is an outlier: its cost grows by d / mu (a few units), not by (d / s)^2.
    rho, _ = lane_sample_nll(np.array([10.0 * s, 20.0 * s]), s, eps, mu)
    assert rho[1] - rho[0] == pytest.approx(2.0 * 10.0 * s / mu, rel=1e-3)


def test_without_a_lane_mask_the_evidence_is_the_laplace_marginal_of_the_landmarks():
    """No lane rows: evidence = (score - prior rows) + log det P_prior - log det P_post, the closed form that
    test_localization_hypotheses checks against a linear-Gaussian model."""
    m = MapMatcher(HDMAP)
    truth = pose_on(250.0)
    frame, _ = synth_frame(truth, np.random.default_rng(4), lanes=False)
    res = m.match(frame, truth + np.r_[0.2, -0.1, 0, 0, 0, 0.003], P_TRACK)
    assert res.converged and res.n_points + res.n_poles >= 2
    expected = hyp.frame_nll(res.score - res.prior_chi2, res.cov_filtered, P_TRACK)
    assert res.evidence == pytest.approx(expected, rel=1e-9, abs=1e-6)


def test_lane_evidence_prefers_the_true_lateral_position_by_a_bounded_amount():
    m = MapMatcher(HDMAP)
    p = m.params
    truth = pose_on(250.0)
    frame, _ = synth_frame(truth, np.random.default_rng(5))
    fd = m.prepare(frame, truth, P_TRACK, None)
    lat = np.r_[-np.sin(truth[5]), np.cos(truth[5])]
    at = {dy: m.lane_evidence(truth + np.r_[dy * lat, 0, 0, 0, 0], fd)[0] for dy in (0.0, 0.3, 0.6, 1.2)}
    assert at[0.0] < at[0.3] < at[0.6]
    # Every sample unseen is the most it can cost: n_eff times (rho at the cap - rho at 0) above a perfect fit.
    s = p.lane_sigma_px * fd.lane_scale
    worst = lane_sample_nll(np.array([p.lane_cap_px * fd.lane_scale * 10, 0.0]), s, p.lane_outlier_fraction,
                            p.lane_outlier_scale_px * fd.lane_scale)[0]  # fmt: skip
    assert max(at.values()) - at[0.0] <= p.lane_evidence_samples * (worst[0] - worst[1])
    # The information is positive semi-definite and says the lanes fix the lateral position.
    _, H = m.lane_evidence(truth, fd)
    assert np.all(np.linalg.eigvalsh(0.5 * (H + H.T)) >= -1e-9) and lat @ H[:2, :2] @ lat > 0


def test_the_evidence_does_not_depend_on_whether_the_solve_used_the_lanes():
    """A solution solved from a wide start (the lanes join late, or never) and the same solution solved from
    itself score their lanes alike: the evidence evaluates the lanes at the pose, whatever the solver used."""
    m = MapMatcher(HDMAP)
    truth = pose_on(170.0)
    frame, _ = synth_frame(truth, np.random.default_rng(6))
    narrow = m.match(frame, truth + np.r_[0.1, 0.05, 0, 0, 0, 0.002], P_TRACK)
    no_lanes = MapMatcher(HDMAP, m.params.model_copy(update={"lane_enable_sigma_m": 1e-3}))
    solved_without = no_lanes.match(frame, truth + np.r_[0.1, 0.05, 0, 0, 0, 0.002], P_TRACK)
    assert narrow.n_lane > 0 and solved_without.n_lane == 0
    assert np.hypot(*(narrow.pose_filtered[:2] - solved_without.pose_filtered[:2])) < 0.3
    assert abs(narrow.evidence - solved_without.evidence) < 10.0
