"""The host's sliding-window factor graph (paper §III-D, "Driving Environment Space State Estimator").

States (GTSAM keys):

* ``x``: Pose3 T_map_body of a connected vehicle at the t_meas of each of its messages;
* ``p``, ``v``: Point3 position and velocity of an obstacle track at each instant it was detected.
  Instants closer than ``time_merge_s`` share one state (all senders of one fleet sample on the same
  10 Hz clock, so in practice this is the 10 Hz grid; with unsynchronised senders it is one state per
  distinct detection time, and a detection up to ``time_merge_s`` off is shifted by the track velocity);
* ``h``: helper Point3s of detections.

Factors (the negative log-likelihood is their sum, the paper's X^D = argmin sum e^T R^-1 e):

* ``PriorFactorPose3`` — each vehicle's self-localization (its covariance over [x, y, z, roll, pitch,
  yaw] mapped to Pose3's tangent, see :mod:`.poses`);
* ``BetweenFactorPose3`` — motion between consecutive frames of a vehicle: translation
  R_a^T (v_a + v_b) / 2 dt from the reported velocities, identity rotation, sigmas
  sqrt((s_v dt)^2 + (s_a dt^2 / 2)^2) and s_w dt. The priors are independent per frame and this factor
  only carries the (independent) velocity information, so nothing is counted twice;
* ``WnoaMotionFactorPoint3`` — constant velocity between consecutive states of a track
  (white noise on acceleration: e = [p_b - p_a - dt v_a, v_b - v_a],
  Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]] per axis);
* a Gaussian prior on [p, v] of one state per track (a ``JacobianFactor`` in a
  ``LinearContainerFactor``): at birth a zero-mean velocity prior (speed_prior_*) and a 1 km position
  regulariser; when the window drops a track's oldest state, what that state knew — its prior and its
  detections, moved to the map frame with the observers' current poses and their reported pose
  covariances, Huber-weighted at the current solution — is predicted through the constant-velocity
  model onto the next state and added to its prior (a per-track Kalman step; it neglects the
  correlation between tracks seen by the same vehicle). Without it the window would forget: a track
  detected only a few times in the last second loses its velocity;
* a detection, exact Cartesian model z = R^T (p - t) + n, n ~ N(0, S_z) in the observer's body frame:
  a helper point h with a Huber-robust ``PriorFactorPoint3(h, z, S_z)`` tied by
  ``ReferenceFrameFactorPoint3Pose3(h, x, p)``, whose error is x.transformFrom(h) - p (sigma
  ``reference_frame_sigma_m``, i.e. nearly hard; semantics checked in tests/unit/test_fusion_graph.py);
* a detection of another connected vehicle (cross-localization): the same tie to a map point q, and q
  tied to the observed vehicle's pose as x_target.transformFrom(g) with a helper g held at the body origin.

Why not ``BearingRangeFactor3D`` (one factor, no helper, faster): in this GTSAM build its bearing
error is expressed in the tangent basis of the *predicted* Unit3, and Unit3 picks that basis by the
smallest component of the direction. For an object straight ahead at road height (body y and z both
near 0) the basis flips between iterations; with the anisotropic bearing noise of a real detector
(vertical 4x tighter than horizontal here) the whitened error then jumps and Gauss-Newton oscillates.

Solve: Levenberg-Marquardt warm-started from the previous solution, starting with no damping (the
Gauss-Newton step, which a warm start almost always accepts) and raising lambda tenfold when the cost
does not decrease. Every iteration eliminates once (multifrontal, COLAMD with the latest state of
every vehicle and track constrained last), so the latest states sit in the root cliques of the Bayes
tree and their joint covariance is read off the root's R: Sigma = (R^T R)^-1 — no extra elimination.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam import VectorValues
from gtsam.symbol_shorthand import H, P, V, X
from scipy.linalg import lapack

from schemas import ObjectClass

from .association import observations_to_map
from .buffer import time_key
from .params import FusionParams
from .poses import pose3_from_vector, pose_cov_to_tangent, vector_from_pose3

__all__ = ["FusionGraph", "SolveReport"]


def _dim(key: int) -> int:
    return 6 if gtsam.Symbol(key).chr() == ord("x") else 3


@dataclass
class _PoseState:
    t: float
    key: int
    pose: np.ndarray  # reported [x, y, z, roll, pitch, yaw]
    cov: np.ndarray  # reported 6x6 over pose
    v_map: np.ndarray


@dataclass
class _TrackState:
    t: float
    pkey: int
    vkey: int
    dets: list = field(default_factory=list)  # (observer pose key, z_body, cov_body)


@dataclass
class _Chain:
    """States of one vehicle or track, sorted by time key, and the motion factors between neighbours."""

    tkeys: list[int] = field(default_factory=list)
    states: dict[int, object] = field(default_factory=dict)
    motion: dict[int, int] = field(default_factory=dict)  # tkey of the earlier state -> factor id
    prior: tuple | None = None  # (time key of the state it is on, mean [p, v], covariance 6x6), tracks
    prior_fid: int = -1
    cls: int = int(ObjectClass.UNKNOWN)

    def latest(self):
        return self.states[self.tkeys[-1]]

    def nearest(self, t: float, tol: float):
        """The state closest to t if it is within tol, else None."""
        if not self.tkeys:
            return None
        k = time_key(t)
        i = bisect.bisect_left(self.tkeys, k)
        best = None
        for j in (i - 1, i):
            if 0 <= j < len(self.tkeys):
                s = self.states[self.tkeys[j]]
                if abs(s.t - t) <= tol + 1e-9 and (best is None or abs(s.t - t) < abs(best.t - t)):
                    best = s
        return best


@dataclass(frozen=True)
class SolveReport:
    iterations: int
    error_before: float
    error_after: float
    factors: int
    variables: int
    covariance_fallbacks: int


class FusionGraph:
    """Sliding-window factor graph over connected-vehicle poses and obstacle tracks (module docstring)."""

    def __init__(self, params: FusionParams):
        self.params = params
        self.values = gtsam.Values()
        self.vehicles: dict[str, _Chain] = {}
        self.tracks: dict[int, _Chain] = {}
        self._factors: dict[int, gtsam.NonlinearFactor] = {}
        self._factor_keys: dict[int, tuple[int, ...]] = {}
        self._key_factors: dict[int, set[int]] = {}
        self._next_fid = 0
        self._pose_states: dict[int, _PoseState] = {}
        self._n = {"x": 0, "p": 0, "h": 0}
        self.covariances: dict[int, np.ndarray] = {}  # latest keys -> marginal covariance (after solve)
        self.track_joint: dict[int, np.ndarray] = {}  # track id -> 6x6 covariance of latest [p, v]
        self.root_dims = 0  # size of the largest root clique in the last solve
        if params.huber_k is not None:
            self._huber = gtsam.noiseModel.mEstimator.Huber.Create(params.huber_k)
        else:
            self._huber = None

    # ------------------------------------------------------------------ bookkeeping
    @property
    def num_factors(self) -> int:
        return len(self._factors)

    @property
    def num_variables(self) -> int:
        return int(self.values.size())

    def _add_factor(self, f: gtsam.NonlinearFactor) -> int:
        fid = self._next_fid
        self._next_fid += 1
        keys = tuple(int(k) for k in f.keys())
        self._factors[fid] = f
        self._factor_keys[fid] = keys
        for k in keys:
            self._key_factors.setdefault(k, set()).add(fid)
        return fid

    def _remove_factor(self, fid: int) -> None:
        if fid not in self._factors:
            return
        del self._factors[fid]
        for k in self._factor_keys.pop(fid):
            fs = self._key_factors.get(k)
            if fs is not None:
                fs.discard(fid)
                if not fs and gtsam.Symbol(k).chr() == ord("h"):  # an orphaned helper point goes too
                    del self._key_factors[k]
                    self.values.erase(k)
                elif fs and gtsam.Symbol(k).chr() == ord("h"):
                    for other in list(fs):  # a helper's prior goes with its tie
                        self._remove_factor(other)

    def _remove_key(self, key: int) -> None:
        for fid in list(self._key_factors.get(key, ())):
            self._remove_factor(fid)
        self._key_factors.pop(key, None)
        if self.values.exists(key):
            self.values.erase(key)
        self.covariances.pop(key, None)

    def _robust(self, cov: np.ndarray):
        base = gtsam.noiseModel.Gaussian.Covariance(cov)
        return base if self._huber is None else gtsam.noiseModel.Robust.Create(self._huber, base)

    # ------------------------------------------------------------------ vehicles
    def add_vehicle_prior(self, vid: str, t: float, pose, pose_cov, v_map) -> int | None:
        """Add a vehicle's self-localization at t; returns its pose key (None if that instant exists)."""
        chain = self.vehicles.setdefault(vid, _Chain(cls=int(ObjectClass.VEHICLE)))
        tk = time_key(t)
        if tk in chain.states:
            return None
        pose = np.asarray(pose, dtype=float)
        cov = np.asarray(pose_cov, dtype=float)
        key = X(self._n["x"])
        self._n["x"] += 1
        T = pose3_from_vector(pose)
        self.values.insert(key, T)
        self._add_factor(gtsam.PriorFactorPose3(key, T, gtsam.noiseModel.Gaussian.Covariance(pose_cov_to_tangent(pose, cov))))
        state = _PoseState(float(t), key, pose, cov, np.asarray(v_map, dtype=float))
        self._pose_states[key] = state
        i = bisect.bisect_left(chain.tkeys, tk)
        chain.tkeys.insert(i, tk)
        chain.states[tk] = state
        if i > 0 and i < len(chain.tkeys) - 1:  # between two existing frames: replace their motion factor
            self._remove_factor(chain.motion.pop(chain.tkeys[i - 1], -1))
        if i > 0:
            self._vehicle_motion(chain, chain.tkeys[i - 1], tk)
        if i < len(chain.tkeys) - 1:
            self._vehicle_motion(chain, tk, chain.tkeys[i + 1])
        return key

    def _vehicle_motion(self, chain: _Chain, ka: int, kb: int) -> None:
        a, b = chain.states[ka], chain.states[kb]
        dt = b.t - a.t
        if dt <= 0 or dt > self.params.motion_factor_max_dt_s:
            return
        p = self.params
        R_a = pose3_from_vector(a.pose).rotation().matrix()
        t_rel = R_a.T @ (0.5 * (a.v_map + b.v_map) * dt)
        s_t = np.hypot(p.vehicle_velocity_sigma_mps * dt, 0.5 * p.vehicle_accel_sigma_mps2 * dt**2)
        s_r = p.vehicle_rate_sigma_radps * dt
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([s_r, s_r, s_r, s_t, s_t, s_t]))
        chain.motion[ka] = self._add_factor(gtsam.BetweenFactorPose3(a.key, b.key, gtsam.Pose3(gtsam.Rot3(), t_rel), noise))

    def vehicle_state(self, vid: str, t: float, tol: float) -> _PoseState | None:
        chain = self.vehicles.get(vid)
        return None if chain is None else chain.nearest(t, tol)

    # ------------------------------------------------------------------ tracks
    def _psd(self, cls: int) -> np.ndarray:
        p = self.params
        h = p.accel_psd_pedestrian if cls in (ObjectClass.PEDESTRIAN, ObjectClass.CYCLIST) else p.accel_psd_vehicle
        return np.array([h, h, p.accel_psd_vertical])

    def track_state(self, track_id: int, t: float, init_p, init_v, cls: int) -> _TrackState:
        """The track's state for time t (an existing one within time_merge_s, else a new one)."""
        chain = self.tracks.get(track_id)
        if chain is None:
            chain = self.tracks[track_id] = _Chain(cls=int(cls))
        s = chain.nearest(t, self.params.time_merge_s)
        if s is not None:
            return s
        tk = time_key(t)
        pkey, vkey = P(self._n["p"]), V(self._n["p"])
        self._n["p"] += 1
        i = bisect.bisect_left(chain.tkeys, tk)
        if chain.tkeys:  # warm start from the neighbour: constant velocity, as the motion factor predicts
            nb = chain.states[chain.tkeys[i - 1 if i > 0 else 0]]
            v_nb = self.values.atPoint3(nb.vkey)
            init_p = self.values.atPoint3(nb.pkey) + v_nb * (t - nb.t)
            init_v = v_nb
        self.values.insert(pkey, np.asarray(init_p, dtype=float))
        self.values.insert(vkey, np.asarray(init_v, dtype=float))
        s = _TrackState(float(t), pkey, vkey)
        chain.tkeys.insert(i, tk)
        chain.states[tk] = s
        if 0 < i < len(chain.tkeys) - 1:
            self._remove_factor(chain.motion.pop(chain.tkeys[i - 1], -1))
        if i > 0:
            self._track_motion(chain, chain.tkeys[i - 1], tk)
        if i < len(chain.tkeys) - 1:
            self._track_motion(chain, tk, chain.tkeys[i + 1])
        if chain.prior is None:
            sv = self._speed_prior(chain.cls)
            mean = np.concatenate([self.values.atPoint3(pkey), np.zeros(3)])
            self._set_prior(chain, tk, mean, np.diag([1e6, 1e6, 1e6, sv**2, sv**2, 0.25]))
        return s

    def _track_motion(self, chain: _Chain, ka: int, kb: int) -> None:
        a, b = chain.states[ka], chain.states[kb]
        f = gtsam.WnoaMotionFactorPoint3(
            gtsam.StateData(a.pkey, a.vkey, a.t), gtsam.StateData(b.pkey, b.vkey, b.t), self._psd(chain.cls)
        )
        chain.motion[ka] = self._add_factor(f)

    def _speed_prior(self, cls: int) -> float:
        p = self.params
        if cls in (ObjectClass.PEDESTRIAN, ObjectClass.CYCLIST):
            return p.speed_prior_pedestrian_mps
        return p.speed_prior_vehicle_mps

    def _set_prior(self, chain: _Chain, tkey: int, mean: np.ndarray, cov: np.ndarray) -> None:
        """Put the Gaussian N(mean, cov) over [p, v] of the state at tkey (replacing the track's prior)."""
        self._remove_factor(chain.prior_fid)
        s = chain.states[tkey]
        cov = 0.5 * (cov + cov.T)
        A = np.linalg.cholesky(np.linalg.inv(cov)).T  # A^T A = cov^-1
        jf = gtsam.JacobianFactor(s.pkey, A[:, :3], s.vkey, A[:, 3:], np.zeros(6), gtsam.noiseModel.Unit.Create(6))
        lin = gtsam.Values()
        lin.insert(s.pkey, np.asarray(mean[:3], dtype=float))
        lin.insert(s.vkey, np.asarray(mean[3:], dtype=float))
        chain.prior = (tkey, np.asarray(mean, dtype=float), cov)
        chain.prior_fid = self._add_factor(gtsam.LinearContainerFactor(jf, lin))

    def _summarize_first(self, chain: _Chain) -> None:
        """Fold the first state's prior and detections into a prior on the second state (module docstring)."""
        k0, k1 = chain.tkeys[0], chain.tkeys[1]
        s0, s1 = chain.states[k0], chain.states[k1]
        info = np.zeros((6, 6))
        eta = np.zeros(6)
        if chain.prior is not None and chain.prior[0] == k0:
            Li = np.linalg.inv(chain.prior[2])
            info += Li
            eta += Li @ chain.prior[1]
        p0 = self.values.atPoint3(s0.pkey)
        k = self.params.huber_k
        for pose_key, z, cov_z in s0.dets:
            ps = self._pose_states.get(pose_key)
            if ps is None or not self.values.exists(pose_key):
                continue
            m, S = observations_to_map(vector_from_pose3(self.values.atPose3(pose_key)), ps.cov, z[None], cov_z[None])
            Si = np.linalg.inv(S[0])
            r = m[0] - p0
            d = float(np.sqrt(r @ Si @ r))
            w = 1.0 if k is None or d <= k else k / d
            info[:3, :3] += w * Si
            eta[:3] += w * Si @ m[0]
        if not s0.dets or chain.prior is None or chain.prior[0] != k0:  # keep it well posed
            sv = self._speed_prior(chain.cls)
            info += np.diag([1e-6, 1e-6, 1e-6, sv**-2, sv**-2, 4.0])
            eta[:3] += 1e-6 * p0
        P0 = np.linalg.inv(info)
        mu0 = P0 @ eta
        dt = s1.t - s0.t
        F = np.eye(6)
        F[:3, 3:] = dt * np.eye(3)
        q = self._psd(chain.cls)
        i = np.arange(3)
        Q = np.zeros((6, 6))
        Q[i, i] = q * dt**3 / 3
        Q[i, i + 3] = Q[i + 3, i] = q * dt**2 / 2
        Q[i + 3, i + 3] = q * dt
        mu1, P1 = F @ mu0, F @ P0 @ F.T + Q
        if chain.prior is not None and chain.prior[0] == k1:  # combine with what the next state already has
            Ia, Ib = np.linalg.inv(chain.prior[2]), np.linalg.inv(P1)
            P1 = np.linalg.inv(Ia + Ib)
            mu1 = P1 @ (Ia @ chain.prior[1] + Ib @ mu1)
        self._set_prior(chain, k1, mu1, P1)

    def _helper(self, z, cov, robust: bool, ties: int = 1) -> int:
        """A helper Point3 h with a prior at z (Huber-robust if ``robust``).

        The ``ties`` reference-frame ties that will hang on it add ties * sigma^2 I to the detection's
        covariance; the prior gets cov - ties * sigma^2 I so that the chain's total is exactly ``cov``.
        """
        h = H(self._n["h"])
        self._n["h"] += 1
        z = np.asarray(z, dtype=float)
        cov = np.asarray(cov, dtype=float)
        reduced = cov - ties * self.params.reference_frame_sigma_m**2 * np.eye(3)
        if np.linalg.eigvalsh(reduced)[0] > 0.1 * np.linalg.eigvalsh(cov)[0]:
            cov = reduced
        self.values.insert(h, z)
        noise = self._robust(cov) if robust else gtsam.noiseModel.Gaussian.Covariance(cov)
        self._add_factor(gtsam.PriorFactorPoint3(h, z, noise))
        return h

    def _tie(self, h: int, pose_key: int, point_key: int) -> None:
        """pose.transformFrom(h) = point, to within reference_frame_sigma_m."""
        tie = gtsam.noiseModel.Isotropic.Sigma(3, self.params.reference_frame_sigma_m)
        self._add_factor(gtsam.ReferenceFrameFactorPoint3Pose3(h, pose_key, point_key, tie))

    def add_detection(self, pose_key: int, state: _TrackState, z_body, cov_body) -> None:
        """A body-frame detection z_body (cov_body) by the vehicle at pose_key of the track state."""
        z = np.asarray(z_body, dtype=float)
        cov = np.asarray(cov_body, dtype=float)
        h = self._helper(z, cov, robust=True)
        self._tie(h, pose_key, state.pkey)
        state.dets.append((pose_key, z, cov))

    def add_cross_detection(self, pose_key: int, target_key: int, z_body, cov_body, offset_body=None) -> None:
        """A body-frame detection of another connected vehicle (cross-localization).

        The detected point q (a Point3 in the map frame) is tied to the observer by the detection
        (helper h, robust prior at z) and to the target as target.transformFrom(g) with a helper g
        held at ``offset_body`` (default: the target's body origin, the reference point detectors report).
        """
        q = H(self._n["h"])
        self._n["h"] += 1
        T_obs = self.values.atPose3(pose_key)
        self.values.insert(q, T_obs.transformFrom(np.asarray(z_body, dtype=float)))
        h = self._helper(z_body, cov_body, robust=True, ties=2)
        self._tie(h, pose_key, q)
        g0 = np.zeros(3) if offset_body is None else np.asarray(offset_body, dtype=float)
        g = self._helper(g0, 1e-8 * np.eye(3), robust=False, ties=0)
        self._tie(g, target_key, q)

    # ------------------------------------------------------------------ window
    def remove_track(self, track_id: int) -> None:
        chain = self.tracks.pop(track_id, None)
        if chain is None:
            return
        for s in chain.states.values():
            self._remove_key(s.pkey)
            self._remove_key(s.vkey)
        self.track_joint.pop(track_id, None)

    def prune(self, t_min: float) -> int:
        """Drop every state older than t_min with its factors; returns the number of states dropped.

        A track's dropped states are first folded into a prior on its oldest kept state.
        """
        kmin = time_key(t_min)
        dropped = 0
        for tid, chain in list(self.tracks.items()):
            while chain.tkeys and chain.tkeys[0] < kmin:
                if len(chain.tkeys) > 1:
                    self._summarize_first(chain)
                tk = chain.tkeys.pop(0)
                chain.motion.pop(tk, None)
                s = chain.states.pop(tk)
                self._remove_key(s.pkey)
                self._remove_key(s.vkey)
                dropped += 1
            if not chain.tkeys:
                del self.tracks[tid]
                self.track_joint.pop(tid, None)
        for vid, chain in list(self.vehicles.items()):
            while chain.tkeys and chain.tkeys[0] < kmin:
                tk = chain.tkeys.pop(0)
                chain.motion.pop(tk, None)
                key = chain.states.pop(tk).key
                self._pose_states.pop(key, None)
                self._remove_key(key)
                dropped += 1
            if not chain.tkeys:
                del self.vehicles[vid]
        return dropped

    # ------------------------------------------------------------------ solve
    def latest_keys(self) -> list[int]:
        keys = [c.latest().key for c in self.vehicles.values()]
        for c in self.tracks.values():
            s = c.latest()
            keys += [s.pkey, s.vkey]
        return keys

    def solve(self) -> SolveReport:
        """Levenberg-Marquardt from the current values; latest-state covariances (module docstring)."""
        graph = gtsam.NonlinearFactorGraph()
        for f in self._factors.values():
            graph.push_back(f)
        latest = self.latest_keys()
        n_vars = self.num_variables
        if graph.size() == 0:
            return SolveReport(0, 0.0, 0.0, 0, n_vars, 0)
        ordering = gtsam.Ordering.ColamdConstrainedLastNonlinearFactorGraph(graph, latest)
        values = self.values
        err0 = err = graph.error(values)
        lam = self.params.lambda_initial
        bt = None
        it = 0
        while it < self.params.max_iterations:
            it += 1
            gfg = graph.linearize(values)
            if lam > 0:
                for k in values.keys():
                    d = _dim(k)
                    gfg.push_back(gtsam.JacobianFactor(k, np.sqrt(lam) * np.eye(d), np.zeros(d), gtsam.noiseModel.Unit.Create(d)))
            try:
                tree = gfg.eliminateMultifrontal(ordering)
            except RuntimeError:  # indeterminate: damp and retry
                lam = max(10 * lam, 1.0)
                continue
            delta = tree.optimize()
            new = values.retract(delta)
            new_err = graph.error(new)
            if new_err <= err or not np.isfinite(err):
                if lam == 0:
                    bt = tree
                decrease = err - new_err
                # Converged when the cost barely moved, or when the linear model predicted the new cost:
                # then the Gauss-Newton step already landed on the minimum of an accurate quadratic model.
                # (robust factors linearize to IRLS quadratics whose values differ from the robust cost by
                # a constant, so compare the predicted and actual decrease, not the values)
                tol = max(self.params.relative_error_tol * new_err, 1e-3)
                predicted = gfg.error(VectorValues.Zero(delta)) - gfg.error(delta)
                model_ok = lam == 0 and abs(predicted - decrease) <= max(self.params.model_tol * new_err, 1e-3)
                values, err = new, new_err
                lam = lam / 10 if lam > 1e-3 else 0.0
                if decrease <= tol or model_ok:
                    break
            else:
                lam = max(10 * lam, 1.0)
        self.values = values
        if bt is None:  # no undamped elimination was accepted: one more at the solution
            bt = graph.linearize(values).eliminateMultifrontal(ordering)
        fallbacks = self._covariances(bt, latest)
        return SolveReport(it, float(err0), float(err), int(graph.size()), n_vars, fallbacks)

    def _covariances(self, bt: gtsam.GaussianBayesTree, latest: list[int]) -> int:
        """Marginal covariances of the latest keys from the root cliques: Sigma = (R^T R)^-1."""
        cov: dict[int, np.ndarray] = {}
        joint: dict[tuple[int, int], np.ndarray] = {}
        self.root_dims = 0
        wanted = set(latest)
        for root in bt.roots():
            c = root.conditional()
            keys = [int(k) for k in c.keys()]
            if not wanted.intersection(keys):
                continue
            R = c.R()
            dims = [_dim(k) for k in keys]
            if sum(dims) != R.shape[1]:  # a root with parents cannot happen; be safe
                continue
            # Only the trailing block of R from the first wanted key on is needed:
            # for R = [[A, B], [0, C]], the covariance of the tail is C^-1 C^-T.
            first = min(i for i, k in enumerate(keys) if k in wanted)
            off = np.cumsum([0, *dims])
            C = R[off[first] :, off[first] :]
            Cinv, info = lapack.dtrtri(C, lower=0)  # unblocked for small n: no BLAS thread wake-ups
            if info != 0:
                continue
            block = {k: slice(off[i] - off[first], off[i + 1] - off[first]) for i, k in enumerate(keys) if i >= first}
            for k in block:
                if k in wanted:
                    rows = Cinv[block[k]]
                    cov[k] = rows @ rows.T
            for chain in self.tracks.values():
                s = chain.latest()
                if s.pkey in block and s.vkey in block:
                    rows = np.vstack([Cinv[block[s.pkey]], Cinv[block[s.vkey]]])
                    joint[(s.pkey, s.vkey)] = rows @ rows.T
            self.root_dims = max(self.root_dims, int(R.shape[1]))
        fallbacks = 0
        for k in wanted - set(cov):
            cov[k] = bt.marginalCovariance(k)
            fallbacks += 1
        self.covariances = cov
        self.track_joint = {}
        for tid, chain in self.tracks.items():
            s = chain.latest()
            J = joint.get((s.pkey, s.vkey))
            if J is None:
                J = np.zeros((6, 6))
                J[:3, :3], J[3:, 3:] = cov[s.pkey], cov[s.vkey]
            self.track_joint[tid] = 0.5 * (J + J.T)
        return fallbacks

    # ------------------------------------------------------------------ results
    def vehicle_estimate(self, vid: str) -> tuple[float, gtsam.Pose3, np.ndarray | None]:
        """(t, Pose3, tangent covariance or None before a solve) of a vehicle's latest frame."""
        s = self.vehicles[vid].latest()
        return s.t, self.values.atPose3(s.key), self.covariances.get(s.key)

    def track_estimate(self, track_id: int) -> tuple[float, np.ndarray, np.ndarray, np.ndarray | None]:
        """(t, p, v, 6x6 covariance of [p, v] or None) of a track's latest state."""
        s = self.tracks[track_id].latest()
        return s.t, self.values.atPoint3(s.pkey), self.values.atPoint3(s.vkey), self.track_joint.get(track_id)
