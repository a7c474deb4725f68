"""Finding a fleet's services and their health: liveliness tokens + health queries.

Used by ``mapc health`` and by the launcher. A service is *alive* while its liveliness token
``mc/{fleet}/alive/{role}/{id}`` exists; its status comes from the queryable on
``mc/{fleet}/health/{role}/{id}``. Exit codes of ``mapc health``: 0 every service answers ``ok``
(and every expected one is there), 1 any degraded/failed/unanswered or expected-but-missing,
2 nothing answers at all.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

from schemas import HealthStatus, decode
from schemas.topics import topic

__all__ = ["ServiceView", "alive_services", "exit_code", "fleet_health", "format_table", "split_key"]


@dataclass
class ServiceView:
    """One service as ``mapc health`` reports it."""

    role: str
    id: str
    alive: bool
    state: str  # ok | degraded | failed | missing (expected, no token) | unresponsive (token, no reply)
    status: HealthStatus | None = None

    def to_json(self) -> dict:
        d = {"role": self.role, "id": self.id, "alive": self.alive, "state": self.state}
        if self.status is not None:
            st = self.status.model_dump(
                mode="json", exclude={"schema_version", "fleet", "sender", "role", "state"}
            )
            d.update(st)
        return d


def split_key(key: str) -> tuple[str, str]:
    """(role, id) from ``mc/{fleet}/alive/{role}/{id}`` or ``mc/{fleet}/health/{role}/{id}``."""
    parts = str(key).split("/")
    if len(parts) < 5:
        raise ValueError(f"not a service key: {key!r}")
    return parts[-2], parts[-1]


def alive_services(session, fleet: str, timeout_s: float = 1.0) -> set[tuple[str, str]]:
    """(role, id) of every liveliness token of ``fleet``."""
    out = set()
    for reply in session.liveliness().get(topic("alive").pattern(fleet=fleet), timeout=timeout_s):
        if reply.ok is not None:
            out.add(split_key(str(reply.ok.key_expr)))
    return out


def query_status(session, fleet: str, timeout_s: float = 1.0) -> dict[tuple[str, str], HealthStatus]:
    """Every health queryable's answer (consolidation off: one reply per service)."""
    import zenoh

    out: dict[tuple[str, str], HealthStatus] = {}
    replies = session.get(
        topic("health").pattern(fleet=fleet), timeout=timeout_s, consolidation=zenoh.ConsolidationMode.NONE
    )
    for reply in replies:
        if reply.ok is None:
            continue
        msg = decode(reply.ok.payload.to_bytes(), HealthStatus)
        if msg:
            out[split_key(str(reply.ok.key_expr))] = msg
    return out


def fleet_health(
    session, fleet: str, expected: Iterable[tuple[str, str]] = (), timeout_s: float = 1.0
) -> list[ServiceView]:
    """Alive services, their status, and expected-but-missing ones; sorted by role then id."""
    alive = alive_services(session, fleet, timeout_s)
    status = query_status(session, fleet, timeout_s)
    keys = alive | set(status) | set(expected)
    views = []
    for role, sid in keys:
        st = status.get((role, sid))
        if st is not None:
            state = st.state
        elif (role, sid) in alive:
            state = "unresponsive"
        else:
            state = "missing"
        views.append(ServiceView(role, sid, (role, sid) in alive, state, st))
    return sorted(views, key=lambda v: (v.role, v.id))


def exit_code(views: list[ServiceView]) -> int:
    if not any(v.alive or v.status is not None for v in views):
        return 2
    return 0 if all(v.state == "ok" for v in views) else 1


def _fmt(x: float | None, spec: str = ".1f") -> str:
    return "-" if x is None else format(x, spec)


def format_table(views: list[ServiceView], fleet: str) -> str:
    head = (
        f"{'role':<10} {'id':<10} {'state':<12} {'uptime':>7} {'in/s':>6} {'out/s':>6} {'kB/s in':>8} "
        f"{'kB/s out':>8} {'p50 ms':>7} {'p99 ms':>7}  rejects / last error / figures"
    )
    lines = [f"fleet {fleet}: {len(views)} services at {time.strftime('%H:%M:%S')}", head]
    for v in views:
        s = v.status
        if s is None:
            lines.append(f"{v.role:<10} {v.id:<10} {v.state:<12}")
            continue
        rej = ",".join(f"{k}={n}" for k, n in sorted(s.rejects.items()))
        figs = " ".join(f"{k}={val:.3g}" for k, val in list(sorted(s.figures.items()))[:8])
        extra = "  ".join(x for x in (rej, s.last_error or "", figs) if x)
        lines.append(
            f"{v.role:<10} {v.id:<10} {v.state:<12} {s.uptime_s:>6.0f}s {s.msgs_in_per_s:>6.1f} "
            f"{s.msgs_out_per_s:>6.1f} {s.bytes_in_per_s / 1e3:>8.1f} {s.bytes_out_per_s / 1e3:>8.1f} "
            f"{_fmt(s.latency_ms_p50):>7} {_fmt(s.latency_ms_p99):>7}  {extra}"
        )
    return "\n".join(lines)
