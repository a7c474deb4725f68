"""The world's cost per tick against the number of connected vehicles (``mapc bench world`` material).

A tick is what the world service does for one frame: :meth:`World.tick` (every actor's state, every
connected vehicle's camera, lane mask, GNSS, odometry and object detections) and the wire encoding of
every SensorFrame and of the GroundTruth. The scenario is scaled to each size by
:func:`~.config.scale_scenario` (the vehicles beyond the scenario's own spread around its ring), so the
scene gets denser as the fleet grows: each camera has more actors in range, reported beside the cost
(``actors_in_range_mean``, ``detections_per_frame_mean``).

The yardstick of the machine's speed at the time is a fixed job of the same kind (numpy projection,
OpenCV line drawing, zlib compression of a camera-sized mask; no code of ours) timed alternately with
each tick: ``tick_over_yardstick`` is the median over the ticks of the tick's time divided by the job's
next to it (paired, as ``mapc bench fusion`` and ``mapc bench security`` pair theirs), so a load that
comes and goes weighs on both alike.
"""

from __future__ import annotations

import time
import zlib

import cv2
import numpy as np

from schemas import encode

from .config import load_scenario, scale_scenario
from .world import World

__all__ = ["Yardstick", "bench_world", "growth_exponent"]


def growth_exponent(sizes, costs) -> float:
    """The exponent b of cost = a N^b fitted by least squares on log-log axes (1: linear growth)."""
    x, y = np.log(np.asarray(sizes, float)), np.log(np.asarray(costs, float))
    if len(x) < 2 or np.ptp(x) == 0:
        raise ValueError(f"need at least two different sizes to fit an exponent, got {list(sizes)}")
    return float(np.polyfit(x, y, 1)[0])


class Yardstick:
    """A fixed job like a camera frame's (seeded data made once): project 20,000 points, draw 300 lines
    of a 1280 x 720 mask one call each, pack the mask to bits and compress it with zlib."""

    def __init__(self, seed: int = 0):
        rng = np.random.default_rng(seed)
        self.p = rng.uniform(-50.0, 50.0, (20_000, 3)) + [0.0, 0.0, 60.0]
        self.R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        self.lines = rng.integers(0, 1280 * 4, (300, 4)).astype(np.int32)
        self.lines[:, 1::2] %= 720 * 4
        self.width = rng.integers(1, 12, 300)

    def __call__(self) -> int:
        q = self.p @ self.R.T
        uv = 1000.0 * q[:, :2] / q[:, 2:]
        mask = np.zeros((720, 1280), np.uint8)
        for (u0, v0, u1, v1), w in zip(self.lines.tolist(), self.width.tolist(), strict=True):
            cv2.line(mask, (u0, v0), (u1, v1), 255, w, cv2.LINE_8, 2)
        return len(zlib.compress(np.packbits(mask > 0).tobytes(), 6)) + int(uv.size)


def _one_size(scenario: str, vehicles: int, seed: int, ticks: int, warmup: int, cull: bool, ref: Yardstick) -> dict:
    sc = scale_scenario(load_scenario(scenario), vehicles)
    with World(sc, seed=seed, fleet="bench", cull=cull) as world:
        range_m = sc.sensors.detector.range_m
        for k in range(warmup):
            world.tick(k)
        wall, cpu, ref_ms, ratio, in_range, dets, nbytes = [], [], [], [], [], [], []
        for k in range(warmup, warmup + ticks):
            y0 = time.perf_counter()
            ref()
            w0, c0 = time.perf_counter(), time.process_time()
            t = world.tick(k)
            size = sum(len(encode(f)) for f in t.frames.values()) + len(encode(t.truth))
            w1, c1 = time.perf_counter(), time.process_time()
            wall.append((w1 - w0) * 1e3)
            cpu.append((c1 - c0) * 1e3)
            ref_ms.append((w0 - y0) * 1e3)
            ratio.append(wall[-1] / ref_ms[-1])
            nbytes.append(size / len(world.vehicle_ids))
            p = np.array([s.p_map[:2] for s in t.states.values()])
            for vid in world.vehicle_ids:
                d = np.linalg.norm(p - t.states[vid].p_map[:2], axis=1)
                in_range.append(int((d <= range_m).sum()) - 1)
                dets.append(len(t.frames[vid].objects.cls))
        n_actors = len(t.states)
    ms = float(np.median(wall))
    r = float(np.median(ratio))
    return {
        "vehicles": vehicles,
        "actors": n_actors,
        "ms_per_tick_p50": round(ms, 2),
        "ms_per_tick_p90": round(float(np.percentile(wall, 90)), 2),
        "cpu_ms_per_tick_p50": round(float(np.median(cpu)), 2),
        "ms_per_vehicle": round(ms / vehicles, 3),
        "yardstick_ms_p50": round(float(np.median(ref_ms)), 3),
        "tick_over_yardstick": round(r, 3),
        "vehicle_over_yardstick": round(r / vehicles, 4),
        "actors_in_range_mean": round(float(np.mean(in_range)), 2),
        "detections_per_frame_mean": round(float(np.mean(dets)), 2),
        "bytes_per_vehicle_mean": round(float(np.mean(nbytes)), 1),
    }


def bench_world(
    vehicles: list[int],
    scenario: str = "paper-urban",
    seed: int = 0,
    ticks: int = 40,
    warmup: int = 5,
    cull: bool = True,
) -> dict:
    """Time ``ticks`` ticks (after ``warmup`` untimed ones) of the scenario scaled to each fleet size in
    ``vehicles``; one World per size, in this process.

    Per size: ``ms_per_tick_p50`` (wall) and ``cpu_ms_per_tick_p50``, ``ms_per_vehicle`` (the median tick
    over the vehicles), the paired ``tick_over_yardstick`` and ``vehicle_over_yardstick``, the actors
    within the detector's range of a vehicle and its detections per frame (the work a camera cannot
    avoid). Over the sizes: ``growth_exponent`` b of ms_per_tick = a N^b (and ``growth_exponent_paired``,
    the same fitted to tick_over_yardstick), and ``per_vehicle_growth``, ms per vehicle at the largest
    size over that at the smallest (paired figures). ``cull`` False: every sensor looks at every actor
    (:class:`World`'s brute force) to show what culling saves.
    """
    sizes = sorted(set(vehicles))
    if len(sizes) < 2 or sizes[0] < 1 or ticks < 1 or warmup < 0:
        raise ValueError(f"need two or more fleet sizes >= 1 and ticks >= 1, got {vehicles}, ticks={ticks}")
    ref = Yardstick()
    rows = [_one_size(scenario, n, seed, ticks, warmup, cull, ref) for n in sizes]
    paired = [r["vehicle_over_yardstick"] for r in rows]
    return {
        "scenario": scenario,
        "seed": seed,
        "ticks": ticks,
        "cull": cull,
        "sizes": rows,
        "growth_exponent": round(growth_exponent(sizes, [r["ms_per_tick_p50"] for r in rows]), 3),
        "growth_exponent_paired": round(growth_exponent(sizes, [r["tick_over_yardstick"] for r in rows]), 3),
        "per_vehicle_growth": round(paired[-1] / paired[0], 3),
    }
