"""A tiny progress bar on stderr (no dependency): ``label [#####.....] k/N  elapsed  eta``."""

from __future__ import annotations

import sys
import time
from typing import TextIO

__all__ = ["Progress"]


class Progress:
    """Count finished work items and redraw one status line.

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
    ):
        if total < 0:
            raise ValueError(f"total must be >= 0, got {total}")
        self.total = int(total)
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.min_interval_s = min_interval_s
        self.enabled = enabled
        self.done = 0
        self._t0 = time.monotonic()
        self._t_drawn = -float("inf")
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._decile = -1
        if enabled:
            self._draw(force=True)

    def update(self, n: int = 1, note: str = "") -> None:
        """``n`` more items are finished; ``note`` is shown after the counters."""
        self.done = min(self.total, self.done + n)
        if self.enabled:
            self._draw(force=self.done >= self.total, note=note)

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
        eta = elapsed / self.done * (self.total - self.done) if self.done else float("nan")
        eta_s = f"eta {_hms(eta)}" if self.done < self.total else "done"
        text = (
            f"{self.label} [{'#' * fill}{'.' * (self.width - fill)}] {self.done}/{self.total} {_hms(elapsed)} {eta_s}"
        )
        return f"{text}  {note}" if note else text

    def _draw(self, force: bool = False, note: str = "") -> None:
        now = time.monotonic()
        if self._tty:
            if not force and now - self._t_drawn < self.min_interval_s:
                return
            self.stream.write("\r\x1b[K" + self.line(note))
        else:  # a log file: one line per 10 % step, never the same step twice
            decile = int(10 * self.done / self.total) if self.total else 10
            if decile == self._decile:
                return
            self._decile = decile
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
