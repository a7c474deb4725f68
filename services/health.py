"""Finding a fleet's services and their health: liveliness tokens + health queries.

Used by ``mapc health`` and by the launcher. A service is *alive* while its liveliness token
``mc/{fleet}/alive/{role}/{id}`` exists; its status comes from the queryable on
``mc/{fleet}/health/{role}/{id}``. Exit codes of ``mapc health``: 0 every service answers a healthy
state (``ok``, ``starting`` in a cold start's expected period, ``finished`` when its input ended with
the run) and every expected one is there, 1 any degraded/failed/unanswered or expected-but-missing,
2 nothing answers at all.

On a signed fleet (a ``verifier`` of the fleet's CA) a status is believed only if it is signed by
the service it is about (the id in its key): a reply that fails is refused and counted, and a
service with no believable reply is ``unverified`` (not healthy).

The table fits 100 columns (one line per service, its reason or refusals cut to fit); ``--json``
has every figure.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

from mapcontainer.security import Verifier, unwrap
from schemas import HealthStatus, decode
from schemas.codec import Rejection
from schemas.topics import topic
from services.runtime import HEALTHY_STATES

__all__ = ["ServiceView", "alive_services", "exit_code", "fleet_health", "format_table", "split_key"]


@dataclass
class ServiceView:
    """One service as ``mapc health`` reports it."""

    role: str
    id: str
    alive: bool
    state: str  # a HealthStatus state | missing | unresponsive (token, no reply) | unverified (no reply believed)
    status: HealthStatus | None = None
    refused: list[str] | None = None  # why replies on its key were not believed (a signed fleet)

    def to_json(self) -> dict:
        d = {"role": self.role, "id": self.id, "alive": self.alive, "state": self.state}
        if self.refused:
            d["refused"] = list(self.refused)
        if self.status is not None:
            st = self.status.model_dump(mode="json", exclude={"schema_version", "fleet", "sender", "role", "state"})
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


def believe_status(
    data: bytes, key: str, verifier: Verifier | None, now: float
) -> tuple[tuple[str, str], HealthStatus | str]:
    """((role, id), the status) of a health reply or put on ``key``, or ((role, id), why it is refused).

    With a ``verifier``, the status must be signed by the service of ``key`` and say it is that service;
    without one, a signed status is read unverified (an open fleet)."""
    role, sid = split_key(key)
    inner = unwrap(data, verifier, now, sid)
    if isinstance(inner, Rejection):
        return (role, sid), f"{inner.reason}: {inner.detail}"
    msg = decode(inner, HealthStatus)
    if isinstance(msg, Rejection):
        return (role, sid), f"{msg.reason}: {msg.detail}"
    if (msg.role, msg.sender) != (role, sid):
        return (role, sid), f"sender_mismatch: the status of {msg.role}/{msg.sender} on {role}/{sid}'s key"
    return (role, sid), msg


def query_status(
    session, fleet: str, timeout_s: float = 1.0, verifier: Verifier | None = None
) -> tuple[dict[tuple[str, str], HealthStatus], dict[tuple[str, str], list[str]]]:
    """Every health queryable's answer (consolidation off: one reply per service), and why replies were
    refused, by service: a believed reply wins over refused ones on the same key."""
    import zenoh

    out: dict[tuple[str, str], HealthStatus] = {}
    refused: dict[tuple[str, str], list[str]] = {}
    replies = session.get(
        topic("health").pattern(fleet=fleet), timeout=timeout_s, consolidation=zenoh.ConsolidationMode.NONE
    )
    for reply in replies:
        if reply.ok is None:
            continue
        try:
            who, msg = believe_status(reply.ok.payload.to_bytes(), str(reply.ok.key_expr), verifier, time.time())
        except ValueError:  # not a service key: not ours to judge
            continue
        if isinstance(msg, str):
            refused.setdefault(who, []).append(msg)
        else:
            out[who] = msg
    return out, refused


def fleet_health(
    session,
    fleet: str,
    expected: Iterable[tuple[str, str]] = (),
    timeout_s: float = 1.0,
    verifier: Verifier | None = None,
) -> list[ServiceView]:
    """Alive services, their status, and expected-but-missing ones; sorted by role then id. With a
    ``verifier`` (the fleet's CA) only statuses signed by their service count (:func:`believe_status`)."""
    alive = alive_services(session, fleet, timeout_s)
    status, refused = query_status(session, fleet, timeout_s, verifier)
    keys = alive | set(status) | set(refused) | set(expected)
    views = []
    for role, sid in keys:
        st = status.get((role, sid))
        if st is not None:
            state = st.state
        elif (role, sid) in refused:
            state = "unverified"
        elif (role, sid) in alive:
            state = "unresponsive"
        else:
            state = "missing"
        views.append(ServiceView(role, sid, (role, sid) in alive, state, st, refused.get((role, sid))))
    return sorted(views, key=lambda v: (v.role, v.id))


def exit_code(views: list[ServiceView]) -> int:
    if not any(v.alive or v.status is not None for v in views):
        return 2
    return 0 if all(v.state in HEALTHY_STATES for v in views) else 1


TABLE_WIDTH = 100


def _fmt(x: float | None, spec: str = ".1f") -> str:
    return "-" if x is None else format(x, spec)


def _note(v: ServiceView) -> str:
    """What a person reads first: the reason of a state that is not ok, else the refusals counted."""
    s = v.status
    if s is None and v.refused:
        return f"health refused: {v.refused[0]}"
    if s is None:
        return "no health token" if v.state == "missing" else "alive, does not answer"
    if v.state != "ok" and s.last_error:
        return s.last_error
    return ("rejected " + ", ".join(f"{k} {n}" for k, n in sorted(s.rejects.items()))) if s.rejects else ""


def format_table(views: list[ServiceView], fleet: str) -> str:
    """One line per service, at most :data:`TABLE_WIDTH` columns (the note is cut; ``--json`` has it all)."""
    head = f"{'service':<16} {'state':<9} {'up':>5} {'in/s':>6} {'out/s':>6} {'kB/s':>6} {'p99 ms':>7}  note"
    lines = [
        f"fleet {fleet}: {len(views)} services at {time.strftime('%H:%M:%S')} (mapc health --json: all figures)",
        head,
    ]
    for v in views:
        s = v.status
        name = f"{v.role}/{v.id}" if v.id != v.role else v.role
        if s is None:
            row = f"{name:<16.16} {v.state:<9} {'':>5} {'':>6} {'':>6} {'':>6} {'':>7}"
        else:
            kb = (s.bytes_in_per_s + s.bytes_out_per_s) / 1e3
            row = (
                f"{name:<16.16} {v.state:<9} {s.uptime_s:>4.0f}s {s.msgs_in_per_s:>6.1f} {s.msgs_out_per_s:>6.1f} "
                f"{kb:>6.1f} {_fmt(s.latency_ms_p99):>7}"
            )
        note = _note(v)
        room = TABLE_WIDTH - len(row) - 2
        if len(note) > room:
            note = note[: room - 3] + "..."
        lines.append(f"{row}  {note}".rstrip())
    return "\n".join(lines)
