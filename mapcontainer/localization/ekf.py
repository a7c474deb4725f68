"""The localizer's extended Kalman filter: plain functions of the state, its covariance and the parameters.

The state is ``y = [x, y, z, roll, pitch, yaw, k_v, b_w, b_E, b_N]``: the body pose in the map, the
wheel-speed scale factor, the gyro bias and the GNSS receiver's horizontal bias (first-order
Gauss-Markov); ``P`` is its 10x10 covariance. Every function returns new arrays and leaves its
arguments alone. ``params`` is a :class:`.LocalizerParams`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..geometry import wrap_angle

if TYPE_CHECKING:
    from .matcher_types import MatchLinearization, MatchResult
    from .params import GnssMeasurement, LocalizerParams, OdometryMeasurement

__all__ = [
    "GB",
    "GYRO",
    "N",
    "SCALE",
    "consider_carry",
    "consider_match_update",
    "gnss_update",
    "gnss_white_var",
    "ground_update",
    "initial_state",
    "kf_update",
    "match_update",
    "predict",
    "sigma_h",
    "transition",
    "widen",
]

N = 10  # state size
SCALE, GYRO, GB = 6, 7, slice(8, 10)  # wheel-speed scale, gyro bias, GNSS bias (E, N)


def predict(
    y: np.ndarray,
    P: np.ndarray,
    dt: float,
    odo_a: OdometryMeasurement | None,
    odo_b: OdometryMeasurement | None,
    params: LocalizerParams,
) -> tuple[np.ndarray, np.ndarray]:
    """Unicycle prediction of the state (y, P) over dt (:func:`transition`): F y, F P F^T + Q."""
    y_new, F, Q = transition(y, dt, odo_a, odo_b, params)
    if F is None:
        return y_new, P.copy()
    P = F @ P @ F.T + Q
    return y_new, 0.5 * (P + P.T)


def transition(
    y: np.ndarray,
    dt: float,
    odo_a: OdometryMeasurement | None,
    odo_b: OdometryMeasurement | None,
    params: LocalizerParams,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The predicted state over dt with the mean of the two odometry readings, the transition's
    Jacobian F and its noise Q (a copy of y and None, None for dt <= 0: nothing moves).

    With odometry v_m, w_m (the mean of the readings given); v = k_v v_m, w = w_m - b_w,
    theta_m = yaw + w dt / 2::

        x += v dt cos(theta_m),  y += v dt sin(theta_m),  yaw += w dt,  b_gnss *= exp(-dt / tau)
        Q = G diag(s_v^2, s_w^2) G^T + Q_c dt

    with s_v^2 = speed_sigma^2 + (speed_scale_sigma v_m)^2 and Q_c the lateral, height, roll, pitch,
    scale, gyro-bias and GNSS-bias process noise. Without odometry the vehicle stands still with
    wide noise (10 m/s, 0.5 rad/s).
    """
    p = params
    y = y.copy()
    if dt <= 0.0:
        return y, None, None
    odos = [o for o in (odo_a, odo_b) if o is not None]
    if odos:
        vm = float(np.mean([o.speed for o in odos]))
        wm = float(np.mean([o.yaw_rate for o in odos]))
        sv2 = p.speed_sigma_mps**2 + (p.speed_scale_sigma * vm) ** 2
        sw2 = p.yaw_rate_sigma_radps**2
    else:  # no odometry: stand still, with wide noise
        vm, wm = 0.0, 0.0
        sv2, sw2 = 10.0**2, 0.5**2
    k, b = y[SCALE], y[GYRO]
    v, w = k * vm, wm - b
    th = y[5] + 0.5 * w * dt
    c, s = np.cos(th), np.sin(th)
    phi = np.exp(-dt / p.gnss_bias_tau_s)
    y[0] += v * dt * c
    y[1] += v * dt * s
    y[5] = wrap_angle(y[5] + w * dt)
    y[GB] *= phi
    F = np.eye(N)
    F[0, 5], F[1, 5] = -v * dt * s, v * dt * c
    F[0, SCALE], F[1, SCALE] = vm * dt * c, vm * dt * s
    F[0, GYRO], F[1, GYRO] = 0.5 * v * dt * dt * s, -0.5 * v * dt * dt * c
    F[5, GYRO] = -dt
    F[8, 8] = F[9, 9] = phi
    G = np.zeros((N, 2))  # d state / d (speed noise, yaw-rate noise)
    G[0, 0], G[1, 0] = k * dt * c, k * dt * s
    G[0, 1], G[1, 1] = -0.5 * v * dt * dt * s, 0.5 * v * dt * dt * c
    G[5, 1] = dt
    Q = G @ np.diag([sv2, sw2]) @ G.T
    lat = np.array([-s, c])
    Q[:2, :2] += np.outer(lat, lat) * p.lateral_sigma_mps**2 * dt**2 + np.eye(2) * 1e-6 * dt
    Q[2, 2] += p.z_sigma_mps**2 * dt
    Q[3, 3] += p.roll_pitch_sigma_radps**2 * dt
    Q[4, 4] += p.roll_pitch_sigma_radps**2 * dt
    Q[SCALE, SCALE] += p.scale_rw_sigma**2 * dt
    Q[GYRO, GYRO] += p.gyro_bias_rw_sigma**2 * dt
    Q[8, 8] += p.gnss_bias_sigma_m**2 * (1.0 - phi**2)
    Q[9, 9] += p.gnss_bias_sigma_m**2 * (1.0 - phi**2)
    return y, F, Q


def match_update(
    y: np.ndarray, P: np.ndarray, match: MatchResult, weight: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Fold the matcher's posterior on the pose into the whole state (information form).

    The matcher solved with the pose marginal (x_pred, P_xx) as its prior and returned the
    posterior (x_f, P_f) (``match.pose_filtered``, ``match.cov_filtered``); its measurement
    information is Lambda = P_f^-1 - P_xx^-1 with the information vector P_f^-1 (x_f - x_pred).
    Adding both to the state's information gives the pose posterior (x_f, P_f) again and updates
    the odometry and GNSS biases through their correlation with the pose.

    ``weight`` w in [0, 1] scales both (the measurement's noise inflated by 1 / w): a view whose errors
    the views before repeat (a landmark's own map error, seen again from nearly the same place) is worth
    a fraction of an independent one::

        Y = P^-1 + w Lambda,   y += Y^-1 w P_f^-1 (x_f - x_pred)

    At w = 1 the pose block is the matcher's (nonlinear) solution x_f exactly.
    """
    if not 0.0 <= weight <= 1.0:
        raise ValueError(f"weight must be in [0, 1], got {weight}")
    Pxx = P[:6, :6]
    I_f = np.linalg.inv(match.cov_filtered)
    Lam = I_f - np.linalg.inv(Pxx)
    d = match.pose_filtered - y[:6]
    d[5] = wrap_angle(d[5])
    Y = np.linalg.inv(P)
    Y[:6, :6] += weight * 0.5 * (Lam + Lam.T)
    P_new = np.linalg.inv(Y)
    eta = np.zeros(N)
    eta[:6] = weight * (I_f @ d)
    dy = P_new @ eta  # the prior is centred on y: delta form
    y = y.copy()
    if weight == 1.0:
        y[:6] = match.pose_filtered  # the exact nonlinear solution for the pose block
        y[6:] += dy[6:]
    else:
        y += dy
        y[5] = wrap_angle(y[5])
    return y, 0.5 * (P_new + P_new.T)


def consider_match_update(
    y: np.ndarray,
    P: np.ndarray,
    C: dict[tuple[str, int], np.ndarray],
    lin: MatchLinearization,
    x_f: np.ndarray,
    sigma_m: float,
) -> tuple[np.ndarray, np.ndarray, dict[tuple[str, int], np.ndarray]]:
    """Fold a match into the state with each landmark's own map error as a consider (Schmidt) state.

    A landmark's map error m_k (3-D, map frame, ``sigma_m`` per axis: the map's stated landmark error,
    ``MatcherParams.landmark_map_sigma_m``) is the same in every view of it, so repeated views of one pole say
    little more than the first about the pose along the road. m_k ~ N(0, sigma_m^2 I) is never estimated (its
    mean stays 0 and its variance sigma_m^2, independent of the other landmarks'); the filter keeps
    C_k = Cov(y, m_k) (``C``: key ('point' | 'pole', map index) -> (N, 3)), from 0 when the landmark is first
    seen. The match's rows, linearised at its solution x_f (``lin``), are the pseudo-measurements::

        landmark k:  J_k x - J_k[:, :3] m_k = J_k x_f - e_k + n_k,   n_k ~ N(0, I)  (the detector's noise alone)
        lanes, rest: H x = H x_f - S^-1/2 U^T g + n,   H = S^1/2 U^T  with the rows' information U S U^T

    (moving a landmark by m moves its projection as moving the vehicle by -m would). With the augmented prior
    P_a = [[P, C], [C^T, sigma_m^2 I]], rows H_a = [H_x, H_m] and r = z - H_x y::

        S = H_a P_a H_a^T + I,   K_y = (P_a H_a^T)[y] S^-1,   y += K_y r,
        P -= (P_a H_a^T)[y] S^-1 (P_a H_a^T)[y]^T,   C_k -= (P_a H_a^T)[y] S^-1 (P_a H_a^T)[k]^T

    P is the true error covariance of this estimate (Schmidt-Kalman: the consider states are not updated, so
    an error the model leaves out cannot make them confident). Every landmark of ``C`` is in P_a: an unseen
    one's cross-covariance changes through the pose's update. With every C_k = 0 this is the matcher's own
    frame model up to its isotropic pixel approximation of the map error; n views of one landmark from a
    standing vehicle leave sigma_m^2 + s^2 / n, not (sigma_m^2 + s^2) / n. Returns (y, P, C) with C holding the
    landmarks of ``C`` and of this match.

    The pose's mean is this linear update's, not the solve's x_f (as :func:`match_update` takes at weight 1):
    x_f also holds the lanes' pull along the road, which their information leaves out
    (``MatcherParams.lane_along_track``), so a mean taken from x_f would move where the covariance says nothing
    is known.
    """
    keys = list(dict.fromkeys([*C.keys(), *lin.keys]))
    col = {k: N + 3 * i for i, k in enumerate(keys)}
    dim = N + 3 * len(keys)
    Pa = np.zeros((dim, dim))
    Pa[:N, :N] = P
    for k, c0 in col.items():
        Ck = C.get(k)
        if Ck is not None:
            Pa[:N, c0 : c0 + 3] = Ck
            Pa[c0 : c0 + 3, :N] = Ck.T
        Pa[c0 : c0 + 3, c0 : c0 + 3] = sigma_m**2 * np.eye(3)
    d = np.asarray(x_f, float) - y[:6]
    d[5] = wrap_angle(d[5])
    rows, res = [], []
    for info, grad in ((lin.info_lanes, lin.grad_lanes), (lin.info_rest, lin.grad_rest)):
        s, U = np.linalg.eigh(0.5 * (info + info.T))
        keep = s > 1e-12 * max(float(s[-1]), 1.0)
        if keep.any():
            sq, Uk = np.sqrt(s[keep]), U[:, keep]
            H = np.zeros((len(sq), dim))
            H[:, :6] = sq[:, None] * Uk.T
            rows.append(H)
            res.append(H[:, :6] @ d - (Uk.T @ grad) / sq)
    for k, Jk, ek in zip(lin.keys, lin.J, lin.e, strict=True):
        H = np.zeros((2, dim))
        H[:, :6] = Jk
        H[:, col[k] : col[k] + 3] = -Jk[:, :3]
        rows.append(H)
        res.append(Jk @ d - ek)
    if not rows:
        return y.copy(), P.copy(), dict(C)
    H, r = np.vstack(rows), np.concatenate(res)
    PH = Pa @ H.T
    S = H @ PH + np.eye(len(r))
    G = np.linalg.solve(S, PH.T)  # S^-1 (P_a H^T)^T
    y = y + PH[:N] @ np.linalg.solve(S, r)
    y[5] = wrap_angle(y[5])
    P = P - PH[:N] @ G[:, :N]
    C = {k: Pa[:N, c0 : c0 + 3] - PH[:N] @ G[:, c0 : c0 + 3] for k, c0 in col.items()}
    return y, 0.5 * (P + P.T), C


def consider_carry(
    C: dict[tuple[str, int], np.ndarray], P_before: np.ndarray, P_after: np.ndarray
) -> dict[tuple[str, int], np.ndarray]:
    """The consider states' cross-covariances after an update of the state alone (GNSS, ground, a match folded
    in without them, a fusion elsewhere): for a Kalman update with the optimal gain (I - K H) = P_after
    P_before^-1, so C_k <- P_after P_before^-1 C_k."""
    if not C:
        return {}
    keys = list(C)
    M = np.linalg.solve(P_before, np.hstack([C[k] for k in keys]))
    M = P_after @ M
    return {k: M[:, 3 * i : 3 * i + 3] for i, k in enumerate(keys)}


def gnss_white_var(gnss: GnssMeasurement | None, params: LocalizerParams) -> float:
    """The white part of a fix's horizontal variance per axis: sigma_h^2 - bias_sigma^2, at least
    ``gnss_white_min_sigma_m``^2 (that minimum without a fix)."""
    p = params
    if gnss is None:
        return p.gnss_white_min_sigma_m**2
    return max(gnss.sigma_h_m**2 - p.gnss_bias_sigma_m**2, p.gnss_white_min_sigma_m**2)


def gnss_update(
    y: np.ndarray, P: np.ndarray, gnss: GnssMeasurement | None, params: LocalizerParams
) -> tuple[np.ndarray, np.ndarray, str]:
    """EKF update with the horizontal fix, z = p_xy + b + white.

    chi^2 = r^T S^-1 r of the residual r = z - H y: beyond ``gnss_gate_chi2`` the fix is dropped,
    beyond ``gnss_soft_chi2`` its noise is scaled by chi^2 / gnss_soft_chi2. Returns (y, P, outcome),
    outcome "used", "rejected" (dropped by the gate) or "" (no fix).
    """
    if gnss is None:
        return y, P, ""
    H = np.zeros((2, N))
    H[:, :2] = np.eye(2)
    H[:, GB] = np.eye(2)
    R = np.eye(2) * gnss_white_var(gnss, params)
    r = gnss.p_map[:2] - H @ y
    S = H @ P @ H.T + R
    chi2 = float(r @ np.linalg.solve(S, r))
    if chi2 > params.gnss_gate_chi2:
        return y, P, "rejected"
    if chi2 > params.gnss_soft_chi2:
        R = R * (chi2 / params.gnss_soft_chi2)
    y, P = kf_update(y, P, H, r, R)
    return y, P, "used"


def ground_update(
    y: np.ndarray, P: np.ndarray, z_ground: float | None, params: LocalizerParams
) -> tuple[np.ndarray, np.ndarray]:
    """Pseudo-measurements in fallback: height on the road (z = z_ground + body_height, if the road's
    height ``z_ground`` is known), roll and pitch at their nominal values."""
    p = params
    rows, res, var = [], [], []
    if z_ground is not None:
        rows.append(np.eye(N)[2])
        res.append(z_ground + p.matcher.body_height_m - y[2])
        var.append(p.ground_sigma_m**2)
    for i, nominal in zip((3, 4), p.matcher.nominal_roll_pitch_rad, strict=True):
        rows.append(np.eye(N)[i])
        res.append(nominal - y[i])
        var.append(p.ground_roll_pitch_sigma_rad**2)
    return kf_update(y, P, np.array(rows), np.array(res), np.diag(var))


def kf_update(y: np.ndarray, P: np.ndarray, H: np.ndarray, r: np.ndarray, R: np.ndarray):
    """Kalman update with residual r = z - H y (Joseph form); yaw wrapped.

    S = H P H^T + R,  K = P H^T S^-1,  y += K r,  P = (I - K H) P (I - K H)^T + K R K^T.
    """
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    y = y + K @ r
    y[5] = wrap_angle(y[5])
    I_KH = np.eye(len(y)) - K @ H
    P = I_KH @ P @ I_KH.T + K @ R @ K.T
    return y, 0.5 * (P + P.T)


def initial_state(
    gnss: GnssMeasurement, yaw: float, sigma_yaw: float, z_ground: float | None, params: LocalizerParams
) -> tuple[np.ndarray, np.ndarray]:
    """The state at the GNSS fix with heading yaw; position error = -(bias + white): tied to the bias.

    Height on the road (``z_ground`` + body height) if the road's height is known, else the fix's;
    roll and pitch nominal; scale 1, biases 0 with their prior sigmas. Position variance
    bias^2 + white^2 + init_extra_sigma_m^2, with covariance -bias^2 between position and GNSS bias.
    """
    p = params
    z0 = z_ground
    x = np.array(
        [
            gnss.p_map[0],
            gnss.p_map[1],
            gnss.p_map[2] if z0 is None else z0 + p.matcher.body_height_m,
            *p.matcher.nominal_roll_pitch_rad,
            wrap_angle(yaw),
        ]
    )
    vb = p.gnss_bias_sigma_m**2
    vh = vb + gnss_white_var(gnss, p) + p.init_extra_sigma_m**2
    vz = gnss.sigma_v_m**2 if z0 is None else p.ground_sigma_m**2
    y = np.concatenate([x, [1.0, 0.0, 0.0, 0.0]])
    P = np.diag(
        [
            vh,
            vh,
            vz,
            p.ground_roll_pitch_sigma_rad**2,
            p.ground_roll_pitch_sigma_rad**2,
            sigma_yaw**2,
            p.scale_init_sigma**2,
            p.gyro_bias_init_sigma_radps**2,
            vb,
            vb,
        ]
    )
    P[0, 8] = P[8, 0] = P[1, 9] = P[9, 1] = -vb
    return y, P


def widen(P: np.ndarray, gnss: GnssMeasurement | None, params: LocalizerParams) -> np.ndarray:
    """P with the position and yaw variance raised to what GNSS alone would give."""
    p = params
    P = P.copy()
    var_h = p.gnss_bias_sigma_m**2 + gnss_white_var(gnss, p) + p.init_extra_sigma_m**2
    P[0, 0] += var_h
    P[1, 1] += var_h
    P[5, 5] += p.init_yaw_sigma_rad**2
    return P


def sigma_h(P: np.ndarray) -> float:
    """The largest horizontal 1-sigma of a pose covariance (m)."""
    return float(np.sqrt(max(np.linalg.eigvalsh(P[:2, :2])[-1], 0.0)))
