"""The obstacle motion model shared by the tracker, the factor graph and the output: constant velocity
with white-noise acceleration (WNOA) of spectral density q per axis, over a state s = [p, v]."""

from __future__ import annotations

import numpy as np

from schemas import ObjectClass

from .params import FusionParams

__all__ = ["accel_psd", "cv_model", "cv_predict", "speed_prior"]

_SLOW = (ObjectClass.PEDESTRIAN, ObjectClass.CYCLIST)


def accel_psd(params: FusionParams, cls: int) -> np.ndarray:
    """q per axis (m^2/s^3) for an object of class ``cls``: horizontal by class, vertical for all."""
    h = params.accel_psd_pedestrian if cls in _SLOW else params.accel_psd_vehicle
    return np.array([h, h, params.accel_psd_vertical])


def speed_prior(params: FusionParams, cls: int) -> float:
    """Sigma of the zero-mean velocity prior of a new track of class ``cls`` (m/s)."""
    return params.speed_prior_pedestrian_mps if cls in _SLOW else params.speed_prior_vehicle_mps


def cv_model(dt, q) -> tuple[np.ndarray, np.ndarray]:
    """s' = F s + w, w ~ N(0, Q): F = [[I, dt I], [0, I]],
    Q = [[q |dt|^3 / 3, q dt |dt| / 2], [q dt |dt| / 2, q |dt|]] per axis (dt may be negative: a
    prediction backwards in time is as uncertain as forwards). Vectorised: dt (...,), q (..., 3) give
    (..., 6, 6)."""
    dt, q = np.asarray(dt, dtype=float), np.asarray(q, dtype=float)
    a = np.abs(dt)[..., None]
    F = np.broadcast_to(np.eye(6), (*dt.shape, 6, 6)).copy()
    i = np.arange(3)
    F[..., i, i + 3] = dt[..., None]
    Q = np.zeros((*dt.shape, 6, 6))
    Q[..., i, i] = q * a**3 / 3
    Q[..., i, i + 3] = Q[..., i + 3, i] = q * dt[..., None] * a / 2
    Q[..., i + 3, i + 3] = q * a
    return F, Q


def cv_predict(x, P, dt, q) -> tuple[np.ndarray, np.ndarray]:
    """Predict states x (..., 6) with covariances P (..., 6, 6) by dt (...,): F x, F P F^T + Q."""
    F, Q = cv_model(dt, q)
    x = np.einsum("...ij,...j->...i", F, np.asarray(x, dtype=float))
    return x, F @ np.asarray(P, dtype=float) @ np.swapaxes(F, -1, -2) + Q
