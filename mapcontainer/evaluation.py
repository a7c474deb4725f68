"""Scoring of fused states against the ground truth: one definition for the live evaluator and the experiments.

Pure functions of :class:`schemas.FusedState` and :class:`schemas.GroundTruth` (numpy, no I/O):
``services/evaluator`` (live fleet) and ``mapcontainer.experiments`` (in process) both call them, so
the same states and truth give the same numbers in both modes.

Conventions.

* Vehicles are paired with the truth by id; objects with true obstacles by one assignment per
  frame, the GOSPA assignment on horizontal (map x-y) distance with cutoff :data:`GOSPA_C_M`
  (:func:`match_objects`). A fused object farther than the cutoff from every unassigned obstacle is
  a false track, an obstacle without a fused object within it a miss.
* "Horizontal" errors are the map-frame x, y components (the paper's figures are planar).
  RMSE = sqrt(mean ||e||^2) over every pair (the paper's eqs. rms1 / rms2).
* NEES is over the full state the covariance describes: 3-D object position (3 dof), 6-DoF vehicle
  pose over the wire parametrization ``[x, y, z, roll, pitch, yaw]`` (6 dof, see :func:`pose_error`).
* GOSPA (order :data:`GOSPA_P`, cutoff :data:`GOSPA_C_M`, alpha :data:`GOSPA_ALPHA`) is reported
  in its three additive parts, in m^p: localization + missed + false = GOSPA^p.

Scope. ``truth_in_scope`` / ``est_in_scope`` (boolean masks, e.g. :func:`within_radius` of the
ego) restrict what a frame counts: the assignment is made over everything (an estimate near the
scope's border still pairs with its obstacle), then a matched pair counts if its obstacle is in
scope, a miss if the obstacle is in scope, a false track if the estimate is in scope.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from schemas import FusedState, GroundTruth
from schemas.arrays import cov_from_upper

from . import geometry as geo
from .metrics import anees_band, chi2_quantile, match_objects, nees

__all__ = [
    "CONFIDENCE",
    "GATE_M",
    "GOSPA_ALPHA",
    "GOSPA_C_M",
    "GOSPA_P",
    "OBJECT_DOF",
    "VEHICLE_DOF",
    "Anees",
    "FrameScore",
    "Gospa",
    "RmseVsTime",
    "Totals",
    "age_of_information",
    "anees",
    "fraction_in_band",
    "frame_row",
    "frame_row_fields",
    "gospa",
    "gospa_parts",
    "horizontal_sq_error",
    "match_objects",
    "match_vehicles",
    "nees_band",
    "obstacle_errors",
    "pose_error",
    "relative_target_errors",
    "rmse_sq",
    "rmse_vs_time",
    "score_frame",
    "score_near_vehicles",
    "vehicle_pose",
    "within_radius",
]

# GOSPA (Rahmathullah, Garcia-Fernandez, Svensson, "Generalized optimal sub-pattern assignment
# metric", FUSION 2017; García-Fernández, Svensson, Morelande, IEEE TAES 2020, for its use on
# tracking output). p = 2 makes the localization part a sum of squared errors, the RMSE's quantity.
# alpha = 2 is the value for which GOSPA splits into localization, missed and false parts.
# c is the largest horizontal error still called a (bad) localization rather than a miss and a
# false track: fused obstacle errors are 0.3-0.4 m RMS (3 sigma about 1.2 m), a car at 14 m/s
# moves 1.4 m in a frame, so a track a frame late is still inside 3 m; pedestrians walking side by
# side are 1-2 m apart, so a much larger c would let an estimate be "explained" by the wrong person.
# 3 m is also the gate every earlier figure used, so coverage stays comparable.
GOSPA_P = 2
GOSPA_ALPHA = 2
GOSPA_C_M = 3.0
GATE_M = GOSPA_C_M  # one assignment for RMSE, coverage, false tracks and GOSPA
CONFIDENCE = 0.95  # two-sided, for every NEES band
VEHICLE_DOF = 6
OBJECT_DOF = 3


# ----------------------------------------------------------------------------- matching


def match_vehicles(est_ids: Sequence[str], true_ids: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Pair vehicles by id: (true index array, estimate index array), in the estimate's order."""
    tid = {v: i for i, v in enumerate(true_ids)}
    pairs = [(tid[v], j) for j, v in enumerate(est_ids) if v in tid]
    a = np.array(pairs, dtype=int).reshape(-1, 2)
    return a[:, 0], a[:, 1]


def within_radius(p, center, radius_m: float) -> np.ndarray:
    """Boolean mask of the rows of ``p`` (N, >=2) within ``radius_m`` of ``center`` horizontally."""
    p = np.asarray(p, dtype=float)
    p = p.reshape(len(p), -1) if p.size else np.zeros((0, 2))
    return np.linalg.norm(p[:, :2] - np.asarray(center, dtype=float)[:2], axis=1) <= radius_m


# ----------------------------------------------------------------------------- errors


def pose_error(pose_est, pose_true) -> np.ndarray:
    """e = [p_hat - p, wrap(rpy_hat - rpy)] over rows (N, 6) or one pose (6,).

    FusedState.vehicle_pose_cov is over the six wire numbers ``[x, y, z, roll, pitch, yaw]``
    (schemas/README.md; the container maps GTSAM's tangent covariance to them with
    ``fusion.poses.pose_cov_from_tangent``), so the error is their difference, each angle wrapped to
    [-pi, pi): to first order the same error the covariance describes.
    """
    e = np.asarray(pose_est, dtype=float) - np.asarray(pose_true, dtype=float)
    e[..., 3:] = geo.wrap_angle(e[..., 3:])
    return e


def horizontal_sq_error(p_est, p_true) -> float:
    """||p_est[:2] - p_true[:2]||^2 (m^2)."""
    d = np.asarray(p_est, dtype=float)[:2] - np.asarray(p_true, dtype=float)[:2]
    return float(d @ d)


def rmse_sq(sq: Iterable[float]) -> float:
    """sqrt(mean of squared error norms): eqs. rms1 / rms2 from stacked ||e||^2; NaN when empty."""
    a = np.asarray(sq if isinstance(sq, np.ndarray) else list(sq), dtype=float)
    return float(np.sqrt(a.mean())) if a.size else float("nan")


def vehicle_pose(state: FusedState | GroundTruth, vid: str) -> np.ndarray | None:
    """The 6-vector pose of ``vid`` in a fused state or the ground truth, None if absent."""
    if vid not in state.vehicle_ids:
        return None
    return np.asarray(state.vehicle_pose[state.vehicle_ids.index(vid)], dtype=float)


def obstacle_errors(
    fused: FusedState, truth: GroundTruth, gate_m: float = GATE_M, within: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Map-frame errors of fused objects matched to true obstacles (:func:`match_objects`).

    ``within``: optional boolean mask over the true obstacles to score (e.g. near the ego).
    Returns (true obstacle ids (m,), errors p_hat - p (m, 3), fused position covariances (m, 3, 3)).
    """
    p_true = _points(truth.obstacle_p_map)
    ti, fi = match_objects(fused.object_p_map, p_true, gate_m)
    if within is not None:
        keep = np.asarray(within, dtype=bool)[ti]
        ti, fi = ti[keep], fi[keep]
    err = _points(fused.object_p_map)[fi] - p_true[ti]
    cov = cov_from_upper(np.asarray(fused.object_cov, dtype=float).reshape(-1, 6)[fi]).reshape(-1, 3, 3)
    return np.asarray(truth.obstacle_id, dtype=np.int64)[ti], err, cov


def relative_target_errors(
    fused: FusedState, truth: GroundTruth, ego: str, radius_m: float, gate_m: float = GATE_M
) -> tuple[np.ndarray, np.ndarray, int]:
    """The paper's rms2 terms: horizontal errors of targets in the ego's body frame.

    For the true obstacles within ``radius_m`` of the true ego position, matched to fused objects in
    the map frame: e_k = [T_hat^-1 p_hat_k - T^-1 p_k]_xy with T / T_hat the true / fused ego pose.
    Returns (true obstacle ids (m,), errors (m, 2), number of true obstacles within the radius).
    """
    pose_true, pose_hat = vehicle_pose(truth, ego), vehicle_pose(fused, ego)
    if pose_true is None or pose_hat is None:
        return np.zeros(0, np.int64), np.zeros((0, 2)), 0
    T_true, T_hat = geo.pose_to_matrix(pose_true), geo.pose_to_matrix(pose_hat)
    p_true = _points(truth.obstacle_p_map)
    near = within_radius(p_true, T_true[:2, 3], radius_m)
    ti, fi = match_objects(fused.object_p_map, p_true, gate_m)
    keep = near[ti]
    ti, fi = ti[keep], fi[keep]
    rel_true = geo.transform_points(geo.inverse(T_true), p_true[ti])
    rel_hat = geo.transform_points(geo.inverse(T_hat), _points(fused.object_p_map)[fi])
    ids = np.asarray(truth.obstacle_id, dtype=np.int64)[ti]
    return ids, (rel_hat - rel_true)[:, :2].reshape(-1, 2), int(near.sum())


def _points(p) -> np.ndarray:
    return np.asarray(p, dtype=float).reshape(-1, 3)


# ----------------------------------------------------------------------------- GOSPA


@dataclass(frozen=True)
class Gospa:
    """GOSPA's additive parts (m^p): localization + missed + false = distance^p."""

    localization: float
    missed: float
    false: float
    p: int = GOSPA_P

    @property
    def total(self) -> float:
        return self.localization + self.missed + self.false

    @property
    def distance(self) -> float:
        return float(self.total ** (1.0 / self.p))


def gospa_parts(d_matched, n_missed: int, n_false: int, c: float = GOSPA_C_M, p: int = GOSPA_P) -> Gospa:
    """GOSPA (alpha = 2) from an assignment: localization = sum_pairs d^p, missed = c^p / 2 * n_missed,
    false = c^p / 2 * n_false (every pair with d < c)."""
    d = np.asarray(d_matched, dtype=float)
    if np.any(d >= c):
        raise ValueError(f"matched distances must be below the cutoff {c}, got max {d.max()}")
    half = c**p / GOSPA_ALPHA
    return Gospa(float(np.sum(d**p)), half * int(n_missed), half * int(n_false), p)


def gospa(p_est, p_true, c: float = GOSPA_C_M, p: int = GOSPA_P) -> Gospa:
    """GOSPA between estimated and true horizontal positions (rows (N, >=2); only x, y are used):

        d_p^(c,2)(X, Y) = [ min_gamma sum_{(i,j) in gamma} d(x_i, y_j)^p + c^p / 2 (|X| + |Y| - 2 |gamma|) ]^(1/p)

    over assignments gamma with d < c (Rahmathullah et al. 2017, eq. 2 with alpha = 2).
    """
    p_est, p_true = np.asarray(p_est, dtype=float), np.asarray(p_true, dtype=float)
    n_est = len(p_est) if p_est.size else 0
    n_true = len(p_true) if p_true.size else 0
    ti, fi = match_objects(p_est, p_true, c, p)
    d = np.linalg.norm(p_est[fi, :2] - p_true[ti, :2], axis=1) if len(ti) else np.zeros(0)
    return gospa_parts(d, n_true - len(ti), n_est - len(fi), c, p)


# ----------------------------------------------------------------------------- consistency


def nees_band(dof: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Two-sided band of one NEES value: chi2.ppf([a/2, 1 - a/2], dof), a = 1 - confidence."""
    a = 1.0 - confidence
    lo, hi = chi2_quantile([a / 2, 1 - a / 2], dof)
    return float(lo), float(hi)


def fraction_in_band(values, dof: int, confidence: float = CONFIDENCE) -> float:
    """Fraction of NEES values (one per cell) inside their own two-sided band; ``confidence`` expected."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return float("nan")
    lo, hi = nees_band(dof, confidence)
    return float(np.mean((v >= lo) & (v <= hi)))


@dataclass(frozen=True)
class Anees:
    """Average NEES of n cells and its band chi2.ppf([a/2, 1 - a/2], n dof) / n (independent cells)."""

    value: float
    lo: float
    hi: float
    n: int

    @property
    def inside(self) -> bool:
        return self.lo <= self.value <= self.hi


def anees(values, dof: int, confidence: float = CONFIDENCE) -> Anees:
    """ANEES = mean NEES over n cells with its band: n ANEES ~ chi2(n dof) if the cells are independent
    and the covariances right. Cells of consecutive frames are correlated, so for a run's cells the
    band is narrower than the statistic's real spread: a strict test."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return Anees(float("nan"), float("nan"), float("nan"), 0)
    lo, hi = anees_band(dof, v.size, confidence)
    return Anees(float(v.mean()), lo, hi, int(v.size))


# ----------------------------------------------------------------------------- one frame


@dataclass(frozen=True)
class FrameScore:
    """One fused state against the truth of its t_meas.

    Vehicles: ``vehicle_ids`` matched by id, errors (n, 6) from :func:`pose_error` and the fused
    covariances (n, 6, 6). Objects: in-scope matched pairs, errors p_hat - p (m, 3), fused position
    covariances (m, 3, 3); ``n_truth`` obstacles and ``n_fused`` fused objects in scope, ``n_false``
    of those unmatched; ``gospa`` over the same assignment.
    """

    t: float
    vehicle_ids: tuple[str, ...]
    vehicle_err: np.ndarray
    vehicle_cov: np.ndarray
    object_truth_ids: np.ndarray
    object_err: np.ndarray
    object_cov: np.ndarray
    n_truth: int
    n_fused: int
    n_false: int
    gospa: Gospa

    @property
    def vehicle_sq(self) -> np.ndarray:
        """Horizontal squared errors ||e_xy||^2 per vehicle (m^2)."""
        return np.sum(self.vehicle_err[:, :2] ** 2, axis=1)

    @property
    def object_sq(self) -> np.ndarray:
        """Horizontal squared errors per matched object (m^2)."""
        return np.sum(self.object_err[:, :2] ** 2, axis=1)

    @property
    def n_matched(self) -> int:
        return len(self.object_err)

    @property
    def coverage(self) -> float | None:
        """Matched obstacles / obstacles in scope; None without obstacles."""
        return self.n_matched / self.n_truth if self.n_truth else None

    @property
    def vehicle_nees(self) -> np.ndarray:
        """6-DoF pose NEES per vehicle: e^T P^-1 e, e = :func:`pose_error`."""
        return nees(self.vehicle_err, self.vehicle_cov) if len(self.vehicle_err) else np.zeros(0)

    @property
    def object_nees(self) -> np.ndarray:
        """3-D position NEES per matched object."""
        return nees(self.object_err, self.object_cov) if len(self.object_err) else np.zeros(0)


def score_frame(
    fused: FusedState,
    truth: GroundTruth,
    c: float = GOSPA_C_M,
    truth_in_scope: np.ndarray | None = None,
    est_in_scope: np.ndarray | None = None,
) -> FrameScore:
    """Score one fused state against the truth of the same t_meas (module docstring: matching, scope)."""
    ti, fi = match_vehicles(fused.vehicle_ids, truth.vehicle_ids)
    v_err = pose_error(np.asarray(fused.vehicle_pose, float).reshape(-1, 6)[fi],
                       np.asarray(truth.vehicle_pose, float).reshape(-1, 6)[ti])  # fmt: skip
    v_cov = cov_from_upper(np.asarray(fused.vehicle_pose_cov, float).reshape(-1, 21)[fi]).reshape(-1, 6, 6)
    p_est, p_true = _points(fused.object_p_map), _points(truth.obstacle_p_map)
    t_in = np.ones(len(p_true), bool) if truth_in_scope is None else np.asarray(truth_in_scope, bool)
    e_in = np.ones(len(p_est), bool) if est_in_scope is None else np.asarray(est_in_scope, bool)
    if t_in.shape != (len(p_true),) or e_in.shape != (len(p_est),):
        raise ValueError(f"scope masks {t_in.shape}, {e_in.shape} for {len(p_true)} obstacles, {len(p_est)} objects")
    oi, oj = match_objects(p_est, p_true, c, GOSPA_P)
    keep = t_in[oi]
    matched_est = np.zeros(len(p_est), bool)
    matched_est[oj] = True
    oi, oj = oi[keep], oj[keep]
    o_err = p_est[oj] - p_true[oi]
    o_cov = cov_from_upper(np.asarray(fused.object_cov, float).reshape(-1, 6)[oj]).reshape(-1, 3, 3)
    n_truth = int(t_in.sum())
    n_false = int(np.sum(e_in & ~matched_est))
    d = np.linalg.norm(o_err[:, :2], axis=1)
    return FrameScore(
        t=float(fused.t_meas),
        vehicle_ids=tuple(fused.vehicle_ids[j] for j in fi),
        vehicle_err=v_err.reshape(-1, 6),
        vehicle_cov=v_cov,
        object_truth_ids=np.asarray(truth.obstacle_id, dtype=np.int64)[oi],
        object_err=o_err.reshape(-1, 3),
        object_cov=o_cov,
        n_truth=n_truth,
        n_fused=len(oj) + n_false,
        n_false=n_false,
        gospa=gospa_parts(d, n_truth - len(oi), n_false, c, GOSPA_P),
    )



def score_near_vehicles(fused: FusedState, truth: GroundTruth, radius_m: float) -> tuple[FrameScore, int]:
    """:func:`score_frame` with the objects scoped to those within ``radius_m`` of any connected vehicle's
    true position (true obstacles and fused objects alike): the scaling experiment's and the centralized
    bench's scope. Returns the score and the number of true obstacles in scope."""
    cv = np.asarray(truth.vehicle_pose, dtype=float).reshape(-1, 6)[:, :2]
    p_true = np.asarray(truth.obstacle_p_map, dtype=float).reshape(-1, 3)[:, :2]
    p_est = np.asarray(fused.object_p_map, dtype=float).reshape(-1, 3)[:, :2]
    t_in = _near_any(p_true, cv, radius_m)
    return score_frame(fused, truth, truth_in_scope=t_in, est_in_scope=_near_any(p_est, cv, radius_m)), int(t_in.sum())


def _near_any(p: np.ndarray, centres: np.ndarray, radius_m: float) -> np.ndarray:
    """Which of the points p (n, 2) lie within radius_m of any of the centres (k, 2)."""
    if not len(p) or not len(centres):
        return np.zeros(len(p), dtype=bool)
    return np.min(np.linalg.norm(p[:, None, :] - centres[None], axis=2), axis=1) <= radius_m

def frame_row(s: FrameScore) -> dict[str, float | int]:
    """A flat per-frame record (the evaluator's ``eval_frames.csv``, the experiments' per-frame tables):
    sums and counts, so frames aggregate exactly."""
    return {
        "t_meas": round(s.t, 6),
        "vehicle_pairs": len(s.vehicle_err),
        "vehicle_sq_sum_m2": float(s.vehicle_sq.sum()),
        "vehicle_nees_sum": float(s.vehicle_nees.sum()),
        "object_pairs": s.n_matched,
        "object_sq_sum_m2": float(s.object_sq.sum()),
        "object_nees_sum": float(s.object_nees.sum()),
        "obstacles": s.n_truth,
        "objects": s.n_fused,
        "false_tracks": s.n_false,
        "gospa_localization_m2": s.gospa.localization,
        "gospa_missed_m2": s.gospa.missed,
        "gospa_false_m2": s.gospa.false,
    }


def frame_row_fields() -> list[str]:
    """The keys of :func:`frame_row`, in order (a CSV header)."""
    return list(_FRAME_ROW_FIELDS)


_FRAME_ROW_FIELDS = (
    "t_meas", "vehicle_pairs", "vehicle_sq_sum_m2", "vehicle_nees_sum", "object_pairs", "object_sq_sum_m2",
    "object_nees_sum", "obstacles", "objects", "false_tracks", "gospa_localization_m2", "gospa_missed_m2",
    "gospa_false_m2",
)  # fmt: skip


# ----------------------------------------------------------------------------- a run


@dataclass
class Totals:
    """Running sums over frames (bounded memory: the live evaluator keeps one for hours).

    :meth:`summary` gives, over the frames added: horizontal RMSE of vehicles (all and by id) and
    matched objects; coverage = sum matched / sum obstacles in scope; false tracks per frame and as a
    fraction of fused objects; GOSPA as the mean of each part per frame (m^2) and
    sqrt(mean GOSPA^2) (m); ANEES with its band and the fraction of cells inside the per-cell band,
    for 6-DoF vehicle poses and 3-D object positions.
    """

    frames: int = 0
    vehicle: list = field(default_factory=lambda: [0.0, 0])  # [sum ||e_xy||^2, pairs]
    by_id: dict[str, list] = field(default_factory=dict)
    object: list = field(default_factory=lambda: [0.0, 0])
    obstacles: int = 0
    matched: int = 0
    fused: int = 0
    false: int = 0
    gospa: list = field(default_factory=lambda: [0.0, 0.0, 0.0])  # localization, missed, false (m^2)
    vehicle_nees: list = field(default_factory=lambda: [0.0, 0, 0])  # [sum, cells, cells in band]
    object_nees: list = field(default_factory=lambda: [0.0, 0, 0])

    def add(self, s: FrameScore) -> None:
        self.frames += 1
        v_sq, o_sq = s.vehicle_sq, s.object_sq
        self.vehicle[0] += float(v_sq.sum())
        self.vehicle[1] += len(v_sq)
        for vid, e2 in zip(s.vehicle_ids, v_sq, strict=True):
            acc = self.by_id.setdefault(vid, [0.0, 0])
            acc[0] += float(e2)
            acc[1] += 1
        self.object[0] += float(o_sq.sum())
        self.object[1] += len(o_sq)
        self.obstacles += s.n_truth
        self.matched += s.n_matched
        self.fused += s.n_fused
        self.false += s.n_false
        for k, x in enumerate((s.gospa.localization, s.gospa.missed, s.gospa.false)):
            self.gospa[k] += x
        for acc, vals, dof in (
            (self.vehicle_nees, s.vehicle_nees, VEHICLE_DOF),
            (self.object_nees, s.object_nees, OBJECT_DOF),
        ):
            lo, hi = nees_band(dof)
            acc[0] += float(vals.sum())
            acc[1] += len(vals)
            acc[2] += int(np.sum((vals >= lo) & (vals <= hi)))

    def summary(self) -> dict:
        def root(acc) -> float | None:
            return float(np.sqrt(acc[0] / acc[1])) if acc[1] else None

        def ratio(a, b) -> float | None:
            return a / b if b else None

        def consistency(acc, dof: int) -> dict:
            if not acc[1]:
                return {"anees": None, "anees_band": None, "nees_in_band": None, "cells": 0}
            return {
                "anees": acc[0] / acc[1],
                "anees_band": list(anees_band(dof, acc[1])),
                "nees_in_band": acc[2] / acc[1],
                "cells": acc[1],
            }

        n = self.frames
        loc, miss, false = (x / n if n else None for x in self.gospa)
        return {
            "frames": n,
            "vehicle_rmse_m": root(self.vehicle),
            "vehicle_pairs": self.vehicle[1],
            "vehicle_rmse_by_id_m": {k: root(a) for k, a in sorted(self.by_id.items()) if a[1]},
            "object_rmse_m": root(self.object),
            "object_pairs": self.object[1],
            "coverage": ratio(self.matched, self.obstacles),
            "false_tracks_per_frame": ratio(self.false, n),
            "false_track_fraction": ratio(self.false, self.fused),
            "gospa_m": float(np.sqrt(sum(self.gospa) / n)) if n else None,
            "gospa_localization_m2": loc,
            "gospa_missed_m2": miss,
            "gospa_false_m2": false,
            "vehicle_nees": consistency(self.vehicle_nees, VEHICLE_DOF),
            "object_nees": consistency(self.object_nees, OBJECT_DOF),
        }


# ----------------------------------------------------------------------------- over time


@dataclass(frozen=True)
class RmseVsTime:
    """Per-bucket RMSE over runs: bucket start times (s), mean over runs, band (percentiles), runs."""

    t_start: np.ndarray
    mean: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    runs: np.ndarray


def rmse_vs_time(t, sq, run, bucket_s: float = 1.0, band: tuple[float, float] = (5.0, 95.0)) -> RmseVsTime:
    """RMSE against time: cells (t_i, ||e_i||^2, run_i) are bucketed by floor(t / bucket_s); in each
    bucket b and run r, RMSE_br = sqrt(mean ||e||^2); over the runs that have cells in b, the mean of
    RMSE_br and its ``band`` percentiles (default the 90 % band, 5-95 %)."""
    if bucket_s <= 0:
        raise ValueError(f"bucket_s must be > 0, got {bucket_s}")
    t, sq = np.asarray(t, dtype=float), np.asarray(sq, dtype=float)
    run = np.asarray(run)
    if not t.shape == sq.shape == run.shape or t.ndim != 1:
        raise ValueError(f"t, sq and run must be 1-D of one length, got {t.shape}, {sq.shape}, {run.shape}")
    if t.size == 0:
        z = np.zeros(0)
        return RmseVsTime(z, z, z, z, np.zeros(0, int))
    b = np.floor(t / bucket_s + 1e-9).astype(np.int64)
    _, r = np.unique(run, return_inverse=True)
    cells, inv = np.unique(np.stack([b, r]), axis=1, return_inverse=True)
    inv = inv.reshape(-1)
    per = np.sqrt(np.bincount(inv, sq) / np.bincount(inv))  # RMSE per (bucket, run)
    buckets, bi = np.unique(cells[0], return_inverse=True)
    bi = bi.reshape(-1)
    order = np.argsort(bi, kind="stable")
    groups = np.split(per[order], np.cumsum(np.bincount(bi))[:-1])
    lo, hi = (np.array([np.percentile(g, q) for g in groups]) for q in band)
    return RmseVsTime(
        buckets * bucket_s, np.array([g.mean() for g in groups]), lo, hi, np.array([len(g) for g in groups])
    )


# ----------------------------------------------------------------------------- freshness


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
