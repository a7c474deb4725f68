"""The world role's core: scenario scaling and the pacing arithmetic (pure, no I/O)."""

from __future__ import annotations

import math

from mapcontainer.sim.config import ScenarioConfig, VehicleSpec

__all__ = ["Pacer", "scale_scenario"]


def scale_scenario(sc: ScenarioConfig, vehicles: int | None) -> ScenarioConfig:
    """The scenario with ``vehicles`` connected vehicles (None: as defined).

    Fewer than defined: the first ones. More: the hook for the scaling experiments — extra vehicles
    are spread evenly over the ring's lanes, starting half-way between the defined ones, at the
    defined vehicles' mean speed. (The scenario generator for large fleets belongs in
    mapcontainer.sim; replace this when it exists.)
    """
    if vehicles is None or vehicles == len(sc.connected):
        return sc
    if vehicles < 1:
        raise ValueError(f"vehicles must be at least 1, got {vehicles}")
    connected = list(sc.connected[:vehicles])
    n_extra = vehicles - len(connected)
    if n_extra > 0:
        lanes = 2 * sc.map.lanes_per_direction
        speed = sum(v.speed_mps for v in sc.connected) / len(sc.connected)
        ring_m = 2 * (sc.map.length_m + sc.map.width_m)  # roughly the ring's length; s wraps anyway
        for i in range(n_extra):
            connected.append(
                VehicleSpec(
                    lane=i % lanes,
                    s0_m=(i + 0.5) * ring_m / n_extra,
                    speed_mps=speed * (0.9 + 0.2 * ((i * 7) % 5) / 4),
                )
            )
    data = sc.model_dump()
    data["connected"] = [v.model_dump() for v in connected]
    return ScenarioConfig.model_validate(data)


class Pacer:
    """Maps frame k to the wall time it is due: wall_ns(k) = epoch_wall_ns + k dt / time_scale.

    ``time_scale`` is scenario seconds per wall second (0.5 runs at half speed).
    """

    def __init__(self, epoch_wall_ns: int, dt: float, time_scale: float):
        if dt <= 0 or time_scale <= 0:
            raise ValueError(f"dt and time_scale must be positive, got dt={dt}, time_scale={time_scale}")
        self.epoch_wall_ns = epoch_wall_ns
        self.dt = dt
        self.time_scale = time_scale

    def t(self, k: int) -> float:
        return k * self.dt

    def due_wall_ns(self, k: int) -> int:
        return self.epoch_wall_ns + int(round(k * self.dt / self.time_scale * 1e9))

    def first_k_at(self, wall_ns: int) -> int:
        """The first frame not yet due at ``wall_ns`` (for resuming a restarted world)."""
        t = (wall_ns - self.epoch_wall_ns) * 1e-9 * self.time_scale
        return max(0, math.ceil(t / self.dt - 1e-9))
