"""Admission of messages per sender: a flood of one sender costs only that sender.

:class:`Admission`: each sender has a token bucket: ``burst`` tokens, refilled at ``rate_hz`` per second; a message
takes one token, and a message that finds none is refused as ``flood``. The table of senders is
bounded: a sender beyond ``max_senders`` distinct ones is refused as ``too_many_senders`` (our
fleets have a fixed set of vehicle ids; a stream of new names is an attack on memory, not traffic).

:class:`Gate`: what a service does with a message of one topic before any work on it, cheapest check
first. (The size bound per topic comes earlier still, before the payload's bytes are even copied out
of Zenoh: ``schemas.topics.Topic.max_bytes``.) A signed fleet's message is verified first
(:class:`mapcontainer.security.Verifier`: a bounded parse of the outer message, the known certificate
digest, validity, the time window and the replay table, then one ECDSA check; the inner message is not
decoded before that), and only then charged to its **verified** sender's budget: anyone can publish on a
vehicle's key, so traffic that fails verification is charged to a separate budget of the source it came
from (the key's sender chunk: Zenoh tells a subscriber nothing else about who published), never to the
vehicle's. While a source's unverified budget is spent, its messages that carry a certificate not
verified before are refused without checking the CA's signature (a stream of fresh fake certificates
would cost one ECDSA each); junk costs the parse that refuses it. Unsigned fleets are admitted by the
sender the key names, as before.

Pure: time is an argument (seconds on any monotonic clock; Unix seconds for the certificates).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from schemas.codec import Rejection

from .security import Verified, Verifier

__all__ = ["Admission", "Gate"]


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

    def peek(self, sender: str, now: float) -> bool:
        """Whether ``sender`` has a token at ``now`` (nothing is taken; an unknown sender has its burst)."""
        b = self._buckets.get(sender)
        if b is None:
            return len(self._buckets) < self.max_senders
        return min(self.burst, b.tokens + max(now - b.t, 0.0) * self.rate_hz) >= 1.0

    def refused(self) -> dict[str, int]:
        """Messages refused as ``flood`` so far, per sender that had any."""
        return {s: b.refused for s, b in self._buckets.items() if b.refused}

    def __len__(self) -> int:
        return len(self._buckets)


class Gate:
    """Admission of one topic's messages, verification before budget (module doc).

    ``admit(payload, source, now, t_unix)`` -> :class:`~mapcontainer.security.Verified` (its payload the
    inner message, ``sender`` the verified sender, or for an unsigned fleet the key's ``source``) or a
    :class:`~schemas.codec.Rejection` (a verifier reason, or ``flood`` / ``too_many_senders``). Not
    thread-safe: a service calls it under one lock (the verifier may be shared by several gates).
    """

    def __init__(
        self, verifier: Verifier | None, rate_hz: float, burst: float, max_senders: int = 256,
        unverified_rate_hz: float | None = None,
    ) -> None:
        self.verifier = verifier
        self.verified = Admission(rate_hz, burst, max_senders)
        u = rate_hz if unverified_rate_hz is None else unverified_rate_hz
        self.unverified = Admission(u, max(u, 1.0), max_senders)
        self.unverified_refused = 0  # messages that failed verification (whatever their reason)

    def admit(self, payload: bytes, source: str, now: float, t_unix: float) -> Verified | Rejection:
        if self.verifier is None:
            sender = source
            inner = payload
            t_gen = t_unix
        else:
            budget_left = self.unverified.peek(source, now)
            out = self.verifier.verify(payload, t_unix, expected_sender=source, new_certificates=budget_left)
            if isinstance(out, Rejection):
                self.unverified_refused += 1
                self.unverified.admit(source, now)  # charged to where it came from, never to a verified sender
                return out
            sender, inner, t_gen = out.sender, out.payload, out.t_gen
        reason = self.verified.admit(sender, now)
        if reason is not None:
            return Rejection(reason, f"{sender}: over its budget of {self.verified.rate_hz:g} messages/s")
        return Verified(inner, sender, t_gen)
