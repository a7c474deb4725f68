"""The host's sliding-window factor graph (paper §III-D, "Driving Environment Space State Estimator").

States (GTSAM keys):

* ``x``: Pose3 T_map_body of a connected vehicle at the t_meas of each of its messages;
* ``s``: Vector6 state [p, v] (map-frame position and velocity) of an obstacle track at each instant
  it was detected within ``track_lag_s`` (0.3 s) of its newest (one 6-D variable rather than two
  Point3s: half the variables, and GTSAM's elimination costs about 15 us per clique here: cycles
  ~10-15 % shorter); older states are folded into the track's prior (below). Instants closer than
  ``time_merge_s`` share one state. All senders of a fleet sample on the same 10 Hz clock, so in
  practice these are the 10 Hz grid; with unsynchronised senders there is one state per distinct
  detection time, and a detection up to ``time_merge_s`` off is shifted by the track's velocity. (A
  fixed grid would need interpolated detections; distinct times need none.)
* ``b``: Vector6, per vehicle, the persistent part of its self-localization error (below).

Factors (the negative log-likelihood is their sum: the paper's X^D = argmin sum e^T R^-1 e):

* each vehicle's self-localization z_k (its covariance over [x, y, z, roll, pitch, yaw] mapped to
  Pose3's tangent, see :mod:`.poses`): ``PriorFactorPose3``, or, with
  ``pose_error_persistent_fraction`` a > 0, a linear factor on (x_k, b) where ``b`` (a Vector6 per
  vehicle, whitened units) is the part of the error that persists over the window: the whitened error
  is b + n_k with b ~ N(0, a I) and n_k ~ N(0, (1 - a) I) independent per frame (``_pose_prior``).
  Map matching tracks its pose, so its errors persist over seconds (measured correlation of its
  whitened horizontal errors 0.1-0.8 at 0.1 s, 0.1-0.45 at 1 s, per vehicle); counting ten such
  priors per second as independent made the fused poses, and through them the objects, too
  confident. Track priors keep their detections' dependence on b (below);
* ``BetweenFactorPose3`` — motion between consecutive frames of a vehicle: translation
  R_a^T (v_a + v_b) / 2 dt from the reported velocities, identity rotation, sigmas
  sqrt((s_v dt)^2 + (s_a dt^2 / 2)^2) and s_w dt. It only carries the (independent) velocity
  information, so nothing is counted twice;
* constant velocity between consecutive states of a track (white noise on acceleration):
  e = s_b - F s_a, F = [[I, dt I], [0, I]], Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]] per axis — the model
  of GTSAM's ``WnoaMotionFactorPoint3``, which is linear, so it is a ``JacobianFactor`` (exact);
* a Gaussian prior on the first state of each track and the persistent errors b_v of the vehicles
  whose detections it holds (``_TrackPrior``, one linear factor): at birth a zero-mean velocity prior
  (speed_prior_*) and a 1 km position regulariser. When a track's first state is older than the lag
  (or the window), what it knew — its prior and its detections, moved to the map frame with the
  observers' reported poses z_k, whose errors are J L (b_v + n_k) in the graph's own model — is
  carried through the constant-velocity model onto the next state, the first state marginalised out
  (``_summarize_first``): information over [s, b_v...]. Its dependence on b_v fades with the
  persistence time (b is first-order Gauss-Markov, ``pose_error_persistence_s``), so old detections
  do not stay tied to a vehicle's current error; b_v leaves the prior when the vehicle leaves the graph
  (``_forget_bias``). A detection older than its track's first state (a late message) goes into the
  prior the same way, retrodicted (``fold_detection``). What this neglects: the frame-to-frame part
  n_k of the folded detections' pose errors is treated as independent of the frames still in the
  window, and so of other tracks' priors (the model-world test measures the cost: ANEES 3.4 vs 3.15
  with the whole window in the graph). Why a lag at all: the graph is dense in time (every vehicle
  sees about half of the objects at every instant), so elimination grows with the number of track
  instants; with 0.3 s instead of the 1 s window the host cycle at 16 vehicles / 100 objects is ~27 %
  shorter, estimates unchanged on the bench and the simulator. Vehicle frames stay for the window,
  so that late messages still find their poses;
* a detection z of track position p by the vehicle at pose x, exact Cartesian model in the observer's
  body frame, e = R^T (p - t) - z, e ~ N(0, S_z), Huber-robust (``huber_k``), as one
  ``LinearContainerFactor`` on (x, s) with Jacobians [[q0]x, -I] (Pose3 tangent [rotation,
  translation]) and [R0^T, 0], q0 = R0^T (p0 - t0), linearised at the estimates x0, s0 when it is
  created. The model is linear in p; what is neglected is second order: 0.5 |dtheta|^2 |z| and the
  cross term |dtheta| |dp|, about 1 mm for the 5 mrad pose uncertainty here against detection sigmas
  of 5-50 cm (a factor is re-linearised when its pose estimate moves by more than ``relinearize_rad``
  / ``relinearize_m``). The Huber weight w = min(1, k / |S_z^-1/2 e|) is iterated across cycles
  (IRLS): recomputed from the current estimate before each solve for detections younger than
  ``reweight_s`` (the first weight comes from the association innovation). The design's first form,
  a helper point h with a robust ``PriorFactorPoint3(h, z)`` tied by
  ``ReferenceFrameFactorPoint3Pose3(h, x, p)``, gives the same estimates (the test oracle in
  tests/unit/test_fusion_graph.py) with two factors and a variable per detection instead of one factor;
* a detection of another connected vehicle (cross-localization): the same model against the observed
  vehicle's body origin, e = R_obs^T (t_target - t_obs) - z (``LinearContainerFactor`` on both poses).

Why not ``BearingRangeFactor3D`` (one factor, nonlinear): in this GTSAM build its bearing error is in the
tangent basis of the *predicted* Unit3, which Unit3 picks by the smallest component of the direction.
For an object straight ahead at road height (body y and z both near 0) the basis flips between
iterations; with the anisotropic bearing noise of a real detector (vertical 4x tighter than
horizontal) the whitened error jumps and Gauss-Newton oscillates (seen in the overlap scenario).

Solve: Levenberg-Marquardt warm-started from the previous solution, starting with no damping (the
Gauss-Newton step, which a warm start almost always accepts) and raising lambda when the cost does not
decrease; it stops when the cost barely moves or the step did what the linear model predicted (one
iteration per cycle in practice). Every iteration eliminates once (multifrontal, COLAMD with the latest
state of every vehicle and track constrained last), so the latest states sit in the root cliques of the
Bayes tree and their covariances come from that elimination: (R^T R)^-1 of the root, and for the few
latest keys in cliques below it the standard top-down recursion (see ``_covariances``) — no extra
elimination; gtsam.Marginals' shortcuts cost ~100 ms per such key here.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, S, X
from scipy.linalg import lapack

from schemas import ObjectClass

from .buffer import time_key
from .motion import accel_psd, cv_model, speed_prior
from .params import FusionParams
from .poses import pose3_from_vector, pose_cov_to_tangent

__all__ = ["FusionGraph", "SolveReport"]

_UNIT3 = gtsam.noiseModel.Unit.Create(3)
_UNIT6 = gtsam.noiseModel.Unit.Create(6)


def _skews(q: np.ndarray) -> np.ndarray:
    """[q]x (N, 3, 3) of vectors q (N, 3): [q]x v = q x v."""
    out = np.zeros((len(q), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -q[:, 2], q[:, 1], -q[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = q[:, 2], -q[:, 1], q[:, 0]
    return out


def _sqrt_info(cov: np.ndarray) -> np.ndarray:
    """W with W^T W = cov^-1 (upper triangular)."""
    return np.linalg.cholesky(np.linalg.inv(cov)).T


def _marginalize(info: np.ndarray, eta: np.ndarray, out: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian information (info, eta) with the variables at indices ``out`` marginalised (Schur
    complement); the others keep their order."""
    keep = np.setdiff1d(np.arange(len(info)), out)
    K = np.linalg.solve(info[np.ix_(out, out)], np.column_stack([info[np.ix_(out, keep)], eta[out]]))
    new_info = info[np.ix_(keep, keep)] - info[np.ix_(keep, out)] @ K[:, :-1]
    return 0.5 * (new_info + new_info.T), eta[keep] - info[np.ix_(keep, out)] @ K[:, -1]


def _sqrt_information(info: np.ndarray, eta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A, r) with A^T A = info and A^T r = eta for stacks (N, n, n), (N, n): A = L^T of the Cholesky
    factor. A track prior's information is only semi-definite in the persistent errors b that its
    detections do not constrain; a ridge of 1e-9 of its largest diagonal (a prior of sigma ~ 3e4 times
    the tightest) makes it definite without changing anything measurable."""
    ridge = 1e-9 * np.max(np.diagonal(info, axis1=1, axis2=2), axis=1)
    L = np.linalg.cholesky(info + ridge[:, None, None] * np.eye(info.shape[1]))
    r = np.linalg.solve(L, eta[..., None])[..., 0]
    return L.transpose(0, 2, 1), r


_BATCH_UNITS = 1e5  # what one more batch of track summaries costs, in units of the padding it avoids


def _batches(sizes: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """Track priors grouped for batched summaries: (number of vehicles m to pad to, indices), largest m
    first. A batch costs about forty numpy calls whatever its size; a prior in it costs ~ (6 + 6 m)^3
    (its inverses and products). A smaller size joins the batch above when padding its priors costs less
    than a batch of its own. Estimated from two timings: a batch ~0.3 ms; padding every prior of the
    16 vehicles / 100 objects bench to the largest size cost ~18 ms more, ~2.6 ns per unit; so a batch is
    worth ~1e5 units. At 4 / 14 that makes one batch; at 16 / 100 the larger sizes stay apart."""
    out: list[tuple[int, np.ndarray]] = []
    for m in np.unique(sizes)[::-1]:
        idx = np.flatnonzero(sizes == m)
        if out and len(idx) * ((6 + 6 * out[-1][0]) ** 3 - (6 + 6 * m) ** 3) < _BATCH_UNITS:
            out[-1] = (out[-1][0], np.concatenate([out[-1][1], idx]))
        else:
            out.append((int(m), idx))
    return out


def _jacobian_factor(keys: list[int], A: np.ndarray, b: np.ndarray) -> gtsam.JacobianFactor:
    """||A y - b||^2 / 2 over the 6-D variables ``keys`` (A's columns in that order), any number of keys
    (the Python JacobianFactor constructors take at most three; a GaussianConditional takes a list of
    terms and is a JacobianFactor, at twice the cost)."""
    blocks = [A[:, 6 * i : 6 * i + 6] for i in range(len(keys))]
    unit = gtsam.noiseModel.Unit.Create(len(b))
    if len(keys) <= 3:
        return gtsam.JacobianFactor(*[x for kb in zip(keys, blocks, strict=True) for x in kb], b, unit)
    return gtsam.JacobianFactor(gtsam.GaussianConditional(list(zip(keys, blocks, strict=True)), 1, b, unit))


@dataclass
class _PoseState:
    t: float
    key: int
    pose: np.ndarray  # reported [x, y, z, roll, pitch, yaw]
    cov: np.ndarray  # reported 6x6 over pose
    v_map: np.ndarray
    cov_xi: np.ndarray  # reported covariance in Pose3's tangent [rotation, translation]
    L_xi: np.ndarray  # its Cholesky factor, L L^T = cov_xi
    T: gtsam.Pose3  # the reported pose
    M: np.ndarray  # and its 4x4 matrix
    dets: list = field(default_factory=list)  # _Detection records made from this frame
    prior_lin: np.ndarray | None = None  # linearization point (4x4) of a self-localization factor with a bias
    vid: str = ""


@dataclass
class _TrackState:
    t: float
    key: int  # Vector6 [p, v]
    dets: list = field(default_factory=list)  # _Detection records of this state


@dataclass(eq=False)
class _Detection:
    """One detection factor: who saw what, and how it is in the graph."""

    pose_key: int
    target_key: int  # track state key, or the observed vehicle's pose key (cross)
    z: np.ndarray
    cov: np.ndarray
    t: float
    cross: bool = False
    weight: float = 1.0
    fid: int = -1
    W: np.ndarray | None = None  # W^T W = cov^-1
    lin_pose: np.ndarray | None = None  # linearization point (4x4) of the observer
    fresh: bool = True  # not yet through a solve: keep the weight from the association innovation


@dataclass
class _TrackPrior:
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


@dataclass
class _Chain:
    """States of one vehicle or track, sorted by time key, and the motion factors between neighbours."""

    tkeys: list[int] = field(default_factory=list)
    states: dict[int, object] = field(default_factory=dict)
    motion: dict[int, int] = field(default_factory=dict)  # tkey of the earlier state -> factor id
    prior: _TrackPrior | None = None  # tracks: on the first state
    prior_fid: int = -1
    pose_prior_fids: dict[int, int] = field(default_factory=dict)  # vehicles: tkey -> self-localization factor
    bias_key: int | None = None  # vehicles: the persistent part of the self-localization error (whitened)
    cls: int = int(ObjectClass.UNKNOWN)

    def latest(self):
        return self.states[self.tkeys[-1]]

    def nearest(self, t: float, tol: float):
        """The state closest to t if it is within tol, else None."""
        if not self.tkeys:
            return None
        i = bisect.bisect_left(self.tkeys, time_key(t))
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
    cliques_below_root: int  # Bayes-tree cliques below a root visited for the latest covariances
    reweighted: int = 0


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
        self._fid_det: dict[int, _Detection] = {}
        self._next_fid = 0
        self._pose_states: dict[int, _PoseState] = {}
        self._n = {"x": 0, "s": 0, "b": 0}
        self._graph = gtsam.NonlinearFactorGraph()  # every factor, in slots (see _factor_graph)
        self._slot: dict[int, int] = {}  # factor id -> index in _graph
        self.covariances: dict[int, np.ndarray] = {}  # latest keys -> marginal covariance (after solve)
        self.root_dims = 0  # size of the largest root clique in the last solve
        self._motion_blocks: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}  # (dt us, class) -> A_a, A_b

    # ------------------------------------------------------------------ bookkeeping
    @property
    def num_factors(self) -> int:
        return len(self._factors)

    @property
    def num_variables(self) -> int:
        return int(self.values.size())

    def _add_factor(self, f: gtsam.NonlinearFactor, keys: tuple[int, ...] | None = None) -> int:
        """Add a factor (``keys``: its keys, if the caller has them); returns its id."""
        fid = self._next_fid
        self._next_fid += 1
        if keys is None:
            keys = tuple(int(k) for k in f.keys())
        self._factors[fid] = f
        self._factor_keys[fid] = keys
        for k in keys:
            self._key_factors.setdefault(k, set()).add(fid)
        self._slot[fid] = self._graph.size()
        self._graph.add(f)
        return fid

    def _remove_factor(self, fid: int) -> None:
        if fid not in self._factors:
            return
        del self._factors[fid]
        self._graph.remove(self._slot.pop(fid))
        self._fid_det.pop(fid, None)
        for k in self._factor_keys.pop(fid):
            fs = self._key_factors.get(k)
            if fs is not None:
                fs.discard(fid)

    def _factor_graph(self) -> gtsam.NonlinearFactorGraph:
        """The graph of all factors; removed factors leave empty slots, squeezed out when they dominate."""
        if self._graph.size() > 2 * len(self._factors) + 64:
            graph = gtsam.NonlinearFactorGraph()
            for i, (fid, f) in enumerate(self._factors.items()):
                graph.add(f)
                self._slot[fid] = i
            self._graph = graph
        return self._graph

    def _remove_key(self, key: int) -> None:
        for fid in list(self._key_factors.get(key, ())):
            self._remove_factor(fid)
        self._key_factors.pop(key, None)
        if self.values.exists(key):
            self.values.erase(key)
        self.covariances.pop(key, None)

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
        M = T.matrix()
        self.values.insert(key, T)
        cov_xi = pose_cov_to_tangent(pose, cov)
        L_xi = np.linalg.cholesky(cov_xi)
        state = _PoseState(float(t), key, pose, cov, np.asarray(v_map, dtype=float), cov_xi, L_xi, T, M, vid=vid)
        self._pose_states[key] = state
        i = bisect.bisect_left(chain.tkeys, tk)
        chain.tkeys.insert(i, tk)
        chain.states[tk] = state
        if 0 < i < len(chain.tkeys) - 1:  # between two existing frames: replace their motion factor
            self._remove_factor(chain.motion.pop(chain.tkeys[i - 1], -1))
        if i > 0:
            self._vehicle_motion(chain, chain.tkeys[i - 1], tk)
        if i < len(chain.tkeys) - 1:
            self._vehicle_motion(chain, tk, chain.tkeys[i + 1])
        self._pose_prior(chain, i)
        return key

    def _pose_prior(self, chain: _Chain, i: int) -> None:
        """(Re)make the self-localization factor of the chain's i-th frame (module docstring).

        With pose_error_persistent_fraction a = 0: PriorFactorPose3 with the reported covariance. With
        a > 0 the whitened prior residual u_k = L_k^-1 r_k (r_k = Local(z_k, x_k), L_k L_k^T = the
        reported covariance in the tangent) is u_k = beta + n_k: beta ~ N(0, a I) one vector per vehicle
        shared by all its frames in the window (the error that persists), n_k ~ N(0, (1 - a) I) per
        frame. Each u_k is N(0, I) (the reported covariance is the marginal), any two frames correlate
        by a. The factor (u_k - beta) / sqrt(1 - a) ~ N(0, I) on (x_k, beta) is linear in the tangent
        increment (d r / d xi = Jr^-1(r) = I + O(|r|), |r| a few mrad / dm) and in beta; it is re-made
        when the pose moves beyond relinearize_rad / relinearize_m (``_relinearize_pose_priors``).
        """
        tk = chain.tkeys[i]
        s = chain.states[tk]
        self._remove_factor(chain.pose_prior_fids.pop(tk, -1))
        a = self.params.pose_error_persistent_fraction
        if a <= 0:
            f = gtsam.PriorFactorPose3(s.key, s.T, gtsam.noiseModel.Gaussian.Covariance(s.cov_xi))
            s.prior_lin = None
        else:
            if chain.bias_key is None:
                chain.bias_key = B(self._n["b"])
                self._n["b"] += 1
                self.values.insert(chain.bias_key, np.zeros(6))
                self._add_factor(
                    gtsam.PriorFactorVector(
                        chain.bias_key, np.zeros(6), gtsam.noiseModel.Isotropic.Sigma(6, np.sqrt(a))
                    )
                )
            c = 1.0 / np.sqrt(1.0 - a)
            W = np.linalg.inv(s.L_xi)
            xk = self.values.atPose3(s.key)
            beta = self.values.atVector(chain.bias_key)
            r = s.T.localCoordinates(xk)
            jf = gtsam.JacobianFactor(s.key, c * W, chain.bias_key, -c * np.eye(6), -c * (W @ r - beta), _UNIT6)
            f = gtsam.LinearContainerFactor(jf, self.values)  # linearised at the current values
            s.prior_lin = xk.matrix()
        chain.pose_prior_fids[tk] = self._add_factor(f)

    def _relinearize_pose_priors(self) -> int:
        """Re-make the self-localization factors (with a persistent part) whose pose moved from its
        linearization point by more than relinearize_rad / relinearize_m; returns how many."""
        moved = self._moved({s.key: s.prior_lin for s in self._pose_states.values() if s.prior_lin is not None})
        n = 0
        for chain in self.vehicles.values():
            for i, tk in enumerate(chain.tkeys):
                if chain.states[tk].key in moved:
                    self._pose_prior(chain, i)
                    n += 1
        return n

    def _moved(self, lin: dict[int, np.ndarray]) -> set[int]:
        """The pose keys whose current value is farther from their linearization point (``lin``: 4x4) than
        relinearize_rad (angle of R0^T R) or relinearize_m (length of R0^T (t - t0)). Vectorised."""
        if not lin:
            return set()
        keys = list(lin)
        M0 = np.array([lin[k] for k in keys])
        M = np.array([self.values.atPose3(k).matrix() for k in keys])
        R0t = M0[:, :3, :3].transpose(0, 2, 1)
        cos = 0.5 * (np.trace(R0t @ M[:, :3, :3], axis1=1, axis2=2) - 1.0)
        dt = np.einsum("nij,nj->ni", R0t, M[:, :3, 3] - M0[:, :3, 3])
        far = (np.arccos(np.clip(cos, -1.0, 1.0)) > self.params.relinearize_rad) | (
            np.linalg.norm(dt, axis=1) > self.params.relinearize_m
        )
        return {k for k, f in zip(keys, far, strict=True) if f}

    def _vehicle_motion(self, chain: _Chain, ka: int, kb: int) -> None:
        a, b = chain.states[ka], chain.states[kb]
        dt = b.t - a.t
        if dt <= 0 or dt > self.params.motion_factor_max_dt_s:
            return
        p = self.params
        t_rel = a.M[:3, :3].T @ (0.5 * (a.v_map + b.v_map) * dt)
        s_t = np.hypot(p.vehicle_velocity_sigma_mps * dt, 0.5 * p.vehicle_accel_sigma_mps2 * dt**2)
        s_r = p.vehicle_rate_sigma_radps * dt
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([s_r, s_r, s_r, s_t, s_t, s_t]))
        f = gtsam.BetweenFactorPose3(a.key, b.key, gtsam.Pose3(gtsam.Rot3(), t_rel), noise)
        chain.motion[ka] = self._add_factor(f)

    def vehicle_state(self, vid: str, t: float, tol: float) -> _PoseState | None:
        chain = self.vehicles.get(vid)
        return None if chain is None else chain.nearest(t, tol)

    # ------------------------------------------------------------------ tracks
    def track_state(self, track_id: int, t: float, init_p, init_v, cls: int) -> _TrackState | None:
        """The track's state for time t (an existing one within time_merge_s, else a new one); None if
        t is before the track's first state, whose prior already holds that past (see
        :meth:`fold_detection`)."""
        chain = self.tracks.get(track_id)
        if chain is None:
            chain = self.tracks[track_id] = _Chain(cls=int(cls))
        s = chain.nearest(t, self.params.time_merge_s)
        if s is not None:
            return s
        tk = time_key(t)
        if chain.tkeys and tk < chain.tkeys[0]:
            return None
        key = S(self._n["s"])
        self._n["s"] += 1
        i = bisect.bisect_left(chain.tkeys, tk)
        if chain.tkeys:  # warm start from the neighbour: constant velocity, as the motion factor predicts
            nb = chain.states[chain.tkeys[max(i - 1, 0)]]
            x = self.values.atVector(nb.key)
            x0 = np.concatenate([x[:3] + x[3:] * (t - nb.t), x[3:]])
        else:
            x0 = np.concatenate([np.asarray(init_p, dtype=float), np.asarray(init_v, dtype=float)])
        self.values.insert(key, x0)
        s = _TrackState(float(t), key)
        chain.tkeys.insert(i, tk)
        chain.states[tk] = s
        if 0 < i < len(chain.tkeys) - 1:
            self._remove_factor(chain.motion.pop(chain.tkeys[i - 1], -1))
        if i > 0:
            self._track_motion(chain, chain.tkeys[i - 1], tk)
        if i < len(chain.tkeys) - 1:
            self._track_motion(chain, tk, chain.tkeys[i + 1])
        if chain.prior is None:
            sv = speed_prior(self.params, chain.cls)
            mean = np.concatenate([x0[:3], np.zeros(3)])
            info = np.diag(1.0 / np.array([1e6, 1e6, 1e6, sv**2, sv**2, 0.25]))
            self._set_prior(chain, _TrackPrior(tk, info, info @ mean))
        return s

    def _track_motion(self, chain: _Chain, ka: int, kb: int) -> None:
        """Constant velocity from state a to b: e = s_b - F s_a ~ N(0, Q) (linear, so exact as a
        linear factor about 0: its error at any values is |W (s_b - F s_a)|^2 / 2)."""
        a, b = chain.states[ka], chain.states[kb]
        ck = (round((b.t - a.t) * 1e6), chain.cls)  # fleets sample on one clock: a few distinct dt
        if ck not in self._motion_blocks:
            F, Q = cv_model(b.t - a.t, accel_psd(self.params, chain.cls))
            W = _sqrt_info(Q)
            self._motion_blocks[ck] = (-W @ F, W)
        A_a, A_b = self._motion_blocks[ck]
        r = A_a @ self.values.atVector(a.key) + A_b @ self.values.atVector(b.key)
        jf = gtsam.JacobianFactor(a.key, A_a, b.key, A_b, -r, _UNIT6)  # about the current values
        chain.motion[ka] = self._add_factor(gtsam.LinearContainerFactor(jf, self.values))

    def _set_prior(self, chain: _Chain, prior: _TrackPrior, sqrt: tuple | None = None) -> None:
        """Put the prior in the graph (replacing the track's prior): a linear factor ||A y - r||^2 / 2 with
        A^T A = info and A^T r = eta, about the current values. ``sqrt``: (A, r) if the caller has them
        (:func:`_sqrt_information`)."""
        self._remove_factor(chain.prior_fid)
        chain.prior = prior
        keys = [chain.states[prior.tkey].key] + [self.vehicles[v].bias_key for v in prior.vids]
        A, r = _sqrt_information(prior.info[None], prior.eta[None]) if sqrt is None else sqrt
        A, r = A.reshape(len(prior.eta), -1), r.reshape(-1)
        y0 = np.concatenate([self.values.atVector(k) for k in keys])
        jf = _jacobian_factor(keys, A, r - A @ y0)
        chain.prior_fid = self._add_factor(gtsam.LinearContainerFactor(jf, self.values), tuple(keys))

    def _in_map(self, dets: list[_Detection]) -> tuple[np.ndarray, ...]:
        """Detections moved to the map frame with their observers' reported poses z_k: m = R z + t, the
        detector's covariance R S_z R^T, the Jacobian J = d m / d xi = [-R [z]x, R] of the observer's
        error xi (Pose3 tangent [rotation, translation]) and L with L L^T = S_xi, the reported pose
        covariance in that tangent. The reported pose, not the estimate: the graph models the true pose as
        z_k (+) L (b + n_k) (``_pose_prior``), so the errors of m are J L b (persistent, kept as b) and
        J L n_k (independent). Vectorised."""
        M = np.array([self._pose_states[d.pose_key].M for d in dets])
        R, t = M[:, :3, :3], M[:, :3, 3]
        z = np.array([d.z for d in dets])
        Sz = np.array([d.cov for d in dets])
        L = np.array([self._pose_states[d.pose_key].L_xi for d in dets])
        zx = np.zeros((len(dets), 3, 3))
        zx[:, 0, 1], zx[:, 0, 2], zx[:, 1, 2] = -z[:, 2], z[:, 1], -z[:, 0]
        zx[:, 1, 0], zx[:, 2, 0], zx[:, 2, 1] = z[:, 2], -z[:, 1], z[:, 0]
        J = np.concatenate([-R @ zx, R], axis=2)
        return np.einsum("nij,nj->ni", R, z) + t, R @ Sz @ R.transpose(0, 2, 1), J, L

    def _detection_information(
        self, dets: list[_Detection], p0: np.ndarray, extra=None, age: float = 0.0
    ) -> tuple[list, np.ndarray, np.ndarray, np.ndarray]:
        """Information of detections about [s, b_v] (s the state whose position they measure, directly or
        through H; b_v the observer's persistent error): r = p - J L b_v - m ~ N(0, C / w),
        C = R S_z R^T + (1 - a) J S_xi J^T (+ ``extra``), w the Huber weight at the estimate p0 (N, 3).
        Without a persistent part (a = 0, or a vehicle without b) C has the whole J S_xi J^T and there is
        no b_v. Returns (vid or None per detection, S = w C^-1 (N, 3, 3), G = -J L (N, 3, 6), m (N, 3)).
        ``age``: the detections are that much older than the b they are tied to, b(t - age) =
        rho b(t) + w (see :meth:`_summarize_first`): G = -rho J L and a (1 - rho^2) J S_xi J^T more noise."""
        a = self.params.pose_error_persistent_fraction
        m, Cz, J, L = self._in_map(dets)
        JL = J @ L
        Cpose = JL @ JL.transpose(0, 2, 1)
        if extra is not None:
            Cz = Cz + extra
        r = m - p0
        dist = np.sqrt(np.einsum("ni,nij,nj->n", r, np.linalg.inv(Cz + Cpose), r))
        k = self.params.huber_k
        w = np.ones(len(dets)) if k is None else np.minimum(1.0, k / np.maximum(dist, 1e-12))
        vids = [self._pose_states[d.pose_key].vid for d in dets]
        has_b = np.array([a > 0 and self.vehicles[v].bias_key is not None for v in vids])
        rho = float(np.exp(-abs(age) / self.params.pose_error_persistence_s))
        C = Cz + np.where(has_b, 1.0 - a * rho**2, 1.0)[:, None, None] * Cpose
        S = w[:, None, None] * np.linalg.inv(C)
        return [v if b else None for v, b in zip(vids, has_b, strict=True)], S, -rho * JL, m

    def _summarize_first(self, chains: list[_Chain]) -> None:
        """Fold each chain's first state (its prior and its detections) into a prior on its second state.

        The prior (information over [s0, b...]) plus the first state's detections (``_detection_information``)
        plus the constant-velocity model s1 = F s0 + w, w ~ N(0, Q), with s0 marginalised out (Schur
        complement); then the persistent errors age by dt: b(t0) = rho b(t1) + w, rho = exp(-dt / tau),
        w ~ N(0, a (1 - rho^2) I), b(t0) marginalised out (tau = pose_error_persistence_s), so that old
        detections do not stay tied to a vehicle's current error. The result is information over
        [s1, b(t1)...]. What this neglects: the correlation of the detections' independent pose errors
        n_k with the frames still in the window. Vectorised in batches (:func:`_batches`): a prior padded
        with zero information over vehicles it does not hold stays zero and uncoupled there through every
        step, and the leading block of a Cholesky factor is the factor of the leading block, so each prior's
        slice of its batch is its own result.
        """
        a = self.params.pose_error_persistent_fraction
        owner, dets = [], []
        for i, c in enumerate(chains):
            for d in c.states[c.tkeys[0]].dets:
                if d.pose_key in self._pose_states:
                    owner.append(i)
                    dets.append(d)
        owner = np.array(owner, dtype=int)
        vid_lists = [list(c.prior.vids) for c in chains]
        slot = np.full(len(dets), -1)
        if dets:
            p0 = np.array([self.values.atVector(d.target_key)[:3] for d in dets])
            dvids, S, G, m = self._detection_information(dets, p0)
            for n, (i, v) in enumerate(zip(owner, dvids, strict=True)):
                if v is not None:
                    if v not in vid_lists[i]:
                        vid_lists[i].append(v)
                    slot[n] = vid_lists[i].index(v)
        dt = np.array([c.states[c.tkeys[1]].t - c.states[c.tkeys[0]].t for c in chains])
        F, Q = cv_model(dt, np.array([accel_psd(self.params, c.cls) for c in chains]))
        Qi = np.linalg.inv(Q)
        if dets:  # each detection's terms: [s, b_v] blocks of S, S G, G^T S G and of eta
            Sm = np.einsum("nij,nj->ni", S, m)
            SG = S @ G
            GSG = G.transpose(0, 2, 1) @ SG
            SGm = np.einsum("nji,nj->ni", SG, m)
            bcol = 6 + 6 * slot[:, None] + np.arange(6)  # the columns of its b_v (where slot >= 0)
            i3 = np.arange(3)
        for mm, idx in _batches(np.array([len(v) for v in vid_lists])):
            g, n = len(idx), 6 + 6 * mm
            info, eta = np.zeros((g, n, n)), np.zeros((g, n))
            for r, i in enumerate(idx):
                k = len(chains[i].prior.info)
                info[r, :k, :k], eta[r, :k] = chains[i].prior.info, chains[i].prior.eta
            if dets:
                row_of = np.full(len(chains), -1)
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
                # b(t0) = rho b(t1) + w, b(t0) marginalised
                rho = np.exp(-np.abs(dt[idx]) / self.params.pose_error_persistence_s)
                omega = 1.0 / (a * (1.0 - rho**2))
                Mi = np.linalg.inv(new[:, 6:, 6:] + omega[:, None, None] * np.eye(6 * mm))
                Lsb, eb = new[:, :6, 6:].copy(), new_eta[:, 6:].copy()
                LM = Lsb @ Mi
                new[:, :6, :6] -= LM @ Lsb.transpose(0, 2, 1)
                new[:, :6, 6:] = (rho * omega)[:, None, None] * LM
                new[:, 6:, :6] = new[:, :6, 6:].transpose(0, 2, 1)
                new[:, 6:, 6:] = (rho**2 * omega)[:, None, None] * (np.eye(6 * mm) - omega[:, None, None] * Mi)
                new_eta[:, :6] -= np.einsum("nij,nj->ni", LM, eb)
                new_eta[:, 6:] = (rho * omega)[:, None] * np.einsum("nij,nj->ni", Mi, eb)
            new = 0.5 * (new + new.transpose(0, 2, 1))
            A, rhs = _sqrt_information(new, new_eta)
            for r, i in enumerate(idx):
                c, k = chains[i], 6 + 6 * len(vid_lists[i])
                prior = _TrackPrior(c.tkeys[1], new[r, :k, :k].copy(), new_eta[r, :k].copy(), tuple(vid_lists[i]))
                self._set_prior(c, prior, (A[r, :k, :k], rhs[r, :k]))

    def fold_detection(self, track_id: int, pose_key: int, z_body, cov_body, weight: float = 1.0) -> None:
        """A detection older than the track's first state (a late message) into the track's prior, whose
        state is dt later: retrodicted through the constant-velocity model, m = p - v dt + w,
        w ~ N(0, Q_pp(dt)) added to its noise (the correlation of w with the prior's own prediction noise
        is neglected). ``weight`` is its first Huber weight (from the association); the fold recomputes it
        at the track's estimate."""
        chain = self.tracks[track_id]
        prior = chain.prior
        ps = self._pose_states[pose_key]
        det = _Detection(pose_key, -1, np.asarray(z_body, dtype=float), np.asarray(cov_body, dtype=float), ps.t)
        dt = chain.states[prior.tkey].t - ps.t
        _, Q = cv_model(dt, accel_psd(self.params, chain.cls))
        H = np.hstack([np.eye(3), -dt * np.eye(3)])
        x = self.values.atVector(chain.states[prior.tkey].key)
        (v,), (S,), (G,), (m,) = self._detection_information([det], (H @ x)[None], Q[None, :3, :3], age=dt)
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
        self._set_prior(chain, _TrackPrior(prior.tkey, info, eta, tuple(vids)))

    def _forget_bias(self, vid: str) -> None:
        """A vehicle leaves the graph: its persistent error b_v is marginalised out of the track priors
        that hold it, at its prior N(0, a I)."""
        a = self.params.pose_error_persistent_fraction
        for chain in self.tracks.values():
            prior = chain.prior
            if prior is None or vid not in prior.vids:
                continue
            j = 6 + 6 * prior.vids.index(vid)
            info = prior.info.copy()
            info[j : j + 6, j : j + 6] += np.eye(6) / a
            new_info, new_eta = _marginalize(info, prior.eta, np.arange(j, j + 6))
            vids = tuple(v for v in prior.vids if v != vid)
            self._set_prior(chain, _TrackPrior(prior.tkey, new_info, new_eta, vids))

    # ------------------------------------------------------------------ detections
    def add_detection(self, pose_key: int, state: _TrackState, z_body, cov_body, weight: float = 1.0) -> None:
        """A body-frame detection z_body (cov_body) of the track state by the vehicle at pose_key.

        ``weight`` is the first Huber weight (from the association innovation); later ones follow the
        estimate (IRLS, see :meth:`_reweight`).
        """
        self.add_detections([(pose_key, state, z_body, cov_body, weight)])

    def add_detections(self, items: list) -> None:
        """Many :meth:`add_detection` calls at once: items of (pose_key, state, z_body, cov_body, weight)."""
        dets = self._new_detections([(pk, state.key, z, cov) for pk, state, z, cov, _ in items], cross=False)
        for det, (_, state, _, _, weight) in zip(dets, items, strict=True):
            det.weight = weight
            state.dets.append(det)
        self._attach(dets)

    def add_cross_detections(self, items: list) -> None:
        """Body-frame detections of other connected vehicles' body origins (cross-localization): items of
        (observer pose key, observed vehicle's pose key, z_body, cov_body)."""
        self._attach(self._new_detections(items, cross=True))

    def _new_detections(self, items: list, cross: bool) -> list[_Detection]:
        """Detection records of items (pose_key, target_key, z_body, cov_body), on their observers' frames."""
        if not items:
            return []
        covs = np.array([it[3] for it in items], dtype=float).reshape(-1, 3, 3)
        Ws = np.linalg.inv(np.linalg.cholesky(covs))  # W^T W = cov^-1
        dets = []
        for (pose_key, target_key, z, _), cov, W in zip(items, covs, Ws, strict=True):
            ps = self._pose_states[pose_key]
            det = _Detection(pose_key, target_key, np.asarray(z, dtype=float), cov, ps.t, cross=cross, W=W)
            ps.dets.append(det)
            dets.append(det)
        return dets

    def _attach(self, dets: list[_Detection]) -> None:
        """Put the detections' factors in the graph."""
        if not dets:
            return
        for det, f in zip(dets, self._linear_factors(dets), strict=True):
            det.fid = self._add_factor(f, (det.pose_key, det.target_key))
            self._fid_det[det.fid] = det

    def _linear_factors(self, dets: list[_Detection]) -> list[gtsam.LinearContainerFactor]:
        """Linearized detection factors (module docstring), both kinds, vectorised.

        e = R^T (p - t) - z at the current observer pose x0 = (R0, t0) and target: p is a track state's
        position (state [p, v]) or an observed vehicle's origin (cross). With q0 = R0^T (p0 - t0):
        d e / d xi = [[q0]x, -I]; d e / d s = [R0^T, 0] (track) or d e / d xi_target = [0, R0^T R_target]
        (cross); e(x0, p0) = q0 - z; whitened by sqrt(weight) W.
        """
        M, mats, q = self._observed(dets)
        R0t = mats[:, :3, :3].transpose(0, 2, 1)
        cross = np.array([d.cross for d in dets])
        W = np.sqrt(np.array([d.weight for d in dets]))[:, None, None] * np.array([d.W for d in dets])
        A_x = np.zeros((len(dets), 3, 6))
        A_x[:, :, :3] = _skews(q)
        A_x[:, :, 3:] = -np.eye(3)
        A_t = np.zeros((len(dets), 3, 6))
        A_t[~cross, :, :3] = R0t[~cross]
        if cross.any():
            R_t = np.array([M[d.target_key][:3, :3] for d in dets if d.cross])
            A_t[cross, :, 3:] = R0t[cross] @ R_t
        WA_x, WA_t = W @ A_x, W @ A_t
        b = np.einsum("nij,nj->ni", W, np.array([d.z for d in dets]) - q)
        out = []
        for n, d in enumerate(dets):
            d.lin_pose = mats[n]
            jf = gtsam.JacobianFactor(d.pose_key, WA_x[n], d.target_key, WA_t[n], b[n], _UNIT3)
            out.append(gtsam.LinearContainerFactor(jf, self.values))
        return out

    def _observed(self, dets: list[_Detection]) -> tuple[dict[int, np.ndarray], np.ndarray, np.ndarray]:
        """Where the detections' targets are in their observers' frames at the current values: the 4x4 of
        every pose involved (by key), the observers' (N, 4, 4) and q = R0^T (p0 - t0) (N, 3), p0 the track
        state's position or the observed vehicle's origin (cross)."""
        M: dict[int, np.ndarray] = {}
        for d in dets:
            for key in (d.pose_key, d.target_key) if d.cross else (d.pose_key,):
                if key not in M:
                    M[key] = self.values.atPose3(key).matrix()
        mats = np.array([M[d.pose_key] for d in dets])
        p0 = np.array([M[d.target_key][:3, 3] if d.cross else self.values.atVector(d.target_key)[:3] for d in dets])
        return M, mats, np.einsum("nji,nj->ni", mats[:, :3, :3], p0 - mats[:, :3, 3])

    def _reweight(self) -> int:
        """IRLS step of the linearized detections: new Huber weights from the current estimate for
        detections younger than reweight_s (those not yet through a solve keep the weight of their
        association innovation), and new linearization points for detections whose poses moved.
        Returns how many factors were replaced."""
        p = self.params
        k = p.huber_k
        moved = self._moved({key: ps.dets[0].lin_pose for key, ps in self._pose_states.items() if ps.dets})
        newest = max((c.latest().t for c in self.vehicles.values()), default=0.0)
        todo = []
        recent = []
        for det in self._fid_det.values():
            if det.fresh:
                det.fresh = False
            elif k is not None and newest - det.t <= p.reweight_s:
                recent.append(det)
            elif det.pose_key in moved or (det.cross and det.target_key in moved):
                todo.append((det, det.weight))
        if recent:
            e = self._observed(recent)[2] - np.array([d.z for d in recent])
            we = np.einsum("nij,nj->ni", np.array([d.W for d in recent]), e)
            dist = np.linalg.norm(we, axis=1)
            w_new = np.minimum(1.0, k / np.maximum(dist, 1e-12))
            for det, w in zip(recent, w_new, strict=True):
                relin = det.pose_key in moved or (det.cross and det.target_key in moved)
                if relin or abs(w - det.weight) > 0.05 * det.weight:
                    todo.append((det, float(w)))
        for det, w in todo:
            det.weight, det.fresh = w, False
            self._remove_factor(det.fid)
        self._attach([det for det, _ in todo])
        return len(todo)

    # ------------------------------------------------------------------ window
    def remove_track(self, track_id: int) -> None:
        chain = self.tracks.pop(track_id, None)
        if chain is None:
            return
        for s in chain.states.values():
            self._drop_track_state(s)

    def _drop_track_state(self, s: _TrackState) -> None:
        for det in s.dets:
            ps = self._pose_states.get(det.pose_key)
            if ps is not None and det in ps.dets:
                ps.dets.remove(det)
        self._remove_key(s.key)

    def prune(self, t_min: float) -> int:
        """Drop every state older than t_min with its factors; returns the number of states dropped.

        A track's dropped states are first folded into a prior on its oldest kept state.
        """
        kmin = time_key(t_min)
        lag = time_key(self.params.track_window_s)
        dropped = 0
        while True:  # one state per track and round, the summaries of a round vectorised
            due = [c for c in self.tracks.values() if c.tkeys and (c.tkeys[0] < kmin or c.tkeys[0] < c.tkeys[-1] - lag)]
            if not due:
                break
            keep = [c for c in due if len(c.tkeys) > 1]
            if keep:
                self._summarize_first(keep)
            for chain in due:
                tk = chain.tkeys.pop(0)
                chain.motion.pop(tk, None)
                self._drop_track_state(chain.states.pop(tk))
                dropped += 1
        for tid, chain in list(self.tracks.items()):
            if not chain.tkeys:
                del self.tracks[tid]
        for vid, chain in list(self.vehicles.items()):
            while chain.tkeys and chain.tkeys[0] < kmin:
                tk = chain.tkeys.pop(0)
                chain.motion.pop(tk, None)
                chain.pose_prior_fids.pop(tk, None)
                key = chain.states.pop(tk).key
                self._pose_states.pop(key, None)
                self._remove_key(key)
                dropped += 1
            if not chain.tkeys:
                if chain.bias_key is not None:
                    self._forget_bias(vid)
                    self._remove_key(chain.bias_key)
                del self.vehicles[vid]
        return dropped

    # ------------------------------------------------------------------ solve
    def snapshot(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[int]]:
        """A copy of the window: its factors (no empty slots), its values and its latest keys."""
        graph = gtsam.NonlinearFactorGraph()
        for f in self._factors.values():
            graph.add(f)
        return graph, gtsam.Values(self.values), self.latest_keys()

    def latest_keys(self) -> list[int]:
        keys = [c.latest().key for c in self.vehicles.values()]
        return keys + [c.latest().key for c in self.tracks.values()]

    def solve(self) -> SolveReport:
        """Levenberg-Marquardt from the current values; latest-state covariances (module docstring)."""
        reweighted = self._reweight() + self._relinearize_pose_priors()
        graph = self._factor_graph()
        latest = self.latest_keys()
        n_vars = self.num_variables
        if not self._factors:
            self.covariances = {}
            return SolveReport(0, 0.0, 0.0, 0, n_vars, 0, reweighted)
        ordering = gtsam.Ordering.ColamdConstrainedLastNonlinearFactorGraph(graph, latest)
        values = self.values
        err = None
        lam = self.params.lambda_initial
        bt = None
        it = 0
        while it < self.params.max_iterations:
            it += 1
            gfg = graph.linearize(values)
            lin0 = gfg.error(values.zeroVectors())  # the linear model's cost at the current values
            if err is None:  # without GTSAM-robust factors that is the cost itself
                err = err0 = lin0
            if lam > 0:
                for key in values.keys():
                    gfg.push_back(gtsam.JacobianFactor(key, np.sqrt(lam) * np.eye(6), np.zeros(6), _UNIT6))
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
                # Converged when the cost barely moved, or when the step did what the linear model
                # predicted: it landed on the minimum of an accurate quadratic model. (Robust factors
                # linearise to IRLS quadratics whose values differ from the robust cost by a constant,
                # so compare predicted and actual decrease, not the values.)
                predicted = lin0 - gfg.error(delta)
                model_ok = lam == 0 and abs(predicted - decrease) <= max(self.params.model_tol * new_err, 1e-3)
                values, err = new, new_err
                lam = lam / 10 if lam > 1e-3 else 0.0
                if decrease <= max(self.params.relative_error_tol * new_err, 1e-3) or model_ok:
                    break
            else:
                lam = max(10 * lam, 1.0)
        self.values = values
        try:
            if bt is None:  # no undamped elimination was accepted: one more at the solution
                bt = graph.linearize(values).eliminateMultifrontal(ordering)
            below = self._covariances(bt, latest)
        except (RuntimeError, np.linalg.LinAlgError):  # a degenerate system: say so with huge covariances
            below = -1
            self.covariances = {k: 1e6 * np.eye(6) for k in latest}
        return SolveReport(it, float(err0), float(err), len(self._factors), n_vars, below, reweighted)

    def _covariances(self, bt: gtsam.GaussianBayesTree, latest: list[int]) -> int:
        """Marginal covariances of the latest states, top-down on the Bayes tree from the roots.

        Each clique on a path from a latest key to its root gets a factor L of its frontal variables,
        as blocks over independent unit noise sources (one per clique), so that
        Cov(x_i, x_j) = sum_s L_i[s] L_j[s]^T: a root R x = d + e has L = R^-1; a clique
        R x_F + S x_S = d + e below has L_F = -R^-1 S L_S plus R^-1 for its own source. With the latest
        states ordered last the roots hold nearly all of them and the paths are short. Returns the number
        of cliques below a root that were visited.
        """
        wanted = set(latest)
        L: dict[int, dict[int, np.ndarray]] = {}  # clique id -> {source clique id: rows of its frontals}
        where: dict[int, tuple[int, int, int]] = {}  # key -> (clique id, row offset, dim)
        self.root_dims = 0
        below = 0

        def visit(clique) -> None:
            nonlocal below
            c = clique.conditional()
            keys = [int(k) for k in c.keys()]
            cid = keys[0]
            if cid in L:
                return
            R = c.R()
            nf, rows = 0, 0
            while rows < R.shape[0]:
                where[keys[nf]] = (cid, rows, 6)
                rows += 6
                nf += 1
            Rinv, info = lapack.dtrtri(R, lower=0)  # unblocked for small n: no BLAS thread wake-ups
            if info != 0:
                raise np.linalg.LinAlgError(f"singular conditional at {gtsam.DefaultKeyFormatter(cid)}")
            blocks = {cid: Rinv}
            parents = keys[nf:]
            if parents:
                below += 1
                visit(clique.parent())  # visits every ancestor: the separator's keys are frontal there
                G = -Rinv @ c.S()
                sep = [where[k] for k in parents]
                sources = set().union(*(L[w[0]].keys() for w in sep))
                for src in sources:
                    cols = next(L[w[0]][src].shape[1] for w in sep if src in L[w[0]])
                    LS = np.zeros((G.shape[1], cols))
                    off = 0
                    for owner, r0, d in sep:
                        if src in L[owner]:
                            LS[off : off + d] = L[owner][src][r0 : r0 + d]
                        off += d
                    blocks[src] = G @ LS if src not in blocks else blocks[src] + G @ LS
            else:
                self.root_dims = max(self.root_dims, int(R.shape[0]))
            L[cid] = blocks

        for key in wanted:
            if key not in where:
                visit(bt[key])

        def cross(a: int, b: int) -> np.ndarray:
            (ca, ra, da), (cb, rb, db) = where[a], where[b]
            La, Lb = L[ca], L[cb]
            out = np.zeros((da, db))
            for s in La.keys() & Lb.keys():
                out += La[s][ra : ra + da] @ Lb[s][rb : rb + db].T
            return out

        self.covariances = {k: 0.5 * (C + C.T) for k in wanted for C in (cross(k, k),)}
        return below

    # ------------------------------------------------------------------ results
    def vehicle_estimate(self, vid: str) -> tuple[float, gtsam.Pose3, np.ndarray | None]:
        """(t, Pose3, tangent covariance or None before a solve) of a vehicle's latest frame."""
        s = self.vehicles[vid].latest()
        return s.t, self.values.atPose3(s.key), self.covariances.get(s.key)

    def track_estimate(self, track_id: int) -> tuple[float, np.ndarray, np.ndarray, np.ndarray | None]:
        """(t, p, v, 6x6 covariance of [p, v] or None) of a track's latest state."""
        s = self.tracks[track_id].latest()
        x = self.values.atVector(s.key)
        return s.t, x[:3], x[3:], self.covariances.get(s.key)
