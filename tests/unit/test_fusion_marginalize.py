"""Track priors alone (mapcontainer.fusion.marginalize): each marginalization against the same linear
Gaussian written out densely with numpy, the detection model's Jacobian checked numerically, batching."""

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import B, S

from mapcontainer.fusion import FusionParams
from mapcontainer.fusion.marginalize import (
    TrackPrior,
    batches,
    birth_prior,
    detection_information,
    fold,
    forget_bias,
    in_map,
    jacobian_factor,
    marginalize,
    prior_factor,
    sqrt_information,
    summarize_first,
)
from mapcontainer.fusion.motion import cv_model


def _spd(n: int, rng) -> np.ndarray:
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


def _dense_marginal(info: np.ndarray, eta: np.ndarray, keep) -> tuple[np.ndarray, np.ndarray]:
    """Information form of the marginal over ``keep``, through the covariance form."""
    cov = np.linalg.inv(info)
    mean = cov @ eta
    info_k = np.linalg.inv(cov[np.ix_(keep, keep)])
    return info_k, info_k @ mean[keep]


def test_marginalize_is_the_covariance_forms_marginal():
    rng = np.random.default_rng(0)
    info, eta = _spd(18, rng), rng.normal(size=18)
    out = np.arange(6, 12)
    keep = np.setdiff1d(np.arange(18), out)
    new_info, new_eta = marginalize(info, eta, out)
    ref_info, ref_eta = _dense_marginal(info, eta, keep)
    np.testing.assert_allclose(new_info, ref_info, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(new_eta, ref_eta, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(new_info, new_info.T)


def test_sqrt_information_factors_the_information():
    rng = np.random.default_rng(1)
    info = np.stack([_spd(12, rng) for _ in range(3)])
    info[2, 6:, :] = info[2, :, 6:] = 0.0  # semi-definite: b not constrained
    eta = rng.normal(size=(3, 12))
    eta[2, 6:] = 0.0
    A, r = sqrt_information(info, eta)
    for n in range(3):
        assert np.allclose(np.tril(A[n], -1), 0.0)
        ridge = 1e-9 * np.max(np.diag(info[n]))
        np.testing.assert_allclose(A[n].T @ A[n], info[n] + ridge * np.eye(12), rtol=1e-10, atol=1e-9)
        np.testing.assert_allclose(A[n].T @ r[n], eta[n], rtol=1e-10, atol=1e-9)


def test_batches_partition_largest_first_and_follow_the_cost_of_a_batch():
    sizes = np.array([4, 3, 4, 2, 0, 8, 8, 8, 1])
    for units in (0.0, 1e5, 1e12):
        out = batches(sizes, units)
        assert sorted(np.concatenate([idx for _, idx in out]).tolist()) == list(range(len(sizes)))
        assert all(m >= sizes[idx].max() for m, idx in out)
        assert [m for m, _ in out] == sorted((m for m, _ in out), reverse=True)
    assert [m for m, _ in batches(sizes, 0.0)] == [8, 4, 3, 2, 1, 0]  # a batch per size
    assert len(batches(sizes, 1e12)) == 1
    # at the graph's 1e5: padding the two priors of 4 vehicles to 8 costs 2 (54^3 - 30^3) = 260928 units,
    # more than a batch; the one of 3 joins them at 30^3 - 24^3 = 13176, and so on down
    out = batches(sizes, 1e5)
    assert [(m, sorted(idx.tolist())) for m, idx in out] == [(8, [5, 6, 7]), (4, [0, 1, 2, 3, 4, 8])]
    assert batches(np.array([], dtype=int), 1e5) == []


@pytest.mark.parametrize("n_keys", [1, 2, 3, 4, 5])
def test_jacobian_factor_error_is_the_least_squares_cost(n_keys):
    rng = np.random.default_rng(n_keys)
    keys = [S(i) for i in range(n_keys)]
    A, b = rng.normal(size=(6 * n_keys, 6 * n_keys)), rng.normal(size=6 * n_keys)
    f = jacobian_factor(keys, A, b)
    assert [int(k) for k in f.keys()] == keys
    y = rng.normal(size=6 * n_keys)
    vv = gtsam.VectorValues()
    for i, k in enumerate(keys):
        vv.insert(k, y[6 * i : 6 * i + 6])
    assert f.error(vv) == pytest.approx(0.5 * np.sum((A @ y - b) ** 2), rel=1e-12)


def test_prior_factor_is_the_priors_quadratic_about_any_values():
    """Its error at y is y^T info y / 2 - eta^T y up to a constant, whatever values it was made about."""
    rng = np.random.default_rng(2)
    prior = TrackPrior(0, _spd(18, rng), rng.normal(size=18), ("cv0", "cv1"))
    keys = [S(0), B(0), B(1)]
    lin = gtsam.Values()
    for k in keys:
        lin.insert(k, rng.normal(size=6))
    f = prior_factor(prior, keys, lin)

    def at(y):
        v = gtsam.Values()
        for i, k in enumerate(keys):
            v.insert(k, y[6 * i : 6 * i + 6])
        return f.error(v)

    y1, y2 = rng.normal(size=18), rng.normal(size=18)
    q = lambda y: 0.5 * y @ prior.info @ y - prior.eta @ y  # noqa: E731
    assert at(y1) - at(y2) == pytest.approx(q(y1) - q(y2), rel=1e-6, abs=1e-6)
    y_min = np.linalg.solve(prior.info, prior.eta)  # the prior's mean: the factor's minimum
    assert at(y_min) == pytest.approx(0.0, abs=1e-6)


def test_birth_prior():
    p0 = np.array([1.0, 2.0, 3.0])
    mean, cov = birth_prior(7, p0, 2.0).marginal(0.5)
    np.testing.assert_allclose(mean, np.concatenate([p0, np.zeros(3)]), atol=1e-12)
    np.testing.assert_allclose(np.diag(cov), [1e6, 1e6, 1e6, 4.0, 4.0, 0.25])


def test_forget_bias_and_marginal_are_the_dense_marginal_at_bs_prior():
    rng = np.random.default_rng(3)
    a = 0.4
    prior = TrackPrior(0, _spd(18, rng), rng.normal(size=18), ("cv0", "cv1"))
    with_b_prior = prior.info + np.diag([0.0] * 6 + [1.0 / a] * 12)
    new = forget_bias(prior, "cv0", a)
    assert new.vids == ("cv1",) and new.tkey == prior.tkey
    info_b1 = prior.info + np.diag([0.0] * 6 + [1.0 / a] * 6 + [0.0] * 6)
    ref_info, ref_eta = _dense_marginal(info_b1, prior.eta, np.r_[0:6, 12:18])
    np.testing.assert_allclose(new.info, ref_info, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(new.eta, ref_eta, rtol=1e-10, atol=1e-12)
    mean, cov = prior.marginal(a)
    full = np.linalg.inv(with_b_prior)
    np.testing.assert_allclose(cov, full[:6, :6], rtol=1e-10)
    np.testing.assert_allclose(mean, (full @ prior.eta)[:6], rtol=1e-10, atol=1e-12)


def _pose(rng) -> np.ndarray:
    T = gtsam.Pose3(gtsam.Rot3.Ypr(*rng.uniform(-1, 1, 3)), rng.normal(0, 10, 3))
    return T.matrix()


def test_in_map_jacobian_is_the_derivative_in_pose3s_tangent():
    """J = d m / d xi with the observer at T exp(xi), xi = [rotation, translation]: central differences."""
    rng = np.random.default_rng(4)
    M = np.stack([_pose(rng) for _ in range(3)])
    z = rng.normal(0, 10, (3, 3))
    Sz = np.stack([_spd(3, rng) for _ in range(3)])
    m, Cz, J = in_map(M, z, Sz)
    for n in range(3):
        T = gtsam.Pose3(M[n])
        np.testing.assert_allclose(m[n], T.transformFrom(z[n]), atol=1e-12)
        np.testing.assert_allclose(Cz[n], M[n, :3, :3] @ Sz[n] @ M[n, :3, :3].T, atol=1e-12)
        h = 1e-6
        num = np.column_stack(
            [
                (T.retract(h * e).transformFrom(z[n]) - T.retract(-h * e).transformFrom(z[n])) / (2 * h)
                for e in np.eye(6)
            ]
        )
        np.testing.assert_allclose(J[n], num, atol=1e-6)


def test_detection_information_covariances_and_huber_weight():
    rng = np.random.default_rng(5)
    M = np.stack([_pose(rng) for _ in range(3)])
    L = np.linalg.cholesky(np.stack([_spd(6, rng) * 1e-4 for _ in range(3)]))
    z, Sz = rng.normal(0, 10, (3, 3)), np.stack([_spd(3, rng) * 0.01 for _ in range(3)])
    m, Cz, J = in_map(M, z, Sz)
    # per observer (a, tau): a per-frame sender, none (no b), a filtered sender
    persist = np.array([[0.5, 1.0], [0.0, 1.0], [0.9, 5.0]])
    age = 0.3
    params = FusionParams(huber_k=None)
    S_, G, m_out = detection_information(M, L, z, Sz, persist, m, params, age=age)
    np.testing.assert_allclose(m_out, m)
    for n in range(3):
        a, tau = persist[n]
        rho = np.exp(-age / tau)
        JL = J[n] @ L[n]
        np.testing.assert_allclose(G[n], -rho * JL, atol=1e-15)
        C = Cz[n] + (1 - a * rho**2) * JL @ JL.T
        np.testing.assert_allclose(S_[n], np.linalg.inv(C), rtol=1e-9)
    # Huber: full weight at the estimate, k / d for a residual of Mahalanobis length d > k
    k = 1.5
    params = FusionParams(huber_k=k)
    C0 = Cz[0] + J[0] @ L[0] @ (J[0] @ L[0]).T
    off = 4.0 * np.linalg.cholesky(C0) @ np.array([1.0, 0.0, 0.0])  # Mahalanobis length 4
    S_h, _, _ = detection_information(M[:1], L[:1], z[:1], Sz[:1], persist[:1], m[:1] + off, params)
    S_0, _, _ = detection_information(M[:1], L[:1], z[:1], Sz[:1], persist[:1], m[:1], params)
    np.testing.assert_allclose(S_h[0], k / 4.0 * S_0[0], rtol=1e-9)


def test_fold_adds_the_detections_quadratic():
    """fold = prior + (H s + G b_v - m)^T S (H s + G b_v - m), written with one stacked Jacobian; a new
    observer's b_v is appended, a detection without b touches s only."""
    rng = np.random.default_rng(6)
    prior = TrackPrior(3, _spd(12, rng), rng.normal(size=12), ("cv0",))
    dt = 0.2
    H = np.hstack([np.eye(3), -dt * np.eye(3)])
    S_, G, m = _spd(3, rng), rng.normal(size=(3, 6)), rng.normal(size=3)
    for v, vids in (("cv0", ("cv0",)), ("cv1", ("cv0", "cv1")), (None, ("cv0",))):
        new = fold(prior, H, v, S_, G, m)
        assert new.vids == vids and new.tkey == 3
        n = 6 + 6 * len(vids)
        Jfull = np.zeros((3, n))
        Jfull[:, :6] = H
        if v is not None:
            j = 6 + 6 * vids.index(v)
            Jfull[:, j : j + 6] = G
        info, eta = np.zeros((n, n)), np.zeros(n)
        info[:12, :12], eta[:12] = prior.info, prior.eta
        np.testing.assert_allclose(new.info, info + Jfull.T @ S_ @ Jfull, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(new.eta, eta + Jfull.T @ S_ @ m, rtol=1e-12, atol=1e-12)


def _summary_by_hand(prior, dets, dt, q, persist, vids_out):
    """The joint Gaussian over [s0, b(t0)..., s1, b(t1)...] of the prior, the detections (S, G, m, vid)
    on s0's position, s1 = F s0 + w and b(t0) = rho b(t1) + w', each written as a stacked Jacobian;
    s0 and every b(t0) eliminated at once by the Schur complement."""
    mb = len(vids_out)
    n0 = 6 + 6 * mb
    N = 2 * n0
    info, eta = np.zeros((N, N)), np.zeros(N)
    k = len(prior.info)
    info[:k, :k], eta[:k] = prior.info, prior.eta  # the prior's own vehicles come first in vids_out
    for S_, G, m, v in dets:
        J = np.zeros((3, N))
        J[:, :3] = np.eye(3)
        if v is not None:
            j = 6 + 6 * vids_out.index(v)
            J[:, j : j + 6] = G
        info += J.T @ S_ @ J
        eta += J.T @ S_ @ m
    F, Q = cv_model(dt, q)
    Jm = np.zeros((6, N))
    Jm[:, :6], Jm[:, n0 : n0 + 6] = -F, np.eye(6)
    info += Jm.T @ np.linalg.inv(Q) @ Jm
    for i in range(mb):
        a, tau = persist[vids_out[i]]
        rho = np.exp(-abs(dt) / tau)
        Jb = np.zeros((6, N))
        Jb[:, 6 + 6 * i : 12 + 6 * i] = np.eye(6)
        Jb[:, n0 + 6 + 6 * i : n0 + 12 + 6 * i] = -rho * np.eye(6)
        info += Jb.T @ Jb / (a * (1 - rho**2))
    o, kk = slice(0, n0), slice(n0, N)
    K = np.linalg.solve(info[o, o], np.column_stack([info[o, kk], eta[o]]))
    return info[kk, kk] - info[kk, o] @ K[:, :-1], eta[kk] - info[kk, o] @ K[:, -1]


def test_summarize_first_is_the_dense_marginal_and_padding_changes_nothing():
    """Three tracks whose priors hold 0, 1 and 2 vehicles, detections with and without b and of a new
    vehicle, the vehicles' errors persisting differently (per-frame and filtered senders): each summary
    equals the dense joint marginalised by hand, in one padded batch or one batch per size."""
    rng = np.random.default_rng(7)
    persist = {"cv0": (0.5, 1.0), "cv1": (0.9, 5.0), "cv2": (0.7, 0.5)}
    priors = [
        TrackPrior(10, _spd(6, rng), rng.normal(size=6), ()),
        TrackPrior(11, _spd(12, rng), rng.normal(size=12), ("cv0",)),
        TrackPrior(12, _spd(18, rng), rng.normal(size=18), ("cv1", "cv0")),
    ]
    owner = np.array([0, 0, 1, 1, 2, 2, 2])
    dvids = ["cv0", None, "cv0", "cv2", None, "cv0", "cv1"]
    n = len(owner)
    S_ = np.stack([_spd(3, rng) for _ in range(n)])
    G = rng.normal(size=(n, 3, 6))
    m = rng.normal(size=(n, 3))
    dt = np.array([0.1, 0.1, 0.2])
    q = np.array([[2.0, 2.0, 0.5], [1.0, 1.0, 0.5], [0.5, 0.5, 0.1]])
    next_tkeys = [20, 21, 22]
    results = {}
    for units in (0.0, 1e12):
        out = summarize_first(priors, next_tkeys, dt, q, owner, (dvids, S_, G, m), persist, units)
        assert sorted(i for i, _, _ in out) == [0, 1, 2]
        results[units] = {i: (p, sq) for i, p, sq in out}
    expect_vids = [("cv0",), ("cv0", "cv2"), ("cv1", "cv0")]
    for i in range(3):
        for units in (0.0, 1e12):
            p, (A, r) = results[units][i]
            assert p.tkey == next_tkeys[i] and p.vids == expect_vids[i]
            dets = [(S_[d], G[d], m[d], dvids[d]) for d in np.flatnonzero(owner == i)]
            ref_info, ref_eta = _summary_by_hand(priors[i], dets, dt[i], q[i], persist, list(expect_vids[i]))
            scale = np.max(np.abs(ref_info))
            np.testing.assert_allclose(p.info, ref_info, rtol=1e-6, atol=1e-8 * scale)
            np.testing.assert_allclose(p.eta, ref_eta, rtol=1e-6, atol=1e-8 * np.max(np.abs(ref_eta)))
            np.testing.assert_allclose(A.T @ r, p.eta, rtol=1e-9, atol=1e-9 * np.max(np.abs(p.eta)))
        np.testing.assert_allclose(results[0.0][i][0].info, results[1e12][i][0].info, rtol=1e-9, atol=1e-9)


def test_summarize_first_without_detections_is_the_prediction():
    """No detections and no vehicles: the prior N(mu, P) on s0 becomes N(F mu, F P F^T + Q) on s1."""
    rng = np.random.default_rng(8)
    prior = TrackPrior(0, _spd(6, rng), rng.normal(size=6))
    dt, q = np.array([0.3]), np.array([[1.0, 1.0, 0.2]])
    ((i, p, _),) = summarize_first([prior], [5], dt, q, np.array([], dtype=int), None, {}, 1e5)
    P = np.linalg.inv(prior.info)
    mu = P @ prior.eta
    F, Q = cv_model(dt[0], q[0])
    np.testing.assert_allclose(np.linalg.inv(p.info), F @ P @ F.T + Q, rtol=1e-9)
    np.testing.assert_allclose(np.linalg.solve(p.info, p.eta), F @ mu, rtol=1e-9, atol=1e-12)
    assert i == 0 and p.tkey == 5 and p.vids == ()
