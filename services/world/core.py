"""The world role's core: scenario scaling and the pacing arithmetic (pure, no I/O)."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

from mapcontainer.sim.config import scale_scenario

__all__ = ["Pacer", "Progress", "scale_scenario"]  # scale_scenario re-exported from the core


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

    def pause(self, k: int, wall_ns: int) -> int:
        """Shift the clock so that frame ``k`` is due at ``wall_ns`` if it is due earlier (the adaptive
        clock's pause while a service is behind); the pause in ns (0: none)."""
        late = wall_ns - self.due_wall_ns(k)
        if late <= 0:
            return 0
        self.epoch_wall_ns += late
        return late

    def first_k_at(self, wall_ns: int) -> int:
        """The first frame not yet due at ``wall_ns`` (for resuming a restarted world)."""
        t = (wall_ns - self.epoch_wall_ns) * 1e-9 * self.time_scale
        return max(0, math.ceil(t / self.dt - 1e-9))


class Progress:
    """What the world's adaptive clock (``--time-scale auto``) waits for before it publishes a frame: every
    vehicle's message for the previous frame, and the host's fused state within ``host_slack_s`` of it.

    The vehicles' and the host's messages report how far each got (``t_meas``; a vehicle's clock may be a
    few milliseconds off, so a frame counts as done within half a period). Thread-safe: Zenoh callbacks
    call :meth:`sent` and :meth:`fused`, the world's loop :meth:`wait_for`.
    """

    def __init__(self, vehicle_ids: list[str], dt: float, host_slack_s: float = 0.5):
        if dt <= 0 or host_slack_s < 0:
            raise ValueError(f"dt must be positive and host_slack_s >= 0, got {dt}, {host_slack_s}")
        self.vehicle_ids = list(vehicle_ids)
        self.dt = dt
        self.host_slack_s = host_slack_s
        self._sent: dict[str, float] = {}
        self._fused: float | None = None
        self._cond = threading.Condition()

    def sent(self, vid: str, t_meas: float) -> None:
        with self._cond:
            if vid in self.vehicle_ids and t_meas > self._sent.get(vid, -math.inf):
                self._sent[vid] = t_meas
                self._cond.notify_all()

    def fused(self, t_meas: float) -> None:
        with self._cond:
            if self._fused is None or t_meas > self._fused:
                self._fused = t_meas
                self._cond.notify_all()

    def behind(self, t: float, vehicles: set[str] | None = None, host: bool = True) -> list[str]:
        """Who is not done with the frame at scenario time ``t``: vehicles (of ``vehicles``, those alive; None:
        all) whose newest message is older, and ``host`` when asked for and its newest fused state is more than
        ``host_slack_s`` older (or none came yet while ``t`` is past the slack)."""
        with self._cond:
            return self._behind(t, vehicles, host)

    def _behind(self, t: float, vehicles: set[str] | None, host: bool) -> list[str]:
        done = t - self.dt / 2
        out = [
            v for v in self.vehicle_ids if (vehicles is None or v in vehicles) and self._sent.get(v, -math.inf) < done
        ]
        if host and t >= self.host_slack_s and (self._fused is None or self._fused < t - self.host_slack_s):
            out.append("host")
        return out

    def wait_for(
        self, t: float, timeout_s: float, vehicles: Callable[[], set[str] | None], host: Callable[[], bool]
    ) -> list[str]:
        """Block until everyone is done with the frame at ``t`` (:meth:`behind`) or ``timeout_s`` passed;
        who is still behind (empty: nobody)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                late = self._behind(t, vehicles(), host())
                left = deadline - time.monotonic()
                if not late or left <= 0:
                    return late
                self._cond.wait(min(left, 0.05))  # also re-reads who is alive
