"""Service configuration: Zenoh session settings and files, command-line flags, logging, a service's main."""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
from collections.abc import Callable
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from mapcontainer.config import ConfigError

# ------------------------------------------------------------------------------ configuration


class ZenohSettings(BaseModel):
    """How a process joins the Zenoh network (the recipes: docs/operations.md, "Several machines").

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


def time_scale_arg(text: str) -> float | str:
    """``auto`` or a number of scenario seconds per wall second."""
    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number or auto: {text!r}") from None
