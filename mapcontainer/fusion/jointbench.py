"""Speed and accuracy of the centralized host (``mapc bench fusion --host joint``).

The distributed bench's synthetic scene (:mod:`.bench`) sends priors; the centralized host needs *raw*
observations (camera features, a lane mask, GNSS, odometry, detections) of a scene with a map, since it
localizes every vehicle itself. So this bench runs the simulator's scaling scene, ``sumo-town`` (a 5 x 5
signalled grid at city density: each vehicle has about 23 other actors within 50 m, the ~25 of the synthetic
bench's ``--density city``), with its first N vehicles connected, and records every vehicle's
RawObservations of every frame (the simulator's work, not timed). Then it replays the recording into a
:class:`~.joint.JointHost`: a cycle is one frame's ingest (decode, buffer) and ``fuse`` (localize every
vehicle, associate, update the joint state), timed in wall and CPU time after ``warmup_s``. The fused state
of every frame is scored by the evaluator as ``mapc experiment scale`` scores it (objects within ``radius_m``
of a connected vehicle).

The machine's speed at the time: a fixed workload (:func:`yardstick_ms`) is timed between cycles
(``yardstick_samples`` times, spread over the run); ``cycle_over_yardstick`` is the cycle's p50 over its
median, comparable across machines and loads where a bare millisecond figure is not.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from schemas import GroundTruth, encode

from ..evaluation import Totals, score_near_vehicles  # the scaling experiment's object scope, scored alike
from ..sim import World, load_scenario
from ..sim.config import scale_scenario
from ..vehicle import VehicleAgent
from .blas import limit_blas_threads
from .joint import JointHost
from .params import FusionParams

__all__ = ["JOINT_WARMUP_S", "RawRecording", "bench_joint", "record_raw", "replay_joint", "yardstick_ms"]

SCENE = "sumo-town"
JOINT_WARMUP_S = 3.0  # the localizers' start-up from GNSS (as mapc experiment scale's warmup)


@dataclass
class RawRecording:
    """Every frame's RawObservations payloads of a run, with the truth to score against."""

    scenario: str
    seed: int
    vehicles: list[str]
    hdmap: object
    frames: list[tuple[float, list[bytes], GroundTruth]]


def record_raw(vehicles: int, seed: int = 0, duration_s: float = 10.0, scenario: str = SCENE) -> RawRecording:
    """The RawObservations every connected vehicle sends in each frame (centralized mode, ideal channel)."""
    sc = scale_scenario(load_scenario(scenario), vehicles)
    with World(sc, seed=seed, fleet="bench") as world:
        agents = {v: VehicleAgent(world.hdmap, v, "bench", "centralized") for v in world.vehicle_ids}
        frames = []
        for tick in world.run(duration_s):
            payloads = [encode(agents[v].handle(tick.t, f)) for v, f in sorted(tick.frames.items())]
            frames.append((tick.t, payloads, tick.truth))
        return RawRecording(sc.name, seed, world.vehicle_ids, world.hdmap, frames)


def yardstick_ms() -> float:
    """Wall time (ms) of a fixed workload, half numpy (a dense 300 x 300 update), half interpreter (a loop)."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(300, 300))
    t0 = time.perf_counter()
    P = A @ A.T + 300 * np.eye(300)
    for _ in range(20):
        H = A[:, :30]
        K = np.linalg.solve(H.T @ P @ H + np.eye(30), H.T @ P).T
        P = P - K @ (H.T @ P)
    s = 0.0
    for i in range(200_000):
        s += i * 0.5
    return (time.perf_counter() - t0) * 1e3


def replay_joint(
    rec: RawRecording,
    params: FusionParams | None = None,
    warmup_s: float = JOINT_WARMUP_S,
    radius_m: float = 50.0,
    yardstick_samples: int = 5,
) -> dict:
    """Feed a recording to a fresh JointHost frame by frame; timing, phase and accuracy figures."""
    host = JointHost(rec.hdmap, params or FusionParams(), "bench", "host", known_senders=set(rec.vehicles))
    timed = [k for k, (t, _, _) in enumerate(rec.frames) if t >= warmup_s - 1e-9]
    if not timed:
        raise ValueError(f"no frame after warmup_s={warmup_s} in a recording of {len(rec.frames)} frames")
    yard_at = {timed[i * len(timed) // yardstick_samples] for i in range(yardstick_samples)}
    wall, cpu, yard, dims, tracks = [], [], [], [], []
    phases: dict[str, list[float]] = {}
    totals = Totals()
    for k, (t, payloads, truth) in enumerate(rec.frames):
        t0, c0 = time.perf_counter(), time.process_time()
        for b in payloads:
            host.ingest(b, t)
        fused = host.fuse(t)
        w, c = (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3
        if k not in timed:
            continue
        if k in yard_at:
            yard.append(yardstick_ms())
        st = host.stats()
        wall.append(w)
        cpu.append(c)
        dims.append(st["state_dim"])
        tracks.append(st["tracks_confirmed"])
        for phase, ms in st["last_phases_cpu_ms"].items():
            phases.setdefault(phase, []).append(ms)
        totals.add(score_near_vehicles(fused, truth, radius_m)[0])
    s = totals.summary()
    st = host.stats()
    p50 = float(np.percentile(wall, 50))
    return {
        "host": "joint",
        "scenario": rec.scenario,
        "seed": rec.seed,
        "vehicles": len(rec.vehicles),
        "frames_timed": len(wall),
        "tracks_confirmed_mean": float(np.mean(tracks)),
        "state_dim_mean": float(np.mean(dims)),
        "cycle_ms_p50": p50,
        "cycle_ms_p99": float(np.percentile(wall, 99)),
        "cycle_ms_max": float(np.max(wall)),
        "cycle_cpu_ms_p50": float(np.percentile(cpu, 50)),
        "cycle_cpu_ms_p99": float(np.percentile(cpu, 99)),
        "phases_cpu_ms_p50": {phase: float(np.median(ms)) for phase, ms in phases.items()},
        "yardstick_ms_p50": float(np.median(yard)),
        "cycle_over_yardstick": p50 / float(np.median(yard)),
        "vehicle_rmse_m": s["vehicle_rmse_m"],
        "vehicle_anees": s["vehicle_nees"]["anees"],
        "object_rmse_m": s["object_rmse_m"],
        "object_anees": s["object_nees"]["anees"],
        "coverage": s["coverage"],
        "numerical_failure": st["numerical_failure"],
        "localizer_failure": st["localizer_failure"],
    }


def bench_joint(
    vehicles: int = 16,
    seed: int = 0,
    duration_s: float = 10.0,
    warmup_s: float = JOINT_WARMUP_S,
    scenario: str = SCENE,
    blas_threads: int | None = 1,
    yardstick_samples: int = 5,
) -> dict:
    """Record ``vehicles`` connected vehicles' raw observations of ``scenario`` and replay them into the
    centralized host (module docstring); ``blas_threads`` as :func:`.bench.bench_fusion`."""
    if vehicles < 1 or duration_s <= warmup_s:
        raise ValueError(f"bad joint bench: vehicles={vehicles}, duration_s={duration_s}, warmup_s={warmup_s}")
    if blas_threads is not None:
        limit_blas_threads(blas_threads)
    rec = record_raw(vehicles, seed, duration_s, scenario)
    return replay_joint(rec, warmup_s=warmup_s, yardstick_samples=yardstick_samples)
