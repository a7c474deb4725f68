"""Admission of messages per sender: a flood of one sender costs only that sender.

Each sender has a token bucket: ``burst`` tokens, refilled at ``rate_hz`` per second; a message
takes one token, and a message that finds none is refused as ``flood``. The table of senders is
bounded: a sender beyond ``max_senders`` distinct ones is refused as ``too_many_senders`` (our
fleets have a fixed set of vehicle ids; a stream of new names is an attack on memory, not traffic).

Pure: time is an argument (seconds on any monotonic clock).
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["Admission"]


@dataclass
class _Bucket:
    tokens: float
    t: float
    refused: int = 0


@dataclass
class Admission:
    """Token bucket per sender, at most ``max_senders`` senders (module doc)."""

    rate_hz: float
    burst: float = 10.0
    max_senders: int = 256
    _buckets: dict[str, _Bucket] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.rate_hz > 0 or not self.burst >= 1 or self.max_senders < 1:
            raise ValueError(
                f"rate_hz must be > 0, burst >= 1 and max_senders >= 1, got {self.rate_hz}, {self.burst}, "
                f"{self.max_senders}"
            )

    def admit(self, sender: str, now: float) -> str | None:
        """None if ``sender``'s message at ``now`` is admitted, else the reason it is refused."""
        b = self._buckets.get(sender)
        if b is None:
            if len(self._buckets) >= self.max_senders:
                return "too_many_senders"
            b = self._buckets[sender] = _Bucket(self.burst, now)
        b.tokens = min(self.burst, b.tokens + max(now - b.t, 0.0) * self.rate_hz)
        b.t = max(b.t, now)
        if b.tokens < 1.0:
            b.refused += 1
            return "flood"
        b.tokens -= 1.0
        return None

    def refused(self) -> dict[str, int]:
        """Messages refused as ``flood`` so far, per sender that had any."""
        return {s: b.refused for s, b in self._buckets.items() if b.refused}

    def __len__(self) -> int:
        return len(self._buckets)
