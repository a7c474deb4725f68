"""What every service process shares: the Zenoh session, health, counters and a clean shutdown.

A role's ``main(settings)`` does::

    with Service("vehicle", settings) as svc:          # session, health queryable, signals
        pub = svc.publisher(topic("prior_tx").key(fleet=svc.fleet, src=svc.id))
        svc.subscribe_queued(topic("sensors").key(...), on_frame)  # counted, errors recorded
        svc.wait()  # declares the liveliness token; returns on SIGINT/SIGTERM/stop()/parent death
    # the session is closed here: a process with callback subscribers that exits without
    # closing its session hangs (docs/architecture.md, "Processes and Zenoh")

Health: every service holds the liveliness token ``mc/{fleet}/alive/{role}/{id}`` and puts a
:class:`schemas.HealthStatus` on ``mc/{fleet}/health/{role}/{id}`` once a second; a queryable on
the same key answers with the current status. HealthStatus's envelope times (``t_meas``,
``t_sent``) are Unix wall-clock seconds for this message (a service may not know scenario time).

Wall-clock instrumentation travels in the Zenoh *attachment* (a small msgpack map, see
:func:`make_attachment`), not in the payload: ``t_wall_ns`` (when this hop published) and a copy of
the world's clock. The clock itself (``epoch_wall_ns`` and ``time_scale``: scenario time ``t``
happened at wall time ``epoch_wall_ns + t / time_scale * 1e9``) travels inside the messages'
envelopes, where their signature covers it, and services take it only from there (:class:`SimClock`):
nobody vouches for an attachment. The evaluator's end-to-end latency is
``t_wall_ns(fused published) - wall(t_meas)``.
"""

from __future__ import annotations

from .clock import SimClock, make_attachment, read_attachment
from .config import (
    ServiceSettings,
    ZenohSettings,
    add_service_args,
    build_zenoh_config,
    listening_locators,
    open_session,
    service_main,
    service_settings_from_args,
    setup_logging,
    time_scale_arg,
    zenoh_config,
    zenoh_error_text,
)
from .metrics import (
    DEGRADING_REJECTS,
    HEALTHY_STATES,
    STATES,
    LatencySamples,
    RateCounter,
    ServiceMetrics,
    build_health,
    flatten_figures,
)
from .service import (
    EXIT_THREAD_DIED,
    CountingPublisher,
    Received,
    Service,
    topic_gate,
    write_json,
)

__all__ = [
    "CountingPublisher",
    "DEGRADING_REJECTS",
    "EXIT_THREAD_DIED",
    "LatencySamples",
    "RateCounter",
    "Received",
    "HEALTHY_STATES",
    "STATES",
    "Service",
    "ServiceMetrics",
    "ServiceSettings",
    "SimClock",
    "ZenohSettings",
    "add_service_args",
    "build_health",
    "build_zenoh_config",
    "flatten_figures",
    "listening_locators",
    "make_attachment",
    "open_session",
    "read_attachment",
    "topic_gate",
    "service_main",
    "service_settings_from_args",
    "setup_logging",
    "time_scale_arg",
    "write_json",
    "zenoh_config",
    "zenoh_error_text",
]
