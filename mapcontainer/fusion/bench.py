"""Speed and accuracy of the host container on a synthetic scene (``mapc bench fusion`` material).

Vehicles and obstacles move on straight lines at constant velocity in a square; every vehicle
detects the obstacles (and the other vehicles) within ``range_m`` with the simulator's detector
noise model (radial / tangential sigma growing with range, see configs/sensors/default.yaml) and
reports its pose with Gaussian noise of a stated covariance, part of which persists over frames (see
:func:`bench_fusion`). Every message goes through the wire
codec. A cycle is one tick: ingesting that tick's messages plus one ``Container.fuse``.
"""

from __future__ import annotations

import time
from contextlib import nullcontext

import gtsam
import numpy as np
from scipy.optimize import linear_sum_assignment

from schemas import LocalizationQuality, ObjectClass, ObjectObservations, VehiclePrior, encode

from .. import geometry as geo
from .blas import limit_blas_threads
from .compiled import COMPILED
from .container import Container
from .laps import cpu_clock
from .params import FusionParams
from .poses import sym_from_upper, upper_from_sym
from .simfeed import pose_covariance

__all__ = ["CITY_OBJECTS_IN_RANGE", "batch_solve_ms", "bench_fusion", "bench_fusion_sizes", "parse_sizes"]

CITY_OBJECTS_IN_RANGE = 25  # obstacles a vehicle sees within range at "city" density


def _detector_cov(p_body: np.ndarray) -> np.ndarray:
    """The default detector's covariance at body positions (N, 3).

    sigma along the line of sight 0.18 + 0.006 r, across it 0.12 + 0.004 r, vertical 0.05 (m).
    """
    r = np.linalg.norm(p_body[:, :2], axis=1)
    b = np.arctan2(p_body[:, 1], p_body[:, 0])
    sr, st = 0.18 + 0.006 * r, 0.12 + 0.004 * r
    u = np.stack([np.cos(b), np.sin(b), np.zeros_like(b)], axis=1)
    w = np.stack([-np.sin(b), np.cos(b), np.zeros_like(b)], axis=1)
    return (
        sr[:, None, None] ** 2 * u[:, :, None] * u[:, None, :]
        + st[:, None, None] ** 2 * w[:, :, None] * w[:, None, :]
        + np.diag([0.0, 0.0, 0.05**2])
    )


def bench_fusion(
    vehicles: int = 4,
    objects: int = 14,
    window: int = 10,
    seed: int = 0,
    ticks: int = 100,
    range_m: float = 50.0,
    rate_hz: float = 10.0,
    params: FusionParams | None = None,
    blas_threads: int | None = 1,
    pose_persistent: float = 0.5,
    pose_tau_s: float = 1.0,
    batch_samples: int = 0,
    density: str = "dense",
    cpu_phases: bool = False,
) -> dict:
    """Run the container on a synthetic scene; returns timing and accuracy figures.

    ``window`` is the number of frames in the sliding window (window_s = window / rate_hz). ``density``
    sizes the square: ``"dense"``, so that a vehicle sees about half of the obstacles (at most all of
    them); ``"city"``, so that a vehicle sees about :data:`CITY_OBJECTS_IN_RANGE` obstacles within
    ``range_m`` whatever the fleet's size (constant density: the square grows with the fleet).
    Timings (ms, wall clock) skip the first ``window`` ticks, while the window fills; ``phases_ms_p50``
    splits the cycle by phase (decoding the messages, the container's phases in
    ``Container.stats()["last_phases_ms"]``; medians, so they need not add up to the cycle's). ``blas_threads``
    limits OpenBLAS for the whole process first (see :mod:`.blas`; None leaves it alone). ``cpu_phases``:
    the phases in this process's CPU time instead of wall time (:func:`.laps.cpu_clock`), for a loaded
    machine (``phases_clock`` says which); the cycle's own figures stay wall (``cycle_ms_*``) and CPU
    (``cycle_cpu_ms_p50``).

    Reported poses err like map matching's: the whitened error is sqrt(a) b_k + sqrt(1 - a) n_k with
    a = ``pose_persistent``, n_k white and b_k per vehicle first-order Gauss-Markov with time constant
    ``pose_tau_s`` (the simulator's map matcher: whitened error correlation 0.1-0.8 at 0.1 s, 0.1-0.45
    at 1 s). ``pose_persistent=0`` gives independent errors per frame (the bench before 2026-12).

    ``batch_samples``: the windows of that many ticks, spread over the timed ones, are each solved once
    more after the run by plain GTSAM (:func:`batch_solve_ms`), a yardstick of the machine's speed at
    the time: ``batch_ms_p50`` is their median, ``cycle_over_batch`` the median over those ticks of the
    tick's cycle divided by its window's batch solve (paired: the window's size changes over the run).
    A batch solve started cold (no previous linearization: ~27 ms at 4 / 14 / 10, ~450 ms at
    16 / 100 / 10 on one 2.8 GHz core) costs more than this lower bound.
    """
    if vehicles < 1 or objects < 0 or window < 1 or ticks <= window or batch_samples < 0:
        raise ValueError(
            f"bad bench size: vehicles={vehicles}, objects={objects}, window={window}, ticks={ticks}, "
            f"batch_samples={batch_samples}"
        )
    if blas_threads is not None:
        limit_blas_threads(blas_threads)
    dt = 1.0 / rate_hz
    rng = np.random.default_rng(seed)
    if density == "dense":
        side = max(60.0, range_m * np.sqrt((vehicles + objects) / 9.0))
    elif density == "city":
        side = max(2.0 * range_m, float(np.sqrt(objects * np.pi * range_m**2 / CITY_OBJECTS_IN_RANGE)))
    else:
        raise ValueError(f"bad density {density!r}: 'dense' or 'city'")
    veh_p0 = np.column_stack([rng.uniform(-side / 2, side / 2, (vehicles, 2)), np.zeros(vehicles)])
    heading = rng.uniform(-np.pi, np.pi, vehicles)
    speed = rng.uniform(5.0, 12.0, vehicles)
    veh_v = np.column_stack([speed * np.cos(heading), speed * np.sin(heading), np.zeros(vehicles)])
    n_ped = objects // 2
    obj_cls = np.array([ObjectClass.PEDESTRIAN] * n_ped + [ObjectClass.VEHICLE] * (objects - n_ped), dtype=np.uint8)
    obj_p0 = np.column_stack([rng.uniform(-side / 2, side / 2, (objects, 2)), np.zeros(objects)])
    oh = rng.uniform(-np.pi, np.pi, objects)
    osp = np.where(obj_cls == ObjectClass.PEDESTRIAN, rng.uniform(0.8, 1.8, objects), rng.uniform(5.0, 12.0, objects))
    obj_v = np.column_stack([osp * np.cos(oh), osp * np.sin(oh), np.zeros(objects)])
    # start everything in the middle of its path so that the scene stays populated
    veh_p0 -= veh_v * ticks * dt / 2
    obj_p0 -= obj_v * ticks * dt / 2

    pose_cov = pose_covariance()
    L_pose = np.linalg.cholesky(pose_cov)
    if not 0 <= pose_persistent < 1 or pose_tau_s <= 0:
        raise ValueError(f"bad pose error model: pose_persistent={pose_persistent}, pose_tau_s={pose_tau_s}")
    rho = float(np.exp(-dt / pose_tau_s))
    pose_bias = rng.normal(size=(vehicles, 6)) if pose_persistent > 0 else np.zeros((vehicles, 6))
    p = params or FusionParams(window_s=window * dt)
    vids = [f"cv{i}" for i in range(vehicles)]
    box = Container(p, "bench", "cv0", known_senders=set(vids))

    cycle_ms, cpu_ms, iters, factors, variables, n_dets = [], [], [], [], [], []
    phases: dict[str, list[float]] = {}
    errors, nees, veh_err = [], [], []
    last_match: dict[int, int] = {}
    switches = 0
    snap_at = {window + i * (ticks - window) // batch_samples for i in range(batch_samples)}
    snapshots = []
    for k in range(ticks):
        t = k * dt
        vp = veh_p0 + veh_v * t
        op = obj_p0 + obj_v * t
        payloads = []
        detections = 0
        if pose_persistent > 0 and k:
            pose_bias = rho * pose_bias + np.sqrt(1 - rho**2) * rng.normal(size=pose_bias.shape)
        for i, vid in enumerate(vids):
            yaw = float(np.arctan2(veh_v[i, 1], veh_v[i, 0]))
            truth = np.array([*vp[i], 0.0, 0.0, yaw])
            T_body_map = geo.inverse(geo.pose_to_matrix(truth))
            targets = np.vstack([op, np.delete(vp, i, axis=0)])
            cls = np.concatenate([obj_cls, np.full(vehicles - 1, ObjectClass.VEHICLE, dtype=np.uint8)])
            pb = geo.transform_points(T_body_map, targets)
            seen = (np.linalg.norm(pb[:, :2], axis=1) <= range_m) & (np.linalg.norm(pb[:, :2], axis=1) > 1.0)
            pb, cls = pb[seen], cls[seen]
            detections += len(pb)
            cov = _detector_cov(pb)
            noisy = pb + np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=pb.shape))
            cov_up = upper_from_sym(cov)  # on the wire: float16 standard deviations, int8 correlations
            prior = VehiclePrior(
                fleet="bench",
                sender=vid,
                seq=k,
                t_meas=t,
                t_sent=t,
                pose=truth
                + L_pose
                @ (np.sqrt(pose_persistent) * pose_bias[i] + np.sqrt(1 - pose_persistent) * rng.normal(size=6)),
                pose_cov=upper_from_sym(pose_cov),
                v_map=veh_v[i] + rng.normal(0.0, 0.1, 3) * [1, 1, 0],
                quality=LocalizationQuality(mode="map_matching"),
                objects=ObjectObservations(p_body_cm=np.round(noisy * 100.0), cov=cov_up, cls=cls),
            )
            payloads.append(encode(prior))
        t0, c0 = time.perf_counter(), time.process_time()
        for b in payloads:
            box.ingest(b, t)
        ingest_ms = ((time.process_time() - c0) if cpu_phases else (time.perf_counter() - t0)) * 1e3
        with cpu_clock() if cpu_phases else nullcontext():
            fused = box.fuse(t)
        elapsed = (time.perf_counter() - t0) * 1e3
        cpu = (time.process_time() - c0) * 1e3
        if k < window:
            continue
        if k in snap_at:
            snapshots.append((elapsed, box.graph.snapshot()))
        st = box.stats()
        cycle_ms.append(elapsed)
        cpu_ms.append(cpu)
        for phase, ms in {"ingest": ingest_ms, **st["last_phases_ms"]}.items():
            phases.setdefault(phase, []).append(ms)
        n_dets.append(detections)
        iters.append(st["last_iterations"])
        factors.append(st["factors"])
        variables.append(st["variables"])
        for i, vid in enumerate(fused.vehicle_ids):
            veh_err.append(fused.vehicle_pose[i, :3] - vp[vids.index(vid)])
        if len(fused.object_id):
            D = np.linalg.norm(op[:, None, :2] - fused.object_p_map[None, :, :2], axis=2)
            rows, cols = linear_sum_assignment(np.where(D < 3.0, D, 1e6))
            for r, c in zip(rows, cols, strict=True):
                if D[r, c] >= 3.0:
                    continue
                e = fused.object_p_map[c].astype(float) - op[r]
                errors.append(e)
                C = sym_from_upper(fused.object_cov[c])
                nees.append(float(e @ np.linalg.solve(C, e)))
                fid = int(fused.object_id[c])
                if r in last_match and last_match[r] != fid:
                    switches += 1
                last_match[r] = fid
    st = box.stats()
    batch_ms = np.array([batch_solve_ms(*snap) for _, snap in snapshots])
    paired = np.array([ms for ms, _ in snapshots]) / batch_ms if len(batch_ms) else batch_ms
    e = np.array(errors).reshape(-1, 3)
    ve = np.array(veh_err).reshape(-1, 3)
    return {
        "vehicles": vehicles,
        "objects": objects,
        "window": window,
        "density": density,
        "solver": p.solver,
        "compiled": COMPILED,  # the host's inner loops compiled by numba (the fast extra) or interpreted
        "seed": seed,
        "ticks": ticks,
        "pose_persistent": pose_persistent,
        "detections_per_tick": float(np.mean(n_dets)),
        "us_per_detection": float(np.percentile(cycle_ms, 50)) * 1e3 / max(float(np.mean(n_dets)), 1.0),
        "cycle_ms_p50": float(np.percentile(cycle_ms, 50)),
        "cycle_ms_p99": float(np.percentile(cycle_ms, 99)),
        "cycle_ms_max": float(np.max(cycle_ms)),
        "cycle_cpu_ms_p50": float(np.percentile(cpu_ms, 50)),
        "phases_ms_p50": {phase: float(np.median(ms)) for phase, ms in phases.items()},
        "phases_clock": "cpu" if cpu_phases else "wall",
        "batch_ms_p50": float(np.median(batch_ms)) if len(batch_ms) else None,
        "cycle_over_batch": float(np.median(paired)) if len(paired) else None,
        "iterations_mean": float(np.mean(iters)),
        "factors_mean": float(np.mean(factors)),
        "variables_mean": float(np.mean(variables)),
        "object_rmse_m": float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) if len(e) else float("nan"),
        "object_anees": float(np.mean(nees)) if nees else float("nan"),
        "object_matches": len(e),
        "vehicle_rmse_m": float(np.sqrt(np.mean(np.sum(ve**2, axis=1)))) if len(ve) else float("nan"),
        "id_switches": switches,
        "tracks_confirmed": st["tracks_confirmed"],
        "association": st["association"],
    }


_EXACT_KEYS = ("object_rmse_m", "object_anees", "vehicle_rmse_m", "object_matches", "cycle_ms_p50")


def bench_fusion_sizes(sizes: list[tuple[int, int]], compare_exact: bool = False, **kwargs) -> dict:
    """:func:`bench_fusion` at several (vehicles, objects) sizes in one process (``kwargs`` for every
    size), and how the cost grows between them: ``growth`` holds the ratio of us_per_detection at each
    size to the first's, and the exponents of log-log least-squares fits of cycle_ms_p50 against
    detections_per_tick and against vehicles (1: linear). ``compare_exact``: every size is run again on
    the same scene and seed with FusionParams(solver="exact"), the oracle (its figures under ``exact``,
    and ``rmse_over_exact`` / ``anees_over_exact``). The exact solve's root grows cubically: at 50 / 500
    one run takes minutes."""
    if not sizes:
        raise ValueError("no sizes")
    params = kwargs.pop("params", None)
    window = kwargs.get("window", 10)
    rate = kwargs.get("rate_hz", 10.0)
    runs = []
    for vehicles, objects in sizes:
        r = bench_fusion(vehicles, objects, params=params, **kwargs)
        if compare_exact:
            base = params or FusionParams(window_s=window / rate)
            ex = bench_fusion(vehicles, objects, params=base.model_copy(update={"solver": "exact"}), **kwargs)
            r["exact"] = {k: ex[k] for k in _EXACT_KEYS}
            r["rmse_over_exact"] = r["object_rmse_m"] / ex["object_rmse_m"]
            r["anees_over_exact"] = r["object_anees"] / ex["object_anees"]
        runs.append(r)
    first = runs[0]
    growth: dict = {
        "us_per_detection_over_first": [r["us_per_detection"] / first["us_per_detection"] for r in runs],
    }
    if len(runs) >= 2:
        cyc = np.log([r["cycle_ms_p50"] for r in runs])
        growth["exponent_vs_detections"] = float(
            np.polyfit(np.log([r["detections_per_tick"] for r in runs]), cyc, 1)[0]
        )
        growth["exponent_vs_vehicles"] = float(np.polyfit(np.log([r["vehicles"] for r in runs]), cyc, 1)[0])
    return {"sizes": [f"{v}/{o}" for v, o in sizes], "runs": runs, "growth": growth}


def parse_sizes(text: str) -> list[tuple[int, int]]:
    """``"4/14,16/100"`` -> [(4, 14), (16, 100)] (vehicles / objects); ValueError with the offending item."""
    out = []
    for item in text.split(","):
        try:
            v, o = (int(x) for x in item.strip().split("/"))
        except ValueError:
            raise ValueError(f"bad size {item.strip()!r}: VEHICLES/OBJECTS, e.g. 16/100") from None
        if v < 1 or o < 0:
            raise ValueError(f"bad size {item.strip()!r}: at least 1 vehicle and 0 objects")
        out.append((v, o))
    return out


def batch_solve_ms(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, latest: list[int]) -> float:
    """Wall time (ms) of the window solved the textbook way: GTSAM's LevenbergMarquardtOptimizer from
    ``values``, then gtsam.Marginals for the ``latest`` keys. From the window's own solution this is one
    iteration: a lower bound of a batch solve of the same window."""
    t0 = time.perf_counter()
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
    marginals = gtsam.Marginals(graph, result)
    for key in latest:
        marginals.marginalCovariance(key)
    return (time.perf_counter() - t0) * 1e3


if __name__ == "__main__":  # python -m mapcontainer.fusion.bench [vehicles objects window seed]
    import json
    import sys

    args = [int(a) for a in sys.argv[1:5]]
    print(json.dumps(bench_fusion(*args), indent=2))
