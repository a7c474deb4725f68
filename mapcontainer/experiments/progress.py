"""A tiny progress bar on stderr (no dependency): ``label [####......] k/N running r failed f retried t  eta``."""

from __future__ import annotations

import sys
import time
from typing import TextIO

__all__ = ["Progress"]


class Progress:
    """Count finished work items and redraw one status line.

    ``done`` items were finished before this bar started (a resumed run): they count towards k/N but
    not towards the rate, so the ETA is this run's own pace (remaining / finished here per second).
    ``running`` and ``retried`` are what the executor last said (:meth:`status`); ``failed`` counts :meth:`fail`.
    On a terminal the line is redrawn in place (carriage return) at most every ``min_interval_s``;
    into a file or pipe a full line is written at every 10 % step, so logs stay short. ``enabled=False``
    makes every call a no-op.
    """

    def __init__(
        self,
        total: int,
        label: str = "",
        stream: TextIO | None = None,
        width: int = 30,
        min_interval_s: float = 0.2,
        enabled: bool = True,
        done: int = 0,
    ):
        if total < 0 or not 0 <= done <= total:
            raise ValueError(f"need 0 <= done <= total, got done={done}, total={total}")
        self.total = int(total)
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.min_interval_s = min_interval_s
        self.enabled = enabled
        self.done = self._done0 = int(done)
        self.running = self.failed = self.retried = 0
        self._note = ""
        self._t0 = time.monotonic()
        self._t_drawn = -float("inf")
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._decile = -1
        self._state: tuple = ()
        if enabled:
            self._draw(force=True)

    def update(self, n: int = 1, note: str = "") -> None:
        """``n`` more items are finished; ``note`` is shown after the counters."""
        self.done = min(self.total, self.done + n)
        self._note = note
        if self.enabled:
            self._draw(force=self.done >= self.total)

    def status(self, running: int, retried: int = 0) -> None:
        """What the executor says now: tasks running, and task runs it started again (a worker was lost)."""
        changed = (running, retried) != (self.running, self.retried)
        self.running, self.retried = running, retried
        if self.enabled and changed and self._tty:
            self._draw()

    def fail(self, text: str) -> None:
        """A work item failed: ``text`` is written at once on its own lines, the bar goes on below."""
        self.failed += 1
        self.message(text)

    def message(self, text: str) -> None:
        """``text`` on its own line(s) above the bar."""
        if not self.enabled:
            return
        self.stream.write(("\r\x1b[K" if self._tty else "") + text.rstrip("\n") + "\n")
        self._t_drawn = -float("inf")
        self._draw(force=True)

    def close(self) -> None:
        """End the line (the bar stays visible)."""
        if self.enabled:
            self._draw(force=True)
            if self._tty:
                self.stream.write("\n")
            self.stream.flush()

    def line(self, note: str = "") -> str:
        """The status line as text."""
        frac = self.done / self.total if self.total else 1.0
        fill = int(round(frac * self.width))
        elapsed = time.monotonic() - self._t0
        here = self.done - self._done0
        eta = elapsed / here * (self.total - self.done) if here else float("nan")
        eta_s = f"eta {_hms(eta)}" if self.done < self.total else "done"
        counts = f" running {self.running} failed {self.failed} retried {self.retried}"
        text = (
            f"{self.label} [{'#' * fill}{'.' * (self.width - fill)}] {self.done}/{self.total}{counts} "
            f"{_hms(elapsed)} {eta_s}"
        )
        return f"{text}  {note}" if note else text

    def _draw(self, force: bool = False) -> None:
        note = self._note
        now = time.monotonic()
        if self._tty:
            if not force and now - self._t_drawn < self.min_interval_s:
                return
            self.stream.write("\r\x1b[K" + self.line(note))
        else:  # a log file: one line per 10 % step, and (forced) when the counts changed; never the same twice
            decile = int(10 * self.done / self.total) if self.total else 10
            state = (self.done, self.running, self.failed, self.retried)
            if decile == self._decile and not (force and state != self._state):
                return
            self._decile, self._state = decile, state
            self.stream.write(self.line(note) + "\n")
        self._t_drawn = now
        self.stream.flush()


def _hms(seconds: float) -> str:
    if seconds != seconds or seconds == float("inf"):  # NaN or inf
        return "--:--"
    s = int(round(seconds))
    h, rem = divmod(s, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m:02d}:{s:02d}"
