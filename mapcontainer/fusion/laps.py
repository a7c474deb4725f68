"""Where a host cycle's time goes: wall time between marks, by phase."""

from __future__ import annotations

import time

__all__ = ["Laps"]


class Laps:
    """Wall-clock milliseconds between successive marks, by phase; a phase marked again accumulates.

    ``laps.mark("associate")`` charges the time since the previous mark (or the start) to "associate".
    """

    def __init__(self):
        self.ms: dict[str, float] = {}
        self._t = time.perf_counter()

    def mark(self, phase: str) -> None:
        t = time.perf_counter()
        self.ms[phase] = self.ms.get(phase, 0.0) + (t - self._t) * 1e3
        self._t = t

    def add(self, phases: dict[str, float]) -> None:
        """Charge phases measured elsewhere (already counted by no mark of this one)."""
        for phase, ms in phases.items():
            self.ms[phase] = self.ms.get(phase, 0.0) + ms
