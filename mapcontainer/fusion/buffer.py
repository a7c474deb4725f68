"""Reorder buffer: hold messages until the host fuses them, in measurement-time order.

Messages arrive in any order (channel latency, jitter, loss). The buffer keeps them in a heap keyed
by ``(t_meas, sender, seq)``; :meth:`ReorderBuffer.pop_until` hands out everything measured at or
before a time, oldest first. What can no longer help is refused with a reason and counted:

* ``duplicate`` — a second message of a sender for the same ``t_meas`` (to 1 ms), within the window.
  Not the same ``(sender, seq)`` alone: a sender that restarts counts its ``seq`` from 0 again, and its
  new messages must not be refused for sharing numbers with old ones (a replay carries its instant);
* ``stale`` — ``t_meas`` older than the window: before ``t_recv - window_s`` or before
  ``horizon - window_s``, where the horizon is the latest time already fused;
* ``future`` — ``t_meas`` more than ``future_tolerance_s`` after ``t_recv`` (a broken clock would
  otherwise drag the window forward and expire everything);
* ``overflow`` — more than ``max_pending`` messages waiting.
"""

from __future__ import annotations

import heapq
from collections import Counter
from typing import Protocol

__all__ = ["ReorderBuffer", "Timestamped", "time_key"]


class Timestamped(Protocol):
    sender: str
    seq: int
    t_meas: float


def time_key(t: float) -> int:
    """Integer milliseconds: the key under which states and messages of one instant are merged."""
    return int(round(t * 1000.0))


class ReorderBuffer:
    """Messages by measurement time over a sliding window; duplicates and stale messages refused."""

    def __init__(self, window_s: float, future_tolerance_s: float = 1.0, max_pending: int = 100_000):
        if window_s <= 0:
            raise ValueError(f"window_s must be positive, got {window_s}")
        self.window_s = float(window_s)
        self.future_tolerance_s = float(future_tolerance_s)
        self.max_pending = int(max_pending)
        self.horizon = float("-inf")  # latest time handed out by pop_until
        self._heap: list[tuple[float, str, int, int, Timestamped]] = []
        self._tie = 0
        self._seen: dict[tuple[str, int], float] = {}  # (sender, time_key) -> t_meas
        self.rejected: Counter[str] = Counter()
        self.accepted = 0

    def __len__(self) -> int:
        return len(self._heap)

    def check(self, msg: Timestamped, t_recv: float) -> str | None:
        """The reason ``msg`` would be refused now, or None if it would be accepted."""
        t = float(msg.t_meas)
        if t > t_recv + self.future_tolerance_s:
            return "future"
        if t < t_recv - self.window_s or t < self.horizon - self.window_s:
            return "stale"
        if (msg.sender, time_key(t)) in self._seen:
            return "duplicate"
        if len(self._heap) >= self.max_pending:
            return "overflow"
        return None

    def push(self, msg: Timestamped, t_recv: float) -> str | None:
        """Store ``msg``; returns None when accepted, else the reason it was refused (also counted)."""
        reason = self.check(msg, t_recv)
        if reason is not None:
            self.rejected[reason] += 1
            return reason
        t = float(msg.t_meas)
        self._seen[(msg.sender, time_key(t))] = t
        heapq.heappush(self._heap, (t, msg.sender, msg.seq, self._tie, msg))
        self._tie += 1
        self.accepted += 1
        self._forget(max(t_recv, self.horizon) - self.window_s)
        return None

    def pop_until(self, t: float) -> list[Timestamped]:
        """All held messages with ``t_meas <= t``, oldest first (ties by sender, then seq)."""
        out = []
        while self._heap and self._heap[0][0] <= t:
            out.append(heapq.heappop(self._heap)[-1])
        self.horizon = max(self.horizon, float(t))
        self._forget(self.horizon - self.window_s)
        return out

    def _forget(self, t_min: float) -> None:
        """Drop duplicate-detection entries older than the window (they are refused as stale anyway)."""
        if len(self._seen) > 4 * max(len(self._heap), 256):
            self._seen = {k: v for k, v in self._seen.items() if v >= t_min}
