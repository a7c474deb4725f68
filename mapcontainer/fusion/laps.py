"""Where a host cycle's time goes: time between marks, by phase (wall clock, or this process's CPU time)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["Laps", "cpu_clock"]


class Laps:
    """Milliseconds between successive marks, by phase; a phase marked again accumulates.

    ``laps.mark("associate")`` charges the time since the previous mark (or the start) to "associate".
    The clock is wall time (``time.perf_counter``) unless made inside :func:`cpu_clock`.
    """

    clock = staticmethod(time.perf_counter)  # of every Laps made from now on (see cpu_clock)

    def __init__(self):
        self.ms: dict[str, float] = {}
        self._clock = Laps.clock
        self._t = self._clock()

    def mark(self, phase: str) -> None:
        t = self._clock()
        self.ms[phase] = self.ms.get(phase, 0.0) + (t - self._t) * 1e3
        self._t = t

    def add(self, phases: dict[str, float]) -> None:
        """Charge phases measured elsewhere (already counted by no mark of this one)."""
        for phase, ms in phases.items():
            self.ms[phase] = self.ms.get(phase, 0.0) + ms


@contextmanager
def cpu_clock() -> Iterator[None]:
    """Every :class:`Laps` made inside charges this process's CPU time (``time.process_time``) instead of
    wall time: phase tables that the waits of a loaded machine do not inflate (its contention for caches
    and memory still slows the work itself). For benchmarks; the host reports wall time."""
    before = Laps.clock
    Laps.clock = staticmethod(time.process_time)
    try:
        yield
    finally:
        Laps.clock = before
