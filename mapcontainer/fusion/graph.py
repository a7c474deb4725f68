"""The host's sliding-window factor graph (paper §III-D, "Driving Environment Space State Estimator").

States (GTSAM keys):

* ``x``: Pose3 T_map_body of a connected vehicle at the t_meas of each of its messages: the pose its
  camera sees in the map (a vehicle's detections are placed from it; the body is off it by the error
  every frame repeats, VehiclePrior.pose_bias_sigma, which the container adds to the output);
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
  Pose3's tangent, see :mod:`.poses`). A filtered estimate (VehiclePrior.pose_filtered, what vehicles
  send) already holds everything the vehicle knows, so only the vehicle's newest frame keeps one, a
  ``PriorFactorPose3``: its information is used once, and the earlier frames hang on it by the motion
  factors. Per-frame evidence (a version 3 sender): ``PriorFactorPose3`` on every frame, or, with
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
  whose detections it holds (one linear factor): at birth a zero-mean velocity prior and a 1 km
  position regulariser; when a track's first state is older than the lag (or the window), it and its
  detections are marginalised into a prior on the next state; late detections are folded in,
  retrodicted; b_v leaves the prior with its vehicle (the model and what it neglects:
  :mod:`.marginalize`). Why a lag at all: the graph is dense in time (every vehicle sees about half
  of the objects at every instant), so elimination grows with the number of track instants; with
  0.3 s instead of the 1 s window the host cycle at 16 vehicles / 100 objects is ~27 % shorter,
  estimates unchanged on the bench and the simulator. Vehicle frames stay for the window, so that
  late messages still find their poses;
* a detection z of a track's position, or of another connected vehicle's origin (cross-localization),
  by the vehicle at pose x: the exact Cartesian model in the observer's body frame, Huber-robust, as
  one linear factor on (x, target), re-linearised when the pose estimate moves (:mod:`.detections`).

Solve: Levenberg-Marquardt warm-started from the previous solution, the latest states' covariances from
its last elimination (:mod:`.solver`).
"""

from __future__ import annotations

import bisect

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, S, X

from schemas import ObjectClass

from . import detections, marginalize, solver
from .buffer import time_key
from .detections import DetectionRecord
from .laps import Laps
from .marginalize import TrackPrior
from .motion import accel_psd, cv_model, speed_prior
from .params import FusionParams
from .poses import pose3_from_vector, pose_cov_to_tangent
from .solver import SolveReport
from .values import vector_table, vectors
from .window import Chain, PoseState, TrackState

__all__ = ["FusionGraph"]

_UNIT6 = gtsam.noiseModel.Unit.Create(6)


def _sqrt_info(cov: np.ndarray) -> np.ndarray:
    """W with W^T W = cov^-1 (upper triangular)."""
    return np.linalg.cholesky(np.linalg.inv(cov)).T


# What one more batch of track summaries costs, in units of the padding it avoids
# (:func:`.marginalize.batches`). Estimated from two timings: a batch ~0.3 ms; padding every prior of
# the 16 vehicles / 100 objects bench to the largest size cost ~18 ms more, ~2.6 ns per unit; so a batch
# is worth ~1e5 units. At 4 / 14 that makes one batch; at 16 / 100 the larger sizes stay apart.
_BATCH_UNITS = 1e5


def _batches(sizes: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """The track summaries' batches (:func:`.marginalize.batches`) at this module's ``_BATCH_UNITS``."""
    return marginalize.batches(sizes, _BATCH_UNITS)


class FusionGraph:
    """Sliding-window factor graph over connected-vehicle poses and obstacle tracks (module docstring)."""

    def __init__(self, params: FusionParams):
        self.params = params
        self.values = gtsam.Values()
        self.vehicles: dict[str, Chain] = {}
        self.tracks: dict[int, Chain] = {}
        self._factors: dict[int, gtsam.NonlinearFactor] = {}
        self._factor_keys: dict[int, tuple[int, ...]] = {}
        self._key_factors: dict[int, set[int]] = {}
        self._fid_det: dict[int, DetectionRecord] = {}
        self._next_fid = 0
        self._pose_states: dict[int, PoseState] = {}
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
    def add_vehicle_prior(self, vid: str, t: float, pose, pose_cov, v_map, filtered: bool = False) -> int | None:
        """Add a vehicle's self-localization at t; returns its pose key (None if that instant exists).

        ``filtered``: the pose is the vehicle's filtered estimate (VehiclePrior.pose_filtered), which holds
        everything the vehicle knows so far: only the newest frame of the vehicle keeps its prior (the
        earlier ones are dropped, a late frame gets none), so the vehicle's information is used once; its
        earlier frames stay, tied by the motion factors, for the detections made from them. Otherwise
        every frame's prior is independent evidence apart from the persistent part (``_pose_prior``).
        """
        chain = self.vehicles.get(vid)
        if chain is None:
            p = self.params
            persist = (
                (p.filtered_pose_error_persistent_fraction, p.filtered_pose_error_persistence_s)
                if filtered
                else (p.pose_error_persistent_fraction, p.pose_error_persistence_s)
            )
            chain = self.vehicles[vid] = Chain(cls=int(ObjectClass.VEHICLE), persist=persist)
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
        state = PoseState(float(t), key, pose, cov, np.asarray(v_map, dtype=float), cov_xi, L_xi, T, M, vid=vid)
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
        if not filtered:
            self._pose_prior(chain, i)
        elif i == len(chain.tkeys) - 1:
            for old in list(chain.pose_prior_fids):
                self._remove_factor(chain.pose_prior_fids.pop(old))
                chain.states[old].prior_lin = None
            self._pose_prior(chain, i)
        return key

    def _pose_prior(self, chain: Chain, i: int) -> None:
        """(Re)make the self-localization factor of the chain's i-th frame (module docstring).

        With the vehicle's persistent fraction a = 0 (``Chain.persist``: pose_error_persistent_fraction for
        per-frame evidence, filtered_pose_error_persistent_fraction for a filtered prior, the only one of
        its vehicle): PriorFactorPose3 with the reported covariance. With
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
        a = chain.persist[0]
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
        moved = detections.moved(
            {s.key: s.prior_lin for s in self._pose_states.values() if s.prior_lin is not None},
            self.values,
            self.params,
        )
        n = 0
        for chain in self.vehicles.values():
            for i, tk in enumerate(chain.tkeys):
                if chain.states[tk].key in moved:
                    self._pose_prior(chain, i)
                    n += 1
        return n

    def _vehicle_motion(self, chain: Chain, ka: int, kb: int) -> None:
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
        chain.motion[ka] = self._add_factor(f, (a.key, b.key))

    def vehicle_state(self, vid: str, t: float, tol: float) -> PoseState | None:
        chain = self.vehicles.get(vid)
        return None if chain is None else chain.nearest(t, tol)

    # ------------------------------------------------------------------ tracks
    def track_state(self, track_id: int, t: float, init_p, init_v, cls: int) -> TrackState | None:
        """The track's state for time t (an existing one within time_merge_s, else a new one); None if
        t is before the track's first state, whose prior already holds that past (see
        :meth:`fold_detection`)."""
        chain = self.tracks.get(track_id)
        if chain is None:
            chain = self.tracks[track_id] = Chain(cls=int(cls))
        s = chain.nearest(t, self.params.time_merge_s)
        if s is not None:
            return s
        tk = time_key(t)
        if chain.tkeys and tk < chain.tkeys[0]:
            return None
        key = S(self._n["s"])
        self._n["s"] += 1
        i = bisect.bisect_left(chain.tkeys, tk)
        x_nb = None
        if chain.tkeys:  # warm start from the neighbour: constant velocity, as the motion factor predicts
            nb = chain.states[chain.tkeys[max(i - 1, 0)]]
            x_nb = self.values.atVector(nb.key)
            x0 = np.concatenate([x_nb[:3] + x_nb[3:] * (t - nb.t), x_nb[3:]])
        else:
            x0 = np.concatenate([np.asarray(init_p, dtype=float), np.asarray(init_v, dtype=float)])
        self.values.insert(key, x0)
        s = TrackState(float(t), key)
        chain.tkeys.insert(i, tk)
        chain.states[tk] = s
        if 0 < i < len(chain.tkeys) - 1:
            self._remove_factor(chain.motion.pop(chain.tkeys[i - 1], -1))
        if i > 0:  # the neighbour before is the warm start's
            self._track_motion(chain, chain.tkeys[i - 1], tk, x_nb, x0)
        if i < len(chain.tkeys) - 1:
            self._track_motion(chain, tk, chain.tkeys[i + 1], x0)
        if chain.prior is None:
            self._set_prior(chain, marginalize.birth_prior(tk, x0[:3], speed_prior(self.params, chain.cls)))
        return s

    def _track_motion(
        self, chain: Chain, ka: int, kb: int, xa: np.ndarray | None = None, xb: np.ndarray | None = None
    ) -> None:
        """Constant velocity from state a to b: e = s_b - F s_a ~ N(0, Q) (linear, so exact as a
        linear factor about 0: its error at any values is |W (s_b - F s_a)|^2 / 2). ``xa``, ``xb``: the
        states' current values, if the caller has them."""
        a, b = chain.states[ka], chain.states[kb]
        ck = (round((b.t - a.t) * 1e6), chain.cls)  # fleets sample on one clock: a few distinct dt
        if ck not in self._motion_blocks:
            F, Q = cv_model(b.t - a.t, accel_psd(self.params, chain.cls))
            W = _sqrt_info(Q)
            self._motion_blocks[ck] = (-W @ F, W)
        A_a, A_b = self._motion_blocks[ck]
        xa = self.values.atVector(a.key) if xa is None else xa
        xb = self.values.atVector(b.key) if xb is None else xb
        r = A_a @ xa + A_b @ xb
        jf = gtsam.JacobianFactor(a.key, A_a, b.key, A_b, -r, _UNIT6)  # about the current values
        chain.motion[ka] = self._add_factor(gtsam.LinearContainerFactor(jf, self.values), (a.key, b.key))

    def _prior_keys(self, chain: Chain, prior: TrackPrior) -> list[int]:
        """The keys a track prior is over: its state's, then its vehicles' ``b``."""
        return [chain.states[prior.tkey].key] + [self.vehicles[v].bias_key for v in prior.vids]

    def _set_prior(
        self, chain: Chain, prior: TrackPrior, sqrt: tuple | None = None, y0: np.ndarray | None = None
    ) -> None:
        """Put the prior in the graph (replacing the track's prior), about the current values
        (:func:`.marginalize.prior_factor`; ``sqrt``: its (A, r) if the caller has them; ``y0``: its keys'
        values stacked, if the caller has them)."""
        self._remove_factor(chain.prior_fid)
        chain.prior = prior
        keys = self._prior_keys(chain, prior)
        f = marginalize.prior_factor(prior, keys, self.values, sqrt, y0)
        chain.prior_fid = self._add_factor(f, tuple(keys))

    def _detection_information(
        self, dets: list[DetectionRecord], p0: np.ndarray, extra: np.ndarray | None = None, age: float = 0.0
    ) -> tuple[list, np.ndarray, np.ndarray, np.ndarray]:
        """Information of detections about [s, b_v] (:func:`.marginalize.detection_information`) with their
        observers' reported poses; returns (vid or None per detection: the vehicle whose persistent error
        b_v it involves, S, G, m)."""
        states = [self._pose_states[d.pose_key] for d in dets]
        vids = [ps.vid for ps in states]
        persist = np.array([self._persistence(v) for v in vids]).reshape(-1, 2)
        has_b = persist[:, 0] > 0
        S, G, m = marginalize.detection_information(
            np.array([ps.M for ps in states]),
            np.array([ps.L_xi for ps in states]),
            np.array([d.z for d in dets]),
            np.array([d.cov for d in dets]),
            persist,
            p0,
            self.params,
            extra,
            age,
        )
        return [v if b else None for v, b in zip(vids, has_b, strict=True)], S, G, m

    def _persistence(self, vid: str) -> tuple[float, float]:
        """(a, tau) of the vehicle's persistent error b_v (``Chain.persist``), (0, 1) while it has no b."""
        chain = self.vehicles[vid]
        return chain.persist if chain.bias_key is not None else (0.0, 1.0)

    def _summarize_first(self, chains: list[Chain]) -> None:
        """Fold each chain's first state (its prior and its detections) into a prior on its second state
        (:func:`.marginalize.summarize_first`)."""
        owner, dets = [], []
        for i, c in enumerate(chains):
            for d in c.states[c.tkeys[0]].dets:
                if d.pose_key in self._pose_states:
                    owner.append(i)
                    dets.append(d)
        info = None
        table = vector_table(self.values)
        if dets:
            info = self._detection_information(dets, vectors(table, [d.target_key for d in dets])[:, :3])
        summaries = marginalize.summarize_first(
            [c.prior for c in chains],
            [c.tkeys[1] for c in chains],
            np.array([c.states[c.tkeys[1]].t - c.states[c.tkeys[0]].t for c in chains]),
            np.array([accel_psd(self.params, c.cls) for c in chains]),
            np.array(owner, dtype=int),
            info,
            {v: c.persist for v, c in self.vehicles.items()},
            _BATCH_UNITS,
        )
        keys = [self._prior_keys(chains[i], prior) for i, prior, _ in summaries]
        y0 = vectors(table, [k for ks in keys for k in ks])  # one look-up for every new prior's keys
        start = np.cumsum([0] + [len(ks) for ks in keys])
        for n, (i, prior, sqrt) in enumerate(summaries):
            self._set_prior(chains[i], prior, sqrt, y0[start[n] : start[n + 1]].ravel())

    def fold_detection(self, track_id: int, pose_key: int, z_body, cov_body, weight: float = 1.0) -> None:
        """A detection older than the track's first state (a late message) into the track's prior, whose
        state is dt later: retrodicted through the constant-velocity model, m = p - v dt + w,
        w ~ N(0, Q_pp(dt)) added to its noise (the correlation of w with the prior's own prediction noise
        is neglected). ``weight`` is its first Huber weight (from the association); the fold recomputes it
        at the track's estimate."""
        chain = self.tracks[track_id]
        prior = chain.prior
        ps = self._pose_states[pose_key]
        det = DetectionRecord(pose_key, -1, np.asarray(z_body, dtype=float), np.asarray(cov_body, dtype=float), ps.t)
        dt = chain.states[prior.tkey].t - ps.t
        _, Q = cv_model(dt, accel_psd(self.params, chain.cls))
        H = np.hstack([np.eye(3), -dt * np.eye(3)])
        x = self.values.atVector(chain.states[prior.tkey].key)
        (v,), (S,), (G,), (m,) = self._detection_information([det], (H @ x)[None], Q[None, :3, :3], age=dt)
        self._set_prior(chain, marginalize.fold(prior, H, v, S, G, m))

    def _forget_bias(self, vid: str) -> None:
        """A vehicle leaves the graph: its persistent error b_v is marginalised out of the track priors
        that hold it, at its prior N(0, a I)."""
        a = self.vehicles[vid].persist[0]
        for chain in self.tracks.values():
            prior = chain.prior
            if prior is None or vid not in prior.vids:
                continue
            self._set_prior(chain, marginalize.forget_bias(prior, vid, a))

    # ------------------------------------------------------------------ detections
    def add_detection(
        self, pose_key: int, state: TrackState, z_body, cov_body, weight: float = 1.0, share: float | None = 1.0
    ) -> None:
        """A body-frame detection z_body (cov_body) of the track state by the vehicle at pose_key.

        ``weight`` is the first Huber weight (from the association innovation); later ones follow the
        estimate (IRLS, see :meth:`_reweight`). ``share``: the part of its information the factor carries (the
        association's probability, for an observer with a GNSS-grade pose), or None: a consider detection
        (:mod:`.detections`): it moves the track, with the observer's reported pose uncertainty in its noise,
        never the observer. Folded into the track's prior, every detection is a whole consider detection.
        """
        self.add_detections([(pose_key, state, z_body, cov_body, weight, share)])

    def add_detections(self, items: list) -> None:
        """Many :meth:`add_detection` calls at once: items of (pose_key, state, z_body, cov_body, weight, share)."""
        dets = self._new_detections([(it[0], it[1].key, it[2], it[3]) for it in items], cross=False)
        for det, (pose_key, state, _, _, weight, share) in zip(dets, items, strict=True):
            det.weight = weight
            if share is None:
                det.pose_cov = self._pose_states[pose_key].cov_xi
            else:
                det.share = float(share)
            state.dets.append(det)
        self._attach(dets)

    def add_cross_detections(self, items: list) -> None:
        """Body-frame detections of other connected vehicles' body origins (cross-localization): items of
        (observer pose key, observed vehicle's pose key, z_body, cov_body)."""
        self._attach(self._new_detections(items, cross=True))

    def _new_detections(self, items: list, cross: bool) -> list[DetectionRecord]:
        """Detection records of items (pose_key, target_key, z_body, cov_body), on their observers' frames."""
        if not items:
            return []
        covs = np.array([it[3] for it in items], dtype=float).reshape(-1, 3, 3)
        Ws = np.linalg.inv(np.linalg.cholesky(covs))  # W^T W = cov^-1
        dets = []
        for (pose_key, target_key, z, _), cov, W in zip(items, covs, Ws, strict=True):
            ps = self._pose_states[pose_key]
            det = DetectionRecord(pose_key, target_key, np.asarray(z, dtype=float), cov, ps.t, cross=cross, W=W)
            ps.dets.append(det)
            dets.append(det)
        return dets

    def _attach(self, dets: list[DetectionRecord]) -> None:
        """Put the detections' factors in the graph."""
        if not dets:
            return
        for det, f in zip(dets, detections.linear_factors(dets, self.values), strict=True):
            det.fid = self._add_factor(f, (det.pose_key, det.target_key))
            self._fid_det[det.fid] = det

    def _reweight(self) -> int:
        """IRLS step of the linearized detections: new Huber weights from the current estimate for
        detections younger than reweight_s (those not yet through a solve keep the weight of their
        association innovation), and new linearization points for detections whose poses moved.
        Returns how many factors were replaced."""
        p = self.params
        k = p.huber_k
        moved = detections.moved(
            {key: ps.dets[0].lin_pose for key, ps in self._pose_states.items() if ps.dets}, self.values, p
        )
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
            weights = detections.robust_weights(recent, self.values, k, p.cross_dcs_phi)
            for det, w in zip(recent, weights, strict=True):
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

    def _drop_track_state(self, s: TrackState) -> None:
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
        """IRLS reweighting, then Levenberg-Marquardt from the current values and the latest states'
        covariances (:func:`.solver.solve`)."""
        laps = Laps()
        reweighted = self._reweight() + self._relinearize_pose_priors()
        graph = self._factor_graph()
        latest = self.latest_keys()
        n_vars = self.num_variables
        laps.mark("reweight")
        if not self._factors:
            self.covariances = {}
            return SolveReport(0, 0.0, 0.0, 0, n_vars, 0, reweighted, laps.ms)
        sol = solver.solve(graph, self.values, latest, self.params)
        laps.add(sol.phases_ms)
        self.values, self.covariances = sol.values, sol.covariances
        if sol.root_dims is not None:
            self.root_dims = sol.root_dims
        return SolveReport(
            sol.iterations,
            sol.error_before,
            sol.error_after,
            len(self._factors),
            n_vars,
            sol.cliques_below_root,
            reweighted,
            laps.ms,
        )

    def vehicles_only(self) -> tuple[list[gtsam.NonlinearFactor], list[tuple[DetectionRecord, str, str]]]:
        """The window without the objects (for the downlink, :mod:`mapcontainer.downlink`): every factor that
        involves no track state (the vehicles' priors and motion, their persistent errors' priors) except the
        cross-detections, which come apart as (record, observer's vid, observed vehicle's vid)."""
        tracks = {s.key for c in self.tracks.values() for s in c.states.values()}
        factors, cross = [], []
        for fid, f in self._factors.items():
            det = self._fid_det.get(fid)
            if det is not None:
                if det.cross:
                    cross.append((det, self._pose_states[det.pose_key].vid, self._pose_states[det.target_key].vid))
            elif not any(k in tracks for k in f.keys()):
                factors.append(f)
        return factors, cross

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
