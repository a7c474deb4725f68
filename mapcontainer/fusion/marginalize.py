"""Track priors of the host's factor graph (:mod:`.graph`): what a track's dropped states knew, as Gaussian
information over [s, b_1, ..., b_m], and the marginalization that makes and updates them.

A Gaussian prior on the first state of each track and the persistent errors b_v of the vehicles whose
detections it holds (:class:`TrackPrior`, one linear factor, :func:`prior_factor`): at birth a zero-mean
velocity prior (speed_prior_*) and a 1 km position regulariser (:func:`birth_prior`). When a track's
first state is older than the lag (or the window), what it knew — its prior and its detections, moved to
the map frame with the observers' reported poses z_k, whose errors are J L (b_v + n_k) in the graph's own
model (:func:`detection_information`) — is carried through the constant-velocity model onto the next
state, the first state marginalised out (:func:`summarize_first`): information over [s, b_v...]. Its
dependence on b_v fades with the persistence time (b is first-order Gauss-Markov,
``pose_error_persistence_s``), so old detections do not stay tied to a vehicle's current error; b_v
leaves the prior when the vehicle leaves the graph (:func:`forget_bias`). A detection older than its
track's first state (a late message) goes into the prior the same way, retrodicted (:func:`fold`). What
this neglects: the frame-to-frame part n_k of the folded detections' pose errors is treated as
independent of the frames still in the window, and so of other tracks' priors (the model-world test
measures the cost: ANEES 3.4 vs 3.15 with the whole window in the graph).

Everything here is numpy on explicit arguments; which states, detections and keys are involved is the
graph's bookkeeping.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from .motion import cv_model
from .params import FusionParams

__all__ = [
    "TrackPrior",
    "batches",
    "birth_prior",
    "detection_information",
    "fold",
    "forget_bias",
    "in_map",
    "jacobian_factor",
    "marginalize",
    "prior_factor",
    "sqrt_information",
    "summarize_first",
]


@dataclass
class TrackPrior:
    """What a track's dropped states knew, as Gaussian information over y = [s, b_1, ..., b_m]: the track
    state it is on and the persistent self-localization errors b_v (whitened, the graph's ``b`` keys) of
    the vehicles ``vids`` whose detections it holds; its negative log-density is y^T info y / 2 - eta^T y.
    Keeping b_v lets the graph know that these detections err together with the vehicle's frames still
    in the window (and with other tracks' priors), instead of counting them as independent evidence."""

    tkey: int  # time key of the state it is on
    info: np.ndarray  # (6 + 6m, 6 + 6m)
    eta: np.ndarray  # (6 + 6m,)
    vids: tuple[str, ...] = ()

    def marginal(self, a: float) -> tuple[np.ndarray, np.ndarray]:
        """Mean and covariance of s with every b_v at its prior N(0, a I)."""
        info = self.info.copy()
        idx = np.arange(6, len(info))
        info[idx, idx] += 1.0 / a if len(idx) else 0.0
        cov = np.linalg.inv(info)
        return (cov @ self.eta)[:6], cov[:6, :6]


def birth_prior(tkey: int, p0: np.ndarray, speed_sigma: float) -> TrackPrior:
    """A new track's prior on its state s = [p, v] at time key ``tkey``: p ~ N(p0, (1 km)^2 I) (a
    regulariser), horizontal velocity ~ N(0, speed_sigma^2), vertical ~ N(0, 0.5^2)."""
    mean = np.concatenate([p0, np.zeros(3)])
    info = np.diag(1.0 / np.array([1e6, 1e6, 1e6, speed_sigma**2, speed_sigma**2, 0.25]))
    return TrackPrior(tkey, info, info @ mean)


def marginalize(info: np.ndarray, eta: np.ndarray, out: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian information (info, eta) with the variables at indices ``out`` marginalised (Schur
    complement): info_kk - info_ko info_oo^-1 info_ok, eta_k - info_ko info_oo^-1 eta_o; the others keep
    their order."""
    keep = np.setdiff1d(np.arange(len(info)), out)
    K = np.linalg.solve(info[np.ix_(out, out)], np.column_stack([info[np.ix_(out, keep)], eta[out]]))
    new_info = info[np.ix_(keep, keep)] - info[np.ix_(keep, out)] @ K[:, :-1]
    return 0.5 * (new_info + new_info.T), eta[keep] - info[np.ix_(keep, out)] @ K[:, -1]


def sqrt_information(info: np.ndarray, eta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A, r) with A^T A = info and A^T r = eta for stacks (N, n, n), (N, n): A = L^T of the Cholesky
    factor. A track prior's information is only semi-definite in the persistent errors b that its
    detections do not constrain; a ridge of 1e-9 of its largest diagonal (a prior of sigma ~ 3e4 times
    the tightest) makes it definite without changing anything measurable."""
    ridge = 1e-9 * np.max(np.diagonal(info, axis1=1, axis2=2), axis=1)
    L = np.linalg.cholesky(info + ridge[:, None, None] * np.eye(info.shape[1]))
    r = np.linalg.solve(L, eta[..., None])[..., 0]
    return L.transpose(0, 2, 1), r


_UNIT: dict[int, gtsam.noiseModel.Unit] = {}  # unit noise models by dimension (jacobian_factor)


def batches(sizes: np.ndarray, batch_units: float) -> list[tuple[int, np.ndarray]]:
    """Track priors grouped for batched summaries: (number of vehicles m to pad to, indices), largest m
    first. A batch costs about forty numpy calls whatever its size; a prior in it costs ~ (6 + 6 m)^3
    (its inverses and products). A smaller size joins the batch above when padding its priors costs less
    than ``batch_units`` (what one more batch costs, in those units)."""
    out: list[tuple[int, np.ndarray]] = []
    for m in np.unique(sizes)[::-1]:
        idx = np.flatnonzero(sizes == m)
        if out and len(idx) * ((6 + 6 * out[-1][0]) ** 3 - (6 + 6 * m) ** 3) < batch_units:
            out[-1] = (out[-1][0], np.concatenate([out[-1][1], idx]))
        else:
            out.append((int(m), idx))
    return out


def jacobian_factor(keys: list[int], A: np.ndarray, b: np.ndarray) -> gtsam.JacobianFactor:
    """||A y - b||^2 / 2 over the 6-D variables ``keys`` (A's columns in that order), any number of keys
    (the Python JacobianFactor constructors take at most three; a GaussianConditional takes a list of
    terms and is a JacobianFactor, at twice the cost)."""
    blocks = [A[:, 6 * i : 6 * i + 6] for i in range(len(keys))]
    unit = _UNIT.get(len(b))
    if unit is None:
        unit = _UNIT[len(b)] = gtsam.noiseModel.Unit.Create(len(b))
    if len(keys) <= 3:
        return gtsam.JacobianFactor(*[x for kb in zip(keys, blocks, strict=True) for x in kb], b, unit)
    return gtsam.JacobianFactor(gtsam.GaussianConditional(list(zip(keys, blocks, strict=True)), 1, b, unit))


def prior_factor(
    prior: TrackPrior, keys: list[int], values: gtsam.Values, sqrt: tuple | None = None, y0: np.ndarray | None = None
) -> gtsam.LinearContainerFactor:
    """The prior as a linear factor ||A y - r||^2 / 2 with A^T A = info and A^T r = eta over ``keys`` (the
    track state's, then the vehicles' ``b`` keys in ``prior.vids`` order), about ``values``: y = y0 + dy,
    ||A dy - (r - A y0)||^2 / 2. ``sqrt``: (A, r) if the caller has them (:func:`sqrt_information`);
    ``y0``: the keys' values stacked, if the caller has them."""
    A, r = sqrt_information(prior.info[None], prior.eta[None]) if sqrt is None else sqrt
    A, r = A.reshape(len(prior.eta), -1), r.reshape(-1)
    if y0 is None:
        y0 = np.concatenate([values.atVector(k) for k in keys])
    jf = jacobian_factor(keys, A, r - A @ y0)
    return gtsam.LinearContainerFactor(jf, values)


def in_map(M: np.ndarray, z: np.ndarray, Sz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Detections z (N, 3) with covariances Sz (N, 3, 3) moved to the map frame with their observers'
    reported poses M (N, 4, 4) = (R, t): m = R z + t, the detector's covariance R S_z R^T and the
    Jacobian J = d m / d xi = [-R [z]x, R] of the observer's error xi (Pose3 tangent [rotation,
    translation]). The reported pose, not the estimate: the graph models the true pose as
    z_k (+) L (b + n_k) (L L^T = S_xi, the reported pose covariance in that tangent), so the errors of m
    are J L b (persistent, kept as b) and J L n_k (independent). Vectorised."""
    R, t = M[:, :3, :3], M[:, :3, 3]
    zx = np.zeros((len(z), 3, 3))
    zx[:, 0, 1], zx[:, 0, 2], zx[:, 1, 2] = -z[:, 2], z[:, 1], -z[:, 0]
    zx[:, 1, 0], zx[:, 2, 0], zx[:, 2, 1] = z[:, 2], -z[:, 1], z[:, 0]
    J = np.concatenate([-R @ zx, R], axis=2)
    return np.einsum("nij,nj->ni", R, z) + t, R @ Sz @ R.transpose(0, 2, 1), J


def detection_information(
    M: np.ndarray,
    L_xi: np.ndarray,
    z: np.ndarray,
    Sz: np.ndarray,
    persist: np.ndarray,
    p0: np.ndarray,
    params: FusionParams,
    extra: np.ndarray | None = None,
    age: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Information of detections (:func:`in_map`'s arguments; L_xi (N, 6, 6) their observers' L, with
    L L^T = S_xi) about [s, b_v] (s the state whose position they measure, directly or through H; b_v the
    observer's persistent error): r = p - J L b_v - m ~
    N(0, C / w), C = R S_z R^T + (1 - a) J S_xi J^T (+ ``extra``), w the Huber weight at the estimate p0
    (N, 3). ``persist`` (N, 2): each observer's (a, tau), its persistent fraction and that part's
    correlation time (the graph's ``FusionGraph.persistence``); where a = 0 (an observer without b) C has the whole
    J S_xi J^T and b_v is not involved. Returns (S = w C^-1 (N, 3, 3), G = -J L (N, 3, 6), m (N, 3)).
    ``age``: the detections are that much older than the b they are tied to, b(t - age) = rho b(t) + w,
    rho = exp(-age / tau) (see :func:`summarize_first`): G = -rho J L and a (1 - rho^2) J S_xi J^T more
    noise."""
    a, tau = persist[:, 0], persist[:, 1]
    m, Cz, J = in_map(M, z, Sz)
    JL = J @ L_xi
    Cpose = JL @ JL.transpose(0, 2, 1)
    if extra is not None:
        Cz = Cz + extra
    r = m - p0
    dist = np.sqrt(np.einsum("ni,nij,nj->n", r, np.linalg.inv(Cz + Cpose), r))
    k = params.huber_k
    w = np.ones(len(z)) if k is None else np.minimum(1.0, k / np.maximum(dist, 1e-12))
    rho = np.exp(-abs(age) / tau)
    C = Cz + (1.0 - a * rho**2)[:, None, None] * Cpose
    S = w[:, None, None] * np.linalg.inv(C)
    return S, -rho[:, None, None] * JL, m


def summarize_first(
    priors: list[TrackPrior],
    next_tkeys: list[int],
    dt: np.ndarray,
    q: np.ndarray,
    owner: np.ndarray,
    dets: tuple | None,
    persist: dict[str, tuple[float, float]],
    batch_units: float,
) -> list[tuple[int, TrackPrior, tuple[np.ndarray, np.ndarray]]]:
    """Each track's first state (its prior ``priors[i]`` and its detections) folded into a prior on its
    second state, ``dt[i]`` later (time key ``next_tkeys[i]``, accel PSD ``q[i]`` (3,)).

    The prior (information over [s0, b...]) plus the first state's detections (``dets``: (vid or None,
    S, G, m) per detection as :func:`detection_information` gives them, ``owner`` the prior each belongs
    to; None if there are none) plus the constant-velocity model s1 = F s0 + w, w ~ N(0, Q), with s0
    marginalised out (Schur complement); then the persistent errors age by dt: b_v(t0) = rho_v b_v(t1) + w,
    rho_v = exp(-dt / tau_v), w ~ N(0, a_v (1 - rho_v^2) I), b(t0) marginalised out (``persist``: vid ->
    (a_v, tau_v), the graph's ``FusionGraph.persistence``), so that old detections do not stay tied to a
    vehicle's current error. The result is information over [s1, b(t1)...], the prior's vehicles and then
    those of its detections.
    Vectorised in batches (:func:`batches`): a prior padded with zero information over vehicles it does
    not hold stays zero and uncoupled there through every step, and the leading block of a Cholesky
    factor is the factor of the leading block, so each prior's slice of its batch is its own result.

    Returns (index, new prior, its :func:`sqrt_information`) per track, batch by batch.
    """
    vid_lists = [list(p.vids) for p in priors]
    slot = np.full(len(owner), -1)
    if dets is not None:
        dvids, S, G, m = dets
        for n, (i, v) in enumerate(zip(owner, dvids, strict=True)):
            if v is not None:
                if v not in vid_lists[i]:
                    vid_lists[i].append(v)
                slot[n] = vid_lists[i].index(v)
    F, Q = cv_model(dt, q)
    Qi = np.linalg.inv(Q)
    if dets is not None:  # each detection's terms: [s, b_v] blocks of S, S G, G^T S G and of eta
        Sm = np.einsum("nij,nj->ni", S, m)
        SG = S @ G
        GSG = G.transpose(0, 2, 1) @ SG
        SGm = np.einsum("nji,nj->ni", SG, m)
        bcol = 6 + 6 * slot[:, None] + np.arange(6)  # the columns of its b_v (where slot >= 0)
        i3 = np.arange(3)
    out = []
    for mm, idx in batches(np.array([len(v) for v in vid_lists]), batch_units):
        g, n = len(idx), 6 + 6 * mm
        info, eta = np.zeros((g, n, n)), np.zeros((g, n))
        for r, i in enumerate(idx):
            k = len(priors[i].info)
            info[r, :k, :k], eta[r, :k] = priors[i].info, priors[i].eta
        if dets is not None:
            row_of = np.full(len(priors), -1)
            row_of[idx] = np.arange(g)
            rows = row_of[owner]
            mine = rows >= 0
            rr = rows[mine]
            np.add.at(info, (rr, slice(0, 3), slice(0, 3)), S[mine])
            np.add.at(eta, (rr, slice(0, 3)), Sm[mine])
            hb = mine & (slot >= 0)
            rb, cb = rows[hb][:, None, None], bcol[hb]
            np.add.at(info, (rb, i3[:, None], cb[:, None, :]), SG[hb])
            np.add.at(info, (rb, cb[:, :, None], i3), SG[hb].transpose(0, 2, 1))
            np.add.at(info, (rb, cb[:, :, None], cb[:, None, :]), GSG[hb])
            np.add.at(eta, (rb[:, 0], cb), SGm[hb])
        # motion s1 = F s0 + w and s0 marginalised: info over [s1, b]
        QF = Qi[idx] @ F[idx]
        K0 = np.linalg.inv(info[:, :6, :6] + F[idx].transpose(0, 2, 1) @ QF)
        QFK = QF @ K0
        new, new_eta = np.empty((g, n, n)), np.empty((g, n))
        new[:, :6, :6] = Qi[idx] - QFK @ QF.transpose(0, 2, 1)
        new_eta[:, :6] = np.einsum("nij,nj->ni", QFK, eta[:, :6])
        if mm:
            Isb = info[:, :6, 6:]
            new[:, :6, 6:] = QFK @ Isb
            new[:, 6:, :6] = new[:, :6, 6:].transpose(0, 2, 1)
            new[:, 6:, 6:] = info[:, 6:, 6:] - Isb.transpose(0, 2, 1) @ K0 @ Isb
            new_eta[:, 6:] = eta[:, 6:] - np.einsum("nji,njk,nk->ni", Isb, K0, eta[:, :6])
            # b(t0) = R b(t1) + w, w ~ N(0, D^-1), b(t0) marginalised; R, D diagonal (per vehicle: rho_v,
            # 1 / (a_v (1 - rho_v^2)); padding (a, tau) = (1, 1): zero information stays zero)
            at = np.ones((g, mm, 2))
            for r, i in enumerate(idx):
                for j, v in enumerate(vid_lists[i]):
                    at[r, j] = persist[v]
            rho = np.repeat(np.exp(-np.abs(dt[idx])[:, None] / at[..., 1]), 6, axis=1)  # (g, 6 mm)
            omega = np.repeat(1.0 / at[..., 0], 6, axis=1) / (1.0 - rho**2)
            Mi = np.linalg.inv(new[:, 6:, 6:] + omega[:, :, None] * np.eye(6 * mm))
            Lsb, eb = new[:, :6, 6:].copy(), new_eta[:, 6:].copy()
            LM = Lsb @ Mi
            MiD = Mi * omega[:, None, :]
            new[:, :6, :6] -= LM @ Lsb.transpose(0, 2, 1)
            new[:, :6, 6:] = LM * (omega * rho)[:, None, :]
            new[:, 6:, :6] = new[:, :6, 6:].transpose(0, 2, 1)
            DMiD = omega[:, :, None] * MiD
            new[:, 6:, 6:] = (rho[:, :, None] * rho[:, None, :]) * (omega[:, :, None] * np.eye(6 * mm) - DMiD)
            new_eta[:, :6] -= np.einsum("nij,nj->ni", LM, eb)
            new_eta[:, 6:] = (rho * omega) * np.einsum("nij,nj->ni", Mi, eb)
        new = 0.5 * (new + new.transpose(0, 2, 1))
        A, rhs = sqrt_information(new, new_eta)
        for r, i in enumerate(idx):
            k = 6 + 6 * len(vid_lists[i])
            prior = TrackPrior(next_tkeys[i], new[r, :k, :k].copy(), new_eta[r, :k].copy(), tuple(vid_lists[i]))
            out.append((int(i), prior, (A[r, :k, :k], rhs[r, :k])))
    return out


def fold(prior: TrackPrior, H: np.ndarray, v: str | None, S: np.ndarray, G: np.ndarray, m: np.ndarray) -> TrackPrior:
    """The prior with one detection's information added (:func:`detection_information`: S (3, 3), G (3, 6),
    m (3,), v the observer whose b it involves or None) measuring H s (H (3, 6)): info += H^T S H,
    eta += H^T S m over s; with v, the [s, b_v] cross terms H^T S G, G^T S G and eta_b += G^T S m (b_v
    appended to the prior's vehicles if new)."""
    vids = list(prior.vids)
    n = len(prior.info)
    if v is not None and v not in vids:
        vids.append(v)
    info, eta = np.zeros((6 + 6 * len(vids),) * 2), np.zeros(6 + 6 * len(vids))
    info[:n, :n], eta[:n] = prior.info, prior.eta
    HS = H.T @ S
    info[:6, :6] += HS @ H
    eta[:6] += HS @ m
    if v is not None:
        b = slice(6 + 6 * vids.index(v), 12 + 6 * vids.index(v))
        info[:6, b] += HS @ G
        info[b, :6] += G.T @ S @ H
        info[b, b] += G.T @ S @ G
        eta[b] += G.T @ S @ m
    return TrackPrior(prior.tkey, info, eta, tuple(vids))


def forget_bias(prior: TrackPrior, vid: str, a: float) -> TrackPrior:
    """The prior with vehicle ``vid``'s persistent error b_v (in ``prior.vids``) marginalised out at its
    prior N(0, a I)."""
    j = 6 + 6 * prior.vids.index(vid)
    info = prior.info.copy()
    info[j : j + 6, j : j + 6] += np.eye(6) / a
    new_info, new_eta = marginalize(info, prior.eta, np.arange(j, j + 6))
    vids = tuple(v for v in prior.vids if v != vid)
    return TrackPrior(prior.tkey, new_info, new_eta, vids)
