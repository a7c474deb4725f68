"""The fleet's Zenoh mesh, authenticated and least-privilege by default (``mapc fleet up``).

The launcher is the fleet's router: every process connects to it as a Zenoh client and logs in with its
own user name and password (Zenoh's ``transport/auth/usrpwd``), made for the run like the signing keys and
written to ``<run dir>/zenoh/`` (mode 0600): ``users.txt`` (the router's dictionary), ``router.json5``
(the launcher's configuration: the dictionary and the access control), ``<process>.json5`` (each
process's login) and ``ops.json5`` (the operator's: ``mapc health``, ``view``, ``record`` find it through
the fleet registry). A session without a login is refused when it connects, so nothing on the machine
can publish or subscribe on the fleet's keys without the run directory's files.

The access control (Zenoh's ``access_control``, default deny) gives each process only its own keys
(:func:`acl`): a vehicle puts only its V2X messages and reads only its sensors and its own downlink; the host
reads only its receive keys (and its on-board vehicle's transmit key) and puts only its own fused state and
its downlink; the channel
reads the transmit keys and the world's truth (a geometric radio places its radios there) and puts the
receive keys; the world puts the simulation's keys (and, for its adaptive clock, reads the vehicles'
transmit keys and the fused states and watches who is alive); the evaluator reads and puts its metrics;
the recorder reads; every process answers health queries on its own key and holds its own liveliness
token; the operator may do everything under the fleet's namespace.

``mapc fleet up --insecure`` keeps the open peer mesh of earlier versions (any process on the machine
can join it) for debugging; the fleet's state, ``mapc fleet status`` and ``mapc health`` say so.
"""

from __future__ import annotations

import json
import os
import secrets
from pathlib import Path
from typing import Any

from ..runtime import ZenohSettings, build_zenoh_config
from .manifest import FleetParams, ProcessSpec

__all__ = ["OPS", "acl", "login_path", "write_mesh"]

OPS = "ops"  # the operator's login (the CLI tools)

# what a subscriber needs (its declaration in, the samples out), a publisher (its puts in), a queryable, a
# liveliness token, a watcher of tokens. Every process also learns of the fleet's subscriptions (their
# declarations out, on any key of the fleet): a client puts only where it knows of a subscriber, and a
# subscription's key expression is a pattern (mc/F/v2x/tx/*/prior) that no one process's keys include.
_SUB = (("ingress", "declare_subscriber"), ("egress", "put"))
_PUB = (("ingress", "put"),)
_LEARN = (("egress", "declare_subscriber"),)
_QUERYABLE = (("ingress", "declare_queryable"), ("ingress", "reply"))
_TOKEN = (("ingress", "liveliness_token"),)
_WATCH = (("ingress", "declare_liveliness_subscriber"), ("egress", "liveliness_token"))
_ALL = (
    ("ingress", "put"), ("ingress", "delete"), ("ingress", "declare_subscriber"), ("ingress", "declare_queryable"),
    ("ingress", "query"), ("ingress", "reply"), ("ingress", "liveliness_token"),
    ("ingress", "declare_liveliness_subscriber"), ("ingress", "liveliness_query"),
    ("egress", "put"), ("egress", "delete"), ("egress", "declare_subscriber"), ("egress", "declare_queryable"),
    ("egress", "query"), ("egress", "reply"), ("egress", "liveliness_token"),
)  # fmt: skip


def login_path(run_dir: str | Path, user: str) -> Path:
    """The Zenoh configuration file with ``user``'s login in a run directory."""
    return Path(run_dir) / "zenoh" / f"{user}.json5"


def _grants(spec: ProcessSpec, params: FleetParams) -> list[tuple[tuple[tuple[str, str], ...], list[str]]]:
    """(flows and messages, key expressions) a process may use, by its role (module doc)."""
    f = f"mc/{params.fleet}"
    own = [
        (_PUB, [f"{f}/health/{spec.role}/{spec.id}"]),
        (_QUERYABLE, [f"{f}/health/{spec.role}/{spec.id}"]),
        ((("egress", "query"),), [f"{f}/health/**"]),  # a health query's selector is a pattern too
        (_LEARN, [f"{f}/**"]),
        (_TOKEN, [f"{f}/alive/{spec.role}/{spec.id}"]),
    ]
    hid, ego = params.host_id, params.ego
    by_role = {
        "vehicle": [
            (_PUB, [f"{f}/v2x/tx/{spec.id}/**"]),
            (_SUB, [f"{f}/sim/{spec.id}/sensors", f"{f}/v2x/rx/{spec.id}/*/downlink"]),  # its own downlink only
        ],
        "world": [
            (_PUB, [f"{f}/sim/**"]),
            # the adaptive clock follows the services it waits for: the vehicles' messages, the fused states, and
            # which vehicles and hosts are alive (services/world/app.py, _follow_progress)
            (_SUB, [f"{f}/v2x/tx/**", f"{f}/host/*/fused"]),
            (_WATCH, [f"{f}/alive/vehicle/*", f"{f}/alive/host/*"]),
        ],
        "channel": [(_SUB, [f"{f}/v2x/tx/**", f"{f}/sim/truth"]), (_PUB, [f"{f}/v2x/rx/**"])],
        "host": [
            (_SUB, [f"{f}/v2x/rx/{hid}/**", f"{f}/v2x/tx/{ego}/**"]),
            (_PUB, [f"{f}/host/{hid}/fused", f"{f}/v2x/tx/{hid}/downlink/*"]),
            (_WATCH, [f"{f}/alive/host/{hid}"]),  # a standby watches its host
        ],
        "evaluator": [
            (_SUB, [f"{f}/sim/truth", f"{f}/host/*/fused", f"{f}/v2x/**"]),
            (_PUB, [f"{f}/eval/metrics"]),
        ],
        "recorder": [(_SUB, [f"{f}/**"])],
    }
    return own + by_role.get(spec.role, [])


def acl(specs: list[ProcessSpec], params: FleetParams) -> dict[str, Any]:
    """The router's ``access_control`` section: default deny, each process its own grants (user = its name)."""
    rules, subjects, policies = [], [], []
    for user, grants in [*((s.name, _grants(s, params)) for s in specs), (OPS, [(_ALL, [f"mc/{params.fleet}/**"])])]:
        ids = []
        for k, (pairs, keys) in enumerate(grants):
            for flow in ("ingress", "egress"):
                messages = sorted({m for fl, m in pairs if fl == flow})
                if messages:
                    rid = f"{user}-{k}-{flow}"
                    rules.append(
                        {"id": rid, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": keys}
                    )
                    ids.append(rid)
        subjects.append({"id": user, "usernames": [user]})
        policies.append({"id": f"{user}-policy", "subjects": [user], "rules": ids})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def write_mesh(run_dir: str | Path, specs: list[ProcessSpec], params: FleetParams, listen: str) -> Path:
    """The run's logins, dictionary and router configuration (module doc); the router's file."""
    d = Path(run_dir) / "zenoh"
    d.mkdir(parents=True, exist_ok=True)
    os.chmod(d, 0o700)
    users = {u: secrets.token_urlsafe(24) for u in [*(s.name for s in specs), OPS]}
    _write_private(d / "users.txt", "".join(f"{u}:{p}\n" for u, p in users.items()))
    for user, password in users.items():  # a client of the launcher's router (--connect gives the endpoint)
        conf = build_zenoh_config(ZenohSettings(mode="client", connect=["tcp/127.0.0.1:1"]))
        del conf["connect"]["endpoints"]
        conf["transport"]["auth"] = {"usrpwd": {"user": user, "password": password}}
        _write_private(login_path(run_dir, user), json.dumps(conf, indent=2) + "\n")
    router = build_zenoh_config(ZenohSettings(mode="router", listen=[listen], adminspace=True))
    router["transport"]["auth"] = {"usrpwd": {"dictionary_file": str(d / "users.txt")}}
    router["access_control"] = acl(specs, params)
    path = d / "router.json5"
    _write_private(path, json.dumps(router, indent=2) + "\n")
    return path
