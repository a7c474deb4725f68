"""What a service counts (rates, latencies, refusals, errors) and the HealthStatus built from it."""

from __future__ import annotations

import logging
import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from schemas import HealthStatus

log = logging.getLogger("mapc.runtime")

# From best to worst (a service reports the worst that applies). ``starting``: in the expected period of a
# cold start (a vehicle searching for its pose in its first seconds); ``finished``: its input ended because
# its source did (the world finished, or a replay did); both are healthy (``mapc health`` exits 0).
STATES = ("ok", "finished", "starting", "degraded", "failed")
HEALTHY_STATES = ("ok", "finished", "starting")
# Refusals that mean lost input (a full queue, a flooding sender, too many senders): any of them in the last
# DEGRADED_AFTER_REJECT_S seconds makes a service degraded. Bad input (invalid, stale, ...) does not: the
# service handled it as it should.
DEGRADING_REJECTS = ("queue_full", "flood", "too_many_senders")
DEGRADED_AFTER_REJECT_S = 10.0



# ------------------------------------------------------------------------------ counters


class RateCounter:
    """Events and bytes per second over a sliding window (thread-safe).

    rate = (events with t in (now - W, now]) / W, with W the window, shortened to the time since
    the counter started while it is younger than W (so the first seconds are not under-reported).
    Events are kept in 0.1 s buckets so memory stays bounded at any rate.
    """

    BUCKET_S = 0.1

    def __init__(self, window_s: float = 5.0, clock: Callable[[], float] = time.monotonic):
        if window_s <= 0:
            raise ValueError(f"window_s must be positive, got {window_s}")
        self.window_s = window_s
        self._clock = clock
        self._t0 = clock()
        self._buckets: deque[list[float]] = deque()  # [bucket start, count, bytes]
        self._lock = threading.Lock()
        self.total = 0
        self.total_bytes = 0
        self.last_t: float | None = None

    def add(self, n_bytes: int = 0, count: int = 1) -> None:
        t = self._clock()
        b = t - (t % self.BUCKET_S)
        with self._lock:
            if self._buckets and self._buckets[-1][0] == b:
                self._buckets[-1][1] += count
                self._buckets[-1][2] += n_bytes
            else:
                self._buckets.append([b, count, n_bytes])
            self.total += count
            self.total_bytes += n_bytes
            self.last_t = t
            self._trim(t)

    def _trim(self, now: float) -> None:
        while self._buckets and self._buckets[0][0] <= now - self.window_s - self.BUCKET_S:
            self._buckets.popleft()

    def rates(self) -> tuple[float, float]:
        """(events per second, bytes per second) over the window."""
        now = self._clock()
        with self._lock:
            self._trim(now)
            lo = now - self.window_s
            n = sum(c for b, c, _ in self._buckets if b + self.BUCKET_S > lo)
            nb = sum(x for b, _, x in self._buckets if b + self.BUCKET_S > lo)
        span = min(self.window_s, max(now - self._t0, self.BUCKET_S))
        return n / span, nb / span

    def idle_s(self) -> float | None:
        """Seconds since the last event; None if there never was one."""
        return None if self.last_t is None else self._clock() - self.last_t


class LatencySamples:
    """The most recent processing times (s); percentiles in milliseconds."""

    def __init__(self, maxlen: int = 1000):
        self._d: deque[float] = deque(maxlen=maxlen)
        self._lock = threading.Lock()

    def add(self, seconds: float) -> None:
        with self._lock:
            self._d.append(seconds)

    def percentiles_ms(self, qs: Iterable[float] = (50, 99)) -> list[float | None]:
        with self._lock:
            v = np.fromiter(self._d, float, len(self._d))
        if v.size == 0:
            return [None for _ in qs]
        return [float(x) for x in np.percentile(v * 1e3, list(qs))]


@dataclass
class ServiceMetrics:
    """Counters a service keeps for its health status."""

    window_s: float = 5.0
    msgs_in: RateCounter = field(init=False)
    msgs_out: RateCounter = field(init=False)
    latency: LatencySamples = field(default_factory=LatencySamples)
    rejects: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    last_error: str | None = None
    last_error_t: float | None = None
    errors: int = 0

    def __post_init__(self) -> None:
        self.msgs_in = RateCounter(self.window_s)
        self.msgs_out = RateCounter(self.window_s)
        self._lock = threading.Lock()
        self._logged: set[str] = set()
        self._last_reject: dict[str, tuple[float, str]] = {}  # reason -> (monotonic time, detail)

    def recent_rejects(self, reasons: Iterable[str], within_s: float) -> dict[str, tuple[int, str]]:
        """Of ``reasons``, those counted in the last ``within_s`` seconds: reason -> (total, last detail)."""
        now = time.monotonic()
        with self._lock:
            return {
                r: (self.rejects[r], self._last_reject[r][1])
                for r in reasons
                if r in self._last_reject and now - self._last_reject[r][0] <= within_s
            }

    def reject(self, reason: str, detail: str = "", logger: logging.Logger | None = None) -> None:
        """Count a rejected input by reason; log the first one of each reason."""
        with self._lock:
            self.rejects[reason] += 1
            self._last_reject[reason] = (time.monotonic(), detail[:200])
            first = reason not in self._logged
            self._logged.add(reason)
        if first:
            (logger or log).warning("rejected input (%s): %s (further ones are only counted)", reason, detail)

    def error(self, message: str) -> None:
        with self._lock:
            self.errors += 1
            self.last_error = message[:500]
            self.last_error_t = time.monotonic()


def flatten_figures(stats: Mapping[str, Any] | None, prefix: str = "") -> dict[str, float]:
    """A core's ``stats()`` as ``{name: float}`` for HealthStatus.figures.

    Nested mappings become dotted names, bools 0/1, a string value ``v`` of ``k`` becomes
    ``k.v = 1`` (e.g. ``mode.map_matching``); None, NaN and other types are left out.
    """
    out: dict[str, float] = {}
    for k, v in (stats or {}).items():
        name = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flatten_figures(v, name + "."))
        elif isinstance(v, bool | np.bool_):
            out[name] = float(v)
        elif isinstance(v, int | float | np.integer | np.floating):
            if np.isfinite(v):
                out[name] = float(v)
        elif isinstance(v, str):
            out[f"{name}.{v}"] = 1.0
    return out


def build_health(
    *,
    fleet: str,
    role: str,
    sid: str,
    seq: int,
    uptime_s: float,
    metrics: ServiceMetrics,
    state: str = "ok",
    note: str | None = None,
    figures: Mapping[str, Any] | None = None,
    now_wall_s: float | None = None,
) -> HealthStatus:
    """One HealthStatus from a service's counters (pure: time is an argument)."""
    if state not in STATES:
        raise ValueError(f"state must be one of {STATES}, got {state!r}")
    t = time.time() if now_wall_s is None else now_wall_s
    mi, bi = metrics.msgs_in.rates()
    mo, bo = metrics.msgs_out.rates()
    p50, p99 = metrics.latency.percentiles_ms((50, 99))
    return HealthStatus(
        fleet=fleet,
        sender=sid,
        seq=seq,
        t_meas=t,
        t_sent=t,
        role=role,
        state=state,
        uptime_s=max(uptime_s, 0.0),
        msgs_in_per_s=mi,
        msgs_out_per_s=mo,
        bytes_in_per_s=bi,
        bytes_out_per_s=bo,
        latency_ms_p50=p50,
        latency_ms_p99=p99,
        rejects=dict(metrics.rejects),
        last_error=note if note is not None else metrics.last_error,
        figures=flatten_figures(figures),
    )


