"""When the host solves a frame: :class:`FrameGate`, the one solve policy of the live host and the pipeline.

Pure: every method takes the time as an argument (the host service passes its monotonic wall clock,
:func:`mapcontainer.pipeline.run_pipeline` the simulated arrival times), so both solve the same frames
at the same moments relative to their inputs.
"""

from __future__ import annotations

__all__ = ["MAX_WAIT_S", "FrameGate"]

MAX_WAIT_S = 0.1  # default wait for late senders: one camera frame at 10 Hz
_EPS_S = 1e-9  # a deadline computed as first + max_wait counts as reached at that time (float rounding)


class FrameGate:
    """Once per camera frame, when the frame is complete or has waited long enough.

    Frames are keyed by ``t_meas`` (to the millisecond). Frame ``t`` is *ready* at time ``now`` when

        expected <= senders(t)      or      now - first(t) >= max_wait_s

    with ``senders(t)`` the senders whose message for ``t`` has arrived, ``first(t)`` when the first
    of them arrived, and ``expected`` the known senders (without a list: those heard from within the
    last ``active_s``). :meth:`due` returns the newest ready frame newer than the last one released;
    older unreleased frames are dropped (their messages are in the container and count in the next
    solve), and messages for a frame at or before the last released one are ignored. Solving a frame
    before a vehicle's message for it has arrived would publish that vehicle's previous pose as its
    pose at ``t`` (about v * 0.1 s off), so the gate trades up to ``max_wait_s`` of latency for
    simultaneous states. ``complete`` and ``timed_out`` count the released frames of each kind.
    """

    def __init__(self, expected: set[str] | None, max_wait_s: float = MAX_WAIT_S, active_s: float = 2.0):
        if max_wait_s < 0:
            raise ValueError(f"max_wait_s must be >= 0, got {max_wait_s}")
        if active_s <= 0:
            raise ValueError(f"active_s must be > 0, got {active_s}")
        self.expected = set(expected) if expected else None
        self.max_wait_s = max_wait_s
        self.active_s = active_s
        self._frames: dict[int, tuple[float, float, set[str]]] = {}  # key -> (t_meas, first arrival, senders)
        self._heard: dict[str, float] = {}
        self._last_key: int | None = None
        self.timed_out = 0
        self.complete = 0

    @staticmethod
    def key(t_meas: float) -> int:
        """The frame key of ``t_meas``: milliseconds."""
        return int(round(t_meas * 1000))

    def arrived(self, sender: str, t_meas: float, now: float) -> None:
        """``sender``'s message for frame ``t_meas`` arrived (and was accepted) at ``now``."""
        self._heard[sender] = now
        key = self.key(t_meas)
        if self._last_key is not None and key <= self._last_key:
            return
        frame = self._frames.setdefault(key, (t_meas, now, set()))
        frame[2].add(sender)

    def _expected(self, now: float) -> set[str]:
        if self.expected is not None:
            return self.expected
        return {s for s, t in self._heard.items() if now - t <= self.active_s}

    def due(self, now: float) -> float | None:
        """The t_meas of the frame to solve now (newest ready), or None; releasing it drops older ones."""
        expected = self._expected(now)
        ready = None
        for key, (t, first, senders) in self._frames.items():
            full = expected <= senders
            if full or now - first >= self.max_wait_s - _EPS_S:
                if ready is None or key > ready[0]:
                    ready = (key, t, full)
        if ready is None:
            return None
        key, t, full = ready
        self.complete += full
        self.timed_out += not full
        self._last_key = key
        self._frames = {k: v for k, v in self._frames.items() if k > key}
        return t

    def next_deadline(self) -> float | None:
        """The earliest time a pending frame times out, None when none is pending."""
        return min((first + self.max_wait_s for _, first, _ in self._frames.values()), default=None)

    @property
    def pending(self) -> int:
        """Frames heard from but not yet released."""
        return len(self._frames)
