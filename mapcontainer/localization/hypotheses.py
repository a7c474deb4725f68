"""The posterior over pose hypotheses (basins of the map-matching cost): their likelihoods, masses and moments.

A start-up or recovery search leaves a few candidate basins; each is tracked with its own filter
(:mod:`.startup`). Which one the vehicle is in is a posterior over a discrete set, and the start-up
accepts a basin when it holds at least ``1 - epsilon`` of the mass, not when it has seen some number
of landmarks. Everything is in -2 log-likelihood units (``nll``), so that the matcher's robust chi^2
costs add to it directly.

* **Camera evidence of one frame** (``MatchResult.evidence``, :func:`frame_nll`): the -2 log-likelihood
  at the matcher's optimum -- the landmarks' robust chi^2, ``inlier_chi2`` per detection left
  unexplained, and the lanes' calibrated evidence (a per-sample mixture of a seen marking and an unseen
  one, averaged over the samples and worth ``lane_evidence_samples`` independent ones:
  :func:`.lanes.lane_sample_nll`) -- with the Laplace correction ``log det P_prior - log det P_post``:
  for a linear-Gaussian model this is the exact marginal likelihood of the frame up to a constant common
  to all hypotheses (peak cost + log of the posterior volume over the prior's). The solver's own lane
  cost is not a likelihood: it charges an unseen sample (cap / sigma)^2, about 25, and a third of the
  samples are unseen at the true pose, a number that changes from pose to pose. A tracked hypothesis'
  prior is its own odometry prediction, so its prior rows (``prior_chi2``) are added: they score how
  well it follows the vehicle's motion.
* **GNSS** (:func:`student_t_nll`): a 2-D Student-t on the fix's offset from the hypothesis, heavy
  tailed because a low-cost receiver jumps by several metres under multipath: a Gaussian would let
  one such fix decide between basins. The receiver's error is correlated for a minute (its bias), so
  only the newest fix counts: the fixes' likelihoods are not multiplied over frames.
* **Elsewhere** (the *null* hypothesis): the true pose may lie in a basin the search did not reach (a
  frame with one pole leaves a continuum of poses that explain it). Per frame the null explains the
  lanes and the unexplained detections as the best hypothesis does and follows the odometry exactly
  (the best one's prediction-prior cost taken off: a wrong lane that fits a pole only by sliding along
  the road against the odometry loses to it), but none of the landmarks the best one explains: it costs
  ``inlier_chi2 - chi2_i`` more per landmark inlier i (:func:`null_increment`).
  Views of one landmark from nearly the same place are not independent evidence (a wrong basin that
  explains a pole once explains it a metre later too): a landmark is credited once per
  ``view_baseline_m`` of travel. Its GNSS term is the density at the prior's expected spread
  (Mahalanobis^2 = 2). So one pole in one frame is not enough; a pole seen over a baseline of travel,
  with the lanes, is.
* **Views, not frames**: by the same argument a hypothesis' own view of a frame is worth the travel since
  its last view over ``view_baseline_m`` (at most 1): its frame -2 log-likelihood is multiplied by that
  weight, and its filter folds the match in with the information scaled by it (:mod:`.startup`).

:func:`masses` normalises, :func:`mixture` moment-matches a set of weighted Gaussians (the pose a
vehicle publishes while it is still ambiguous: wide and honest, never one basin among rivals).
"""

from __future__ import annotations

import numpy as np
from scipy.special import gammaln

from ..geometry import wrap_angle

__all__ = ["frame_nll", "masses", "mixture", "null_increment", "student_t_nll"]

_YAW = 5


def student_t_nll(d: np.ndarray, S: np.ndarray, dof: float) -> float:
    """-2 log of the d-dimensional Student-t density (location 0, scale matrix S, ``dof`` degrees of
    freedom) at d."""
    d = np.asarray(d, float).reshape(-1)
    k = len(d)
    m2 = float(d @ np.linalg.solve(S, d))
    log_pdf = (
        gammaln(0.5 * (dof + k))
        - gammaln(0.5 * dof)
        - 0.5 * k * np.log(dof * np.pi)
        - 0.5 * np.linalg.slogdet(S)[1]
        - 0.5 * (dof + k) * np.log1p(m2 / dof)
    )
    return float(-2.0 * log_pdf)


def frame_nll(score: float, P_post: np.ndarray, P_prior: np.ndarray) -> float:
    """-2 log-likelihood of one frame under a hypothesis (Laplace): the matcher's score at its optimum
    plus log det P_prior - log det P_post (both the pose's 6x6)."""
    return float(score + np.linalg.slogdet(P_prior)[1] - np.linalg.slogdet(P_post)[1])


def null_increment(best_nll: float, inliers_chi2, inlier_chi2: float) -> float:
    """This frame's -2 log-likelihood of *elsewhere*: the best hypothesis' (``best_nll``) with each of its
    credited landmark inliers (their chi^2 ``inliers_chi2``) left unexplained instead (``inlier_chi2`` each)."""
    c = np.asarray(inliers_chi2, float)
    return float(best_nll + np.sum(inlier_chi2 - np.minimum(c, inlier_chi2)))


def masses(nll: np.ndarray) -> np.ndarray:
    """Posterior masses from -2 log-likelihoods (equal priors): exp(-nll / 2), normalised."""
    a = -0.5 * np.asarray(nll, float)
    if len(a) == 0:
        return a
    a = a - np.max(a)
    w = np.exp(a)
    return w / w.sum()


def mixture(means: list[np.ndarray], covs: list[np.ndarray], weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The moment-matched Gaussian of a mixture of poses (x y z roll pitch yaw ...): the weighted mean
    (yaw averaged on the circle, as offsets from the heaviest component's) and covariance
    sum w_i (P_i + (x_i - m)(x_i - m)^T)."""
    w = np.asarray(weights, float)
    w = w / w.sum()
    ref = means[int(np.argmax(w))]
    D = np.array([_delta(x, ref) for x in means])
    mean_d = w @ D
    m = ref + mean_d
    if len(m) > _YAW:
        m[_YAW] = wrap_angle(m[_YAW])
    C = sum(wi * (Pi + np.outer(di - mean_d, di - mean_d)) for wi, Pi, di in zip(w, covs, D, strict=True))
    return m, 0.5 * (C + C.T)


def _delta(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    d = np.asarray(x, float) - ref
    if len(d) > _YAW:
        d[3 : _YAW + 1] = wrap_angle(d[3 : _YAW + 1])
    return d
