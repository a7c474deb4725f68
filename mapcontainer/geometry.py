"""Rigid-body geometry and the pinhole camera, with analytic Jacobians.

Conventions (README "Frames and units"):

* ``T_a_b`` is a 4x4 homogeneous transform that maps points from frame b into frame a,
  ``p_a = T_a_b @ p_b``; ``R_a_b`` is its rotation. Compositions chain:
  ``T_map_cam = T_map_body @ T_body_cam``.
* Map frame: local ENU, metres, z up. Body frame: x forward, y left, z up (ISO 8855).
  Camera frame: x right, y down, z forward (OpenCV).
* A pose is the 6-vector ``[x, y, z, roll, pitch, yaw]`` of the body in the map frame with
  ``R_map_body = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (intrinsic z-y'-x''). This is the paper's
  6-DoF parameterisation p_c = (C_x, C_y, C_z, phi, theta, psi) and the order the wire
  covariance uses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "R_BODY_CAM",
    "CameraIntrinsics",
    "camera_extrinsic",
    "circular_mean",
    "inverse",
    "matrix_to_pose",
    "matrix_to_rpy",
    "point_line_distance",
    "pose_to_matrix",
    "project_line",
    "project_points",
    "project_points_grid",
    "project_points_jac",
    "project_points_pose",
    "rot_x",
    "rot_y",
    "rot_z",
    "rpy_to_matrix",
    "rpy_to_matrix_jac",
    "se3",
    "skew",
    "so3_exp",
    "so3_log",
    "transform_points",
    "wrap_angle",
]

# Columns are the camera axes expressed in the body frame: camera x (right) = -y_body,
# camera y (down) = -z_body, camera z (forward) = +x_body.
R_BODY_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def wrap_angle(a):
    """Wrap angle(s) to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def circular_mean(angles) -> float:
    """Mean direction of angles (rad), in [-pi, pi]: the angle of the mean unit vector."""
    return float(np.angle(np.mean(np.exp(1j * np.asarray(angles)))))


def skew(v) -> np.ndarray:
    """[v]x such that skew(v) @ w == np.cross(v, w)."""
    x, y, z = np.asarray(v, dtype=float)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rpy_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll), written out (scalars first, then one array: this and
    :func:`rpy_to_matrix_jac` run tens of times per camera frame in the map matcher)."""
    sr, cr = math.sin(roll), math.cos(roll)
    sp, cp = math.sin(pitch), math.cos(pitch)
    sy, cy = math.sin(yaw), math.cos(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def rpy_to_matrix_jac(roll: float, pitch: float, yaw: float):
    """R and its partial derivatives dR/droll = R [e_x]x, dR/dpitch = Rz Ry [e_y]x Rx and
    dR/dyaw = [e_z]x R (each 3x3), written out."""
    R = rpy_to_matrix(roll, pitch, yaw)
    sr, cr = math.sin(roll), math.cos(roll)
    sp, cp = math.sin(pitch), math.cos(pitch)
    sy, cy = math.sin(yaw), math.cos(yaw)
    d_roll = np.array([[0.0, R[0, 2], -R[0, 1]], [0.0, R[1, 2], -R[1, 1]], [0.0, R[2, 2], -R[2, 1]]])
    d_pitch = np.array(
        [
            [-cy * sp, cy * cp * sr, cy * cp * cr],
            [-sy * sp, sy * cp * sr, sy * cp * cr],
            [-cp, -sp * sr, -sp * cr],
        ]
    )
    d_yaw = np.array([[-R[1, 0], -R[1, 1], -R[1, 2]], [R[0, 0], R[0, 1], R[0, 2]], [0.0, 0.0, 0.0]])
    return R, d_roll, d_pitch, d_yaw


def matrix_to_rpy(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rpy_to_matrix` (pitch in [-pi/2, pi/2])."""
    R = np.asarray(R, dtype=float)
    pitch = np.arcsin(np.clip(-R[2, 0], -1.0, 1.0))
    roll = np.arctan2(R[2, 1], R[2, 2])
    yaw = np.arctan2(R[1, 0], R[0, 0])
    return np.array([roll, pitch, yaw])


def so3_exp(w) -> np.ndarray:
    """Rodrigues' formula: the rotation matrix of rotation vector w (rad)."""
    w = np.asarray(w, dtype=float)
    theta = float(np.linalg.norm(w))
    W = skew(w)
    if theta < 1e-9:
        return np.eye(3) + W + 0.5 * W @ W
    return np.eye(3) + np.sin(theta) / theta * W + (1.0 - np.cos(theta)) / theta**2 * W @ W


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of R (inverse of :func:`so3_exp` for angles below pi)."""
    R = np.asarray(R, dtype=float)
    cos_theta = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos_theta)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-9:
        return 0.5 * v
    if np.pi - theta < 1e-6:
        # Near pi: axis from the symmetric part.
        A = (R + np.eye(3)) / 2.0
        axis = A[:, int(np.argmax(np.diag(A)))]
        axis = axis / np.linalg.norm(axis)
        return theta * axis
    return theta / (2.0 * np.sin(theta)) * v


def se3(R: np.ndarray, t) -> np.ndarray:
    """4x4 homogeneous transform from rotation R and translation t."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float)
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform: T_b_a from T_a_b."""
    R, t = T[:3, :3], T[:3, 3]
    return se3(R.T, -R.T @ t)


def pose_to_matrix(pose) -> np.ndarray:
    """T_map_body from the 6-vector [x, y, z, roll, pitch, yaw]."""
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (6,):
        raise ValueError(f"pose must have shape (6,), got {pose.shape}")
    return se3(rpy_to_matrix(*pose[3:]), pose[:3])


def matrix_to_pose(T: np.ndarray) -> np.ndarray:
    """[x, y, z, roll, pitch, yaw] from T_map_body."""
    return np.concatenate([T[:3, 3], matrix_to_rpy(T[:3, :3])])


def transform_points(T: np.ndarray, p) -> np.ndarray:
    """Apply T_a_b to points p_b of shape (N, 3) (or (3,)), giving p_a."""
    p = np.asarray(p, dtype=float)
    return p @ T[:3, :3].T + T[:3, 3]


def camera_extrinsic(x: float, y: float, z: float, pitch: float = 0.0) -> np.ndarray:
    """T_body_cam for a forward-looking camera at body position (x, y, z), tilted down by ``pitch`` rad."""
    return se3(rot_y(pitch) @ R_BODY_CAM, (x, y, z))


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics (pixels) and image size; no distortion (images are rectified)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        return (
            (uv[:, 0] >= margin)
            & (uv[:, 0] <= self.width - 1 - margin)
            & (uv[:, 1] >= margin)
            & (uv[:, 1] <= self.height - 1 - margin)
        )

    def scaled(self, factor: float) -> CameraIntrinsics:
        """The same camera at another resolution (e.g. 0.5 for a half-size lane mask)."""
        return CameraIntrinsics(
            self.fx * factor,
            self.fy * factor,
            (self.cx + 0.5) * factor - 0.5,
            (self.cy + 0.5) * factor - 0.5,
            int(round(self.width * factor)),
            int(round(self.height * factor)),
        )


def project_points(intr: CameraIntrinsics, T_cam_map: np.ndarray, p_map):
    """Pinhole projection u = K R [I | -C] X (paper, camera model Pi).

    Returns pixel coordinates ``uv`` (N, 2) and depths ``z_cam`` (N,); points with
    ``z_cam <= 0`` are behind the camera and their ``uv`` is meaningless.
    """
    p_cam = transform_points(T_cam_map, np.asarray(p_map, dtype=float).reshape(-1, 3))
    z = p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * p_cam[:, 0] / z + intr.cx
        v = intr.fy * p_cam[:, 1] / z + intr.cy
    return np.stack([u, v], axis=1), z


def _camera_points(intr: CameraIntrinsics, pose, T_body_cam: np.ndarray, p_map, R: np.ndarray):
    """d = p_map - t, p_cam (N, 3) and uv (N, 2) of :func:`project_points_jac` (shared, so that
    :func:`project_points_pose` agrees with it to the bit)."""
    d = np.asarray(p_map, dtype=float).reshape(-1, 3) - pose[:3]
    p_cam = (d @ R - T_body_cam[:3, 3]) @ T_body_cam[:3, :3]
    X, Y, Z = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = 1.0 / Z
        uv = np.stack([intr.fx * X * inv_z + intr.cx, intr.fy * Y * inv_z + intr.cy], axis=1)
    return d, p_cam, inv_z, uv


def project_points_pose(intr: CameraIntrinsics, pose, T_body_cam: np.ndarray, p_map):
    """``uv`` (N, 2) and ``z_cam`` (N,) of :func:`project_points_jac`, without the Jacobian."""
    pose = np.asarray(pose, dtype=float)
    _, p_cam, _, uv = _camera_points(intr, pose, T_body_cam, p_map, rpy_to_matrix(*pose[3:]))
    return uv, p_cam[:, 2]


def project_points_jac(intr: CameraIntrinsics, pose, T_body_cam: np.ndarray, p_map, rot_jac=None):
    """Projection of map points by a camera on a body at ``pose`` = [x, y, z, roll, pitch, yaw].

    pi_P(p_map, pose): p_body = R^T (p_map - t), p_cam = R_body_cam^T (p_body - t_body_cam),
    u = fx X/Z + cx, v = fy Y/Z + cy.

    Returns ``uv`` (N, 2), ``z_cam`` (N,) and ``J_pose`` (N, 2, 6) = d uv / d pose
    = (d uv / d p_cam) R_body_cam^T (d p_body / d pose). ``rot_jac``: the pose's
    :func:`rpy_to_matrix_jac`, if the caller has it already (the map matcher does, per evaluation).
    """
    pose = np.asarray(pose, dtype=float)
    R, dR_roll, dR_pitch, dR_yaw = rpy_to_matrix_jac(*pose[3:]) if rot_jac is None else rot_jac
    d, p_cam, inv_z, uv = _camera_points(intr, pose, T_body_cam, p_map, R)
    n = len(d)
    X, Y = p_cam[:, 0], p_cam[:, 1]
    with np.errstate(invalid="ignore"):
        J_proj = np.zeros((n, 2, 3))
        J_proj[:, 0, 0] = intr.fx * inv_z
        J_proj[:, 0, 2] = -intr.fx * X * inv_z**2
        J_proj[:, 1, 1] = intr.fy * inv_z
        J_proj[:, 1, 2] = -intr.fy * Y * inv_z**2
    # d p_body / d [t, roll, pitch, yaw], laid out (3, N, 6): R_body_cam^T applies to all points in one product.
    dpb = np.empty((3, n, 6))
    dpb[:, :, :3] = -R.T[:, None, :]
    dpb[:, :, 3] = (d @ dR_roll).T
    dpb[:, :, 4] = (d @ dR_pitch).T
    dpb[:, :, 5] = (d @ dR_yaw).T
    J_cam = (T_body_cam[:3, :3].T @ dpb.reshape(3, 6 * n)).reshape(3, n, 6).transpose(1, 0, 2)  # (N, 3, 6)
    with np.errstate(invalid="ignore"):
        return uv, p_cam[:, 2], J_proj @ J_cam


def project_points_grid(intr: CameraIntrinsics, pose, T_body_cam: np.ndarray, offsets, yaws, p_map):
    """Projection of map points from a grid of poses: the body at ``pose`` shifted horizontally by each
    of ``offsets`` (P, 2) and turned to each absolute heading of ``yaws`` (Y,), roll, pitch and height
    kept. Returns ``u``, ``v`` (px) and the depth ``z_cam``, each (P, Y, K) for K points; no Jacobians.
    """
    pose = np.asarray(pose, dtype=float)
    p_map = np.asarray(p_map, dtype=float).reshape(-1, 3)
    offsets = np.asarray(offsets, dtype=float).reshape(-1, 2)
    R_rp = rpy_to_matrix_jac(pose[3], pose[4], 0.0)[0]  # R = Rz(yaw) R_rp
    M = T_body_cam[:3, :3].T @ R_rp.T
    o = T_body_cam[:3, :3].T @ T_body_cam[:3, 3]
    d = p_map[None, :, :] - pose[:3]
    d = np.broadcast_to(d, (len(offsets), *d.shape[1:])).copy()
    d[..., :2] -= offsets[:, None, :]
    c, s = np.cos(yaws)[None, :, None], np.sin(yaws)[None, :, None]
    rx = c * d[:, None, :, 0] + s * d[:, None, :, 1]
    ry = -s * d[:, None, :, 0] + c * d[:, None, :, 1]
    rz = d[:, None, :, 2]
    X = M[0, 0] * rx + M[0, 1] * ry + M[0, 2] * rz - o[0]
    Y = M[1, 0] * rx + M[1, 1] * ry + M[1, 2] * rz - o[1]
    Z = M[2, 0] * rx + M[2, 1] * ry + M[2, 2] * rz - o[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return intr.fx * X / Z + intr.cx, intr.fy * Y / Z + intr.cy, Z


def project_line(intr: CameraIntrinsics, pose, T_body_cam: np.ndarray, P1, P2):
    """pi_L: project a 3-D segment (P1, P2) to l = (u1, v1, u2, v2) with d l / d pose (4, 6).

    Both endpoints must be in front of the camera (check the returned depths).
    """
    uv, z, J_pose = project_points_jac(intr, pose, T_body_cam, np.stack([P1, P2]))
    return uv.reshape(4), z, J_pose.reshape(4, 6)


def point_line_distance(A, B, m):
    """Signed distance of image point(s) m to the infinite line through A and B, and d dist / d m.

    This is the term of the paper's D_L: |(M1 - M2) x (m - M1)| / ||M1 - M2|| without the
    absolute value, so that it is differentiable. ``m`` may be (2,) or (N, 2); the gradient
    with respect to m is the unit normal n of the line (the same for every point).
    """
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float)
    d = B - A
    length = float(np.hypot(d[0], d[1]))
    if length < 1e-9:
        raise ValueError(f"degenerate line: endpoints {A} and {B} coincide")
    normal = np.array([-d[1], d[0]]) / length
    dist = (np.asarray(m, dtype=float) - A) @ normal
    return dist, normal
