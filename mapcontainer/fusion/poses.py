"""Conversions between the wire pose ``[x, y, z, roll, pitch, yaw]`` and GTSAM's ``Pose3``.

The wire pose (schemas.VehiclePrior) is ``p = [t_map, rpy]`` with R_map_body = Rz(yaw) Ry(pitch) Rx(roll);
its covariance is over those six numbers. GTSAM's Pose3 is perturbed on the right in the body frame,

    R <- R Exp(dtheta),   t <- t + R dt          (xi = [dtheta, dt], rotation first),

so a noise model or a marginal covariance of a Pose3 lives in xi. To first order

    dt     = R^T dt_map
    dtheta = E(rpy) drpy,     E = [[1, 0, -sin(pitch)],
                                   [0, cos(roll), sin(roll) cos(pitch)],
                                   [0, -sin(roll), cos(roll) cos(pitch)]]

(E maps roll/pitch/yaw rates to the body angular rate: the columns are R^T dR/d(angle) as vectors),
hence xi = J p with J = [[0, E], [R^T, 0]] and Sigma_xi = J Sigma_p J^T; back: Sigma_p = J^-1 Sigma_xi J^-T.
"""

from __future__ import annotations

import gtsam
import numpy as np

from .. import geometry as geo

__all__ = [
    "euler_rate_matrix",
    "sym_from_upper",
    "upper_from_sym",
    "pose3_from_vector",
    "pose_cov_from_tangent",
    "pose_cov_to_tangent",
    "tangent_jacobian",
    "vector_from_pose3",
]


def euler_rate_matrix(roll: float, pitch: float) -> np.ndarray:
    """E(rpy): body angular rate = E @ d[roll, pitch, yaw]/dt for R = Rz(yaw) Ry(pitch) Rx(roll)."""
    sr, cr = np.sin(roll), np.cos(roll)
    sp, cp = np.sin(pitch), np.cos(pitch)
    return np.array([[1.0, 0.0, -sp], [0.0, cr, sr * cp], [0.0, -sr, cr * cp]])


def tangent_jacobian(pose) -> np.ndarray:
    """J = d xi / d p at ``pose`` (6x6): rows [dtheta_body, dt_body], columns [x, y, z, roll, pitch, yaw]."""
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (6,):
        raise ValueError(f"pose must have shape (6,), got {pose.shape}")
    J = np.zeros((6, 6))
    J[:3, 3:] = euler_rate_matrix(pose[3], pose[4])
    J[3:, :3] = geo.rpy_to_matrix(*pose[3:]).T
    return J


def pose_cov_to_tangent(pose, cov) -> np.ndarray:
    """Covariance over [x, y, z, roll, pitch, yaw] -> covariance over Pose3's tangent xi."""
    J = tangent_jacobian(pose)
    out = J @ np.asarray(cov, dtype=float) @ J.T
    return 0.5 * (out + out.T)


def pose_cov_from_tangent(pose, cov_xi) -> np.ndarray:
    """Inverse of :func:`pose_cov_to_tangent`."""
    Jinv = np.linalg.inv(tangent_jacobian(pose))
    out = Jinv @ np.asarray(cov_xi, dtype=float) @ Jinv.T
    return 0.5 * (out + out.T)


def pose3_from_vector(pose) -> gtsam.Pose3:
    """gtsam.Pose3 (T_map_body) of the wire pose vector."""
    return gtsam.Pose3(geo.pose_to_matrix(pose))


def vector_from_pose3(T: gtsam.Pose3) -> np.ndarray:
    """[x, y, z, roll, pitch, yaw] of a gtsam.Pose3."""
    return geo.matrix_to_pose(T.matrix())


_TRIU = {n: np.triu_indices(n) for n in (3, 6)}
_FROM = {len(_TRIU[n][0]): n for n in (3, 6)}


def sym_from_upper(upper) -> np.ndarray:
    """Symmetric (..., n, n) from row-major upper triangles (..., 6) or (..., 21) (fast path of
    schemas.arrays.cov_from_upper for the two sizes the container uses)."""
    upper = np.asarray(upper, dtype=np.float64)
    n = _FROM[upper.shape[-1]]
    i, j = _TRIU[n]
    out = np.empty(upper.shape[:-1] + (n, n))
    out[..., i, j] = upper
    out[..., j, i] = upper
    return out


def upper_from_sym(cov) -> np.ndarray:
    """Row-major upper triangle of symmetric (..., n, n), n in (3, 6)."""
    cov = np.asarray(cov)
    i, j = _TRIU[cov.shape[-1]]
    return cov[..., i, j]
