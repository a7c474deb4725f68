"""Evaluation figures: RMSE (the paper's rms1 / rms2), NEES / ANEES with chi-square bands, percentiles."""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.special import chdtri

__all__ = ["anees_band", "chi2_quantile", "match_objects", "nees", "percentile", "rmse"]


def chi2_quantile(p, dof):
    """The chi-square quantile: x with P(X <= x) = p for X ~ chi2(dof) (``scipy.stats.chi2.ppf``, through
    scipy.special: importing scipy.stats takes about 1.5 s, a third of a host's restart)."""
    return chdtri(dof, 1.0 - np.asarray(p, dtype=float))


def rmse(errors) -> float:
    """sqrt(mean ||e||^2) over rows of ``errors`` (N, d) — the paper's eqs. rms1 and rms2.

    For rms1 stack every vehicle i and run j at time t; for rms2 every target k and run j.
    Returns NaN for no errors.
    """
    e = np.asarray(errors, dtype=float)
    if e.size == 0:
        return float("nan")
    e = e.reshape(len(e), -1)
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def nees(errors, covs) -> np.ndarray:
    """Normalised estimation error squared e^T P^-1 e per row: errors (N, d), covs (N, d, d)."""
    e = np.asarray(errors, dtype=float)
    P = np.asarray(covs, dtype=float)
    if e.ndim == 1:
        e, P = e[None], P[None]
    return np.einsum("ni,ni->n", e, np.linalg.solve(P, e[..., None])[..., 0])


def anees_band(dof: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided band for the average of n independent NEES values of dimension dof.

    n * ANEES ~ chi2(n * dof), so the band is chi2.ppf([a/2, 1 - a/2], n dof) / n.
    """
    if n <= 0:
        raise ValueError(f"n must be positive, got {n}")
    a = 1.0 - confidence
    lo, hi = chi2_quantile([a / 2, 1 - a / 2], n * dof) / n
    return float(lo), float(hi)


def percentile(values, q: float) -> float:
    v = np.asarray(values, dtype=float)
    return float(np.percentile(v, q)) if v.size else float("nan")


def match_objects(p_est, p_true, gate_m: float = 3.0, order: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Pair estimated with true positions on horizontal distance: the GOSPA assignment with cutoff ``gate_m``.

    The Hungarian algorithm minimises sum_pairs min(d_ij, c)^p over complete assignments
    (c = ``gate_m``, p = ``order``, d_ij the x-y distance); pairs with d_ij >= c are then dropped. A
    pair at the cutoff costs c^p, the same as leaving both unassigned (a miss and a false track,
    c^p / 2 each), so this is the optimal assignment of GOSPA with alpha = 2
    (:func:`mapcontainer.evaluation.gospa`): the matched pairs, misses and false tracks of every
    figure come from one assignment. Returns (true index array, estimate index array).
    """
    if gate_m <= 0 or order < 1:
        raise ValueError(f"gate_m must be > 0 and order >= 1, got {gate_m}, {order}")
    p_est = np.asarray(p_est, dtype=float)
    p_true = np.asarray(p_true, dtype=float)
    if p_est.size == 0 or p_true.size == 0:
        return np.zeros(0, int), np.zeros(0, int)
    d = np.linalg.norm(p_true[:, None, :2] - p_est[None, :, :2], axis=2)
    rows, cols = linear_sum_assignment(np.minimum(d, gate_m) ** order)
    ok = d[rows, cols] < gate_m
    return rows[ok], cols[ok]
