"""The world role's core: scenario scaling and the pacing arithmetic (pure, no I/O)."""

from __future__ import annotations

import math

from mapcontainer.sim.config import scale_scenario

__all__ = ["Pacer", "scale_scenario"]  # scale_scenario re-exported from the core


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
