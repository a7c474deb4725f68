"""The downlink, host side: what the other vehicles know about each vehicle's pose, its own share removed.

The host fuses every vehicle's self-localization with what the others see of it. Sent back as it is, that
estimate would hand a vehicle its own information again: fused with the vehicle's estimate it would be counted
twice, and the next prior would carry it back to the host (rumour). The topology is a star (vehicle -> host ->
vehicle), so the exact remedy is a channel filter per link: the host knows exactly what the vehicle itself sent
and takes it out.

**Which window.** Not the host's whole window: its object tracks carry the vehicles' own past. When a track's
first state leaves the lag it is folded into a prior with its detections placed by their observers' *reported*
poses, each frame's taken as independent evidence (:mod:`.fusion.marginalize`); but a reported pose is the
observer's filtered estimate, whose error persists for seconds. So a track a vehicle saw before is anchored
where that vehicle's own past estimates put it, with a confidence that grows with every frame, and the
vehicle's newest detection of it tells the host where the vehicle is -- from its own past (a vehicle that alone
sees two parked cars got a downlink of 0.2-0.4 m though nobody saw it, ``tests/unit/test_downlink.py``); the
others' persistent errors come back the same way, counted as independent. On development seed 11
(paper-suburban, 10 s, every error source off) the others' view from the whole window had an NIS against the
truth of 6.3-8.2 per vehicle (2 when consistent); from the window without the objects, 1.4-3.5. The host
cannot take that out after the fact (a track prior keeps no trace of whose poses it folded), so the others'
view is computed from the **window without the objects** (:func:`cross_localization`): every vehicle's prior
and motion and the cross-detections between connected vehicles, solved at the host's estimate (one
Gauss-Newton step; the host's own solution also holds the objects). Each cross-detection there counts as the
mean of its observer's detections of that vehicle does (the detector's persistent error does not average
out; the host's graph counts them as independent).

In that window a vehicle's own information is one factor: the prior on its newest frame (a filtered prior
holds everything the vehicle knows, so the graph keeps only the newest, :mod:`.fusion.graph`). Every other
factor (its motion, the others' detections of it, its detections of the others) is independent of the
vehicle's own estimate. For a unary Gaussian factor the posterior's information is the sum, so on the newest
frame's pose x (Pose3 tangent at the window's estimate, first order):

    Y_post = Y_own + Y_others,      Y_post * 0 = Y_own * d_own + Y_others * d_others

with Y = P^-1, d the mean's offset from the window's estimate (d_own = Log(T_post^-1 T_own)). Hence

    Y_others = Y_post - Y_own,      d_others = -Y_others^+ Y_own d_own          (:func:`remove_own`)

exact for a linear-Gaussian model (``tests/unit/test_downlink.py`` checks it against the posterior of the
others' measurements alone). Y_others is only positive semi-definite: the others see a position, rarely a
heading; so the message carries it as it is, in information form (PoseDownlink.pose_info, over the wire
pose's six numbers: Y_p = J^T Y_xi J with xi = J p, :mod:`.fusion.poses`), of which the message keeps
the marginal of the horizontal position (:func:`horizontal` says why). Eigenvalues below ``MIN_INFO``
(a 1-sigma of 100 m or rad) are set to zero, numerical noise of the subtraction; a vehicle whose horizontal
position the others know to no better than ``max_sigma_m`` (the information of the position given the rest)
gets no message at all (a vehicle nobody sees gets nothing).

Where the correlation is not known (the receiving vehicle's filter carries downlink information it was
seeded with) the vehicle fuses by covariance intersection: :mod:`.onboard`.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from schemas import PoseDownlink
from schemas.arrays import cov_to_upper

from .fusion.detections import linear_factors
from .fusion.hostcore import persistent_share
from .fusion.poses import tangent_jacobian, vector_from_pose3

__all__ = [
    "MAX_DOWNLINK_SIGMA_M",
    "MIN_INFO",
    "OthersOnly",
    "cross_localization",
    "downlink_messages",
    "horizontal",
    "others_only",
    "remove_own",
]

MAX_DOWNLINK_SIGMA_M = 5.0  # no message when the others know the vehicle's position to no better than this (1 sigma)
MIN_INFO = 1e-4  # information below this (a 1-sigma of 100 m or rad) is no information


@dataclass(frozen=True)
class OthersOnly:
    """What the others know about one vehicle's pose: ``mean`` (offset or pose), ``info`` (6x6 information
    matrix, positive semi-definite), ``rank`` its informed directions' count."""

    mean: np.ndarray
    info: np.ndarray
    rank: int

    def position_sigma_m(self) -> float:
        """The largest horizontal 1-sigma the others know the position to, the rest of the pose given (inf: none)."""
        w = np.linalg.eigvalsh(self.info[:2, :2])[0]
        return float(np.inf) if w <= MIN_INFO else float(1.0 / np.sqrt(w))


def remove_own(cov_host: np.ndarray, d_own: np.ndarray, cov_own: np.ndarray, min_info: float = MIN_INFO) -> OthersOnly:
    """The others' share of a posterior N(0, cov_host) (the mean is the origin of the coordinates) from which
    the factor N(d_own, cov_own) is removed, in information form (module docstring):

        Y_o = P_host^-1 - P_own^-1 (eigenvalues below ``min_info`` set to 0),  d_o = -Y_o^+ P_own^-1 d_own.

    Returns ``mean`` d_o (an offset from the posterior's mean) and ``info`` Y_o. ValueError on shapes or
    non-finite values."""
    P_h, P_o, d = (np.asarray(a, dtype=float) for a in (cov_host, cov_own, d_own))
    n = len(d)
    if P_h.shape != (n, n) or P_o.shape != (n, n):
        raise ValueError(f"covariances must be {n}x{n}, got {P_h.shape} and {P_o.shape}")
    if not (np.all(np.isfinite(P_h)) and np.all(np.isfinite(P_o)) and np.all(np.isfinite(d))):
        raise ValueError("remove_own needs finite covariances and offsets")
    Y_own = np.linalg.inv(P_o)
    Y = np.linalg.inv(P_h) - Y_own
    w, U = np.linalg.eigh(0.5 * (Y + Y.T))
    keep = w > min_info
    Uk, wk = U[:, keep], w[keep]
    d_o = -(Uk / wk) @ (Uk.T @ (Y_own @ d))  # the pseudo-inverse on the informed directions
    info = (Uk * wk) @ Uk.T
    return OthersOnly(d_o, 0.5 * (info + info.T), int(keep.sum()))


def others_only(T_host: gtsam.Pose3, cov_host_xi: np.ndarray, T_own: gtsam.Pose3, cov_own_xi: np.ndarray) -> OthersOnly:
    """:func:`remove_own` on a pose: the host's estimate ``T_host`` with its tangent covariance, the vehicle's
    own prior ``T_own`` with its own; returns the others' pose [x, y, z, roll, pitch, yaw] and its information
    over those six numbers (J^T Y_xi J, J = :func:`~.fusion.poses.tangent_jacobian` at that pose)."""
    d_own = gtsam.Pose3.Logmap(T_host.between(T_own))
    o = remove_own(cov_host_xi, d_own, cov_own_xi)
    T = T_host.compose(gtsam.Pose3.Expmap(o.mean))
    pose = vector_from_pose3(T)
    J = tangent_jacobian(pose)
    info = J.T @ o.info @ J
    return OthersOnly(pose, 0.5 * (info + info.T), o.rank)


def horizontal(o: OthersOnly) -> OthersOnly:
    """Only what the others know about the horizontal position: the marginal information of x, y (the generalised
    Schur complement Y_aa - Y_ab Y_bb^+ Y_ba, exact for a positive semi-definite Y), nothing about the rest.

    Why: the others see a vehicle's position; its heading reaches them only through chains of the others' and
    its own errors (bearings, the motion since). Measured when the others' view still came from the whole window
    (before :func:`cross_localization`): the full 6-D downlink's NIS against the truth averaged 2.6-6.2 per
    dimension on development seed 12 (urban, 10 s; 1 when consistent), its horizontal marginal 0.5-1.9; the
    6-D view from the window without the objects was not measured again."""
    Y = o.info
    a, b = slice(0, 2), slice(2, 6)
    m = Y[a, a] - Y[a, b] @ np.linalg.pinv(Y[b, b]) @ Y[b, a]
    w, U = np.linalg.eigh(0.5 * (m + m.T))
    keep = w > MIN_INFO
    info = np.zeros((6, 6))
    info[a, a] = (U[:, keep] * w[keep]) @ U[:, keep].T
    return OthersOnly(o.mean, info, int(keep.sum()))


def cross_localization(graph) -> dict[int, tuple[gtsam.Pose3, np.ndarray]]:
    """The posterior of the window without the objects (module docstring), at each vehicle's newest frame:
    key -> (pose, its tangent covariance). The vehicles' priors, their motion and the cross-detections between
    them, one Gauss-Newton step from the host's estimate (the host's own solution holds the objects too).

    The n detections of one vehicle by one observer in the window share the persistent part of the detector's
    error, a share f = :func:`~.fusion.hostcore.persistent_share` of each one's variance: their mean's variance
    is s^2 (f + (1 - f) / n), which n independent detections of variance s^2 (1 + f (n - 1)) have too; each is
    weighted so (the host's own graph counts them as independent)."""
    factors, cross = graph.vehicles_only()
    poses, tied = set(), set()
    for chain in graph.vehicles.values():
        poses.update(s.key for s in chain.states.values())
        i = len(chain.tkeys) - 1
        tied.add(chain.states[chain.tkeys[i]].key)
        while i > 0 and chain.tkeys[i - 1] in chain.motion:
            i -= 1
            tied.add(chain.states[chain.tkeys[i]].key)
    # frames before a gap in a vehicle's motion (no motion factor) hang on nothing once the objects are out (a
    # filtered sender's only prior is on its newest frame): what touches them says nothing about the frames tied
    # to a prior and is left out (exact; a per-frame sender's such frames have priors: leaving them out is
    # conservative)
    loose = poses - tied
    nfg = gtsam.NonlinearFactorGraph()
    for f in factors:
        if loose.isdisjoint(f.keys()):
            nfg.add(f)
    cross = [(d, obs, tgt) for d, obs, tgt in cross if d.pose_key in tied and d.target_key in tied]
    share = persistent_share(graph.params)
    n = Counter((obs, tgt) for _, obs, tgt in cross)
    dets = [replace(d, weight=d.weight / (1.0 + share * (n[(obs, tgt)] - 1))) for d, obs, tgt in cross]
    for f in linear_factors(dets, graph.values) if dets else []:
        nfg.add(f)
    if nfg.size() == 0:
        return {}
    gfg = nfg.linearize(graph.values)
    dx = gfg.optimize()
    marginals = gtsam.Marginals(gfg, dx)
    out = {}
    for chain in graph.vehicles.values():
        key = chain.latest().key
        if not dx.exists(key):
            continue
        T = graph.values.atPose3(key).compose(gtsam.Pose3.Expmap(dx.at(key)))
        out[key] = (T, marginals.marginalCovariance(key))
    return out


def downlink_messages(graph, fleet: str, host_id: str, t_sent: float, seq0: int,
                      max_sigma_m: float = MAX_DOWNLINK_SIGMA_M) -> list[PoseDownlink]:  # fmt: skip
    """One PoseDownlink per vehicle of ``graph`` (a solved :class:`~.fusion.graph.FusionGraph`) that the others
    know something about: its newest frame in the window without the objects (:func:`cross_localization`), which
    holds its own prior, with that prior removed, of the horizontal
    position only (:func:`horizontal`); numbered from ``seq0``. Skipped: a vehicle whose newest frame has no
    covariance yet or no prior (a late frame), one that sends per-frame priors (``pose_filtered`` false: its own
    share is spread over the window, not one factor), and one whose horizontal position the others know to no
    better than ``max_sigma_m`` (:meth:`OthersOnly.position_sigma_m`)."""
    out = []
    posterior = None
    for vid in sorted(graph.vehicles):
        chain = graph.vehicles[vid]
        s = chain.latest()
        if graph.covariances.get(s.key) is None or list(chain.pose_prior_fids) != [chain.tkeys[-1]]:
            continue  # not solved yet; a late frame; or per-frame priors, the own share spread over the window
        if posterior is None:
            posterior = cross_localization(graph)
        if s.key not in posterior:
            continue
        o = horizontal(others_only(*posterior[s.key], s.T, s.cov_xi))
        if o.rank == 0 or o.position_sigma_m() > max_sigma_m:
            continue
        out.append(
            PoseDownlink(
                fleet=fleet,
                sender=host_id,
                seq=seq0 + len(out),
                t_meas=float(s.t),
                t_sent=float(t_sent),
                target=vid,
                pose=o.mean.astype(np.float32),
                pose_info=cov_to_upper(o.info).astype(np.float32),
            )
        )
    return out
