"""The downlink's channel filter: the host's estimate minus the vehicle's own prior is what the others know."""

import gtsam
import numpy as np
import pytest

from mapcontainer import geometry as geo
from mapcontainer.downlink import (
    OthersOnly,
    cross_localization,
    downlink_messages,
    horizontal,
    others_only,
    remove_own,
)
from mapcontainer.fusion import Container, FusionParams
from mapcontainer.fusion.buffer import time_key
from mapcontainer.fusion.poses import pose3_from_vector, pose_cov_to_tangent, sym_from_upper
from schemas import PoseDownlink, decode, encode

from .test_fusion_container import prior


def _spd(rng, n, scale):
    A = rng.normal(size=(n, n)) * scale
    return A @ A.T + scale**2 * np.eye(n)


@pytest.mark.parametrize("seed", range(5))
def test_removing_the_own_prior_leaves_the_posterior_of_the_others_measurements(seed):
    """Linear-Gaussian: x (6) with the vehicle's prior N(m_own, P_own) and the others' measurements z_i = H_i x + n_i
    (each sees 3 of its 6 numbers). The joint posterior minus the own prior is exactly the posterior of the others'
    measurements alone (flat prior): same mean on the directions they inform, same information."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=6)
    m_own, P_own = x + rng.normal(size=6) * 0.1, _spd(rng, 6, 0.1)
    Hs = [rng.normal(size=(3, 6)) for _ in range(3)]
    Rs = [_spd(rng, 3, 0.3) for _ in Hs]
    zs = [H @ x + rng.multivariate_normal(np.zeros(3), R) for H, R in zip(Hs, Rs, strict=True)]
    Y_o = sum(H.T @ np.linalg.solve(R, H) for H, R in zip(Hs, Rs, strict=True))
    eta_o = sum(H.T @ np.linalg.solve(R, z) for H, R, z in zip(Hs, Rs, zs, strict=True))
    m_o = np.linalg.solve(Y_o, eta_o)  # the others alone (9 measurements of 6 numbers: full rank)
    Y_h = Y_o + np.linalg.inv(P_own)
    P_h = np.linalg.inv(Y_h)
    m_h = P_h @ (eta_o + np.linalg.solve(P_own, m_own))
    out = remove_own(P_h, m_own - m_h, P_own)
    assert out.rank == 6
    np.testing.assert_allclose(m_h + out.mean, m_o, rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(out.info, Y_o, rtol=1e-6, atol=1e-6)


def test_directions_the_others_do_not_see_are_uninformed():
    """The others see the position only: their heading is no information, their position exact."""
    rng = np.random.default_rng(1)
    P_own = _spd(rng, 6, 0.05)
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    R = np.diag([0.2, 0.3, 0.4]) ** 2
    z = np.array([1.0, -2.0, 0.5])
    m_own = np.array([1.1, -1.9, 0.45, 0.01, -0.02, 0.3])
    Y_h = H.T @ np.linalg.solve(R, H) + np.linalg.inv(P_own)
    P_h = np.linalg.inv(Y_h)
    m_h = P_h @ (H.T @ np.linalg.solve(R, z) + np.linalg.solve(P_own, m_own))
    out = remove_own(P_h, m_own - m_h, P_own)
    assert out.rank == 3
    np.testing.assert_allclose((m_h + out.mean)[:3], z, atol=1e-8)
    np.testing.assert_allclose(out.info[:3, :3], np.linalg.inv(R), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(out.info[3:], 0.0, atol=1e-6)


def test_nothing_but_the_own_prior_leaves_nothing():
    P = np.diag([0.1, 0.1, 0.05, 0.01, 0.01, 0.01]) ** 2
    out = remove_own(P, np.zeros(6), P * (1 + 1e-12))
    assert out.rank == 0
    np.testing.assert_array_equal(out.info, 0.0)


def test_bad_shapes_and_values_are_refused():
    with pytest.raises(ValueError, match="6x6"):
        remove_own(np.eye(6), np.zeros(6), np.eye(3))
    with pytest.raises(ValueError, match="finite"):
        remove_own(np.eye(6), np.full(6, np.nan), np.eye(6))


def test_on_a_pose_the_subtraction_works_in_the_tangent():
    """The own prior and the others' position fused on SE(3) and taken apart again (small offsets)."""
    pose_h = np.array([10.0, 5.0, 0.2, 0.01, -0.02, 1.0])
    T_h = pose3_from_vector(pose_h)
    cov_own = np.diag([0.05, 0.08, 0.03, 0.004, 0.004, 0.003]) ** 2
    T_own = T_h.compose(gtsam.Pose3.Expmap(np.array([0.001, -0.002, 0.003, 0.04, -0.03, 0.01])))
    cov_own_xi = pose_cov_to_tangent(geo.matrix_to_pose(T_own.matrix()), cov_own)
    Y_others = np.zeros((6, 6))
    Y_others[3:, 3:] = np.linalg.inv(np.diag([0.3, 0.3, 0.5]) ** 2)
    cov_h = np.linalg.inv(np.linalg.inv(cov_own_xi) + Y_others)
    o = others_only(T_h, cov_h, T_own, cov_own_xi)
    assert o.rank == 3
    # the others' horizontal sigmas, turned into the map frame (yaw 1 rad): 0.3 m each, so unchanged
    np.testing.assert_allclose(np.linalg.eigvalsh(o.info[:2, :2]), [0.09**-1, 0.09**-1], rtol=1e-3)
    assert o.position_sigma_m() == pytest.approx(0.3, rel=1e-3)


def _three_vehicles(n=20):
    """cv0 and cv1 drive 8 m apart and detect each other; cv2, 200 m away, sees nothing and nobody sees it."""
    msgs = []
    for k in range(n):
        t = 0.1 * k
        poses = {
            "cv0": [8 * t, 0, 0, 0, 0, 0.0],
            "cv1": [8 * t + 8, -3.5, 0, 0, 0, 0.0],
            "cv2": [200 + 8 * t, 50, 0, 0, 0, 0],
        }
        for vid, pose in poses.items():
            other = {"cv0": "cv1", "cv1": "cv0"}.get(vid)
            seen = [poses[other][:3]] if other else []
            z = geo.transform_points(geo.inverse(geo.pose_to_matrix(np.array(pose))), np.array(seen).reshape(-1, 3))
            m = prior(vid, k, t, pose=pose, objects=z if len(z) else np.zeros((0, 3)), v=(8, 0, 0))
            msgs.append(m.model_copy(update={"pose_filtered": True}))
    return msgs


def test_a_vehicle_nobody_sees_gets_nothing_and_the_seen_ones_get_the_others_view():
    box = Container(FusionParams(), "f", "host")
    for m in _three_vehicles():
        box.ingest(encode(m), m.t_meas)
        if m.sender == "cv2":
            box.fuse(m.t_meas)
    msgs = box.downlink(2.0, 0)
    assert sorted(m.target for m in msgs) == ["cv0", "cv1"]
    for m in msgs:
        back = decode(encode(m), PoseDownlink)
        assert isinstance(back, PoseDownlink) and back.target == m.target and back.sender == "host"
        info = sym_from_upper(m.pose_info)
        # the others' view: about the partner's detection of it (its noise, the partner's pose) -- wider than own
        assert 0.05 < np.linalg.eigvalsh(info[:2, :2])[0] ** -0.5 < 1.0
        truth = {"cv0": [8 * 1.9, 0.0], "cv1": [8 * 1.9 + 8, -3.5]}[m.target]
        assert abs(m.t_meas - 1.9) < 1e-9
        d = np.asarray(m.pose[:2], float) - truth
        assert d @ info[:2, :2] @ d < 13.8  # chi2(2) at 1e-3 (the angles known: the conditional information)
    assert [m.seq for m in msgs] == [0, 1]


def test_no_downlink_before_a_solve_nor_for_per_frame_priors():
    box = Container(FusionParams(), "f", "host")
    box.ingest(encode(prior("cv0", 0, 0.0)), 0.0)  # not fused yet: no covariance
    assert downlink_messages(box.graph, "f", "host", 0.0, 0) == []
    per_frame = Container(FusionParams(), "f", "host")  # version 3 senders: every frame keeps its own prior
    for m in _three_vehicles():
        per_frame.ingest(encode(m.model_copy(update={"pose_filtered": False})), m.t_meas)
        if m.sender == "cv2":
            per_frame.fuse(m.t_meas)
    assert per_frame.downlink(2.0, 0) == []


def test_the_horizontal_marginal_is_the_information_of_x_y_with_the_rest_unknown():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(4, 6))
    Y = A.T @ A  # rank 4: positive semi-definite, as the others' information is
    out = horizontal(OthersOnly(np.zeros(6), Y, 4))
    Sab = Y[:2, 2:] @ np.linalg.pinv(Y[2:, 2:]) @ Y[2:, :2]
    np.testing.assert_allclose(out.info[:2, :2], Y[:2, :2] - Sab, atol=1e-8)
    np.testing.assert_array_equal(out.info[2:], 0.0)
    assert out.rank <= 2 and np.all(np.linalg.eigvalsh(out.info) > -1e-9)
    # a whole pose known: the marginal is the x, y block of its covariance
    full = OthersOnly(np.zeros(6), np.linalg.inv(np.diag([0.2, 0.3, 0.1, 0.01, 0.01, 0.02]) ** 2), 6)
    np.testing.assert_allclose(np.linalg.inv(horizontal(full).info[:2, :2]), np.diag([0.04, 0.09]), rtol=1e-9)


def _alone_past_parked_cars(n=25):
    """cv3 drives alone at 8 m/s past two parked cars ahead, left and right, that only it sees; 0.1 s frames."""
    cars = np.array([[30.0, 5.0, 0.0], [26.0, -6.0, 0.0]])
    for k in range(n):
        t = 0.1 * k
        pose = [8 * t, 0, 0, 0, 0, 0.0]
        z = geo.transform_points(geo.inverse(geo.pose_to_matrix(np.array(pose))), cars)
        yield prior("cv3", k, t, pose=pose, objects=z, v=(8, 0, 0)).model_copy(update={"pose_filtered": True})


def test_a_vehicle_that_alone_sees_an_object_does_not_get_its_own_past_back():
    """Rumour through the objects: once the cars' tracks are older than the lag, their priors hold cv3's detections
    placed with cv3's reported poses (its own estimates); cv3's newest detections of them then tells the host where
    cv3 is -- from cv3's own past. Subtracting the newest prior leaves that in: the channel filter of the window
    with the objects sent cv3 a downlink (1-sigmas 0.23 and 0.41 m) though nobody sees it. Without them: nothing."""
    box = Container(FusionParams(), "f", "host")
    for m in _alone_past_parked_cars():
        box.ingest(encode(m), m.t_meas)
        box.fuse(m.t_meas)
    assert box.graph.tracks and any(c.prior is not None and c.prior.info[0, 0] > 1.0 for c in box.graph.tracks.values())
    assert box.downlink(2.5, 0) == []


def test_without_objects_and_persistent_detector_error_the_window_is_the_hosts_posterior():
    """The vehicles-only window equals the host's own solution when there are no objects, and with the detector's
    persistent share its cross-detections count as their mean does: less information, the same pose."""
    plain = FusionParams(detection_persistent_fraction=0.0)
    box = Container(plain, "f", "host")
    for m in _three_vehicles():
        box.ingest(encode(m), m.t_meas)
        if m.sender == "cv2":
            box.fuse(m.t_meas)
    post = cross_localization(box.graph)
    for chain in box.graph.vehicles.values():
        key = chain.latest().key
        T, cov = post[key]
        np.testing.assert_allclose(T.matrix(), box.graph.values.atPose3(key).matrix(), atol=1e-6)
        np.testing.assert_allclose(cov, box.graph.covariances[key], rtol=1e-6, atol=1e-12)
    info = {m.target: sym_from_upper(m.pose_info)[:2, :2] for m in downlink_messages(box.graph, "f", "h", 2.0, 0)}
    box.graph.params = FusionParams(detection_persistent_fraction=0.5)
    shared = {m.target: sym_from_upper(m.pose_info)[:2, :2] for m in downlink_messages(box.graph, "f", "h", 2.0, 0)}
    assert sorted(info) == sorted(shared) == ["cv0", "cv1"]
    for vid in info:  # ten detections by one partner in the window, 0.43 of their variance shared (the partner's
        # own pose error does not average out either: about half the information along the line of sight)
        assert np.linalg.eigvalsh(shared[vid])[1] < 0.65 * np.linalg.eigvalsh(info[vid])[1]


def test_frames_past_a_gap_in_the_motion_do_not_break_the_window_without_objects():
    """cv2's frames before a 0.6 s gap (no motion factor) hang only on its detections of a parked car in the host's
    window; without the objects they hang on nothing, and the downlink is still made."""
    box = Container(FusionParams(), "f", "host")
    for m in _three_vehicles(16):
        if m.sender == "cv2" and 0.65 < m.t_meas < 1.25:
            continue
        if m.sender == "cv2":
            m = m.model_copy(update={"objects": prior(objects=((20.0, 3.0, 0.0),)).objects})
        box.ingest(encode(m), m.t_meas)
        if m.sender == "cv2":
            box.fuse(m.t_meas)
    chain = box.graph.vehicles["cv2"]
    assert chain.tkeys[1] < time_key(0.7) < time_key(1.2) < chain.tkeys[-1]  # two frames before the gap, tied
    assert sorted(m.target for m in box.downlink(1.5, 0)) == ["cv0", "cv1"]
