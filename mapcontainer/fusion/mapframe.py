"""Detections in the map frame and their distances to candidates (the association's geometry).

A body-frame detection z (covariance S_z) seen from a pose [x, y, z, roll, pitch, yaw] (covariance S_pose)
is, to first order,

    m = R z + t,     S_m = R S_z R^T + J S_pose J^T,     J = d m / d [x, y, z, roll, pitch, yaw]
                                                            = [I, dR/droll z, dR/dpitch z, dR/dyaw z],

and its distance to a candidate c (covariance S_c) is d^2 = (m - c)^T (S_m + S_c)^-1 (m - c).
"""

from __future__ import annotations

import numpy as np

from .. import geometry as geo

__all__ = ["mahalanobis_logdet", "mahalanobis_matrix", "observations_to_map", "rotated_to_map"]


def observations_to_map(pose, pose_cov, p_body, cov_body) -> tuple[np.ndarray, np.ndarray]:
    """Map-frame positions (N, 3) and covariances (N, 3, 3) of body-frame detections.

    ``pose`` = [x, y, z, roll, pitch, yaw] with covariance ``pose_cov`` (6, 6); ``p_body`` (N, 3) with
    covariances ``cov_body`` (N, 3, 3). First-order propagation of both uncertainties (module docstring).
    """
    pose = np.asarray(pose, dtype=float)
    return rotated_to_map(pose, geo.rpy_to_matrix_jac(*pose[3:]), pose_cov, p_body, cov_body)


def rotated_to_map(pose, jac, pose_cov, p_body, cov_body, rowwise: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """:func:`observations_to_map` with the pose's rotation and its derivatives ``jac`` given
    (:func:`mapcontainer.geometry.rpy_to_matrix_jac`), for a caller that has them already. ``rowwise``: each
    row's Jacobian as one (1, 3) product, the numbers of N calls with one row each to the last bit (BLAS
    rounds an (N, 3) product's rows differently)."""
    p_body = np.asarray(p_body, dtype=float).reshape(-1, 3)
    cov_body = np.asarray(cov_body, dtype=float).reshape(-1, 3, 3)
    R, dR_r, dR_p, dR_y = jac
    m = p_body @ R.T + pose[:3]
    J = np.empty((len(p_body), 3, 6))
    J[:, :, :3] = np.eye(3)
    rows = p_body[:, None, :] if rowwise else p_body
    J[:, :, 3] = (rows @ dR_r.T).reshape(-1, 3)
    J[:, :, 4] = (rows @ dR_p.T).reshape(-1, 3)
    J[:, :, 5] = (rows @ dR_y.T).reshape(-1, 3)
    S = R @ cov_body @ R.T + J @ np.asarray(pose_cov, dtype=float) @ J.transpose(0, 2, 1)
    return m, 0.5 * (S + S.transpose(0, 2, 1))


def mahalanobis_matrix(m, S_m, c, S_c) -> np.ndarray:
    """d2[i, j] = (m_i - c_j)^T (S_m_i + S_c_j)^-1 (m_i - c_j) for (N, 3) / (K, 3) points and their covariances."""
    return mahalanobis_logdet(m, S_m, c, S_c)[0]


def mahalanobis_logdet(m, S_m, c, S_c) -> tuple[np.ndarray, np.ndarray]:
    """:func:`mahalanobis_matrix` and ln det(S_m_i + S_c_j) of every pair (inf where not positive definite)."""
    m = np.asarray(m, dtype=float).reshape(-1, 3)
    c = np.asarray(c, dtype=float).reshape(-1, 3)
    if len(m) == 0 or len(c) == 0:
        return np.zeros((len(m), len(c))), np.zeros((len(m), len(c)))
    diff = m[:, None, :] - c[None, :, :]
    S = np.asarray(S_m, dtype=float)[:, None] + np.asarray(S_c, dtype=float)[None, :]
    return _quad_inv3(S, diff, logdet=True)


def _quad_inv3(S: np.ndarray, d: np.ndarray, logdet: bool = False):
    """d^T S^-1 d for stacks of symmetric positive definite 3x3 S (..., 3, 3) and vectors d (..., 3), by
    the adjugate (closed form; a batched LAPACK solve costs ~1 us of overhead per matrix); with ``logdet``
    also ln det S."""
    a, b, c = S[..., 0, 0], S[..., 0, 1], S[..., 0, 2]
    e, f, i = S[..., 1, 1], S[..., 1, 2], S[..., 2, 2]
    A00, A01, A02 = e * i - f * f, c * f - b * i, b * f - c * e
    A11, A12, A22 = a * i - c * c, b * c - a * f, a * e - b * b
    det = a * A00 + b * A01 + c * A02
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    q = A00 * x * x + A11 * y * y + A22 * z * z + 2.0 * (A01 * x * y + A02 * x * z + A12 * y * z)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(det > 0, q / det, np.inf)
        if logdet:
            return out, np.where(det > 0, np.log(np.where(det > 0, det, 1.0)), np.inf)
    return out
