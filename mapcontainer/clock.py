"""The world's clock as another part of the system sees it: scenario time <-> wall time.

Pure (time is an argument where it matters): the services keep one per process
(``services.runtime.SimClock``), and replay and the ROS 2 export read a recording's times with the same
rules.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from typing import Any

from schemas.models import MAX_TIME_SCALE, MIN_TIME_SCALE

__all__ = ["SimClock"]


class SimClock:
    """The world's clock as seen from another service: scenario time <-> wall time.

    ``t_scenario = (wall_ns - epoch_wall_ns) * 1e-9 * time_scale``. The world puts ``epoch_wall_ns``,
    ``time_scale`` and ``t_next`` into the envelope of every message it sends (:class:`schemas.Envelope`'s
    optional clock fields); the vehicles and the host copy them into theirs. A service takes the clock from
    a message it decoded (from a verified one where messages are signed), never from a Zenoh attachment:
    anyone can write those, and copies of genuine priors whose attachment said ``epoch_wall_ns = 1`` made a
    host refuse every genuine prior as stale. (Attachments still carry the clock as instrumentation, for
    recordings.) A clock outside the world's own limits is ignored.

    The adaptive clock (``--time-scale auto``) pauses while a service is behind: the world then moves its
    epoch forward, and its messages carry ``t_next``, the scenario time of its next frame, which the clock
    does not pass before that frame is out. So ``now`` is capped at ``t_next``: during a pause a message
    received is not stamped seconds ahead of the frames (the host refused such messages as stale), and the
    epoch kept is the latest (a message relayed late carries an older one, which is ignored). A message
    whose time scale differs from the known one changes the clock (a restarted world, or a liar) and is
    counted, with its sender, for the host's health to name; unless its time is older than the newest seen
    on the clock in force: it was sent before the change and relayed late, and is ignored.
    """

    TIME_SCALE_MIN, TIME_SCALE_MAX = MIN_TIME_SCALE, MAX_TIME_SCALE
    PLAUSIBLE_S = 0.5  # scenario seconds: how far a new epoch may put the present before the newest time seen

    def __init__(self) -> None:
        self.epoch_wall_ns: int | None = None
        self.time_scale: float | None = None
        self.t_next: float | None = None
        self.t_seen: float | None = None  # the newest scenario time of a message that was not from the future
        self.changes = 0  # how often a message changed the clock's scale, or moved its epoch implausibly
        self.changed_by: str | None = None  # the sender of the message that did it last

    def update(self, msg: Mapping[str, Any] | Any, wall_ns: int | None = None) -> bool:
        """Take the clock of ``msg`` (a decoded message, or a mapping such as :func:`schemas.codec.peek`'s),
        received at ``wall_ns`` (now); False when it carries none (or an impossible one).

        A newer epoch of the same scale is taken only where it is plausible, a pause of the world's: the
        present on it is not before the newest time already seen (within ``PLAUSIBLE_S``). An epoch an hour
        ahead in one signed message would otherwise have put the present an hour back for good (older
        epochs are ignored); it is counted as a change, with its sender, and not taken."""
        get = msg.get if isinstance(msg, Mapping) else lambda k: getattr(msg, k, None)
        e, s = get("epoch_wall_ns"), get("time_scale")
        if not (
            type(e) is int  # not bool
            and 0 < e < 2**63
            and type(s) in (int, float)
            and self.TIME_SCALE_MIN <= s <= self.TIME_SCALE_MAX  # not inf, nan
        ):
            return False
        wall_ns = time.time_ns() if wall_ns is None else wall_ns
        t_meas = get("t_meas")
        if self.time_scale is not None and float(s) != self.time_scale:  # another clock altogether
            if self._from_the_past(t_meas):  # sent on the clock before this one, relayed late
                return True
            self._changed(get("sender"))
            self.epoch_wall_ns, self.time_scale, self.t_next, self.t_seen = e, float(s), None, None
        elif self.epoch_wall_ns is None:
            self.epoch_wall_ns, self.time_scale = e, float(s)
        elif e > self.epoch_wall_ns:  # moved on by a pause, if the present it gives has not passed already
            present = (wall_ns - e) * 1e-9 * float(s)
            if self.t_seen is not None and present < self.t_seen - self.PLAUSIBLE_S:
                self._changed(get("sender"))
            else:
                self.epoch_wall_ns = e
        t_next = get("t_next")
        if type(t_next) in (int, float) and math.isfinite(t_next):
            self.t_next = float(t_next) if self.t_next is None else max(self.t_next, float(t_next))
        now = self.now(wall_ns)
        if type(t_meas) in (int, float) and now is not None and t_meas <= now + self.PLAUSIBLE_S:  # not the future
            self.t_seen = float(t_meas) if self.t_seen is None else max(self.t_seen, float(t_meas))
        return True

    def _from_the_past(self, t_meas: Any) -> bool:
        """Whether a message's time is before the newest time seen: a message of another time scale that is
        was sent before the clock in force began and only arrived now (the first message of a genuine change
        that is older is ignored too; the change comes with the next one)."""
        return type(t_meas) in (int, float) and self.t_seen is not None and t_meas < self.t_seen

    def _changed(self, sender: Any) -> None:
        self.changes += 1
        self.changed_by = sender if isinstance(sender, str) else None

    @property
    def known(self) -> bool:
        return self.epoch_wall_ns is not None

    def now(self, wall_ns: int | None = None) -> float | None:
        """Scenario time now (or at ``wall_ns``); None until a clock was seen."""
        if self.epoch_wall_ns is None or self.time_scale is None:
            return None
        wall_ns = time.time_ns() if wall_ns is None else wall_ns
        t = (wall_ns - self.epoch_wall_ns) * 1e-9 * self.time_scale
        return t if self.t_next is None else min(t, self.t_next)

    def wall_ns(self, t: float) -> int | None:
        """Wall time (ns) at which scenario time ``t`` happened."""
        if self.epoch_wall_ns is None or self.time_scale is None:
            return None
        return self.epoch_wall_ns + int(round(t / self.time_scale * 1e9))

    def fields(self) -> dict[str, Any]:
        """The clock fields, for a message's envelope (or an attachment); None while unknown."""
        return {"epoch_wall_ns": self.epoch_wall_ns, "time_scale": self.time_scale, "t_next": self.t_next}

    def stamp(self, msg):
        """``msg`` (a model) with this clock in its envelope (unchanged while the clock is unknown)."""
        return msg if self.epoch_wall_ns is None else msg.model_copy(update=self.fields())
