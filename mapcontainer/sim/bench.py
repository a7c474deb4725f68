"""The world's cost per tick against the number of connected vehicles (``mapc bench world`` material).

A tick is what the world service does for one frame: :meth:`World.tick` (every actor's state, every
connected vehicle's camera, lane mask, GNSS, odometry and object detections) and the wire encoding of
every SensorFrame and of the GroundTruth. The scenario is scaled to each size by
:func:`~.config.scale_scenario` (the vehicles beyond the scenario's own spread around its ring), so the
scene gets denser as the fleet grows: each camera has more actors in range, reported beside the cost
(``actors_in_range_mean``, ``detections_per_frame_mean``). With ``density="constant"`` the ring grows
with the fleet instead (:func:`spread_scene`), so what a camera sees stays about the same and the cost
per vehicle shows the simulator's own growth.

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

from .config import ScenarioConfig, load_scenario, scale_scenario
from .world import World

__all__ = ["Yardstick", "bench_world", "growth_exponent", "spread_scene"]


def growth_exponent(sizes, costs) -> float:
    """The exponent b of cost = a N^b fitted by least squares on log-log axes (1: linear growth)."""
    x, y = np.log(np.asarray(sizes, float)), np.log(np.asarray(costs, float))
    if len(x) < 2 or np.ptp(x) == 0:
        raise ValueError(f"need at least two different sizes to fit an exponent, got {list(sizes)}")
    return float(np.polyfit(x, y, 1)[0])


def spread_scene(sc: ScenarioConfig, vehicles: int) -> ScenarioConfig:
    """Scenario ``sc`` with ``vehicles`` connected vehicles on a ring stretched to keep the scene's density.

    Factor f = max(1, vehicles / the scenario's connected vehicles): the ring's straights are lengthened
    so that its length (about 2 (length + width)) is f times the scenario's; the obstacle vehicles and
    pedestrians are copied n = round(f) times, copy j moved by j / n of the ring (copies of a pedestrian
    on a crossing walk another crossing where there is one); lamps and signs are n times as many, the
    crossings too up to the generator's four (one on each straight), with their pairs of traffic lights.
    The connected vehicles then come from :func:`~.config.scale_scenario` on that ring.
    """
    if sc.sumo is not None:
        raise ValueError(f"{sc.name}: a SUMO scenario has its own network, it cannot be stretched")
    m = sc.map
    f = max(1.0, vehicles / len(sc.connected))
    n = max(1, round(f))
    ring_m = f * 2 * (m.length_m + m.width_m)
    step = ring_m / n
    crossings = min(m.crossings * n, _MAX_CROSSINGS)
    lights = m.traffic_lights * crossings // m.crossings if m.crossings else m.traffic_lights * n
    data = sc.model_dump()
    data["map"].update(
        length_m=ring_m / 2 - m.width_m,
        lamps=m.lamps * n,
        traffic_lights=lights,
        signs=m.signs * n,
        crossings=crossings,
    )
    data["obstacle_vehicles"] = [
        {**v.model_dump(), "s0_m": v.s0_m + j * step} for j in range(n) for v in sc.obstacle_vehicles
    ]
    peds = []
    for j in range(n):
        for p in sc.pedestrians:
            if p.area < 2:  # a sidewalk: around the ring
                peds.append({**p.model_dump(), "s0_m": p.s0_m + j * step})
            else:  # a crossing: the same one or another
                peds.append({**p.model_dump(), "area": 2 + (p.area - 2 + j * m.crossings) % crossings})
    data["pedestrians"] = peds
    return scale_scenario(ScenarioConfig.model_validate(data), vehicles)


_MAX_CROSSINGS = 4  # the ring generator puts at most one crossing on each of its four straights


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


def _one_size(
    sc: ScenarioConfig, vehicles: int, seed: int, ticks: int, warmup: int, cull: bool, ref: Yardstick
) -> dict:
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
    density: str = "fixed",
) -> dict:
    """Time ``ticks`` ticks (after ``warmup`` untimed ones) of the scenario scaled to each fleet size in
    ``vehicles``; one World per size, in this process.

    Per size: ``ms_per_tick_p50`` (wall) and ``cpu_ms_per_tick_p50``, ``ms_per_vehicle`` (the median tick
    over the vehicles), the paired ``tick_over_yardstick`` and ``vehicle_over_yardstick``, the actors
    within the detector's range of a vehicle and its detections per frame (the work a camera cannot
    avoid). Over the sizes: ``growth_exponent`` b of ms_per_tick = a N^b (and ``growth_exponent_paired``,
    the same fitted to tick_over_yardstick), and ``per_vehicle_growth``, ms per vehicle at the largest
    size over that at the smallest (paired figures). ``cull`` False: every sensor looks at every actor
    (:class:`World`'s brute force) to show what culling saves. ``density``: "fixed", the scenario's scene
    with the vehicles added (:func:`~.config.scale_scenario`, as ``mapc fleet up --vehicles``), or
    "constant", a ring grown with the fleet (:func:`spread_scene`).
    """
    sizes = sorted(set(vehicles))
    if len(sizes) < 2 or sizes[0] < 1 or ticks < 1 or warmup < 0:
        raise ValueError(f"need two or more fleet sizes >= 1 and ticks >= 1, got {vehicles}, ticks={ticks}")
    if density not in ("fixed", "constant"):
        raise ValueError(f"density must be 'fixed' or 'constant', got {density!r}")
    sc = load_scenario(scenario)
    scenes = {n: scale_scenario(sc, n) if density == "fixed" else spread_scene(sc, n) for n in sizes}
    ref = Yardstick()
    rows = [_one_size(scenes[n], n, seed, ticks, warmup, cull, ref) for n in sizes]
    paired = [r["vehicle_over_yardstick"] for r in rows]
    return {
        "scenario": scenario,
        "seed": seed,
        "ticks": ticks,
        "cull": cull,
        "density": density,
        "sizes": rows,
        "growth_exponent": round(growth_exponent(sizes, [r["ms_per_tick_p50"] for r in rows]), 3),
        "growth_exponent_paired": round(growth_exponent(sizes, [r["tick_over_yardstick"] for r in rows]), 3),
        "per_vehicle_growth": round(paired[-1] / paired[0], 3),
    }
