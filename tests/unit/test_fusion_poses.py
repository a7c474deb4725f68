"""Wire pose <-> gtsam.Pose3: the covariance conversion's Jacobian, checked numerically."""

import gtsam
import numpy as np
import pytest

from mapcontainer import geometry as geo
from mapcontainer.fusion.poses import (
    euler_rate_matrix,
    pose3_from_vector,
    pose_cov_from_tangent,
    pose_cov_to_tangent,
    sym_from_upper,
    tangent_jacobian,
    upper_from_sym,
    vector_from_pose3,
)
from schemas.arrays import cov_from_upper, cov_to_upper

POSES = [
    np.array([1.0, -2.0, 0.3, 0.0, 0.0, 0.0]),
    np.array([10.0, 5.0, -0.2, 0.05, -0.03, 2.5]),
    np.array([-3.0, 7.0, 1.0, -0.4, 0.6, -2.9]),
]


@pytest.mark.parametrize("pose", POSES)
def test_tangent_jacobian_matches_pose3_local_coordinates(pose):
    """xi = Pose3(p).localCoordinates(Pose3(p + dp)) ~ J dp (central differences)."""
    T0 = pose3_from_vector(pose)
    eps = 1e-6
    J_num = np.zeros((6, 6))
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        xi_p = T0.localCoordinates(pose3_from_vector(pose + d))
        xi_m = T0.localCoordinates(pose3_from_vector(pose - d))
        J_num[:, i] = (xi_p - xi_m) / (2 * eps)
    np.testing.assert_allclose(tangent_jacobian(pose), J_num, atol=1e-7)


@pytest.mark.parametrize("pose", POSES)
def test_euler_rate_matrix_is_body_angular_rate(pose):
    """E columns are vee(R^T dR/d angle)."""
    _, d_roll, d_pitch, d_yaw = geo.rpy_to_matrix_jac(*pose[3:])
    R = geo.rpy_to_matrix(*pose[3:])
    cols = [R.T @ d for d in (d_roll, d_pitch, d_yaw)]
    E = np.array([[c[2, 1], c[0, 2], c[1, 0]] for c in cols]).T
    np.testing.assert_allclose(euler_rate_matrix(pose[3], pose[4]), E, atol=1e-12)


def test_covariance_conversion_by_sampling():
    """Sampled wire poses mapped to Pose3's tangent have the converted covariance."""
    rng = np.random.default_rng(0)
    pose = POSES[1]
    sig = np.array([0.1, 0.2, 0.05, 0.01, 0.02, 0.03])
    C = np.diag(sig**2)
    C[0, 5] = C[5, 0] = 0.5 * sig[0] * sig[5]
    samples = rng.multivariate_normal(pose, C, 20000)
    T0 = pose3_from_vector(pose)
    xi = np.array([T0.localCoordinates(pose3_from_vector(p)) for p in samples])
    emp = np.cov(xi.T)
    conv = pose_cov_to_tangent(pose, C)
    np.testing.assert_allclose(emp, conv, atol=0.05 * np.sqrt(np.outer(np.diag(conv), np.diag(conv))).max())
    np.testing.assert_allclose(np.sqrt(np.diag(emp)), np.sqrt(np.diag(conv)), rtol=0.03)


@pytest.mark.parametrize("pose", POSES)
def test_round_trips(pose):
    np.testing.assert_allclose(vector_from_pose3(pose3_from_vector(pose)), pose, atol=1e-12)
    A = np.random.default_rng(1).normal(size=(6, 6))
    C = A @ A.T + np.eye(6)
    np.testing.assert_allclose(pose_cov_from_tangent(pose, pose_cov_to_tangent(pose, C)), C, atol=1e-9)
    assert isinstance(pose3_from_vector(pose), gtsam.Pose3)


def test_fast_triangles_match_schema_helpers():
    rng = np.random.default_rng(2)
    for n in (3, 6):
        A = rng.normal(size=(4, n, n))
        C = A @ A.transpose(0, 2, 1)
        np.testing.assert_array_equal(upper_from_sym(C), cov_to_upper(C))
        np.testing.assert_array_equal(sym_from_upper(cov_to_upper(C)), cov_from_upper(cov_to_upper(C)))
