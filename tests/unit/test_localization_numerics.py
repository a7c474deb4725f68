"""The map matcher's numerics written for speed agree with their plain definitions.

The projection without Jacobian agrees with :func:`geometry.project_points_jac` to the bit (the
association projects lane samples with it and the residuals with the Jacobian version; a difference
would change associations), a projection is independent of the batch it is made in, the bilinear
lookup's gradient is the derivative of its value, and the information Jacobian leaves the lanes'
along-track component out.
"""

from __future__ import annotations

import numpy as np
import pytest

from mapcontainer import geometry as geo
from mapcontainer.localization.lanes import bilinear_with_grad
from mapcontainer.localization.residuals import _Eval

INTR = geo.CameraIntrinsics(1000.0, 1000.0, 640.0, 360.0, 1280, 720)
T_BC = geo.camera_extrinsic(1.5, 0.0, 1.4, 0.05)


def _scene(rng, n):
    pts = rng.normal(size=(n, 3)) * [20.0, 5.0, 1.0] + [30.0, 0.0, 0.0]
    pose = rng.normal(size=6) * [1.0, 1.0, 0.1, 0.02, 0.02, 3.0]
    return pose, pts


@pytest.mark.parametrize("n", [1, 7, 300])
def test_projection_without_jacobian_is_bit_identical(n):
    rng = np.random.default_rng(n)
    for _ in range(10):
        pose, pts = _scene(rng, n)
        uv, z, _ = geo.project_points_jac(INTR, pose, T_BC, pts)
        uv_p, z_p = geo.project_points_pose(INTR, pose, T_BC, pts)
        assert np.array_equal(uv, uv_p) and np.array_equal(z, z_p)


def test_projection_does_not_depend_on_the_batch_or_a_given_rotation():
    rng = np.random.default_rng(0)
    pose, pts = _scene(rng, 200)
    uv, z, J = geo.project_points_jac(INTR, pose, T_BC, pts)
    parts = [geo.project_points_jac(INTR, pose, T_BC, pts[a:b]) for a, b in ((0, 13), (13, 150), (150, 200))]
    assert np.array_equal(uv, np.vstack([p[0] for p in parts]))
    assert np.array_equal(J, np.concatenate([p[2] for p in parts]))
    rot = geo.rpy_to_matrix_jac(*pose[3:])
    uv_r, z_r, J_r = geo.project_points_jac(INTR, pose, T_BC, pts, rot_jac=rot)
    assert np.array_equal(uv, uv_r) and np.array_equal(z, z_r) and np.array_equal(J, J_r)


def test_projection_jacobian_matches_numerical():
    rng = np.random.default_rng(1)
    pose, pts = _scene(rng, 20)
    _, _, J = geo.project_points_jac(INTR, pose, T_BC, pts)
    eps = 1e-6
    for i in range(6):
        dp = np.zeros(6)
        dp[i] = eps
        up, _ = geo.project_points_pose(INTR, pose + dp, T_BC, pts)
        um, _ = geo.project_points_pose(INTR, pose - dp, T_BC, pts)
        np.testing.assert_allclose(J[:, :, i], (up - um) / (2 * eps), rtol=1e-5, atol=1e-4)


def test_bilinear_gradient_is_the_derivative_of_the_value():
    rng = np.random.default_rng(2)
    img = rng.random((40, 60)).astype(np.float32)
    uv = rng.random((50, 2)) * [57.0, 37.0] + 0.5
    uv = uv[np.all((uv - np.floor(uv) > 0.01) & (uv - np.floor(uv) < 0.99), axis=1)]  # away from cell borders
    val, du, dv = bilinear_with_grad(img, uv)
    eps = 1e-4
    np.testing.assert_allclose(val[:1], [img[int(uv[0, 1]), int(uv[0, 0])]], atol=1.0)  # in the cell's range
    for k, g in ((0, du), (1, dv)):
        d = np.zeros(2)
        d[k] = eps
        num = (bilinear_with_grad(img, uv + d)[0] - bilinear_with_grad(img, uv - d)[0]) / (2 * eps)
        np.testing.assert_allclose(g, num, rtol=1e-6, atol=1e-6)
    corners = np.array([[3.0, 5.0], [10.0, 20.0]])
    np.testing.assert_array_equal(bilinear_with_grad(img, corners)[0], img[[5, 20], [3, 10]])


def test_information_jacobian_removes_the_lanes_along_track_part():
    rng = np.random.default_rng(3)
    m, yaw, rows = 12, 0.7, slice(4, 9)
    ev = _Eval(
        rng.normal(size=m),
        rng.normal(size=(m, 6)),
        np.ones(m),
        0.0,
        0.0,
        0,
        np.zeros(0),
        np.zeros(0),
        0,
        rows,
        yaw,
        False,
    )
    h = np.array([np.cos(yaw), np.sin(yaw)])
    J_info = ev.J_info
    np.testing.assert_allclose(J_info[rows, :2] @ h, 0.0, atol=1e-12)
    np.testing.assert_array_equal(np.delete(J_info, np.arange(4, 9), axis=0), np.delete(ev.J, np.arange(4, 9), axis=0))
    np.testing.assert_array_equal(J_info[:, 2:], ev.J[:, 2:])
    kept = _Eval(ev.e, ev.J, ev.w, 0.0, 0.0, 0, np.zeros(0), np.zeros(0), 0, rows, yaw, True)
    assert kept.J_info is kept.J
