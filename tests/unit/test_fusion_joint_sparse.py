"""The centralized host's updates touch only what they must (mapcontainer.fusion.joint, issue 36): each is
checked against the dense textbook form it replaced (a full-width H and Joseph's form, every track's F P F^T
one block at a time), and a seeded scene run by both gives the same fused states."""

import numpy as np
import pytest

from mapcontainer import geometry as geo
from mapcontainer.fusion import FusionParams
from mapcontainer.fusion.joint import JointHost
from mapcontainer.fusion.motion import accel_psd, cv_model
from mapcontainer.fusion.symupdate import sym_rank_update
from mapcontainer.hdmap.generator import generate_map
from mapcontainer.sim import load_scenario


class DenseJointHost(JointHost):
    """The joint host with the dense updates of before issue 36 (full-width H, Joseph's form written out,
    the conditioning on index arrays, one track predicted at a time): the oracle of the sparse ones."""

    def _ekf_update(self, obs_key, rows, free=None):
        if not rows:
            return
        n, m = len(self.mu), 3 * len(rows)
        so = self._sl(obs_key)
        x_o = self.mu[so]
        R, dR_r, dR_p, dR_y = geo.rpy_to_matrix_jac(*x_o[3:6])
        H, r, Rn = np.zeros((m, n)), np.zeros(m), np.zeros((m, m))
        for k, (tkey, z, cov) in enumerate(rows):
            st = self._sl(tkey)
            d = self.mu[st][:3] - x_o[:3]
            i = slice(3 * k, 3 * k + 3)
            r[i] = z - R.T @ d
            H[i, so.start : so.start + 3] = -R.T
            H[i, so.start + 3], H[i, so.start + 4], H[i, so.start + 5] = dR_r.T @ d, dR_p.T @ d, dR_y.T @ d
            H[i, st.start : st.start + 3] = R.T
            Rn[i, i] = cov
        PHt = self.P @ H.T
        S = H @ PHt + Rn
        hk = self.params.huber_k
        for j in range(len(rows)):
            i = slice(3 * j, 3 * j + 3)
            d = float(np.sqrt(r[i] @ np.linalg.solve(S[i, i], r[i])))
            if hk is not None and d > hk:
                S[i, i] += (d / hk - 1.0) * Rn[i, i]
        K = np.linalg.solve(S, PHt.T).T
        for idx in self._considered(free):
            K[idx] = 0.0
        self.mu += K @ r
        KHP = K @ PHt.T
        P = self.P - KHP - KHP.T + K @ S @ K.T
        self.P = 0.5 * (P + P.T)
        self._wrap_yaws()

    def _condition(self, key, F, y_pred, P_pred, y_post, P_post):
        s = self._sl(key)
        o = np.setdiff1d(np.arange(len(self.mu)), np.arange(s.start, s.stop))
        P = self.P
        P_vo = F @ P[s][:, o]
        self.mu[s] = y_post
        if len(o):
            K = np.linalg.solve(P_pred, P_vo).T
            d = y_post - y_pred
            d[5] = geo.wrap_angle(d[5])
            self.mu[o] += K @ d
            P[np.ix_(o, o)] += K @ (P_post - P_pred) @ K.T
            P_ov = K @ P_post
            P[np.ix_(o, np.arange(s.start, s.stop))] = P_ov
            P[s, o] = P_ov.T
        P[s, s] = 0.5 * (P_post + P_post.T)
        self._wrap_yaws()
        return True

    def _predict_tracks(self, t):
        for key in self._keys:
            if key[0] != "o" or self._t[key] == t:
                continue
            tr = self.tracker.by_id(key[1])
            F, Q = cv_model(t - self._t[key], accel_psd(self.params, tr.cls if tr else 0))
            s = self._sl(key)
            self.mu[s] = F @ self.mu[s]
            self.P[s, :] = F @ self.P[s, :]
            self.P[:, s] = self.P[:, s] @ F.T
            self.P[s, s] += Q
            self._t[key] = t


@pytest.fixture(scope="module")
def hdmap():
    return generate_map(load_scenario("overlap").map)


def _state(hosts, rng, blocks):
    """The same random joint Gaussian over ``blocks`` in every host; vehicles 2 m, tracks 10-40 m apart."""
    n = sum(10 if k[0] == "v" else 6 for k in blocks)
    A = rng.normal(size=(n, n))
    P = A @ A.T / n + 0.1 * np.eye(n)
    mu = rng.normal(size=n) * 0.1
    for h in hosts:
        h.mu, h.P, h._keys, h._t = np.zeros(0), np.zeros((0, 0)), [], {}
        h._reindex()
        for key in blocks:
            h._set_block(key, np.zeros(h._size(key)), np.eye(h._size(key)), 0.0)
        h.mu, h.P = mu.copy(), P.copy()
        for j, key in enumerate(k for k in blocks if k[0] == "o"):
            h.mu[h._sl(key)][:3] += [10.0 + 5 * j, -8.0 + 3 * j, 0.5]
    return mu, P


def _pair(hdmap):
    return JointHost(hdmap, FusionParams(), "f", "host"), DenseJointHost(hdmap, FusionParams(), "f", "host")


def test_symmetric_rank_update_is_the_dense_one():
    rng = np.random.default_rng(1)
    for n, m in ((1, 1), (7, 3), (128, 5), (300, 12)):  # below, at and across the mirrored block's size
        A = rng.normal(size=(n, n))
        P = A @ A.T
        P0 = P.copy()
        U, V = rng.normal(size=(n, m)), rng.normal(size=(n, m))
        out = sym_rank_update(P, U, V)
        np.testing.assert_allclose(out, P - U @ V.T - V @ U.T, atol=1e-10)
        np.testing.assert_array_equal(out, out.T)
        np.testing.assert_array_equal(P, P0)  # P untouched
    with pytest.raises(ValueError, match="sym_rank_update"):
        sym_rank_update(np.eye(3), np.zeros((3, 2)), np.zeros((3, 1)))


def test_detection_update_is_the_dense_joseph_update(hdmap):
    """Several detections of one observer (one of them far off: Huber at play), a cross-observation of
    another vehicle, a consider state (a vehicle in fallback): the same mean and covariance as the full-width
    H and Joseph's form."""
    from types import SimpleNamespace

    rng = np.random.default_rng(21)
    sparse, dense = _pair(hdmap)
    blocks = [("v", "a"), ("o", 1), ("v", "b"), ("o", 2), ("o", 3), ("v", "c"), ("o", 4)]
    _state((sparse, dense), rng, blocks)
    for h in (sparse, dense):
        h._results = {
            v: SimpleNamespace(mode=m) for v, m in (("a", "map_matching"), ("b", "fallback"), ("c", "map_matching"))
        }

    def rows(h, obs, targets, off):
        x = h.mu[h._sl(("v", obs))]
        R = geo.rpy_to_matrix(*x[3:6])
        out = []
        for tkey, e in zip(targets, off, strict=True):
            z = R.T @ (h.mu[h._sl(tkey)][:3] - x[:3]) + e
            out.append((tkey, z, np.diag([0.04, 0.09, 0.01])))
        return out

    off = [np.array([0.1, -0.05, 0.0]), np.array([3.0, 2.0, 0.0]), np.zeros(3)]  # the second: Huber
    for h in (sparse, dense):
        h._ekf_update(("v", "a"), rows(h, "a", [("o", 1), ("o", 2), ("v", "c")], off))
        h._ekf_update(("v", "b"), rows(h, "b", [("o", 3)], [np.array([0.2, 0.1, 0.0])]))  # b considered
        h._ekf_update(("v", "b"), rows(h, "b", [("o", 4)], [np.zeros(3)]), free=("v", "b"))
    np.testing.assert_allclose(sparse.mu, dense.mu, atol=1e-10)
    np.testing.assert_allclose(sparse.P, dense.P, atol=1e-10)
    assert sparse.stats()["numerical_failure"] == 0


def test_conditioning_and_prediction_are_the_dense_ones(hdmap):
    rng = np.random.default_rng(23)
    sparse, dense = _pair(hdmap)
    blocks = [("o", 1), ("v", "a"), ("o", 2), ("v", "b"), ("o", 3)]
    _state((sparse, dense), rng, blocks)
    F = np.eye(10) + 0.05 * rng.normal(size=(10, 10))
    A = rng.normal(size=(10, 10))
    P_pred = A @ A.T / 10 + 0.1 * np.eye(10)
    y_pred = rng.normal(size=10) * 0.1
    P_post = 0.5 * P_pred
    y_post = y_pred + 0.05 * rng.normal(size=10)
    for h in (sparse, dense):
        assert h._condition(("v", "b"), F, y_pred, P_pred, y_post, P_post)
        h._t[("o", 2)] = 0.05  # tracks at two different times: two lags
        h._predict_tracks(0.1)
    np.testing.assert_allclose(sparse.mu, dense.mu, atol=1e-10)
    np.testing.assert_allclose(sparse.P, dense.P, atol=1e-10)
    assert all(sparse._t[k] == 0.1 for k in sparse._keys if k[0] == "o")


def test_an_update_that_fails_numerically_leaves_the_state_as_it_was(hdmap):
    rng = np.random.default_rng(25)
    host, _ = _pair(hdmap)
    _state((host,), rng, [("v", "a"), ("o", 1)])
    mu, P = host.mu.copy(), host.P.copy()
    host._ekf_update(("v", "a"), [(("o", 1), np.array([np.nan, 0.0, 0.0]), np.eye(3))])
    host._condition(("v", "a"), np.eye(10), np.zeros(10), np.zeros((10, 10)), np.zeros(10), np.eye(10))
    np.testing.assert_array_equal(host.mu, mu)
    np.testing.assert_array_equal(host.P, P)
    assert host.stats()["numerical_failure"] == 2


@pytest.mark.slow
def test_a_seeded_scene_fuses_as_the_dense_host(hdmap):
    """Raw observations of three vehicles (overlap, development seed 7, 4 s) through both hosts: every
    fused vehicle and object agrees (the state differs by rounding only)."""
    from mapcontainer.fusion.jointbench import record_raw

    rec = record_raw(3, seed=7, duration_s=4.0, scenario="overlap")
    hosts = [
        cls(rec.hdmap, FusionParams(), "bench", "host", known_senders=set(rec.vehicles))
        for cls in (JointHost, DenseJointHost)
    ]
    objects = 0
    for t, payloads, _ in rec.frames:
        out = []
        for h in hosts:
            for b in payloads:
                h.ingest(b, t)
            out.append(h.fuse(t))
        a, b = out
        assert a.vehicle_ids == b.vehicle_ids
        np.testing.assert_allclose(a.vehicle_pose, b.vehicle_pose, atol=1e-6)
        np.testing.assert_array_equal(a.object_id, b.object_id)
        np.testing.assert_allclose(a.object_p_map, b.object_p_map, atol=1e-4)  # float32 on the wire
        objects += len(a.object_id)
    assert objects > 0
    assert hosts[0]._counts["detections"] > 0
