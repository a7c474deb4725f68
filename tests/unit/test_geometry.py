"""Rigid-body helpers and the pinhole camera: identities and analytic Jacobians vs numerical ones."""

import numpy as np
import pytest

from mapcontainer import geometry as geo

RNG = np.random.default_rng(7)
INTR = geo.CameraIntrinsics(1000.0, 1000.0, 639.5, 359.5, 1280, 720)
T_BODY_CAM = geo.camera_extrinsic(1.5, 0.1, 1.5, pitch=0.03)


def numerical_jacobian(f, x, eps=1e-6):
    x = np.asarray(x, dtype=float)
    f0 = np.asarray(f(x))
    J = np.zeros(f0.shape + x.shape)
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = eps
        J[..., i] = (np.asarray(f(x + dx)) - np.asarray(f(x - dx))) / (2 * eps)
    return J


@pytest.mark.parametrize("rpy", [(0.0, 0.0, 0.0), (0.1, -0.2, 2.5), (-0.3, 0.4, -3.0)])
def test_rpy_round_trip(rpy):
    R = geo.rpy_to_matrix(*rpy)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(geo.matrix_to_rpy(R), rpy, atol=1e-12)


def test_rpy_derivatives_match_numerical():
    rpy = np.array([0.1, -0.2, 0.7])
    _, *dR = geo.rpy_to_matrix_jac(*rpy)
    J = numerical_jacobian(lambda a: geo.rpy_to_matrix(*a), rpy)
    for k in range(3):
        np.testing.assert_allclose(dR[k], J[..., k], atol=1e-8)


def test_so3_exp_log_round_trip():
    for _ in range(20):
        axis = RNG.normal(size=3)
        w = axis / np.linalg.norm(axis) * RNG.uniform(0, 3.1)
        np.testing.assert_allclose(geo.so3_log(geo.so3_exp(w)), w, atol=1e-9)
    np.testing.assert_allclose(geo.so3_exp(np.zeros(3)), np.eye(3))


def test_transform_chain_and_inverse():
    T_map_body = geo.pose_to_matrix([3.0, -2.0, 0.1, 0.01, 0.02, 1.2])
    T_map_cam = T_map_body @ T_BODY_CAM
    p_cam = RNG.normal(size=(5, 3))
    p_map = geo.transform_points(T_map_cam, p_cam)
    np.testing.assert_allclose(geo.transform_points(geo.inverse(T_map_cam), p_map), p_cam, atol=1e-12)
    np.testing.assert_allclose(geo.matrix_to_pose(T_map_body), [3.0, -2.0, 0.1, 0.01, 0.02, 1.2], atol=1e-12)


def test_camera_looks_along_body_x():
    # A point 10 m straight ahead of the camera projects to the principal point.
    pose = np.zeros(6)
    T_cam_map = geo.inverse(geo.pose_to_matrix(pose) @ geo.camera_extrinsic(1.5, 0.0, 1.5))
    uv, z = geo.project_points(INTR, T_cam_map, [[11.5, 0.0, 1.5]])
    np.testing.assert_allclose(uv[0], [INTR.cx, INTR.cy])
    assert z[0] == pytest.approx(10.0)
    # Left of the vehicle (+y body) is left in the image (smaller u); up (+z) is smaller v.
    uv, _ = geo.project_points(INTR, T_cam_map, [[11.5, 1.0, 2.5]])
    assert uv[0, 0] < INTR.cx and uv[0, 1] < INTR.cy


def test_point_projection_jacobians_match_numerical():
    pose = np.array([5.0, 2.0, 0.05, 0.02, -0.03, 0.4])
    p_map = geo.transform_points(geo.pose_to_matrix(pose) @ T_BODY_CAM, RNG.uniform([-5, -3, 5], [5, 3, 40], (6, 3)))
    uv, z, J_pose = geo.project_points_jac(INTR, pose, T_BODY_CAM, p_map)
    T_cam_map = geo.inverse(geo.pose_to_matrix(pose) @ T_BODY_CAM)
    np.testing.assert_allclose(uv, geo.project_points(INTR, T_cam_map, p_map)[0], atol=1e-9)
    assert np.all(z > 0)
    Jn_pose = numerical_jacobian(lambda x: geo.project_points_jac(INTR, x, T_BODY_CAM, p_map)[0], pose)
    np.testing.assert_allclose(J_pose, Jn_pose, rtol=1e-5, atol=1e-4)


def test_line_projection_and_distance_jacobians():
    pose = np.array([0.0, 0.0, 0.0, 0.0, 0.01, 0.1])
    P1, P2 = np.array([20.0, 4.0, 0.0]), np.array([20.0, 4.0, 8.0])
    l4, z, J = geo.project_line(INTR, pose, T_BODY_CAM, P1, P2)
    assert np.all(z > 0)
    Jn = numerical_jacobian(lambda x: geo.project_line(INTR, x, T_BODY_CAM, P1, P2)[0], pose)
    np.testing.assert_allclose(J, Jn, rtol=1e-5, atol=1e-4)
    A, B = np.array([100.0, 50.0]), np.array([110.0, 300.0])
    m = np.array([[120.0, 80.0], [90.0, 200.0]])
    d, n = geo.point_line_distance(A, B, m)
    for i in range(2):
        Jd = numerical_jacobian(lambda q: geo.point_line_distance(A, B, q)[0], m[i])
        np.testing.assert_allclose(Jd, n, atol=1e-8)
        # |d| equals the paper's cross-product form of D_L.
        cross = abs((B - A)[0] * (m[i] - A)[1] - (B - A)[1] * (m[i] - A)[0]) / np.linalg.norm(B - A)
        assert abs(d[i]) == pytest.approx(cross)
    with pytest.raises(ValueError):
        geo.point_line_distance(A, A, m)


def test_pose_shape_is_checked():
    with pytest.raises(ValueError, match="shape"):
        geo.pose_to_matrix([1, 2, 3])


def test_grid_projection_matches_the_single_pose_projection():
    intr = geo.CameraIntrinsics(1000.0, 1000.0, 639.5, 359.5, 1280, 720)
    T_bc = geo.camera_extrinsic(1.5, 0.2, 1.4, pitch=0.03)
    pose = np.array([10.0, -3.0, 0.4, 0.01, -0.02, 0.7])
    pts = np.array([[30.0, 5.0, 3.0], [25.0, -8.0, 0.0], [40.0, 12.0, 6.0]])
    offsets, yaws = np.array([[0.0, 0.0], [1.5, -0.5]]), np.array([0.7, 0.65, 0.9])
    u, v, z = geo.project_points_grid(intr, pose, T_bc, offsets, yaws, pts)
    assert u.shape == (2, 3, 3)
    for i, off in enumerate(offsets):
        for j, yaw in enumerate(yaws):
            p = pose.copy()
            p[:2] += off
            p[5] = yaw
            uv, zc, _ = geo.project_points_jac(intr, p, T_bc, pts)
            np.testing.assert_allclose(np.stack([u[i, j], v[i, j]], axis=1), uv, atol=1e-9)
            np.testing.assert_allclose(z[i, j], zc, atol=1e-12)


def test_circular_mean_wraps_across_pi():
    assert abs(abs(geo.circular_mean(np.radians([179.0, -179.0]))) - np.pi) < 1e-12
    assert geo.circular_mean(np.radians([10.0, 30.0])) == pytest.approx(np.radians(20.0))
