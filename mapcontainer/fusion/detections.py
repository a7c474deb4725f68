"""Detection factors of the host's factor graph (:mod:`.graph`): the measurement model, its linearization
and its IRLS weights.

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
  vehicle's body origin, e = R_obs^T (t_target - t_obs) - z (``LinearContainerFactor`` on both poses),
  robust by dynamic covariance scaling (``cross_dcs_phi``, :func:`robust_weights`);
* a *consider* detection of a track (``DetectionRecord.pose_cov`` set): the observer's pose is not
  estimated from it but its uncertainty is in the noise (Schmidt's consider update, as the joint host's),
  e = R0^T (p - t0) - z ~ N(0, S_z + A_x C A_x^T), A_x = [[q0]x, -I], C the observer's reported tangent
  covariance: a factor on the track alone, for a detection made by a vehicle whose pose is GNSS grade that
  says nothing about that pose (the container decides): it moves the track, never its observer;
* a detection's factor carries ``DetectionRecord.share`` of its information (1 but for an observer whose
  pose is GNSS grade: the association's probability, EM's soft data association).

Why not ``BearingRangeFactor3D`` (one factor, nonlinear): in this GTSAM build its bearing error is in the
tangent basis of the *predicted* Unit3, which Unit3 picks by the smallest component of the direction.
For an object straight ahead at road height (body y and z both near 0) the basis flips between
iterations; with the anisotropic bearing noise of a real detector (vertical 4x tighter than
horizontal) the whitened error jumps and Gauss-Newton oscillates (seen in the overlap scenario).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from .params import FusionParams

__all__ = ["DetectionRecord", "robust_weights", "linear_factors", "moved", "observed", "skews"]

_UNIT3 = gtsam.noiseModel.Unit.Create(3)


@dataclass(eq=False)
class DetectionRecord:
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
    pose_cov: np.ndarray | None = None  # a consider detection: its observer's pose covariance (6x6, tangent)
    share: float = 1.0  # the part of its information its factor carries (the association's probability)


def skews(q: np.ndarray) -> np.ndarray:
    """[q]x (N, 3, 3) of vectors q (N, 3): [q]x v = q x v."""
    out = np.zeros((len(q), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -q[:, 2], q[:, 1], -q[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = q[:, 2], -q[:, 1], q[:, 0]
    return out


def observed(dets: list[DetectionRecord], values: gtsam.Values) -> tuple[dict[int, np.ndarray], np.ndarray, np.ndarray]:
    """Where the detections' targets are in their observers' frames at ``values``: the 4x4 of every pose
    involved (by key), the observers' (N, 4, 4) and q = R0^T (p0 - t0) (N, 3), p0 the track state's
    position or the observed vehicle's origin (cross)."""
    M: dict[int, np.ndarray] = {}
    for d in dets:
        for key in (d.pose_key, d.target_key) if d.cross else (d.pose_key,):
            if key not in M:
                M[key] = values.atPose3(key).matrix()
    mats = np.array([M[d.pose_key] for d in dets])
    p0 = np.array([M[d.target_key][:3, 3] if d.cross else values.atVector(d.target_key)[:3] for d in dets])
    return M, mats, np.einsum("nji,nj->ni", mats[:, :3, :3], p0 - mats[:, :3, 3])


def linear_factors(dets: list[DetectionRecord], values: gtsam.Values) -> list[gtsam.LinearContainerFactor]:
    """Detection factors (module docstring), both kinds, linearized at ``values``; vectorised. Sets each
    detection's ``lin_pose``.

    e = R^T (p - t) - z at the current observer pose x0 = (R0, t0) and target: p is a track state's
    position (state [p, v]) or an observed vehicle's origin (cross). With q0 = R0^T (p0 - t0):
    d e / d xi = [[q0]x, -I]; d e / d s = [R0^T, 0] (track) or d e / d xi_target = [0, R0^T R_target]
    (cross); e(x0, p0) = q0 - z; whitened by sqrt(weight share) W.
    """
    M, mats, q = observed(dets, values)
    R0t = mats[:, :3, :3].transpose(0, 2, 1)
    cross = np.array([d.cross for d in dets])
    A_x = _pose_jacobians(q)
    W = np.sqrt(np.array([d.weight * d.share for d in dets]))[:, None, None] * _whiteners(dets, A_x)
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
        if d.pose_cov is None:
            jf = gtsam.JacobianFactor(d.pose_key, WA_x[n], d.target_key, WA_t[n], b[n], _UNIT3)
        else:  # consider: on the track alone, the pose's uncertainty in W
            jf = gtsam.JacobianFactor(d.target_key, WA_t[n], b[n], _UNIT3)
        out.append(gtsam.LinearContainerFactor(jf, values))
    return out


def _pose_jacobians(q: np.ndarray) -> np.ndarray:
    """d e / d xi = [[q0]x, -I] (N, 3, 6) of the detections' residuals at q0 (N, 3)."""
    A_x = np.zeros((len(q), 3, 6))
    A_x[:, :, :3] = skews(q)
    A_x[:, :, 3:] = -np.eye(3)
    return A_x


def _whiteners(dets: list[DetectionRecord], A_x: np.ndarray) -> np.ndarray:
    """W (N, 3, 3), W^T W = the noise's inverse: the detection's own (``DetectionRecord.W``), or for a consider
    detection S_z + A_x C A_x^T (its observer's pose covariance C through the pose Jacobian A_x)."""
    W = np.array([d.W for d in dets])
    idx = [n for n, d in enumerate(dets) if d.pose_cov is not None]
    if idx:
        A = A_x[idx]
        C = np.array([dets[n].cov for n in idx]) + A @ np.array([dets[n].pose_cov for n in idx]) @ A.transpose(0, 2, 1)
        W[idx] = np.linalg.inv(np.linalg.cholesky(C))
    return W


def robust_weights(dets: list[DetectionRecord], values: gtsam.Values, k: float, phi: float | None = None) -> np.ndarray:
    """IRLS weights of the detections' residuals e = R^T (p - t) - z at ``values``: Huber w = min(1, k / |W e|)
    for detections of tracks; for cross-observations, with ``phi``, dynamic covariance scaling (Agarwal et
    al., "Robust map optimization using dynamic covariance scaling", ICRA 2013): w = s^2,
    s = min(1, 2 phi / (phi + |W e|^2)), whose influence vanishes far out, so a detection of another
    vehicle wrongly associated with this one cannot drag it (Huber's influence stays k)."""
    q = observed(dets, values)[2]
    e = q - np.array([d.z for d in dets])
    we = np.einsum("nij,nj->ni", _whiteners(dets, _pose_jacobians(q)), e)
    dist = np.linalg.norm(we, axis=1)
    w = np.minimum(1.0, k / np.maximum(dist, 1e-12))
    if phi is not None:
        cross = np.array([d.cross for d in dets])
        w[cross] = np.minimum(1.0, 2.0 * phi / (phi + dist[cross] ** 2)) ** 2
    return w


def moved(lin: dict[int, np.ndarray], values: gtsam.Values, params: FusionParams) -> set[int]:
    """The pose keys whose value in ``values`` is farther from their linearization point (``lin``: 4x4)
    than relinearize_rad (angle of R0^T R) or relinearize_m (length of R0^T (t - t0)). Vectorised."""
    if not lin:
        return set()
    keys = list(lin)
    M0 = np.array([lin[k] for k in keys])
    M = np.array([values.atPose3(k).matrix() for k in keys])
    R0t = M0[:, :3, :3].transpose(0, 2, 1)
    cos = 0.5 * (np.trace(R0t @ M[:, :3, :3], axis1=1, axis2=2) - 1.0)
    dt = np.einsum("nij,nj->ni", R0t, M[:, :3, 3] - M0[:, :3, 3])
    far = (np.arccos(np.clip(cos, -1.0, 1.0)) > params.relinearize_rad) | (
        np.linalg.norm(dt, axis=1) > params.relinearize_m
    )
    return {k for k, f in zip(keys, far, strict=True) if f}
