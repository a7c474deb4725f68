"""When the host solves a frame: :class:`FrameGate`, the one solve policy of the live host and the pipeline.

Pure: every method takes the time as an argument (the host service passes its monotonic wall clock,
:func:`mapcontainer.pipeline.run_pipeline` the simulated arrival times), so both solve the same frames
at the same moments relative to their inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["FRAME_TOLERANCE_S", "MAX_WAIT_S", "FrameGate"]

MAX_WAIT_S = 0.1  # default wait for late senders: one camera frame at 10 Hz
# Messages whose t_meas differ by at most this belong to one frame: the vehicles' clocks are a few ms
# apart (sensors.clock.offset_sigma_s, 3 ms), frames 100 ms (10 Hz).
FRAME_TOLERANCE_S = 0.02
_EPS_S = 1e-9  # a deadline computed as first + max_wait counts as reached at that time (float rounding)


class FrameGate:
    """Once per camera frame, when the frame is complete or has waited long enough.

    A *frame* gathers the messages whose ``t_meas`` lie within ``tolerance_s`` of the frame's first
    one: the vehicles stamp a frame with their own clocks, a few ms apart (``sensors.clock``). Its
    time ``t`` is the ``t_meas`` of the ``reference`` sender (the vehicle the host runs on: the
    host's own clock) once that has arrived, else of the first message. Frame ``t`` is *ready* at
    time ``now`` when

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

    def __init__(
        self,
        expected: set[str] | None,
        max_wait_s: float = MAX_WAIT_S,
        active_s: float = 2.0,
        tolerance_s: float = FRAME_TOLERANCE_S,
        reference: str | None = None,
    ):
        if max_wait_s < 0:
            raise ValueError(f"max_wait_s must be >= 0, got {max_wait_s}")
        if active_s <= 0:
            raise ValueError(f"active_s must be > 0, got {active_s}")
        if not 0 <= tolerance_s < 0.5:
            raise ValueError(f"tolerance_s must be in [0, 0.5) s, got {tolerance_s}")
        self.expected = set(expected) if expected else None
        self.max_wait_s = max_wait_s
        self.active_s = active_s
        self.tolerance_s = tolerance_s
        self.reference = reference
        self._frames: list[_Frame] = []  # pending, in order of their first message
        self._heard: dict[str, float] = {}
        self._last_t: float | None = None
        self.timed_out = 0
        self.complete = 0

    def arrived(self, sender: str, t_meas: float, now: float) -> None:
        """``sender``'s message stamped ``t_meas`` arrived (and was accepted) at ``now``."""
        self._heard[sender] = now
        tol = self.tolerance_s + _EPS_S
        if self._last_t is not None and t_meas <= self._last_t + tol:
            return
        frame = min(
            (f for f in self._frames if abs(f.t_first - t_meas) <= tol),
            key=lambda f: abs(f.t_first - t_meas),
            default=None,
        )
        if frame is None:
            frame = _Frame(t_meas, t_meas, now, set())
            self._frames.append(frame)
        if sender == self.reference:
            frame.t = t_meas
        frame.senders.add(sender)

    def _expected(self, now: float) -> set[str]:
        if self.expected is not None:
            return self.expected
        return {s for s, t in self._heard.items() if now - t <= self.active_s}

    def due(self, now: float) -> float | None:
        """The time of the frame to solve now (newest ready), or None; releasing it drops older ones."""
        expected = self._expected(now)
        ready = [f for f in self._frames if expected <= f.senders or now - f.first >= self.max_wait_s - _EPS_S]
        if not ready:
            return None
        f = max(ready, key=lambda f: f.t_first)
        full = expected <= f.senders
        self.complete += full
        self.timed_out += not full
        self._last_t = max(f.t, f.t_first)
        self._frames = [g for g in self._frames if g.t_first > f.t_first]
        return f.t

    def solved(self, t: float) -> None:
        """Frame ``t`` was solved outside :meth:`due` (re-fusion at recorded times): the frames up to it are
        dropped and later messages for them ignored, as after releasing it."""
        self._last_t = t if self._last_t is None else max(self._last_t, t)
        self._frames = [f for f in self._frames if f.t_first > t + self.tolerance_s + _EPS_S]

    def next_deadline(self) -> float | None:
        """The earliest time a pending frame times out, None when none is pending."""
        return min((f.first + self.max_wait_s for f in self._frames), default=None)

    @property
    def pending(self) -> int:
        """Frames heard from but not yet released."""
        return len(self._frames)


@dataclass
class _Frame:
    t: float  # the frame's time: the reference sender's t_meas, else the first message's
    t_first: float  # t_meas of its first message: what later messages are grouped by
    first: float  # when its first message arrived
    senders: set[str]
