"""Traffic drawn per run: the scenario's actors with start, speed profile, lane and walking varied by seed.

:func:`draw_traffic` turns a scenario's vehicle and pedestrian lists into the ones a run uses, drawn
from their own stream (``SeedSequence([seed, TRAFFIC_STREAM])``): the sensors' streams are not touched,
so switching traffic variation on or off leaves every sensor's random draws as they were (the
measurements still differ where the traffic does). With ``traffic.enabled`` false the lists come back
as written, with the default speed phases filled in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import PedestrianSpec, ScenarioConfig, TrafficConfig, VehicleSpec

__all__ = ["TRAFFIC_STREAM", "Traffic", "draw_traffic"]

TRAFFIC_STREAM = 0x54524146  # "TRAF": spawn key of the traffic stream


@dataclass(frozen=True)
class Traffic:
    """The actors of one run (every vehicle's ``speed_phase_rad`` set)."""

    connected: list[VehicleSpec]
    obstacle_vehicles: list[VehicleSpec]
    pedestrians: list[PedestrianSpec]


def _default_phases(specs: list[VehicleSpec]) -> list[VehicleSpec]:
    """Phases as listed, or spread evenly over the list (2 pi i / n) where none is given."""
    n = max(len(specs), 1)
    return [
        v if v.speed_phase_rad is not None else v.model_copy(update={"speed_phase_rad": 2 * np.pi * i / n})
        for i, v in enumerate(specs)
    ]


def _truncated(rng: np.random.Generator, sigma: float, size=None) -> np.ndarray:
    """N(0, sigma^2) truncated at +-2 sigma (clipped)."""
    return np.clip(rng.normal(0.0, 1.0, size), -2.0, 2.0) * sigma


def _vehicle(v: VehicleSpec, tc: TrafficConfig, z: dict[str, float], lanes: int) -> VehicleSpec:
    speed = v.speed_mps * (1.0 + z["speed"])
    lane = v.lane
    if z["swap"] < tc.lane_swap_p and lanes >= 4:
        lane = v.lane ^ 2  # lanes 0 <-> 2 and 1 <-> 3: the other lane of the same direction
    return v.model_copy(
        update={
            "lane": lane,
            "s0_m": v.s0_m + z["s0"],
            "speed_mps": max(speed, 0.0),
            "speed_amp_mps": v.speed_amp_mps * z["amp"],
            "speed_period_s": v.speed_period_s * z["period"],
            "speed_phase_rad": float(v.speed_phase_rad + z["phase"]),
        }
    )


def _draws(rng: np.random.Generator, tc: TrafficConfig) -> dict[str, float]:
    """One vehicle's (or one platoon's) draws: always the same number, whatever is configured."""
    u = rng.random(3)
    return {
        "s0": float(_truncated(rng, tc.s0_sigma_m)),
        "speed": float(_truncated(rng, tc.speed_sigma)),
        "amp": tc.speed_amp_scale[0] + u[0] * (tc.speed_amp_scale[1] - tc.speed_amp_scale[0]),
        "period": tc.speed_period_scale[0] + u[1] * (tc.speed_period_scale[1] - tc.speed_period_scale[0]),
        "phase": float(rng.normal(0.0, tc.speed_phase_sigma_rad)),
        "swap": float(u[2]),
        "gap": float(_truncated(rng, tc.gap_sigma_m)),
    }


def draw_traffic(
    sc: ScenarioConfig, seed: int, path_lengths: list[float] | None = None, lane_lengths: list[float] | None = None
) -> Traffic:
    """The actors of run ``seed`` of scenario ``sc`` (class docstring of :class:`TrafficConfig`).

    ``path_lengths``: the lengths of the map's walkable paths (needed for uniform pedestrian starts);
    ``lane_lengths``: of its lane centre lines (needed for ``min_gap_m``).
    Connected vehicles draw from one child stream, obstacle vehicles from a second, pedestrians from a
    third, so adding a pedestrian does not change the vehicles' draws.
    """
    connected = _default_phases(list(sc.connected))
    obstacles = _default_phases(list(sc.obstacle_vehicles))
    pedestrians = list(sc.pedestrians)
    tc = sc.traffic
    if not tc.enabled:
        return Traffic(connected, obstacles, pedestrians)
    lanes = 2 * sc.map.lanes_per_direction
    ss_platoon, ss_cv, ss_ov, ss_ped = np.random.SeedSequence([int(seed), TRAFFIC_STREAM]).spawn(4)
    platoon = _draws(np.random.default_rng(ss_platoon), tc)

    def vary(specs: list[VehicleSpec], ss: np.random.SeedSequence) -> list[VehicleSpec]:
        rng = np.random.default_rng(ss)
        out = []
        for v in specs:
            own = _draws(rng, tc)
            if tc.platoon:  # the scene moves together; each vehicle only moves by its gap jitter
                z = {**platoon, "s0": platoon["s0"] + own["gap"], "swap": 1.0}
            else:
                z = own
            out.append(_vehicle(v, tc, z, lanes))
        return out

    rng = np.random.default_rng(ss_ped)
    peds = []
    for p in pedestrians:
        u = rng.random(3)
        speed = tc.pedestrian_speed_mps[0] + tc.pedestrian_speed_mps[1] * rng.normal()
        s0 = p.s0_m
        if tc.pedestrian_s0_uniform:
            if path_lengths is None:
                raise ValueError("uniform pedestrian starts need the walkable paths' lengths (path_lengths)")
            s0 = float(u[0] * path_lengths[p.area])
        peds.append(
            p.model_copy(
                update={
                    "s0_m": s0,
                    "speed_mps": float(np.clip(speed, *tc.pedestrian_speed_range_mps)),
                    "direction": -p.direction if u[1] < tc.pedestrian_reverse_p else p.direction,
                }
            )
        )
    cv, ov = vary(connected, ss_cv), vary(obstacles, ss_ov)
    if tc.min_gap_m > 0:
        if lane_lengths is None:
            raise ValueError("a minimum gap needs the lanes' lengths (lane_lengths)")
        cv, ov = _spread(cv, ov, tc.min_gap_m, lane_lengths)
    return Traffic(cv, ov, peds)


def _spread(cv: list[VehicleSpec], ov: list[VehicleSpec], gap: float, lane_lengths: list[float]):
    """Starts wrapped onto [0, lane length) and pushed forward until vehicles of one lane are ``gap`` apart."""
    vehicles = [*cv, *ov]
    s0 = [v.s0_m % lane_lengths[v.lane] for v in vehicles]
    for lane in {v.lane for v in vehicles}:
        idx = sorted((i for i, v in enumerate(vehicles) if v.lane == lane), key=lambda i: s0[i])
        for a, b in zip(idx, idx[1:], strict=False):
            s0[b] = max(s0[b], s0[a] + gap)
    out = [v.model_copy(update={"s0_m": float(s)}) for v, s in zip(vehicles, s0, strict=True)]
    return out[: len(cv)], out[len(cv) :]
