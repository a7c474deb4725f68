"""Router service: a Python process opened in Zenoh ``router`` mode (scouting delay 0).

One per host in a multi-host fleet: the host's services connect to it as clients
(``--zenoh-mode client --connect tcp/127.0.0.1:7447``) and the routers connect to each other
(``--connect tcp/<other-host>:7447``). It holds the usual liveliness token and health
status, so ``mapc health`` lists it. The listening endpoints are a health figure-free log line
(read from the admin space).
"""

from __future__ import annotations

import argparse

from pydantic import Field

from ..runtime import (
    Service,
    ServiceSettings,
    add_service_args,
    listening_locators,
    service_settings_from_args,
    setup_logging,
)

__all__ = ["main", "parse_args"]


class RouterSettings(ServiceSettings):
    keys: str | None = Field(None, description="the fleet's keys directory: sign the health status (as its id)")


def parse_args(argv: list[str] | None = None) -> RouterSettings:
    p = argparse.ArgumentParser(prog="python -m services.router", description=__doc__.splitlines()[0])
    add_service_args(p, "router", default_id="router")
    p.add_argument("--keys", default=None, help="the fleet's keys directory (mapc keys init): sign the health status")
    p.set_defaults(zenoh_mode="router")
    a = p.parse_args(argv)
    s = service_settings_from_args(a)
    z = s.zenoh.model_copy(update={"adminspace": True, "exit_on_failure": False})
    return RouterSettings(**{**s.model_dump(), "zenoh": z, "stale_input_s": None, "keys": a.keys})


def main(s: RouterSettings) -> int:
    log = setup_logging("router", s.id, s.log_level)
    log.info("settings: %s", s.model_dump_json())
    with Service("router", s, keys=s.keys) as svc:
        log.info("listening on %s", listening_locators(svc.session))
        svc.wait()
    return 0
