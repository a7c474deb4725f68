"""Association probabilities (JPDA's single-detection marginals), detection by detection and for a frame whose
detections share their observer's pose error.

A detection i with gated candidates j (tracks, connected vehicles) and the hypothesis "none of them" (a false
alarm or an object not yet tracked, spatial density lambda_i) is of candidate j with probability

    P[i, j] = N_ij / (lambda_i + sum_k N_ik),   N_ij = N(m_i; c_j, S_i + S_j)                          (1)

(:func:`match_probability`). That treats the detections of one frame as independent, but they are placed in the
map from one pose: where the observer's position is uncertain (GNSS fallback) its whole frame may sit on the
neighbouring objects, each detection near a candidate it is not of, and (1) is sure of every one of them. Given
the observer's horizontal position error delta (covariance P_hh), the detections are independent:

    m_i(delta) = m_i + J_i G delta,   G = P[:, h] P_hh^-1,   S_i|delta = R S_z,i R^T + J_i (P - G P[h, :]) J_i^T

(J_i = d m_i / d pose, as in :mod:`.mapframe`), and the frame's probabilities are (1) averaged over delta with the
weight of the whole frame's likelihood,

    P_frame[i, j] = E[ l(delta) P[i, j | delta] ] / E[ l(delta) ],   l(delta) = prod_i (lambda_i + sum_k N_ik(delta)),

the expectation over the prior delta ~ N(0, P_hh) (:func:`frame_match_probability`, on a ``points`` x ``points``
grid over +-4 sigma of the whitened shift, each point weighted by the prior). A frame that another shift
explains about as well is not sure of its assignment.
"""

from __future__ import annotations

import numpy as np
from scipy.special import logsumexp

from .. import geometry as geo
from .mapframe import rotated_to_map

__all__ = ["frame_match_probability", "match_probability"]

_LOG_2PI = np.log(2.0 * np.pi)


def match_probability(nll: np.ndarray, gated: np.ndarray, density) -> np.ndarray:
    """(1) from nll = d2 + ln det S (N, K) of the gated pairs; ``density``: lambda, one for every row or (N,)."""
    if nll.size == 0:
        return np.zeros_like(nll)
    log_lam = np.broadcast_to(np.log(np.asarray(density, dtype=float)), nll.shape[:1])[:, None]
    log_n = np.where(gated, -0.5 * nll - 1.5 * _LOG_2PI, -np.inf)
    top = np.maximum(log_n.max(axis=1, keepdims=True, initial=-np.inf), log_lam)
    n = np.exp(log_n - top)
    return n / (np.exp(log_lam - top) + n.sum(axis=1, keepdims=True))


def frame_match_probability(
    p_body: np.ndarray,
    cov_body: np.ndarray,
    pose: np.ndarray,
    pose_cov: np.ndarray,
    c: np.ndarray,
    S_c: np.ndarray,
    gated: np.ndarray,
    density,
    points: int = 64,
) -> np.ndarray:
    """P_frame (module docstring) of one frame's detections (body frame p_body (N, 3), cov_body (N, 3, 3)) seen from
    ``pose`` (6,) with ``pose_cov`` (6, 6), against candidates c (K, 3), S_c (K, 3, 3), where ``gated`` (N, K)."""
    pose = np.asarray(pose, dtype=float)
    P = np.asarray(pose_cov, dtype=float)
    P_hh = P[:2, :2]
    G = np.linalg.solve(P_hh, P[:2, :]).T  # (6, 2): the pose error's mean given the horizontal shift
    P_cond = P - G @ P[:2, :]
    P_cond = 0.5 * (P_cond + P_cond.T)
    P_cond[:2, :] = P_cond[:, :2] = 0.0
    jac = geo.rpy_to_matrix_jac(*pose[3:])
    m, S = rotated_to_map(pose, jac, P_cond, p_body, cov_body)
    n = len(m)
    J = np.zeros((n, 3, 6))
    J[:, :, :3] = np.eye(3)
    for k, dR in enumerate(jac[1:]):
        J[:, :, 3 + k] = p_body @ dR.T
    B = J @ G  # (N, 3, 2)
    u = np.linspace(-4.0, 4.0, points)
    grid = np.stack(np.meshgrid(u, u, indexing="ij"), axis=-1).reshape(-1, 2)
    delta = grid @ np.linalg.cholesky(P_hh).T  # (s, 2)
    log_prior = -0.5 * np.einsum("sa,sa->s", grid, grid)
    i, j = np.nonzero(gated)
    log_n = np.full((len(delta), n, len(c)), -np.inf)
    if len(i):
        Sij = S[i] + S_c[j]
        sign, logdet = np.linalg.slogdet(Sij)
        Sinv = np.linalg.inv(Sij)
        r = m[i][None] + np.einsum("pab,sb->spa", B[i], delta) - c[j][None]  # (s, pairs, 3)
        d2 = np.einsum("spa,pab,spb->sp", r, Sinv, r)
        log_n[:, i, j] = np.where(sign > 0, -0.5 * (d2 + logdet) - 1.5 * _LOG_2PI, -np.inf)
    log_lam = np.broadcast_to(np.log(np.asarray(density, dtype=float)), (n,))
    row = np.logaddexp(log_lam[None], logsumexp(log_n, axis=2))  # (s, N): ln(lambda_i + sum_k N_ik(delta))
    frame = log_prior + row.sum(axis=1)
    w = np.exp(frame - frame.max())
    w /= w.sum()
    return np.einsum("s,sij->ij", w, np.exp(log_n - row[:, :, None]))
