"""What every service process shares: the Zenoh session, health, counters and a clean shutdown.

A role's ``main(settings)`` does::

    with Service("vehicle", settings) as svc:          # session, health queryable, signals
        pub = svc.publisher(topic("prior_tx").key(fleet=svc.fleet, src=svc.id))
        svc.subscribe_queued(topic("sensors").key(...), on_frame)  # counted, errors recorded
        svc.wait()  # declares the liveliness token; returns on SIGINT/SIGTERM/stop()/parent death
    # the session is closed here: a process with callback subscribers that exits without
    # closing its session hangs (ZENOH.md)

Health: every service holds the liveliness token ``mc/{fleet}/alive/{role}/{id}`` and puts a
:class:`schemas.HealthStatus` on ``mc/{fleet}/health/{role}/{id}`` once a second; a queryable on
the same key answers with the current status. HealthStatus's envelope times (``t_meas``,
``t_sent``) are Unix wall-clock seconds for this message (a service may not know scenario time).

Wall-clock instrumentation travels in the Zenoh *attachment* (a small msgpack map, see
:func:`make_attachment`), not in the payload, so that payload byte counts are exactly what the V2X
link carries. Fields: ``t_wall_ns`` (when this hop published), ``epoch_wall_ns`` and
``time_scale`` (the world's clock: scenario time ``t`` happened at wall time
``epoch_wall_ns + t / time_scale * 1e9``). Each service passes the world's clock on, so that any
service can map scenario time to wall time (:class:`SimClock`) — the evaluator's end-to-end
latency is ``t_wall_ns(fused published) - wall(t_meas)``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import queue
import re
import signal
import sys
import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import msgpack
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mapcontainer import jsonout
from mapcontainer.admission import Admission
from mapcontainer.config import ConfigError
from schemas import HealthStatus, decode, encode
from schemas.topics import topic

__all__ = [
    "EXIT_THREAD_DIED",
    "LatencySamples",
    "Received",
    "RateCounter",
    "Service",
    "ServiceMetrics",
    "ServiceSettings",
    "SimClock",
    "ZenohSettings",
    "add_service_args",
    "build_health",
    "build_zenoh_config",
    "flatten_figures",
    "sender_admission",
    "listening_locators",
    "make_attachment",
    "open_session",
    "read_attachment",
    "service_main",
    "service_settings_from_args",
    "setup_logging",
    "zenoh_config",
    "zenoh_error_text",
]

log = logging.getLogger("mapc.runtime")

STATES = ("ok", "degraded", "failed")
# Refusals that mean lost input (a full queue, a flooding sender, too many senders): any of them in the last
# DEGRADED_AFTER_REJECT_S seconds makes a service degraded. Bad input (invalid, stale, ...) does not: the
# service handled it as it should.
DEGRADING_REJECTS = ("queue_full", "flood", "too_many_senders")
DEGRADED_AFTER_REJECT_S = 10.0
EXIT_THREAD_DIED = 70  # EX_SOFTWARE: a service whose worker thread died exits with it


# ------------------------------------------------------------------------------ configuration


class ZenohSettings(BaseModel):
    """How a process joins the Zenoh network (the verified recipes are in ZENOH.md).

    peer (default): listen on a loopback port (``tcp/127.0.0.1:0`` picks a free one), connect to a
    rendezvous endpoint with ``exit_on_failure`` so a missing rendezvous fails fast; gossip forms
    the mesh. client: connect to a router (or a peer) only. router: listen (default
    ``tcp/0.0.0.0:7447``) and connect to other hosts' routers. Multicast scouting stays off
    unless asked for.

    ``config_file`` (JSON5, e.g. deploy/zenoh/*.json5): the file is the configuration, and only
    what is given explicitly here is laid over it (``mode`` when not None, ``listen`` when not
    None, ``connect`` when not empty, ``adminspace`` when true) — e.g. the launcher's rendezvous
    endpoint over a TLS client file.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    mode: Literal["peer", "client", "router"] | None = Field(None, description="None: the file's, else peer")
    listen: list[str] | None = Field(
        None, description="endpoints; None: tcp/127.0.0.1:0 (peer), tcp/0.0.0.0:7447 (router)"
    )
    connect: list[str] = Field(default_factory=list)
    lease_ms: int = Field(1500, ge=500, le=60_000, description="transport lease: a frozen peer is dropped after it")
    connect_timeout_ms: int = Field(3000, ge=0)
    exit_on_failure: bool = True
    multicast_scouting: bool = False
    adminspace: bool = False
    config_file: str | None = None


class ServiceSettings(BaseModel):
    """What every service takes: fleet namespace, its id, Zenoh and health settings."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    fleet: str = Field("mc", pattern=r"^[A-Za-z0-9_\-]{1,64}$")
    id: str = Field(pattern=r"^[A-Za-z0-9_\-]{1,64}$")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    health_period_s: float = Field(1.0, gt=0)
    rate_window_s: float = Field(5.0, gt=0, description="sliding window of the per-second rates")
    stale_input_s: float | None = Field(
        3.0, gt=0, description="degraded when input was flowing and then stopped for this long; None: never"
    )
    log_level: str = "INFO"
    watch_parent: bool = Field(False, description="stop when the parent process (the launcher) dies")


def build_zenoh_config(s: ZenohSettings) -> dict[str, Any]:
    """The JSON5 configuration tree (as a dict) for ``s``; pure, unit-tested."""
    mode = s.mode or "peer"
    conf: dict[str, Any] = {
        "mode": mode,
        "scouting": {
            "multicast": {"enabled": s.multicast_scouting},
            "delay": 0,  # routers and peers: no scouting wait before the session is usable
        },
        "transport": {"link": {"tx": {"lease": s.lease_ms}}},
    }
    if mode == "peer":
        conf["scouting"]["gossip"] = {
            "enabled": True,
            "autoconnect_strategy": {"peer": {"to_router": "always", "to_peer": "greater-zid"}},
        }
    listen = s.listen
    if listen is None:
        listen = {"peer": ["tcp/127.0.0.1:0"], "router": ["tcp/0.0.0.0:7447"], "client": []}[mode]
    if mode != "client" and listen:
        conf["listen"] = {"endpoints": list(listen)}
    if s.connect:
        conf["connect"] = {
            "endpoints": list(s.connect),
            "timeout_ms": s.connect_timeout_ms,
            "exit_on_failure": s.exit_on_failure,
        }
    if s.adminspace:
        conf["adminspace"] = {"enabled": True}
    return conf


def zenoh_error_text(exc: BaseException) -> str:
    """A Zenoh error's message without the Rust source location it ends with."""
    return re.sub(r"\s+at /\S+\.rs:\d+\.?\s*$", "", str(exc)).strip()


def zenoh_config(s: ZenohSettings):
    """The ``zenoh.Config`` for ``s``; ConfigError when Zenoh refuses it (a malformed endpoint, a
    configuration file that is missing or not JSON5), before any session is opened."""
    import zenoh

    try:
        return _zenoh_config(s)
    except zenoh.ZError as exc:
        source = f"the Zenoh configuration file {s.config_file}" if s.config_file else "the Zenoh endpoints"
        raise ConfigError(f"{source}: {zenoh_error_text(exc)}") from None


def _zenoh_config(s: ZenohSettings):
    import zenoh

    if s.config_file:
        conf = zenoh.Config.from_file(s.config_file)
        if s.mode is not None:
            conf.insert_json5("mode", json.dumps(s.mode))
        if s.listen is not None:
            conf.insert_json5("listen/endpoints", json.dumps(list(s.listen)))
        if s.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(s.connect)))
        if s.adminspace:
            conf.insert_json5("adminspace/enabled", "true")
        return conf
    return zenoh.Config.from_json5(json.dumps(build_zenoh_config(s)))


def open_session(s: ZenohSettings):
    """Open a Zenoh session for ``s``. Close it (``with``/``finally``) before the process exits."""
    import zenoh

    return zenoh.open(zenoh_config(s))


def listening_locators(session, timeout_s: float = 2.0) -> list[str]:
    """The endpoints this session really listens on (port 0 resolved), from the admin space.

    Needs ``adminspace`` enabled in the session's configuration.
    """
    zid = str(session.zid())
    for reply in session.get(f"@/{zid}/*", timeout=timeout_s):
        if reply.ok is None:
            continue
        key = str(reply.ok.key_expr)
        if key.endswith(("/peer", "/router", "/client")):
            return list(json.loads(reply.ok.payload.to_bytes()).get("locators", []))
    return []


def add_service_args(p: argparse.ArgumentParser, role: str, default_id: str | None = None) -> None:
    """The flags every service shares (fleet, id, Zenoh endpoints, health, logging)."""
    g = p.add_argument_group("service")
    g.add_argument("--fleet", default=os.environ.get("MAPC_FLEET", "mc"), help="fleet name (key namespace)")
    g.add_argument("--id", default=default_id, required=default_id is None, help=f"this {role}'s id")
    g.add_argument("--log-level", default=os.environ.get("MAPC_LOG_LEVEL", "INFO"))
    g.add_argument("--health-period", type=float, default=1.0, help="seconds between status puts")
    z = p.add_argument_group("zenoh")
    z.add_argument(
        "--zenoh-mode",
        dest="zenoh_mode",
        choices=["peer", "client", "router"],
        default=None,
        help="default: peer, or the mode of --zenoh-config",
    )
    z.add_argument(
        "--connect",
        action="append",
        default=None,
        help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable; env MAPC_ZENOH_CONNECT)",
    )
    z.add_argument("--listen", action="append", default=None, help="endpoint to listen on (repeatable)")
    z.add_argument("--lease-ms", type=int, default=1500)
    z.add_argument("--zenoh-config", default=None, help="a Zenoh JSON5 configuration file to start from")


def service_main(parse_args: Callable[[], Any], main: Callable[[Any], int]) -> int:
    """A service's ``__main__``: ``main(parse_args())``, where settings that do not validate (a bad flag
    value, config file, scenario or network name) are one line naming the problem and exit 2, not a
    traceback."""
    from pydantic import ValidationError

    from mapcontainer.config import config_error

    prog = f"python -m {main.__module__.rsplit('.', 1)[0]}"
    try:
        try:
            settings = parse_args()
        except ValidationError as exc:
            raise config_error(exc, "the command line") from None
        return main(settings)  # which loads its scenario, network profile, ...: ConfigError too
    except ConfigError as exc:
        print(f"{prog}: configuration error: {exc}", file=sys.stderr)
        return 2


def service_settings_from_args(args: argparse.Namespace) -> ServiceSettings:
    connect = args.connect
    if connect is None and os.environ.get("MAPC_ZENOH_CONNECT"):
        connect = [e for e in os.environ["MAPC_ZENOH_CONNECT"].split(",") if e]
    return ServiceSettings(
        fleet=args.fleet,
        id=args.id,
        zenoh=ZenohSettings(
            mode=args.zenoh_mode,
            connect=connect or [],
            listen=args.listen,
            lease_ms=args.lease_ms,
            config_file=args.zenoh_config,
        ),
        health_period_s=args.health_period,
        log_level=args.log_level,
        watch_parent=os.environ.get("MAPC_WATCH_PARENT") == "1",
    )


def setup_logging(role: str, sid: str, level: str = "INFO") -> logging.Logger:
    """Log to stderr with the service's name bound into every line."""
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format=f"%(asctime)s %(levelname)-7s {role}/{sid} %(name)s: %(message)s",
        force=True,
    )
    return logging.getLogger(f"mapc.{role}")


# ------------------------------------------------------------------------------ attachments


def make_attachment(**fields: int | float | str | None) -> bytes:
    """A msgpack map of instrumentation fields (None values left out)."""
    return msgpack.packb({k: v for k, v in fields.items() if v is not None}, use_bin_type=True)


def read_attachment(sample_or_bytes) -> dict[str, Any]:
    """The attachment map of a sample (or raw attachment bytes); {} if absent or unreadable."""
    att = getattr(sample_or_bytes, "attachment", sample_or_bytes)
    if att is None:
        return {}
    try:
        raw = att.to_bytes() if hasattr(att, "to_bytes") else bytes(att)
        obj = msgpack.unpackb(raw, raw=False)
    except Exception:  # instrumentation only: a bad attachment is ignored, never fatal
        return {}
    if not isinstance(obj, dict):
        return {}
    return {k: v for k, v in obj.items() if isinstance(k, str)}  # names only: fields are passed on as keywords


class SimClock:
    """The world's clock as seen from another service: scenario time <-> wall time.

    The world puts ``epoch_wall_ns`` and ``time_scale`` into every attachment it sends; services
    pass them on. ``t_scenario = (wall_ns - epoch_wall_ns) * 1e-9 * time_scale``. A clock outside
    the world's own limits (``time_scale`` in [TIME_SCALE_MIN, TIME_SCALE_MAX], an epoch after 1970
    that fits int64) is ignored: attachments are unauthenticated, and a time scale of 1e-300 made
    every conversion overflow.
    """

    TIME_SCALE_MIN, TIME_SCALE_MAX = 1e-3, 100.0

    def __init__(self) -> None:
        self.epoch_wall_ns: int | None = None
        self.time_scale: float | None = None

    def update(self, att: Mapping[str, Any]) -> bool:
        e, s = att.get("epoch_wall_ns"), att.get("time_scale")
        if (
            type(e) is int  # not bool
            and 0 < e < 2**63
            and type(s) in (int, float)
            and self.TIME_SCALE_MIN <= s <= self.TIME_SCALE_MAX  # not inf, nan
        ):
            self.epoch_wall_ns, self.time_scale = e, float(s)
            return True
        return False

    @property
    def known(self) -> bool:
        return self.epoch_wall_ns is not None

    def now(self, wall_ns: int | None = None) -> float | None:
        """Scenario time now (or at ``wall_ns``); None until a clock was seen."""
        if self.epoch_wall_ns is None or self.time_scale is None:
            return None
        wall_ns = time.time_ns() if wall_ns is None else wall_ns
        return (wall_ns - self.epoch_wall_ns) * 1e-9 * self.time_scale

    def wall_ns(self, t: float) -> int | None:
        """Wall time (ns) at which scenario time ``t`` happened."""
        if self.epoch_wall_ns is None or self.time_scale is None:
            return None
        return self.epoch_wall_ns + int(round(t / self.time_scale * 1e9))

    def fields(self) -> dict[str, Any]:
        """The clock fields to forward in an attachment."""
        return {"epoch_wall_ns": self.epoch_wall_ns, "time_scale": self.time_scale}


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


# ------------------------------------------------------------------------------ the service


@dataclass(frozen=True)
class Received:
    """A sample handed to a queued handler: payload bytes, key, attachment and wall time of arrival."""

    key: str
    payload: bytes
    attachment: dict[str, Any]
    t_recv_wall_ns: int


class CountingPublisher:
    """A Zenoh publisher whose puts are counted as messages/bytes out."""

    def __init__(self, pub, metrics: ServiceMetrics):
        self._pub = pub
        self._metrics = metrics
        self.key = str(pub.key_expr)

    def put(self, payload: bytes, attachment: bytes | None = None) -> None:
        self._pub.put(payload, attachment=attachment)
        self._metrics.msgs_out.add(len(payload))

    @property
    def matching(self) -> bool:
        return bool(self._pub.matching_status.matching)

    def undeclare(self) -> None:
        self._pub.undeclare()


def sender_admission(topic_name: str, time_scale: float = 1.0, max_senders: int = 256) -> Admission:
    """Per-sender admission for a topic: twice its nominal rate in wall time (``time_scale`` scenario seconds
    per wall second), with one second of that as the burst."""
    rate = 2.0 * (topic(topic_name).rate_hz or 10.0) * max(time_scale, 1.0)
    return Admission(rate_hz=rate, burst=rate, max_senders=max_senders)


class Service:
    """A service process's runtime: session, liveliness token, health, counters, signals.

    Use as a context manager in the main thread. ``figures`` (a callable returning the core's
    stats dict) and ``health_check`` (returning ``(state, note)``) refine the health status.
    Worker threads started with :meth:`spawn` are joined before the session closes. A worker thread
    that dies of an exception turns the health to failed and stops the service, which then exits
    with :data:`EXIT_THREAD_DIED` so that the launcher restarts it as it restarts a crashed one (a
    process alive but dead inside would never be restarted).
    """

    OVERFLOW_MAX = 256  # subscribe_queued: samples waiting for the overflow handler (a cold start's search: 2-3 s)

    def __init__(
        self,
        role: str,
        settings: ServiceSettings,
        figures: Callable[[], Mapping[str, Any]] | None = None,
        health_check: Callable[[], tuple[str, str | None]] | None = None,
        session_opener: Callable[[ZenohSettings], Any] = open_session,
    ):
        self.role = role
        self.settings = settings
        self.fleet = settings.fleet
        self.id = settings.id
        self.log = logging.getLogger(f"mapc.{role}")
        self.metrics = ServiceMetrics(settings.rate_window_s)
        self.figures = figures
        self.health_check = health_check
        self.running = threading.Event()
        self.stop_requested = threading.Event()
        self.session = None
        self._opener = session_opener
        self._t0 = time.monotonic()
        self._health_seq = 0
        self._state: str = "ok"
        self._state_note: str | None = None
        self._threads: list[threading.Thread] = []
        self.thread_died: str | None = None  # the first worker thread that died, and why
        self._admission_lock = threading.Lock()
        self._declared: list[Any] = []
        self._old_handlers: dict[int, Any] = {}
        self._parent = os.getppid()
        self.health_key = topic("health").key(fleet=self.fleet, role=role, id=self.id)
        self.alive_key = topic("alive").key(fleet=self.fleet, role=role, id=self.id)

    # -- lifecycle ------------------------------------------------------------------------
    def __enter__(self) -> Service:
        self._install_signals()
        self.session = self._opener(self.settings.zenoh)
        try:
            import zenoh

            self._health_pub = self.session.declare_publisher(
                self.health_key, congestion_control=zenoh.CongestionControl.DROP
            )
            self._queryable = self.session.declare_queryable(self.health_key, self._on_health_query)
            self._token = None
            self.running.set()
            self.spawn(self._health_loop, name="health")
        except BaseException:
            self.session.close()
            raise
        self.log.info(
            "up: %s (zenoh %s, connect %s)",
            self.alive_key,
            self.settings.zenoh.mode,
            self.settings.zenoh.connect,
        )
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is not None and not isinstance(exc, KeyboardInterrupt):
            self.metrics.error(f"{type(exc).__name__}: {exc}")
            self.log.error("stopping after an error: %s", exc, exc_info=(exc_type, exc, tb))
        self.stop()
        self.running.clear()
        for th in self._threads:
            if th is not threading.current_thread():
                th.join(timeout=5.0)
                if th.is_alive():
                    self.log.warning("thread %s did not stop within 5 s", th.name)
        try:
            for d in reversed(self._declared):
                try:
                    d.undeclare()
                except Exception as e:  # already undeclared or session gone: nothing to do
                    self.log.debug("undeclare: %s", e)
            if self._token is not None:
                self._token.undeclare()
            self._queryable.undeclare()
            self._health_pub.undeclare()
        finally:
            self.session.close()
            self._restore_signals()
            self.log.info("stopped after %.1f s", time.monotonic() - self._t0)
        if self.thread_died is not None and exc is None:
            raise SystemExit(EXIT_THREAD_DIED)

    def ready(self) -> None:
        """Declare the liveliness token: the service is wired (subscribers declared) and working.

        The launcher starts the next group when it sees the token, so roles call this after their
        subscribers exist; :meth:`wait` calls it if the role did not.
        """
        if self._token is None:
            self._token = self.session.liveliness().declare_token(self.alive_key)
            self.log.info("ready: %s", self.alive_key)

    def stop(self) -> None:
        """Ask the service to stop (safe from any thread or a signal handler)."""
        self.stop_requested.set()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until stop is requested (True) or ``timeout`` passes (False). Signal-friendly."""
        self.ready()
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self.stop_requested.is_set():
            left = 0.25 if deadline is None else min(0.25, deadline - time.monotonic())
            if left <= 0:
                return False
            self.stop_requested.wait(left)
        return True

    @property
    def uptime_s(self) -> float:
        return time.monotonic() - self._t0

    def _install_signals(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._old_handlers[sig] = signal.signal(sig, self._on_signal)

    def _restore_signals(self) -> None:
        for sig, h in self._old_handlers.items():
            signal.signal(sig, h)
        self._old_handlers.clear()

    def _on_signal(self, signum, frame) -> None:
        self.log.info("signal %s: stopping", signal.Signals(signum).name)
        self.stop()

    def spawn(self, target: Callable[[], None], name: str) -> threading.Thread:
        """Start a daemon thread that should return once ``stop_requested`` is set."""

        def run():
            try:
                target()
            except Exception as e:
                self.metrics.error(f"{name}: {type(e).__name__}: {e}")
                self.set_state("failed", f"thread {name} died: {type(e).__name__}: {e}")
                self.log.exception("thread %s died: the service stops and exits %d", name, EXIT_THREAD_DIED)
                self.thread_died = self.thread_died or f"{name}: {type(e).__name__}: {e}"
                self.stop()

        th = threading.Thread(target=run, name=f"{self.role}-{name}", daemon=True)
        self._threads.append(th)
        th.start()
        return th

    # -- state and health -------------------------------------------------------------------
    def set_state(self, state: str, note: str | None = None) -> None:
        if state not in STATES:
            raise ValueError(f"state must be one of {STATES}, got {state!r}")
        self._state, self._state_note = state, note

    def current_state(self) -> tuple[str, str | None]:
        """The worst of: the state set explicitly, the role's check, stalled input, recent errors."""
        candidates: list[tuple[str, str | None]] = [(self._state, self._state_note)]
        if self.health_check is not None:
            try:
                candidates.append(self.health_check())
            except Exception as e:
                candidates.append(("degraded", f"health check raised {type(e).__name__}: {e}"))
        idle = self.metrics.msgs_in.idle_s()
        stale = self.settings.stale_input_s
        if stale is not None and idle is not None and idle > stale:
            candidates.append(("degraded", f"input stalled for {idle:.1f} s"))
        if self.metrics.last_error_t is not None and time.monotonic() - self.metrics.last_error_t < 10.0:
            candidates.append(("degraded", self.metrics.last_error))
        for reason, (n, detail) in self.metrics.recent_rejects(DEGRADING_REJECTS, DEGRADED_AFTER_REJECT_S).items():
            candidates.append(("degraded", f"input lost: {reason} ({n} so far; the last: {detail})"))
        return max(candidates, key=lambda c: STATES.index(c[0]))

    def health(self) -> HealthStatus:
        state, note = self.current_state()
        figures: Mapping[str, Any] = {}
        if self.figures is not None:
            try:
                figures = self.figures()
            except Exception as e:
                self.metrics.error(f"figures: {type(e).__name__}: {e}")
        self._health_seq += 1
        return build_health(
            fleet=self.fleet,
            role=self.role,
            sid=self.id,
            seq=self._health_seq,
            uptime_s=self.uptime_s,
            metrics=self.metrics,
            state=state,
            note=note if state != "ok" else None,
            figures=figures,
        )

    def _on_health_query(self, query) -> None:
        try:
            query.reply(self.health_key, encode(self.health()))
        except Exception as e:  # a failed reply must not kill the Zenoh callback thread
            self.log.warning("health reply failed: %s", e)

    def _health_loop(self) -> None:
        next_t = time.monotonic()
        while not self.stop_requested.is_set():
            if self.settings.watch_parent and os.getppid() != self._parent:
                self.log.warning("parent process %d is gone: stopping", self._parent)
                self.stop()
                break
            now = time.monotonic()
            if now >= next_t:
                try:
                    self._health_pub.put(encode(self.health()))
                except Exception as e:
                    self.log.warning("health put failed: %s", e)
                next_t = now + self.settings.health_period_s
            self.stop_requested.wait(min(0.25, max(next_t - time.monotonic(), 0.01)))

    # -- pub/sub helpers --------------------------------------------------------------------
    def publisher(self, key: str, drop: bool = False, express: bool = False) -> CountingPublisher:
        """A counted publisher; ``drop=True`` for telemetry where newest wins (CongestionControl.DROP)."""
        import zenoh

        cc = zenoh.CongestionControl.DROP if drop else zenoh.CongestionControl.BLOCK
        pub = self.session.declare_publisher(key, congestion_control=cc, express=express)
        self._declared.append(pub)
        return CountingPublisher(pub, self.metrics)

    def subscribe(self, key: str, callback: Callable[[Received], None], count: bool = True):
        """A callback subscriber (runs on a Zenoh thread: keep ``callback`` short).

        Input is counted; an exception in ``callback`` is recorded as the last error, never raised
        into Zenoh.
        """

        def on_sample(sample) -> None:
            payload = sample.payload.to_bytes()
            if count:
                self.metrics.msgs_in.add(len(payload))
            try:
                callback(Received(str(sample.key_expr), payload, read_attachment(sample), time.time_ns()))
            except Exception as e:
                self.metrics.error(f"{type(e).__name__}: {e}")
                self.log.exception("subscriber callback on %s failed", sample.key_expr)

        sub = self.session.declare_subscriber(key, on_sample)
        self._declared.append(sub)
        return sub

    def watch_alive(self, key: str) -> threading.Event:
        """An event that is set while the liveliness token ``key`` exists (Zenoh tells of a killed process
        within milliseconds, of a frozen one after its lease)."""
        import zenoh

        alive = threading.Event()

        def on_token(sample) -> None:
            (alive.set if sample.kind == zenoh.SampleKind.PUT else alive.clear)()

        self._declared.append(self.session.liveliness().declare_subscriber(key, on_token, history=True))
        return alive

    def admit(self, admission: Admission, sender: str, what: str) -> bool:
        """Whether ``sender``'s message (``what``, for the log) passes its per-sender admission; a refusal
        (``flood``, ``too_many_senders``) is counted. Thread-safe: Zenoh runs callbacks on several threads."""
        with self._admission_lock:
            reason = admission.admit(sender, time.monotonic())
        if reason is not None:
            self.metrics.reject(reason, f"{what} from {sender}", self.log)
        return reason is None

    def subscribe_queued(
        self,
        key: str,
        handler: Callable[[Received], None],
        maxsize: int = 16,
        name: str = "worker",
        overflow: Callable[[Received], None] | None = None,
    ):
        """Subscribe with a bounded queue and one worker thread running ``handler`` in arrival order.

        When ``maxsize`` samples wait for ``handler``, a new sample is counted as reject ``queue_full``
        and dropped; with ``overflow`` it is counted as ``skipped`` and passed to ``overflow`` instead, in
        the same worker and in arrival order (a cheap partial handling: a vehicle keeps the odometry of a
        frame it has no time to match), until ``OVERFLOW_MAX`` samples wait for it, beyond
        which it is dropped as ``queue_full`` too (a flood must not grow the queue without bound). The
        handler's run time is recorded as the processing latency.
        """
        q: queue.SimpleQueue[tuple[Received, bool]] = queue.SimpleQueue()
        lock = threading.Lock()
        waiting = 0  # samples in q for ``handler``
        skipping = 0  # samples in q for ``overflow``

        def enqueue(msg: Received) -> None:
            nonlocal waiting, skipping
            with lock:
                full = waiting >= maxsize
                drop = full and (overflow is None or skipping >= self.OVERFLOW_MAX)
                waiting += not full
                skipping += full and not drop
            if drop:
                self.metrics.reject("queue_full", f"{name}: {maxsize} samples waiting, dropped", self.log)
                return
            if full:
                self.metrics.reject("skipped", f"{name}: {maxsize} samples waiting, handled in part", self.log)
            q.put((msg, not full))

        def work() -> None:
            nonlocal waiting, skipping
            while not self.stop_requested.is_set():
                try:
                    msg, whole = q.get(timeout=0.2)
                except queue.Empty:
                    continue
                with lock:
                    if whole:
                        waiting -= 1
                    else:
                        skipping -= 1
                t0 = time.perf_counter()
                try:
                    (handler if whole else overflow)(msg)
                except Exception as e:
                    self.metrics.error(f"{type(e).__name__}: {e}")
                    self.log.exception("handler %s failed on %s", name, msg.key)
                if whole:
                    self.metrics.latency.add(time.perf_counter() - t0)

        self.spawn(work, name)
        return self.subscribe(key, enqueue)

    def decode_or_reject(self, payload: bytes, model):
        """``schemas.decode``; a Rejection is counted by reason and None returned."""
        msg = decode(payload, model)
        if not msg:
            self.metrics.reject(msg.reason, msg.detail, self.log)
            return None
        return msg

    def wait_matching(self, pubs: Iterable[CountingPublisher], timeout_s: float) -> bool:
        """Wait until every publisher has a matching subscriber (or the timeout, or stop)."""
        pubs = list(pubs)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not self.stop_requested.is_set():
            if all(p.matching for p in pubs):
                return True
            self.stop_requested.wait(0.05)
        return all(p.matching for p in pubs)


def write_json(path: Path, data: Any) -> None:
    """Write JSON atomically (write to a temporary file, then rename)."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(jsonout.dumps(data, indent=2, default=str))
    os.replace(tmp, path)
