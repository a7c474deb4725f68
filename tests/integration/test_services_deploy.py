"""deploy/zenoh/*.json5 work as documented: they parse, user/password and mutual TLS admit the right
clients only, the access-control rules drop what a vehicle may not publish (another vehicle's keys
included, by user name and by certificate common name), and ``mapc health --zenoh-config`` logs in to
a secured router.

Routers listen on loopback port 0 (read back from the admin space, or from the router process's log);
file paths inside the configurations are pointed at this checkout and at test certificates made in a
temporary directory by deploy/zenoh/secure/gen-test-certs.sh.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import time
from pathlib import Path

import pytest

from services.runtime import listening_locators

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
ZDIR = REPO / "deploy" / "zenoh"
USERS = str(ZDIR / "secure" / "users.txt")


def _config(name: str, **over):
    import zenoh

    conf = zenoh.Config.from_file(str(ZDIR / name))
    for key, value in over.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def _open(name: str, **over):
    import zenoh

    return zenoh.open(_config(name, **over))


def _router(name: str, endpoint: str, **over):
    session = _open(name, **{"listen/endpoints": [endpoint], "adminspace/enabled": True, **over})
    return session, listening_locators(session)[0]


def test_every_configuration_parses():
    files = sorted(ZDIR.rglob("*.json5"))
    assert len(files) >= 8
    for f in files:
        conf = _config(str(f.relative_to(ZDIR)))
        assert json.loads(conf.get_json("scouting/multicast/enabled")) is False, f


def test_user_password_admits_known_users_only():
    import zenoh

    router, ep = _router(
        "secure/router-usrpwd.json5", "tcp/127.0.0.1:0", **{"transport/auth/usrpwd/dictionary_file": USERS}
    )
    try:
        client = _open("secure/client-usrpwd.json5", **{"connect/endpoints": [ep]})
        client.close()
        with pytest.raises(zenoh.ZError):
            _open(
                "secure/client-usrpwd.json5",
                **{
                    "connect/endpoints": [ep],
                    "connect/timeout_ms": 1000,
                    "transport/auth/usrpwd/password": "wrong",
                },
            )
    finally:
        router.close()


TLS = "transport/link/tls/"
needs_openssl = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl to make test certificates")


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    """Test certificates from gen-test-certs.sh (made once for this module's TLS tests)."""
    out = tmp_path_factory.mktemp("certs")
    subprocess.run([str(ZDIR / "secure" / "gen-test-certs.sh"), str(out)], check=True, capture_output=True)
    return out


def _tls_router(certs: Path, **over):
    """A router-tls.json5 router on a free loopback port with the test certificates: (session, port)."""
    c = {n: str(certs / n) for n in ("ca.pem", "router.pem", "router-key.pem")}
    router, ep = _router(
        "secure/router-tls.json5",
        "tls/127.0.0.1:0",
        **{
            TLS + "root_ca_certificate": c["ca.pem"],
            TLS + "listen_certificate": c["router.pem"],
            TLS + "listen_private_key": c["router-key.pem"],
            TLS + "connect_certificate": c["router.pem"],
            TLS + "connect_private_key": c["router-key.pem"],
        },
        **over,
    )
    return router, ep.rsplit(":", 1)[1]


def _tls_client(certs: Path, port: str, name: str):
    """A client-tls.json5 session presenting the certificate ``name``.pem (its common name is ``name``)."""
    return _open(
        "secure/client-tls.json5",
        **{
            "connect/endpoints": [f"tls/localhost:{port}"],
            TLS + "root_ca_certificate": str(certs / "ca.pem"),
            TLS + "connect_certificate": str(certs / f"{name}.pem"),
            TLS + "connect_private_key": str(certs / f"{name}-key.pem"),
        },
    )


@needs_openssl
def test_mutual_tls_admits_certified_clients_only(certs):
    import zenoh

    router, port = _tls_router(certs)
    try:
        got = []
        a = _tls_client(certs, port, "vehicle")
        b = _tls_client(certs, port, "vehicle")
        try:
            sub = b.declare_subscriber("mc/t/tls", lambda s: got.append(s.payload.to_bytes()))
            deadline = time.monotonic() + 5
            while not got and time.monotonic() < deadline:
                a.put("mc/t/tls", b"over tls")
                time.sleep(0.05)
            sub.undeclare()
            assert got and got[0] == b"over tls"
        finally:
            a.close()
            b.close()
        no_cert = {
            "mode": "client",
            "scouting": {"multicast": {"enabled": False}},
            "connect": {"endpoints": [f"tls/localhost:{port}"], "timeout_ms": 1000, "exit_on_failure": True},
            "transport": {"link": {"tls": {"root_ca_certificate": str(certs / "ca.pem")}}},
        }
        with pytest.raises(zenoh.ZError):
            zenoh.open(zenoh.Config.from_json5(json.dumps(no_cert)))
    finally:
        router.close()


def _login(user: str) -> dict:
    """Overrides of client-usrpwd.json5 (which logs in as cv0) for another user of users.txt."""
    return {"transport/auth/usrpwd/user": user, "transport/auth/usrpwd/password": f"TEST-ONLY-{user}-password"}


def _acl_router():
    return _router("secure/router-acl.json5", "tcp/127.0.0.1:0", **{"transport/auth/usrpwd/dictionary_file": USERS})


def test_access_control_drops_what_a_vehicle_may_not_publish():
    router, ep = _acl_router()
    vehicle = _open("secure/client-usrpwd.json5", **{"connect/endpoints": [ep]})  # cv0
    ops = _open("secure/client-usrpwd.json5", **{"connect/endpoints": [ep], **_login("ops")})
    try:
        got: list[str] = []
        sub = ops.declare_subscriber("mc/f/**", lambda s: got.append(str(s.key_expr)))
        deadline = time.monotonic() + 5
        while "mc/f/v2x/tx/cv0/prior" not in got and time.monotonic() < deadline:
            vehicle.put("mc/f/sim/truth", b"forged truth")  # denied: vehicles may not publish truth
            vehicle.put("mc/f/v2x/tx/cv0/prior", b"prior")  # allowed
            time.sleep(0.05)
        # the subscription is in place now: a denied put followed by an allowed marker on the same
        # session (delivered in order) shows the denied one was dropped, not merely late
        vehicle.put("mc/f/sim/truth", b"forged truth")
        vehicle.put("mc/f/sim/cv0/sensors", b"forged sensors")  # denied: a vehicle reads its sensors only
        vehicle.put("mc/f/v2x/tx/cv0/end", b"marker")
        while "mc/f/v2x/tx/cv0/end" not in got and time.monotonic() < deadline + 5:
            time.sleep(0.02)
        sub.undeclare()
        assert "mc/f/v2x/tx/cv0/end" in got
        assert "mc/f/v2x/tx/cv0/prior" in got
        assert "mc/f/sim/truth" not in got
        assert "mc/f/sim/cv0/sensors" not in got
        token = vehicle.liveliness().declare_token("mc/f/alive/vehicle/cv0")
        deadline = time.monotonic() + 5
        seen: list[str] = []
        while not seen and time.monotonic() < deadline:
            seen = [str(r.ok.key_expr) for r in ops.liveliness().get("mc/f/alive/**", timeout=1.0) if r.ok]
        assert seen == ["mc/f/alive/vehicle/cv0"]
        token.undeclare()
    finally:
        vehicle.close()
        ops.close()
        router.close()


def test_access_control_keeps_each_vehicle_to_its_own_keys():
    """cv0 may not speak for cv1: its puts on cv1's V2X and health keys and its token on cv1's liveliness
    key are dropped by the router, while its own pass and cv1's own pass."""
    router, ep = _acl_router()
    cv0 = _open("secure/client-usrpwd.json5", **{"connect/endpoints": [ep]})
    cv1 = _open("secure/client-usrpwd.json5", **{"connect/endpoints": [ep], **_login("cv1")})
    ops = _open("secure/client-usrpwd.json5", **{"connect/endpoints": [ep], **_login("ops")})
    tokens = []
    try:
        got: list[str] = []
        sub = ops.declare_subscriber("mc/f/**", lambda s: got.append(str(s.key_expr)))
        alive: list[str] = []
        live = ops.liveliness().declare_subscriber("mc/f/alive/**", lambda s: alive.append(str(s.key_expr)))
        deadline = time.monotonic() + 5
        while not {"mc/f/v2x/tx/cv0/prior", "mc/f/v2x/tx/cv1/prior"} <= set(got) and time.monotonic() < deadline:
            cv0.put("mc/f/v2x/tx/cv0/prior", b"cv0's own")
            cv1.put("mc/f/v2x/tx/cv1/prior", b"cv1's own")  # the key itself is open to its owner
            time.sleep(0.05)
        assert {"mc/f/v2x/tx/cv0/prior", "mc/f/v2x/tx/cv1/prior"} <= set(got), got
        # both subscriptions are in place: cv0's forgeries, then an allowed marker on the same session
        cv1.close()  # from here on, anything on cv1's keys could only come from cv0
        got.clear()
        cv0.put("mc/f/v2x/tx/cv1/prior", b"forged prior")
        cv0.put("mc/f/health/vehicle/cv1", b"forged status")
        cv0.put("mc/f/health/vehicle/cv0", b"marker")
        tokens.append(cv0.liveliness().declare_token("mc/f/alive/vehicle/cv1"))
        tokens.append(cv0.liveliness().declare_token("mc/f/alive/vehicle/cv0"))
        deadline = time.monotonic() + 5
        while not ("mc/f/health/vehicle/cv0" in got and "mc/f/alive/vehicle/cv0" in alive):
            assert time.monotonic() < deadline, (got, alive)
            time.sleep(0.02)
        assert "mc/f/v2x/tx/cv1/prior" not in got and "mc/f/health/vehicle/cv1" not in got, got
        assert alive == ["mc/f/alive/vehicle/cv0"], alive
        held: list[str] = []
        while not held and time.monotonic() < deadline + 5:  # a liveliness query can come back empty once
            held = [str(r.ok.key_expr) for r in ops.liveliness().get("mc/f/alive/**", timeout=1.0) if r.ok]
        assert held == ["mc/f/alive/vehicle/cv0"]
        sub.undeclare()
        live.undeclare()
    finally:
        for tok in tokens:
            tok.undeclare()
        cv0.close()
        cv1.close()
        ops.close()
        router.close()


@needs_openssl
def test_access_control_by_certificate_common_name(certs):
    """The TLS variant of router-acl.json5 as its header describes it: the same rules and policies, the
    subjects matching the certificates' common names (cv0..cv3, host, ops) instead of user names."""
    import zenoh

    acl = json.loads(zenoh.Config.from_file(str(ZDIR / "secure" / "router-acl.json5")).get_json("access_control"))
    acl["subjects"] = [{"id": s["id"], "cert_common_names": s["usernames"]} for s in acl["subjects"]]
    router, port = _tls_router(certs, access_control=acl)
    cv0, ops = _tls_client(certs, port, "cv0"), _tls_client(certs, port, "ops")
    try:
        got: list[str] = []
        sub = ops.declare_subscriber("mc/f/**", lambda s: got.append(str(s.key_expr)))
        deadline = time.monotonic() + 5
        while "mc/f/v2x/tx/cv0/prior" not in got and time.monotonic() < deadline:
            cv0.put("mc/f/v2x/tx/cv0/prior", b"cv0's own")
            time.sleep(0.05)
        cv0.put("mc/f/v2x/tx/cv1/prior", b"forged")  # denied, then an allowed marker on the same session
        cv0.put("mc/f/v2x/tx/cv0/end", b"marker")
        while "mc/f/v2x/tx/cv0/end" not in got and time.monotonic() < deadline + 5:
            time.sleep(0.02)
        sub.undeclare()
        assert "mc/f/v2x/tx/cv0/end" in got and "mc/f/v2x/tx/cv1/prior" not in got, got
    finally:
        cv0.close()
        ops.close()
        router.close()


def test_health_logs_in_to_a_secured_router(tmp_path, fleet_name, spawn, mapc, wait_for):
    """mapc health --zenoh-config: with the ops login it lists the router and a vehicle behind router-acl.json5
    (the vehicle answering through its per-vehicle rules); without a login it cannot connect, and with a
    vehicle's login the ACL lets nothing answer it."""
    from services.runtime import Service, ServiceSettings, ZenohSettings

    router = spawn(
        "services.router",
        "--fleet",
        fleet_name,
        "--id",
        "gw",
        "--zenoh-config",
        "deploy/zenoh/secure/router-acl.json5",
        "--listen",
        "tcp/127.0.0.1:0",
    )
    line = wait_for(
        lambda: re.search(r"listening on \['(tcp/127\.0\.0\.1:\d+)'", router.log_path.read_text()),
        timeout=60,
        what="the router's endpoint in its log",
    )
    ep = line.group(1)
    vehicle_file = ZDIR / "secure" / "client-usrpwd.json5"
    ops_file = tmp_path / "client-ops.json5"
    text = vehicle_file.read_text()
    ops_text = text.replace(
        'user: "cv0", password: "TEST-ONLY-cv0-password"', 'user: "ops", password: "TEST-ONLY-ops-password"'
    )
    assert ops_text != text
    ops_file.write_text(ops_text)

    settings = ServiceSettings(
        fleet=fleet_name, id="cv0", zenoh=ZenohSettings(mode="client", connect=[ep], config_file=str(vehicle_file))
    )
    with Service("vehicle", settings) as svc:
        svc.ready()

        def listed():
            proc = mapc("health", "--fleet", fleet_name, "--connect", ep, "--zenoh-config", str(ops_file), "--json")
            views = {(v["role"], v["id"]): v for v in json.loads(proc.stdout or "[]")}
            found = proc.returncode in (0, 1) and {("vehicle", "cv0"), ("router", "gw")} <= set(views)
            return found and (proc, views)

        proc, views = wait_for(listed, timeout=30, what="mapc health listing the router and cv0", every=0.5)
        assert views[("router", "gw")]["state"] == "ok", proc.stdout
        assert views[("vehicle", "cv0")]["alive"], proc.stdout
        assert views[("vehicle", "cv0")]["state"] not in ("unresponsive", "missing"), proc.stdout  # it answered

        anonymous = mapc("health", "--fleet", fleet_name, "--connect", ep, "--json")
        assert anonymous.returncode == 2 and anonymous.stdout.strip() == "[]", anonymous
        assert "cannot reach" in anonymous.stderr and "--zenoh-config" in anonymous.stderr, anonymous.stderr

        as_vehicle = mapc("health", "--fleet", fleet_name, "--connect", ep, "--zenoh-config", str(vehicle_file))
        assert as_vehicle.returncode == 2 and "nothing answers" in as_vehicle.stdout, as_vehicle


def test_health_zenoh_config_errors_are_one_line(tmp_path, mapc):
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: client, ,, ")
    for path in (str(tmp_path / "missing.json5"), str(bad)):
        proc = mapc("health", "--connect", "tcp/127.0.0.1:9", "--zenoh-config", path)
        assert proc.returncode == 2, proc
        assert proc.stderr.startswith("mapc: configuration error:") and path in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr, proc.stderr
