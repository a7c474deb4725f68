"""The misbehaviour monitor's bias test against closed forms: its threshold from the stated false-alarm rate,
the views and the combined estimate against a dense least squares, its false-alarm and detection probabilities
on synthetic Gaussian sightings drawn from the stated errors, and the frame at which a constant bias is
flagged."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2, ncx2

from mapcontainer.fusion import FusionParams
from mapcontainer.fusion.misbehaviour import MisbehaviourMonitor, Sighting, View, bias_test, view_of

I2 = np.eye(2)


def sighting(offset, white, persistent, weight=1.0, observer="cv0", shape=None) -> Sighting:
    z = np.zeros(2)
    shape = np.zeros((2, 2)) if shape is None else shape
    return Sighting(0.0, observer, np.asarray(offset, float), white, persistent, shape, weight, z, I2)


def test_the_threshold_follows_from_the_stated_false_alarm_rate() -> None:
    """alpha = F dt / 3600 per test; for 2 dof P(q > h) = exp(-h / 2), so h = -2 ln alpha."""
    for rate, dt in ((0.1, 0.1), (1.0, 0.05), (0.01, 0.2)):
        mon = MisbehaviourMonitor(FusionParams(misbehaviour_false_alarms_per_hour=rate, misbehaviour_test_period_s=dt))
        alpha = rate * dt / 3600.0
        assert mon.alpha == pytest.approx(alpha, rel=1e-12)
        assert mon.threshold == pytest.approx(-2.0 * np.log(alpha), rel=1e-9)
    assert MisbehaviourMonitor(FusionParams()).threshold == pytest.approx(25.6, abs=0.05)  # the default: 0.1 / h


def test_a_view_is_the_weighted_least_squares_mean_with_the_repeated_error_added() -> None:
    rng = np.random.default_rng(7)
    A = [np.diag(rng.uniform(0.01, 0.2, 2)) for _ in range(5)]
    B = [np.diag(rng.uniform(0.01, 0.1, 2)) for _ in range(5)]
    d = rng.normal(0.0, 0.5, (5, 2))
    w = np.array([1.0, 0.5, 0.9, 1.0, 0.2])
    P0 = np.diag([0.04, 0.09])
    D = [np.diag(rng.uniform(0.01, 0.1, 2)) for _ in range(5)]
    v = view_of([sighting(d[k], A[k], B[k], w[k], shape=D[k]) for k in range(5)], P0)
    # dense weighted least squares of a constant from the five offsets
    W = [w[k] * np.linalg.inv(A[k]) for k in range(5)]
    cov = np.linalg.inv(sum(W))
    y = cov @ sum(W[k] @ d[k] for k in range(5))
    C = cov + sum(w[k] * B[k] for k in range(5)) / w.sum()
    K = sum(w[k] * D[k] for k in range(5)) / w.sum()
    assert v.y == pytest.approx(y) and v.C == pytest.approx(C) and v.K == pytest.approx(K)
    assert v.q == pytest.approx(y @ np.linalg.solve(P0 + C + K, y))
    one = view_of([sighting(d[0], A[0], B[0])], P0)  # a single sighting: its offset, A + B
    assert one.y == pytest.approx(d[0]) and one.C == pytest.approx(A[0] + B[0])


def test_the_bias_test_is_the_generalised_least_squares_of_the_views() -> None:
    rng = np.random.default_rng(8)
    views = []
    for _ in range(3):
        L = rng.normal(0.0, 0.3, (2, 2))
        views.append(View(rng.normal(0.0, 1.0, 2), L @ L.T + 0.05 * I2, rng.uniform(0.0, 0.05) * I2, 0.0))
    P0 = np.array([[0.05, 0.01], [0.01, 0.03]])
    test = bias_test(views, P0)
    # stacked: y_k = b + e_k, e_k ~ N(0, C_k): b^ = (H^T W H)^-1 H^T W Y with H = [I; I; I]
    H = np.vstack([I2] * 3)
    W = np.zeros((6, 6))
    for k, v in enumerate(views):
        W[2 * k : 2 * k + 2, 2 * k : 2 * k + 2] = np.linalg.inv(v.C)
    Y = np.concatenate([v.y for v in views])
    P = np.linalg.inv(H.T @ W @ H)
    b = P @ H.T @ W @ Y
    assert test.b == pytest.approx(b) and test.P == pytest.approx(P) and test.n == 3
    K = np.mean([v.K for v in views], axis=0)  # what every view shares does not average over them
    assert test.q == pytest.approx(b @ np.linalg.solve(P0 + K + P, b))
    assert test.r == pytest.approx((Y - H @ b) @ W @ (Y - H @ b))


def _draw(rng, bias, n_obs: int, k: int, p0: float, a: float, beta: float) -> list[View]:
    """Sightings drawn from the errors the test assumes: a vehicle off by b ~ N(0, p0 I) (honest, ``bias``
    None) or by ``bias``; ``n_obs`` observers, each with a repeated error c ~ N(0, beta I) and ``k`` sightings
    with white noise N(0, a I)."""
    b = rng.normal(0.0, np.sqrt(p0), 2) if bias is None else np.asarray(bias, float)
    P0 = p0 * I2
    views = []
    for o in range(n_obs):
        c = rng.normal(0.0, np.sqrt(beta), 2)
        d = b + c + rng.normal(0.0, np.sqrt(a), (k, 2))
        views.append(view_of([sighting(d[i], a * I2, beta * I2, observer=f"cv{o}") for i in range(k)], P0))
    return views


def test_on_gaussian_sightings_from_the_stated_errors_the_false_alarm_and_detection_rates_are_the_closed_forms() -> (
    None
):
    """Honest (b ~ N(0, P0)): q ~ chi2(2) and r ~ chi2(2 (n - 1)), so each exceeds its 1 - alpha quantile with
    probability alpha. Biased by a fixed b, with every covariance isotropic, b^ ~ N(b, p I) (p = (a / k + beta)
    / n), so q (p0 + p) / p ~ noncentral chi2(2, |b|^2 / p): the detection probability is its tail."""
    rng = np.random.default_rng(90)
    p0, a, beta, n_obs, k, alpha, runs = 0.02, 0.09, 0.01, 3, 6, 0.05, 2500
    h, h_r = chi2.isf(alpha, 2), chi2.isf(alpha, 2 * (n_obs - 1))
    P0 = p0 * I2
    honest = [bias_test(_draw(rng, None, n_obs, k, p0, a, beta), P0) for _ in range(runs)]
    tol = 4.0 * np.sqrt(alpha * (1 - alpha) / runs)
    assert np.mean([t.q > h for t in honest]) == pytest.approx(alpha, abs=tol)
    assert np.mean([t.r > h_r for t in honest]) == pytest.approx(alpha, abs=tol)
    p = (a / k + beta) / n_obs
    for b in ((0.3, 0.0), (0.0, 0.5)):
        power = float(ncx2.sf(h * (p0 + p) / p, 2, np.dot(b, b) / p))
        biased = [bias_test(_draw(rng, b, n_obs, k, p0, a, beta), P0) for _ in range(runs)]
        tol = 4.0 * np.sqrt(power * (1 - power) / runs) + 1e-3
        assert np.mean([t.q > h for t in biased]) == pytest.approx(power, abs=tol), b
        assert np.mean([t.r > h_r for t in biased]) == pytest.approx(alpha, abs=tol + 0.01)  # a bias they share


def test_a_constant_bias_is_flagged_at_the_frame_the_closed_form_says() -> None:
    """Three observers see cv9 (stated error p0 I) 1 m off from t = 0, one noise-free sighting each per frame
    (white a I, repeated beta I). After K frames every view is y = b with C = (a / K + beta) I, so b^ = b,
    P^ = C / 3 and q_K = |b|^2 / (p0 + (a / K + beta) / 3): flagged at the first K >= min_sightings with
    q_K above the threshold, and not before; nobody else."""
    pp = FusionParams()
    p0, a, beta = 0.01, 0.5, 0.01
    mon = MisbehaviourMonitor(pp)
    b = np.array([0.0, 1.0])
    q = [np.dot(b, b) / (p0 + (a / K + beta) / 3) for K in range(1, 21)]
    expect = next(K for K in range(pp.misbehaviour_min_sightings, 21) if q[K - 1] > mon.threshold)
    first = None
    for K in range(1, 21):
        t = 0.1 * (K - 1)
        for o in ("cv1", "cv2", "cv3"):
            rep = (
                np.array(["cv9", o]),
                np.array([[0.0, 0.0, 0.0], [30.0, 30.0, 0.0]]),
                np.tile(p0 * np.eye(3), (2, 1, 1)),
            )
            p = np.array([[*b, 0.0]])
            errors = ((a * np.eye(3))[None], (beta * np.eye(3))[None], np.zeros((1, 3, 3)))
            mon.observe(o, t, p, ((a + beta) * np.eye(3))[None], np.array([2]), rep, errors)
        if "cv9" in mon.update(t) and first is None:
            first = K
    assert first == expect, (first, expect, q)
    assert list(mon.flagged) == ["cv9"]
    assert mon.tests["cv9"].q == pytest.approx(q[-1])
    assert mon.disputed == set()  # no single view is off by more than its errors allow: together they are
