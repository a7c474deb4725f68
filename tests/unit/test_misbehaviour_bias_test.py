"""The misbehaviour monitor's bias test against closed forms: its threshold from the stated false-alarm rate,
the views and the combined estimate against a dense least squares, its false-alarm and detection probabilities
on synthetic Gaussian sightings drawn from the stated errors, and the frame at which a constant bias is
flagged."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2, ncx2

from mapcontainer.fusion import FusionParams
from mapcontainer.fusion.misbehaviour import MisbehaviourMonitor, Sighting, View, network_test, view_of

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


def test_observers_that_know_where_they_are_reduce_the_network_test_to_the_least_squares_of_the_views() -> None:
    """Observers stating (almost) no error: b^ = P^ sum C^-1 y, P^ = (sum C^-1)^-1 + K (the seen-as error every
    view shares does not average over them), q = b^T (P0 + P^)^-1 b^, r = sum (y - b^)^T C^-1 (y - b^)."""
    rng = np.random.default_rng(8)
    views, stated = {}, {"cv9": np.array([[0.05, 0.01], [0.01, 0.03]])}
    K = 0.02 * I2
    for o in ("cv1", "cv2", "cv3"):
        L = rng.normal(0.0, 0.3, (2, 2))
        views[(o, "cv9")] = View(rng.normal(0.0, 1.0, 2), L @ L.T + 0.05 * I2, K, 0.0)
        stated[o] = 1e-12 * I2
    test = network_test(views, stated, "cv9")
    G = [np.linalg.inv(v.C) for v in views.values()]
    P = np.linalg.inv(sum(G))
    b = P @ sum(g @ v.y for g, v in zip(G, views.values(), strict=True))
    assert test.b == pytest.approx(b, abs=1e-6) and test.P == pytest.approx(P + K, abs=1e-6) and test.n == 3
    assert test.q == pytest.approx(b @ np.linalg.solve(stated["cv9"] + P + K, b), rel=1e-5)
    assert test.r == pytest.approx(sum((v.y - b) @ g @ (v.y - b) for g, v in zip(G, views.values(), strict=True)))


def _draw(rng, bias, p0: float, a: float, beta: float, k: int) -> tuple[dict, dict]:
    """Views drawn from the errors the test assumes: cv9 off by b ~ N(0, p0 I) (honest, ``bias`` None) or by
    ``bias``, seen by cv1 and cv2 and seeing cv3, every other vehicle off by N(0, p0 I); each view from ``k``
    sightings with white noise N(0, a I) and a repeated error N(0, beta I) (no seen-as error)."""
    b = {x: rng.normal(0.0, np.sqrt(p0), 2) for x in ("cv1", "cv2", "cv3", "cv9")}
    if bias is not None:
        b["cv9"] = np.asarray(bias, float)
    views = {}
    for o, v in (("cv1", "cv9"), ("cv2", "cv9"), ("cv9", "cv3")):
        d = b[v] - b[o] + rng.normal(0.0, np.sqrt(beta), 2) + rng.normal(0.0, np.sqrt(a), (k, 2))
        z = np.zeros((2, 2))
        ss = [Sighting(0.0, o, d[i], a * I2, beta * I2, z, 1.0, np.zeros(2), I2) for i in range(k)]
        views[(o, v)] = view_of(ss, 2 * p0 * I2)
    return views, {x: p0 * I2 for x in b}


def test_on_gaussian_sightings_from_the_stated_errors_the_false_alarm_and_detection_rates_are_the_closed_forms() -> (
    None
):
    """Honest (every b ~ N(0, P0)): q ~ chi2(2), so it exceeds its 1 - alpha quantile with probability alpha.
    Biased by a fixed b, with every covariance isotropic, b^ ~ N(b, p I) (p = P^), so q (p0 + p) / p ~
    noncentral chi2(2, |b|^2 / p): the detection probability is its tail."""
    rng = np.random.default_rng(90)
    p0, a, beta, k, alpha, runs = 0.02, 0.09, 0.01, 6, 0.05, 2000
    h = chi2.isf(alpha, 2)
    honest = [network_test(*_draw(rng, None, p0, a, beta, k), "cv9") for _ in range(runs)]
    tol = 4.0 * np.sqrt(alpha * (1 - alpha) / runs)
    assert np.mean([t.q > h for t in honest]) == pytest.approx(alpha, abs=tol)
    p = float(honest[0].P[0, 0])
    assert honest[0].P == pytest.approx(p * I2)
    for b in ((0.4, 0.0), (0.0, 0.6)):
        power = float(ncx2.sf(h * (p0 + p) / p, 2, np.dot(b, b) / p))
        biased = [network_test(*_draw(rng, b, p0, a, beta, k), "cv9") for _ in range(runs)]
        tol = 4.0 * np.sqrt(power * (1 - power) / runs) + 1e-3
        assert np.mean([t.q > h for t in biased]) == pytest.approx(power, abs=tol), b


def test_a_constant_bias_is_flagged_at_the_frame_the_closed_form_says() -> None:
    """Three observers, each stating the error p0 I, see cv9 (the same) 1 m off from t = 0, one noise-free
    sighting each per frame (white a I, repeated beta I). After K frames every view is y = b with
    C = (a / K + beta) I; with each observer's own offset b_O ~ N(0, p0 I) in its view alone, b^ = b,
    P^ = (C + p0 I) / 3 and q_K = |b|^2 / (p0 + (a / K + beta + p0) / 3): flagged at the first
    K >= min_sightings with q_K above the threshold, and not before; nobody else."""
    pp = FusionParams()
    p0, a, beta = 0.01, 0.5, 0.01
    mon = MisbehaviourMonitor(pp)
    b = np.array([0.0, 1.0])
    q = [np.dot(b, b) / (p0 + (a / K + beta + p0) / 3) for K in range(1, 21)]
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
    assert mon.disputed == set()  # no single view is off by more than the errors allow: together they are
