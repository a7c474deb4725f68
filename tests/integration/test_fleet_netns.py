"""A fleet across two "machines": network namespaces made by the test, joined by a veth pair and by two
Zenoh routers over TLS with mutual certificates and an access control; machine A runs the host, the
channel, the evaluator and the world (manifest fleet-host-a), machine B the vehicles (fleet-host-b), each
launcher a client of its machine's router, both with one fleet CA (signed messages). The same checks as
the local fleet: every process answers health across the routers, the run fuses and meets its accuracy.

Needs root (``ip netns``), openssl and the ``ip`` tool; skipped otherwise.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import uuid
from pathlib import Path

import pytest

from .conftest import REPO, wait_for

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def _can_make_namespaces() -> bool:
    if os.geteuid() != 0 or shutil.which("ip") is None or shutil.which("openssl") is None:
        return False
    name = f"mapcprobe{uuid.uuid4().hex[:6]}"
    ok = subprocess.run(["ip", "netns", "add", name], capture_output=True).returncode == 0
    subprocess.run(["ip", "netns", "del", name], capture_output=True)
    return ok


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True)


@pytest.fixture
def machines():
    """Two namespaces joined by a veth pair: {"a": (namespace, address), "b": (...)}."""
    if not _can_make_namespaces():
        pytest.skip("needs root and ip netns")
    tag = uuid.uuid4().hex[:6]
    octet = int(tag[:2], 16) % 250 + 1
    out = {m: (f"mapc{m}{tag}", f"10.239.{octet}.{1 + i}") for i, m in enumerate("ab")}
    veth = {m: f"v{m}{tag}" for m in "ab"}
    for m, (ns, _) in out.items():
        _ip("netns", "add", ns)
    try:
        _ip("link", "add", veth["a"], "type", "veth", "peer", "name", veth["b"])
        for m, (ns, addr) in out.items():
            _ip("link", "set", veth[m], "netns", ns)
            _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", veth[m])
            _ip("-n", ns, "link", "set", veth[m], "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        yield out
    finally:
        for ns, _ in out.values():  # what the test left in its namespaces, and the namespaces
            pids = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True).stdout.split()
            for pid in pids:
                if pid.isdigit() and int(pid) > 1:
                    try:
                        os.kill(int(pid), signal.SIGKILL)
                    except ProcessLookupError:
                        pass
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


_CLIENT = """
import json, time, zenoh
c = zenoh.Config()
c.insert_json5("mode", '"client"')
c.insert_json5("connect/endpoints", '["tcp/127.0.0.1:7447"]')
c.insert_json5("scouting/multicast/enabled", "false")
s = zenoh.open(c)
"""
_PROBES = ["mc/FLEET/probe/**", "elsewhere/probe/**"]


def _router_config(certs: Path, listen: list[str], connect: list[str], fleet: str) -> dict:
    """A router with mutual TLS towards the other machine's router, loopback for this machine's clients,
    and an access control: default deny; this machine's clients (loopback) and the other router (its
    certificate's common name) may use the fleet's keys only."""
    tls = {
        "root_ca_certificate": str(certs / "ca.pem"),
        "listen_certificate": str(certs / "router.pem"),
        "listen_private_key": str(certs / "router-key.pem"),
        "connect_certificate": str(certs / "router.pem"),
        "connect_private_key": str(certs / "router-key.pem"),
        "enable_mtls": True,
        "verify_name_on_connect": True,
    }
    everything = ["put", "delete", "declare_subscriber", "declare_queryable", "query", "reply", "liveliness_token",
                  "declare_liveliness_subscriber", "liveliness_query"]  # fmt: skip
    acl = {
        "enabled": True,
        "default_permission": "deny",
        "rules": [{"id": "fleet", "permission": "allow", "flows": ["ingress", "egress"], "messages": everything,
                   "key_exprs": [f"mc/{fleet}/**"]}],  # fmt: skip
        "subjects": [{"id": "local", "interfaces": ["lo"]}, {"id": "routers", "cert_common_names": ["router"]}],
        "policies": [{"id": "fleet-policy", "rules": ["fleet"], "subjects": ["local", "routers"]}],
    }
    conf = {
        "mode": "router",
        "listen": {"endpoints": listen},
        "scouting": {"multicast": {"enabled": False}, "delay": 0},
        "transport": {"link": {"tx": {"lease": 2000}, "tls": tls}},
        "access_control": acl,
    }
    if connect:
        conf["connect"] = {"endpoints": connect}
    return conf


def test_a_fleet_split_over_two_namespaces_through_tls_routers(tmp_path, fleet_name, machines):
    certs = tmp_path / "certs"
    (ns_a, addr_a), (ns_b, addr_b) = machines["a"], machines["b"]
    subprocess.run(["bash", str(REPO / "deploy/zenoh/secure/gen-test-certs.sh"), str(certs),
                    f"IP:{addr_a},IP:{addr_b},IP:127.0.0.1"], check=True, capture_output=True)  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    procs: list[subprocess.Popen] = []

    def start(ns: str, log: str, *argv: str) -> subprocess.Popen:
        with open(tmp_path / log, "wb") as f:
            p = subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, *argv], stdout=f, stderr=subprocess.STDOUT,
                                 cwd=REPO, env=env, start_new_session=True)  # fmt: skip
        procs.append(p)
        return p

    def run(ns: str, *argv: str, timeout: float = 300) -> subprocess.CompletedProcess:
        return subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-m", "services.cli", *argv],
                              capture_output=True, text=True, timeout=timeout, cwd=REPO, env=env)  # fmt: skip

    configs = {
        "a": _router_config(certs, [f"tls/{addr_a}:7447", "tcp/127.0.0.1:7447"], [], fleet_name),
        "b": _router_config(certs, ["tcp/127.0.0.1:7447"], [f"tls/{addr_a}:7447"], fleet_name),
    }
    for m, conf in configs.items():
        (tmp_path / f"router-{m}.json5").write_text(json.dumps(conf))
    keys = tmp_path / "keys"
    signers = "world,evaluator,host,host-standby,channel,recorder,router-a,router-b"  # each signs its health
    assert run(ns_a, "keys", "init", "--out", str(keys), "--count", "2", "--services", signers).returncode == 0
    try:
        for m, ns in (("a", ns_a), ("b", ns_b)):
            start(ns, f"router-{m}.log", "-m", "services.router", "--fleet", fleet_name, "--id", f"router-{m}",
                  "--zenoh-config", str(tmp_path / f"router-{m}.json5"), "--keys", str(keys))  # fmt: skip
        common = ("--join", "tcp/127.0.0.1:7447", "--fleet", fleet_name, "--vehicles", "2", "--keys", str(keys))
        b = run(ns_b, "fleet", "up", "--detach", "--json", "--manifest", "fleet-host-b", *common,
                "--runs-dir", str(tmp_path / "runs-b"))  # fmt: skip
        assert b.returncode == 0, b.stdout + b.stderr
        a = start(ns_a, "fleet-a.log", "-m", "services.cli", "fleet", "up", "--json", "--no-summary", "--manifest",
                  "fleet-host-a", *common, "--duration", "20", "--network", "ideal", "--runs-dir",
                  str(tmp_path / "runs-a"))  # fmt: skip

        def all_healthy():
            h = run(ns_a, "health", "--fleet", fleet_name, "--json", "--connect", "tcp/127.0.0.1:7447", timeout=60)
            rows = json.loads(h.stdout) if h.stdout.strip() else []
            roles = {(r["role"], r["id"]) for r in rows if r.get("alive")}
            return rows if {("vehicle", "cv0"), ("vehicle", "cv1"), ("host", "host"), ("world", "world")} <= roles else None

        rows = wait_for(all_healthy, timeout=240, what="both machines' services in health", every=2.0)
        # the routers' access control: the fleet's keys cross from B to A, other keys do not
        heard = tmp_path / "heard.txt"
        probes = [k.replace("FLEET", fleet_name) for k in _PROBES]
        listener = start(ns_a, "listener.log", "-c", _CLIENT + textwrap.dedent(f"""
            got = []
            subs = [s.declare_subscriber(k, lambda x: got.append(str(x.key_expr))) for k in {probes!r}]
            time.sleep(8)
            open({str(heard)!r}, "w").write("\\n".join(got))
            s.close()
        """))  # fmt: skip
        time.sleep(3)
        start(ns_b, "talker.log", "-c", _CLIENT + textwrap.dedent(f"""
            for _ in range(20):
                for k in {probes!r}:
                    s.put(k.replace("**", "x"), b"probe")
                time.sleep(0.1)
            s.close()
        """))  # fmt: skip
        assert listener.wait(timeout=60) == 0, (tmp_path / "listener.log").read_text()
        keys_heard = set(heard.read_text().split())
        assert keys_heard == {f"mc/{fleet_name}/probe/x"}, keys_heard
        assert {("router", "router-a"), ("router", "router-b"), ("evaluator", "evaluator")} <= {
            (r["role"], r["id"]) for r in rows
        }
        assert not [r for r in rows if r["state"] == "unverified"], rows  # every status signed by its service
        assert a.wait(timeout=400) == 0, (tmp_path / "fleet-a.log").read_text()[-3000:]
        report = json.loads(next((tmp_path / "runs-a").glob("*/report.json")).read_text())
        ev = report["evaluation"]
        assert ev["evaluated"] > 50 and ev["tx_msgs_total"]["cv1"] > 20, ev  # cv1's priors crossed the routers
        assert ev["vehicle_rmse_by_id_m"]["cv0"] < 0.5, ev["vehicle_rmse_by_id_m"]  # the ego, localized and fused
        assert all(p["exit_codes"] and p["exit_codes"][-1] == 0 for p in report["processes"]), report["processes"]
    finally:
        run(ns_b, "fleet", "down", "--fleet", fleet_name, timeout=180)
        for p in procs:  # each in its own process group (start_new_session)
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=10)
