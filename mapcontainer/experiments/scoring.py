"""Per-frame error figures shared by the experiments (pure functions of FusedState / GroundTruth).

Conventions: "horizontal" errors are the map-frame x, y components (the paper's figures are
planar); object errors are matched to the true obstacles with :func:`mapcontainer.metrics.match_objects`
(Hungarian on horizontal distance, 3 m gate), so an estimate farther than the gate counts as a
miss, not as an error — the coverage figures next to every RMSE say how many were missed.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from schemas import FusedState, GroundTruth
from schemas.arrays import cov_from_upper

from .. import geometry as geo
from ..metrics import match_objects

__all__ = [
    "age_of_information",
    "horizontal_sq_error",
    "obstacle_errors",
    "relative_target_errors",
    "rmse_sq",
    "vehicle_pose",
]

GATE_M = 3.0


def vehicle_pose(state: FusedState | GroundTruth, vid: str) -> np.ndarray | None:
    """The 6-vector pose of ``vid`` in a fused state or the ground truth, None if absent."""
    if vid not in state.vehicle_ids:
        return None
    return np.asarray(state.vehicle_pose[state.vehicle_ids.index(vid)], dtype=float)


def horizontal_sq_error(p_est, p_true) -> float:
    """||p_est[:2] - p_true[:2]||^2 (m^2)."""
    d = np.asarray(p_est, dtype=float)[:2] - np.asarray(p_true, dtype=float)[:2]
    return float(d @ d)


def rmse_sq(sq: Iterable[float]) -> float:
    """sqrt(mean of squared error norms): eqs. rms1 / rms2 from stacked ||e||^2; NaN when empty."""
    a = np.asarray(list(sq) if not isinstance(sq, np.ndarray) else sq, dtype=float)
    return float(np.sqrt(a.mean())) if a.size else float("nan")


def relative_target_errors(
    fused: FusedState, truth: GroundTruth, ego: str, radius_m: float, gate_m: float = GATE_M
) -> tuple[np.ndarray, np.ndarray, int]:
    """The paper's rms2 terms: horizontal errors of targets in the ego's body frame.

    For the true obstacles within ``radius_m`` of the true ego position, matched to fused objects in
    the map frame: e_k = [T_hat^-1 p_hat_k - T^-1 p_k]_xy with T / T_hat the true / fused ego pose.
    Returns (true obstacle ids (m,), errors (m, 2), number of true obstacles within the radius). The
    same figure as :func:`mapcontainer.pipeline.relative_errors`, plus the ids (to compare views on
    the targets both estimate).
    """
    pose_true, pose_hat = vehicle_pose(truth, ego), vehicle_pose(fused, ego)
    if pose_true is None or pose_hat is None:
        return np.zeros(0, np.int64), np.zeros((0, 2)), 0
    T_true, T_hat = geo.pose_to_matrix(pose_true), geo.pose_to_matrix(pose_hat)
    p_true = np.asarray(truth.obstacle_p_map, dtype=float).reshape(-1, 3)
    near = np.linalg.norm(p_true[:, :2] - T_true[:2, 3], axis=1) <= radius_m
    ti, fi = match_objects(fused.object_p_map, p_true, gate_m)
    keep = near[ti]
    ti, fi = ti[keep], fi[keep]
    rel_true = geo.transform_points(geo.inverse(T_true), p_true[ti])
    rel_hat = geo.transform_points(geo.inverse(T_hat), np.asarray(fused.object_p_map, dtype=float)[fi])
    ids = np.asarray(truth.obstacle_id, dtype=np.int64)[ti]
    return ids, (rel_hat - rel_true)[:, :2], int(near.sum())


def obstacle_errors(
    fused: FusedState, truth: GroundTruth, gate_m: float = GATE_M, within: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Map-frame errors of fused objects matched to true obstacles.

    ``within``: optional boolean mask over the true obstacles to score (e.g. near the ego).
    Returns (true obstacle ids (m,), errors p_hat - p (m, 3), fused position covariances (m, 3, 3)).
    """
    p_true = np.asarray(truth.obstacle_p_map, dtype=float).reshape(-1, 3)
    ti, fi = match_objects(fused.object_p_map, p_true, gate_m)
    if within is not None:
        keep = np.asarray(within, dtype=bool)[ti]
        ti, fi = ti[keep], fi[keep]
    err = np.asarray(fused.object_p_map, dtype=float).reshape(-1, 3)[fi] - p_true[ti]
    cov = cov_from_upper(np.asarray(fused.object_cov, dtype=float).reshape(-1, 6)[fi]).reshape(-1, 3, 3)
    return np.asarray(truth.obstacle_id, dtype=np.int64)[ti], err, cov


def age_of_information(
    deliveries: Sequence[tuple[str, float, float]], senders: Sequence[str], times: Sequence[float], t_start: float = 0.0
) -> np.ndarray:
    """Age of the remote information at the host, (len(times), len(senders)) seconds.

    For fuse time t and sender v: t - max{t_meas of v's messages that arrived at the host by t}
    (``deliveries`` are (src, t_meas, t_arrive); in the pipeline a message is sent at its t_meas).
    Before anything from v has arrived the age counts from ``t_start``: t - t_start.
    """
    times = np.asarray(times, dtype=float)
    out = np.empty((len(times), len(senders)))
    for j, v in enumerate(senders):
        d = np.array([(tm, ta) for src, tm, ta in deliveries if src == v], dtype=float).reshape(-1, 2)
        if len(d) == 0:
            out[:, j] = times - t_start
            continue
        order = np.argsort(d[:, 1], kind="stable")
        t_arr = d[order, 1]
        newest = np.maximum.accumulate(d[order, 0])  # newest t_meas among arrivals so far
        k = np.searchsorted(t_arr, times, side="right")  # arrivals with t_arrive <= t
        got = k > 0
        out[:, j] = times - t_start
        out[got, j] = times[got] - newest[k[got] - 1]
    return out
