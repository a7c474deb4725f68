"""The launcher with a real fleet on loopback: up, health, crash and restart, down leaving nothing behind.

Every fleet gets a unique name, its own runs directory and a rendezvous on a free port.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest

from schemas.topics import topic
from services.launcher.app import pointer_path, running_launcher
from services.runtime import ZenohSettings, open_session

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def _state(run_dir: Path) -> dict:
    return json.loads((run_dir / "state.json").read_text())


def _events(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "events.jsonl").read_text().splitlines() if line.strip()]


def test_fleet_up_health_kill_restart_and_down(
    tmp_path, fleet_name, mapc, wait_for, watch_liveliness, process_groups_alive
):
    runs = tmp_path / "runs"
    up = mapc(
        "fleet",
        "up",
        "--detach",
        "--json",
        "--fleet",
        fleet_name,
        "--vehicles",
        "2",
        "--network",
        "ideal",
        # the fixed clock: this test is about health, a crash and a restart; at the adaptive clock's pace on a
        # loaded machine the vehicles' cold starts (starting, not ok) outlast the waits below
        "--time-scale",
        "1",
        "--runs-dir",
        str(runs),
        timeout=240,
    )
    assert up.returncode == 0, up.stdout + up.stderr
    info = json.loads(up.stdout)
    run_dir = Path(info["run_dir"])
    try:
        state = _state(run_dir)
        assert state["status"] == "running"
        names = {p["name"] for p in state["processes"]}
        assert names == {"evaluator", "host", "host-standby", "channel", "vehicle-cv0", "vehicle-cv1", "world"}
        pgids = {p["pgid"] for p in state["processes"]} | {info["launcher_pid"]}

        elsewhere = tmp_path / "elsewhere"
        elsewhere.mkdir()
        status = mapc("fleet", "status", "--json", "--fleet", fleet_name, cwd=elsewhere)  # from any directory
        assert status.returncode == 0
        fleets = json.loads(status.stdout)
        assert [f["fleet"] for f in fleets] == [fleet_name] and fleets[0]["endpoints"]

        # the same fleet again: refused with the reason, before anything starts
        again = mapc("fleet", "up", "--detach", "--fleet", fleet_name, "--runs-dir", str(tmp_path / "again"))
        assert again.returncode == 2 and "already running" in again.stderr, again.stderr
        assert not (tmp_path / "again").exists()

        # every expected service answers and is healthy (after the first frames have flowed)
        def healthy():
            h = mapc("health", "--fleet", fleet_name, "--json", cwd=elsewhere)
            rows = json.loads(h.stdout) if h.stdout.strip() else []
            ok = h.returncode == 0 and len(rows) == 7 and all(r["state"] == "ok" for r in rows)
            return rows if ok else None  # (starting while a vehicle searches for its pose: exit 0 too)

        rows = wait_for(healthy, timeout=60, what="all seven services ok", every=0.5)
        assert {(r["role"], r["id"]) for r in rows} == {
            ("evaluator", "evaluator"),
            ("host", "host"),
            ("host", "host-standby"),
            ("channel", "channel"),
            ("vehicle", "cv0"),
            ("vehicle", "cv1"),
            ("world", "world"),
        }
        assert all(r["state"] == "ok" for r in rows)

        # SIGKILL a vehicle: its token disappears within 2 s and the launcher restarts it
        endpoint = next(e for e in state["endpoints"] if "127.0.0.1" in e)
        session = open_session(ZenohSettings(connect=[endpoint], config_file=state["zenoh_login"]))  # the operator
        try:
            alive = watch_liveliness(session, topic("alive").pattern(fleet=fleet_name))
            key = topic("alive").key(fleet=fleet_name, role="vehicle", id="cv1")
            alive.wait_alive(key, timeout=10)
            victim = next(p for p in state["processes"] if p["name"] == "vehicle-cv1")
            t_kill_wall = time.time()
            t_kill = time.monotonic()
            os.kill(victim["pid"], signal.SIGKILL)
            seen_gone = alive.wait_gone(key, timeout=5)
            assert seen_gone - t_kill < 2.0
            alive.wait_alive(key, timeout=60)  # back: restarted by the launcher
        finally:
            session.close()

        def restarted():
            ev = [e for e in _events(run_dir) if e["process"] == "vehicle-cv1" and e["t_wall"] >= t_kill_wall - 0.5]
            kinds = [e["event"] for e in ev]
            return ev if {"exited", "started", "ready"} <= set(kinds) else None

        ev = wait_for(restarted, timeout=30, what="the launcher's restart events")
        exited = next(e for e in ev if e["event"] == "exited")
        assert exited["returncode"] == -signal.SIGKILL
        assert exited["t_wall"] - t_kill_wall < 2.0

        def restarted_in_state():  # state.json is rewritten periodically: it may lag the event log
            v = next(p for p in _state(run_dir)["processes"] if p["name"] == "vehicle-cv1")
            return v if v["restarts"] >= 1 else None

        vehicle = wait_for(restarted_in_state, timeout=10, what="the restart in state.json")
        assert vehicle["restarts"] == 1 and vehicle["pid"] != victim["pid"]
        pgids.add(vehicle["pgid"])
    finally:
        down = mapc("fleet", "down", "--fleet", fleet_name, timeout=180, cwd=tmp_path)
    assert down.returncode == 0, down.stdout + down.stderr
    assert "no process left" in down.stdout
    assert process_groups_alive(pgids) == []
    assert not (pointer_path(fleet_name, "local")).exists()
    assert _state(run_dir)["status"] == "stopped"
    report = json.loads((run_dir / "report.json").read_text())
    assert report["summary"]["restarts"] == 1
    assert {p["name"]: p["state"] for p in report["processes"]}["world"] == "stopped"
    assert (run_dir / "logs" / "vehicle-cv1.log").read_text().count("start:") == 2
    assert mapc("fleet", "status", "--fleet", fleet_name).returncode == 1


@pytest.mark.parametrize(("mode", "network"), [("distributed", "dsrc"), ("centralized", "ideal")])
def test_fleet_runs_for_a_duration_and_writes_its_report(tmp_path, fleet_name, mapc, mode, network):
    runs = tmp_path / "runs"
    proc = mapc(
        "fleet",
        "up",
        "--fleet",
        fleet_name,
        "--mode",
        mode,
        "--vehicles",
        "2",
        "--duration",
        "6",
        "--network",
        network,
        # centralized: the host localizes every vehicle itself (about 0.26 s of CPU per frame for two
        # vehicles starting cold with the realistic errors), so it runs on a clock at a quarter of real time
        "--time-scale",
        "0.25" if mode == "centralized" else "1",
        "--runs-dir",
        str(runs),
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    lines = proc.stdout.strip().splitlines()
    assert any("up 7/7" in line for line in lines), lines[:5]  # with the warm standby
    # the run ends with the table a person reads; its last line names the run directory
    assert lines[-1].strip().startswith("run dir"), lines[-12:]
    assert any(line.strip().startswith("objects") for line in lines[-12:]), lines[-12:]
    run_dir = Path(lines[-1].split()[2])
    summary = json.loads((run_dir / "report.json").read_text())["summary"]
    assert summary["restarts"] == 0 and summary["fleet"] == fleet_name
    for name in (
        "config.json",
        "state.json",
        "events.jsonl",
        "metrics.jsonl",
        "report.json",
        "eval_summary.json",
        "birdseye.png",
        "errors.png",
        "logs/world.log",
        "logs/host.log",
    ):
        assert (run_dir / name).stat().st_size > 0, name
    config = json.loads((run_dir / "config.json").read_text())
    assert config["params"]["fleet"] == fleet_name and len(config["processes"]) == 7  # with the warm standby
    assert config["params"]["mode"] == mode
    ev = json.loads((run_dir / "eval_summary.json").read_text())
    assert ev["evaluated"] > 10
    assert ev["tx_msgs_total"]["cv0"] > 10
    # a prior is a few hundred bytes; raw observations (with the lane mask) several kB
    assert 0 < ev["tx_bytes_per_msg"]["cv1"] < (2000 if mode == "distributed" else 50_000)
    assert ev["delivered_fraction"] is not None and ev["delivered_fraction"] > 0.8
    assert ev["vehicle_rmse_m"] is not None and ev["object_rmse_m"] is not None
    metrics = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert len(metrics) >= 3 and metrics[-1]["fleet"] == fleet_name
    report = json.loads((run_dir / "report.json").read_text())
    assert all(p["exit_codes"] and p["exit_codes"][-1] == 0 for p in report["processes"]), report["processes"]
    assert not (pointer_path(fleet_name, "local")).exists()


def test_ctrl_c_stops_the_fleet_writes_the_report_and_exits_130(
    tmp_path, fleet_name, spawn, wait_for, process_groups_alive
):
    fleet = spawn(
        "services.cli",
        *("fleet", "up", "--fleet", fleet_name, "--vehicles", "1", "--network", "ideal"),
        *("--runs-dir", str(tmp_path / "runs"), "--no-summary", "--json"),
        name="fleet",
    )

    def running():
        ptr = running_launcher(fleet_name, "local")
        state = ptr and json.loads((Path(ptr["run_dir"]) / "state.json").read_text() or "{}")
        return state if state and state.get("status") == "running" else None

    state = wait_for(running, timeout=180, what="the fleet running", every=0.5)
    fleet.send_signal(signal.SIGINT)
    assert fleet.wait(timeout=120) == 130  # not 0: the run was cut short
    run_dir = Path(state["run_dir"])
    assert json.loads((run_dir / "report.json").read_text())["summary"]["fleet"] == fleet_name
    out = fleet.log_path.read_text().splitlines()  # --no-summary: no live line, but the start and the end (--json)
    assert any("ready: world" in line for line in out) and json.loads(out[-1])["fleet"] == fleet_name
    assert process_groups_alive({p["pgid"] for p in state["processes"]}) == []
    assert not (pointer_path(fleet_name, "local")).exists()


def test_a_standby_host_publishes_while_the_host_is_gone(tmp_path, fleet_name, mapc, wait_for, watch_liveliness):
    """mapc fleet up --standby: a second host fuses the same input and publishes the fused state on the
    host's key only while the host's liveliness token is gone (SIGKILL to its process group here), so the
    fused output goes on while the launcher restarts the host, and stops doubling once it is back."""
    from mapcontainer.security import inner_payload
    from schemas import FusedState, decode

    runs = tmp_path / "runs"
    up = mapc(
        *("fleet", "up", "--detach", "--json", "--fleet", fleet_name, "--vehicles", "2", "--network", "ideal"),
        *("--standby", "--runs-dir", str(runs)),
        timeout=240,
    )
    assert up.returncode == 0, up.stdout + up.stderr
    info = json.loads(up.stdout)
    run_dir = Path(info["run_dir"])
    try:
        state = _state(run_dir)
        assert {p["name"] for p in state["processes"]} >= {"host", "host-standby"}
        endpoint = next(e for e in state["endpoints"] if "127.0.0.1" in e)
        session = open_session(ZenohSettings(connect=[endpoint], config_file=state["zenoh_login"]))  # the operator
        got: list[tuple[float, str]] = []  # (monotonic arrival, the fusing host's id)

        def on_fused(sample) -> None:
            msg = decode(inner_payload(sample.payload.to_bytes()), FusedState)  # signed by the host or its standby
            if msg:
                got.append((time.monotonic(), msg.sender))

        try:
            alive = watch_liveliness(session, topic("alive").pattern(fleet=fleet_name))
            key = topic("alive").key(fleet=fleet_name, role="host", id="host")
            alive.wait_alive(key, timeout=30)
            sub = session.declare_subscriber(topic("fused").key(fleet=fleet_name, hid="host"), on_fused)
            wait_for(lambda: len(got) >= 20, timeout=120, what="fused output", every=0.2)
            host = next(p for p in state["processes"] if p["name"] == "host")
            t_kill = time.monotonic()
            os.killpg(host["pgid"], signal.SIGKILL)
            alive.wait_gone(key, timeout=5)
            alive.wait_alive(key, timeout=90)  # restarted by the launcher
            t_back = time.monotonic()
            wait_for(lambda: any(t > t_back + 2 and s == "host" for t, s in got), timeout=60, what="the host again")
            sub.undeclare()
        finally:
            session.close()
    finally:
        down = mapc("fleet", "down", "--fleet", fleet_name, timeout=180)
    assert down.returncode == 0, down.stdout + down.stderr
    before = [s for t, s in got if t < t_kill]
    during = [s for t, s in got if t_kill + 0.5 < t < t_back]
    after = [s for t, s in got if t > t_back + 2]
    assert set(before) == {"host"}  # the standby is silent while the host is there
    assert during and set(during) == {"host-standby"}, got  # ... and speaks while it is gone
    assert after and set(after) == {"host"}
    arrivals = [t for t, _ in got if t_kill - 1 < t < t_back]
    gap = max(b - a for a, b in zip(arrivals, arrivals[1:], strict=False))
    print(f"fused output gap after SIGKILL of the host: {gap:.2f} s; host back after {t_back - t_kill:.1f} s")


def test_fleet_down_removes_the_shared_memory_of_killed_processes(tmp_path, fleet_name, mapc, wait_for):
    """The probe: fleets whose processes were killed left their ``*.zenoh`` segments (and the host's
    multiprocessing semaphores) in /dev/shm. The launcher notes what its processes map; after a SIGKILL of
    the host (which cannot clean up) and ``fleet down``, none of it is left."""
    import os
    import signal

    up = mapc(
        *("fleet", "up", "--detach", "--json", "--fleet", fleet_name, "--vehicles", "1", "--network", "ideal"),
        *("--runs-dir", str(tmp_path / "runs")),
        timeout=240,
    )
    assert up.returncode == 0, up.stdout + up.stderr
    run_dir = Path(json.loads(up.stdout)["run_dir"])
    try:
        host = next(p for p in _state(run_dir)["processes"] if p["name"] == "host")
        segments = wait_for(
            lambda: [s for s in _state(run_dir).get("shm", []) if Path(s).exists()], timeout=30, what="noted segments"
        )
        os.killpg(host["pgid"], signal.SIGKILL)  # the host and its fusion worker: no chance to clean up
    finally:
        down = mapc("fleet", "down", "--fleet", fleet_name, timeout=180)
    assert down.returncode == 0, down.stdout + down.stderr
    noted = set(_state(run_dir).get("shm", []))
    assert set(segments) <= noted and any(s.endswith(".zenoh") for s in noted), noted
    assert [s for s in noted if Path(s).exists()] == []


def test_the_default_fleet_admits_only_its_own_processes_each_to_its_own_keys(tmp_path, fleet_name, mapc, wait_for):
    """The probe: the default mesh had no authentication. Now a client without the run's login cannot join
    (so it can neither publish nor subscribe); a vehicle's login cannot put on another vehicle's key or the
    host's fused key; the operator's login (what mapc health uses) sees the fleet."""
    import zenoh

    from services.launcher.mesh import login_path

    up = mapc(
        *("fleet", "up", "--detach", "--json", "--fleet", fleet_name, "--vehicles", "2", "--network", "ideal"),
        *("--runs-dir", str(tmp_path / "runs")),
        timeout=240,
    )
    assert up.returncode == 0, up.stdout + up.stderr
    run_dir = Path(json.loads(up.stdout)["run_dir"])
    endpoint = next(e for e in _state(run_dir)["endpoints"] if "127.0.0.1" in e)
    try:
        assert _state(run_dir)["insecure"] is False and oct(login_path(run_dir, "ops").stat().st_mode)[-3:] == "600"
        anonymous = ZenohSettings(mode="client", connect=[endpoint], connect_timeout_ms=1000)
        with pytest.raises(Exception):  # noqa: B017 - Zenoh's error for a refused login
            open_session(anonymous).close()
        wrong = json.loads(login_path(run_dir, "vehicle-cv0").read_text())
        wrong["transport"]["auth"]["usrpwd"]["password"] = "guessed"
        (tmp_path / "wrong.json5").write_text(json.dumps(wrong))
        with pytest.raises(Exception):  # noqa: B017
            open_session(ZenohSettings(connect=[endpoint], config_file=str(tmp_path / "wrong.json5"))).close()

        def login(user: str):
            return open_session(ZenohSettings(connect=[endpoint], config_file=str(login_path(run_dir, user))))

        ops, cv0 = login("ops"), login("vehicle-cv0")
        try:
            got: list[tuple[str, bytes]] = []
            sub = ops.declare_subscriber(
                f"mc/{fleet_name}/**", lambda s: got.append((str(s.key_expr), s.payload.to_bytes()))
            )
            mine = topic("prior_tx").key(fleet=fleet_name, src="cv0")
            theirs = [topic("prior_tx").key(fleet=fleet_name, src="cv1"), topic("fused").key(fleet=fleet_name, hid="host")]
            wait_for(lambda: any(k == mine for k, _ in got), timeout=30, what="cv0's priors at the operator")
            for _ in range(20):
                for key in theirs:
                    cv0.put(key, b"\x92forged")
                time.sleep(0.05)
            time.sleep(1.0)
            assert [k for k, p in got if p == b"\x92forged"] == []  # nothing of cv0 reached those keys
            assert any(k == theirs[1] for k, _ in got)  # while the host's own fused states did
            sub.undeclare()
        finally:
            ops.close()
            cv0.close()
        health = mapc("health", "--fleet", fleet_name, "--json")
        assert health.returncode in (0, 1) and len(json.loads(health.stdout)) == 7, health.stdout + health.stderr
        host = next(v for v in json.loads(health.stdout) if v["role"] == "host")
        assert host["rejects"].get("unsigned", 0) == 0  # the forged puts never reached the host
    finally:
        mapc("fleet", "down", "--fleet", fleet_name, timeout=180)
