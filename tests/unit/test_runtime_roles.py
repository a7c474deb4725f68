"""The roles' pure pieces: world pacing, manifests, restart backoff, frame gate, relay, evaluator."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from mapcontainer.config import ConfigError
from mapcontainer.sim.config import load_scenario
from schemas import FusedState, GroundTruth
from services.channel.app import Relay, parse_receivers
from services.evaluator.core import Evaluator, match_objects
from services.evaluator.plot import ellipse_params
from services.host.app import fused_lag, fusion_stall, lag_causes
from services.launcher.app import parse_args as launcher_parse_args
from services.launcher.control import launcher_argv
from services.launcher.manifest import FleetParams, Manifest, RestartPolicy, load_manifest, resolve
from services.world.core import Pacer, scale_scenario

# ------------------------------------------------------------------------------ world


def test_pacer_maps_frames_to_wall_time() -> None:
    p = Pacer(epoch_wall_ns=10**12, dt=0.1, time_scale=0.5)
    assert p.due_wall_ns(0) == 10**12
    assert p.due_wall_ns(10) == 10**12 + 2 * 10**9  # 1 s of scenario at half speed
    assert p.first_k_at(10**12 + 2 * 10**9) == 10
    assert p.first_k_at(10**12 + 2 * 10**9 + 1) == 11
    assert p.first_k_at(0) == 0
    with pytest.raises(ValueError):
        Pacer(0, 0.0, 1.0)


def test_scale_scenario_trims_and_extends() -> None:
    sc = load_scenario("paper-urban")
    assert scale_scenario(sc, None) is sc
    assert len(scale_scenario(sc, 2).connected) == 2
    big = scale_scenario(sc, 9)
    assert len(big.connected) == 9 and big.connected[:4] == sc.connected
    with pytest.raises(ValueError):
        scale_scenario(sc, 0)


# ------------------------------------------------------------------------------ manifest


def test_default_manifest_resolves() -> None:
    m = load_manifest()
    specs = resolve(m, FleetParams(fleet="f1", vehicles=3, duration_s=None), "/tmp/run", "tcp/127.0.0.1:9")
    names = [s.name for s in specs]
    assert names[0] == "evaluator" and names[-1] == "world"
    assert {"vehicle-cv0", "vehicle-cv1", "vehicle-cv2", "host", "channel"} <= set(names)
    orders = [s.start_order for s in specs]
    assert orders == sorted(orders)
    world = specs[-1]
    assert "--duration" not in world.argv  # optional pair left out
    assert world.argv[world.argv.index("--vehicles") + 1] == "3"
    for s in specs:
        a = s.argv
        assert a[1:3] == ["-m", s.module]
        assert a[a.index("--fleet") + 1] == "f1" and a[a.index("--id") + 1] == s.id
        assert a[a.index("--connect") + 1] == "tcp/127.0.0.1:9"
    host = next(s for s in specs if s.role == "host")
    assert host.argv[host.argv.index("--known-senders") + 1] == "cv0,cv1,cv2"
    with_duration = resolve(m, FleetParams(duration_s=12.0), "/tmp/run", "tcp/x:1")
    assert with_duration[-1].argv[with_duration[-1].argv.index("--duration") + 1] == "12.0"


def test_a_fleet_runs_as_many_vehicles_as_its_scenario_unless_told() -> None:
    m = load_manifest()
    for scenario, n in [("overlap", 2), ("blindspot-beyond", 2), ("paper-urban", 4)]:
        params = m.defaults.model_copy(update={"scenario": scenario})
        specs = resolve(m, params, "/tmp/run", "tcp/x:1")
        assert len(load_scenario(scenario).connected) == n
        assert sorted(s.id for s in specs if s.role == "vehicle") == [f"cv{i}" for i in range(n)]
        world = next(s for s in specs if s.role == "world")
        assert "--vehicles" not in world.argv  # the world keeps the scenario's own vehicles
    told = resolve(m, m.defaults.model_copy(update={"scenario": "overlap", "vehicles": 3}), "/r", "tcp/x:1")
    assert len([s for s in told if s.role == "vehicle"]) == 3


def test_manifest_errors_name_the_problem() -> None:
    base = {
        "name": "m",
        "processes": [
            {"name": "a", "module": "services.world", "role": "world", "id": "w", "args": ["--x", "{nope}"]}
        ],
    }
    with pytest.raises(ConfigError, match="nope"):
        resolve(Manifest.model_validate(base), FleetParams(), "/r", "tcp/x:1")
    dup = {
        "name": "m",
        "processes": [
            {"name": "a", "module": "m", "role": "r", "id": "i"},
            {"name": "a", "module": "m", "role": "r", "id": "j"},
        ],
    }
    with pytest.raises(ConfigError, match="unique"):
        resolve(Manifest.model_validate(dup), FleetParams(), "/r", "tcp/x:1")
    none_arg = {
        "name": "m",
        "processes": [{"name": "a", "module": "m", "role": "r", "id": "i", "args": ["{duration_s}"]}],
    }
    with pytest.raises(ConfigError, match="pair"):
        resolve(Manifest.model_validate(none_arg), FleetParams(), "/r", "tcp/x:1")


def test_a_process_with_when_runs_only_when_its_fleet_parameter_is_true() -> None:
    m = load_manifest("fleet")
    names = {sp.name for sp in resolve(m, FleetParams(), "/r", "tcp/x:1")}
    assert "host-standby" not in names and "host" in names
    standby = {sp.name: sp for sp in resolve(m, FleetParams(standby=True), "/r", "tcp/x:1")}["host-standby"]
    assert (standby.role, standby.id) == ("host", "host-standby")
    assert standby.argv[standby.argv.index("--standby-for") + 1] == "host"
    bad = {"name": "m", "processes": [{"name": "a", "module": "m", "role": "r", "id": "i", "when": "scenario"}]}
    with pytest.raises(ConfigError, match="not a boolean fleet parameter"):
        resolve(Manifest.model_validate(bad), FleetParams(), "/r", "tcp/x:1")


def test_restart_policy_backoff() -> None:
    p = RestartPolicy(backoff_initial_s=0.5, backoff_factor=2.0, backoff_max_s=3.0, max_restarts=5)
    assert [p.delay_s(n) for n in range(1, 6)] == [0.5, 1.0, 2.0, 3.0, 3.0]
    assert p.wants_restart(-9, 0) and p.wants_restart(1, 4)
    assert not p.wants_restart(0, 0)  # on-failure: a clean exit stays down
    assert not p.wants_restart(1, 5)  # gave up
    assert RestartPolicy(policy="always").wants_restart(0, 0)
    assert not RestartPolicy(policy="never").wants_restart(-9, 0)
    with pytest.raises(ValueError):
        p.delay_s(0)


def test_detached_launcher_command_line_round_trips(tmp_path) -> None:
    s = launcher_parse_args(
        [
            "--fleet",
            "abc",
            "--vehicles",
            "2",
            "--duration",
            "5",
            "--network",
            "ideal",
            "--runs-dir",
            str(tmp_path),
        ]
    )
    argv = launcher_argv(s, tmp_path / "run")
    back = launcher_parse_args(argv[3:])
    assert back.params == s.params
    assert back.run_dir == str(tmp_path / "run") and not back.summary


def test_host_stall_names_the_rejections_since_the_last_fused_state() -> None:
    then, now = {"stale": 4, "duplicate": 1}, {"stale": 40, "duplicate": 1, "future": 2}
    why = fusion_stall(5.0, 0.1, now, then, stall_s=3.0)
    assert why is not None and "nothing was fused for 5.0 s" in why and "36 stale, 2 future" in why
    assert "duplicate" not in why  # none since the last fused state
    assert fusion_stall(2.0, 0.1, now, then, stall_s=3.0) is None  # fused recently
    assert fusion_stall(5.0, 4.0, now, then, stall_s=3.0) is None  # no input: the generic "input stalled"
    assert fusion_stall(5.0, None, now, then, stall_s=3.0) is None  # never had input
    assert fusion_stall(5.0, 0.1, now, then, stall_s=None) is None  # check disabled
    assert "(rejected since then: none)" in fusion_stall(5.0, 0.1, then, then, stall_s=3.0)


# ------------------------------------------------------------------------------ channel relay


def test_relay_delivers_after_the_link_latency_and_keeps_attachments() -> None:
    from mapcontainer.channel import Channel, NetworkProfile

    clk = [0.0]
    relay = Relay(
        Channel(NetworkProfile.custom(latency_ms=20.0), seed=1), {"host": ["cv0"]}, clock=lambda: clk[0]
    )
    relay.offer("prior", "cv1", b"payload-1", {"epoch_wall_ns": 5})
    relay.offer("prior", "cv1", b"payload-1", {"epoch_wall_ns": 1})  # an attacker's copy: its attachment is ignored
    relay.offer("prior", "cv0", b"payload-0", {})  # on board the host: not relayed
    stop = threading.Event()
    clk[0] = 0.019
    assert relay.due(stop, max_wait_s=0.0) == []
    clk[0] = 0.021
    out = relay.due(stop, max_wait_s=0.0)
    assert len(out) == 2 and out[0][2] == out[1][2]  # the copy is relayed (the receiver refuses it as a replay)
    d, kind, att, late = out[0]
    assert (d.src, d.dst, d.payload, kind, att) == (
        "cv1",
        "host",
        b"payload-1",
        "prior",
        {"epoch_wall_ns": 5},
    )
    assert late == pytest.approx(0.001)
    st = relay.stats()
    assert st["offered_msgs"] == 2 and st["delivered_fraction"] == 1.0
    assert parse_receivers(["host=cv0,cv9", "rsu"]) == {"host": ["cv0", "cv9"], "rsu": []}
    assert parse_receivers(None) == {"host": []}


# ------------------------------------------------------------------------------ evaluator


def _truth(t: float, p_vehicle, p_obstacles) -> GroundTruth:
    n = len(p_obstacles)
    return GroundTruth(
        fleet="f",
        sender="world",
        seq=int(t * 10),
        t_meas=t,
        t_sent=t,
        vehicle_ids=["cv0"],
        vehicle_pose=np.array([[*p_vehicle, 0, 0, 0, 0]], float),
        vehicle_v_map=np.zeros((1, 3)),
        obstacle_id=np.arange(1, n + 1, dtype=np.uint32),
        obstacle_cls=np.ones(n, np.uint8),
        obstacle_p_map=np.array([[*p, 0] for p in p_obstacles], float).reshape(-1, 3),
        obstacle_v_map=np.zeros((n, 3)),
        obstacle_yaw=np.zeros(n),
    )


def _fused(t: float, p_vehicle, p_objects) -> FusedState:
    n = len(p_objects)
    cov6 = [0.04, 0, 0, 0.04, 0, 0.04]
    cov21 = np.zeros(21)
    cov21[[0, 6, 11, 15, 18, 20]] = 0.01
    return FusedState(
        fleet="f",
        sender="host",
        seq=int(t * 10),
        t_meas=t,
        t_sent=t,
        vehicle_ids=["cv0"],
        vehicle_pose=np.array([[*p_vehicle, 0, 0, 0, 0]], float),
        vehicle_pose_cov=cov21[None],
        object_id=np.arange(n, dtype=np.uint32),
        object_cls=np.ones(n, np.uint8),
        object_p_map=np.array([[*p, 0] for p in p_objects], float).reshape(-1, 3),
        object_v_map=np.zeros((n, 3)),
        object_cov=np.array([cov6] * n, float).reshape(-1, 6),
    )


def test_evaluator_rmse_latency_and_bandwidth() -> None:
    ev = Evaluator("f", window_s=5.0, onboard={"host": {"cv0"}}, settle_s=0.5)
    for k in range(10):
        t = k * 0.1
        ev.on_truth(_truth(t, (10.0 + t, 0.0), [(0.0, 0.0), (20.0, 0.0)]))
        # vehicle 0.3 m off in x, objects 0.4 m off in y, one false object far away
        ev.on_fused(
            _fused(t, (10.3 + t, 0.0), [(0.0, 0.4), (20.0, -0.4), (50.0, 50.0)]),
            pub_wall_ns=int((100 + t) * 1e9) + 50_000_000,
            t_meas_wall_ns=int((100 + t) * 1e9),
            now_wall=100 + t,
        )
        ev.on_tx("cv1", k, 400, now_wall=100 + t)
        ev.on_tx("cv0", k, 380, now_wall=100 + t)
        if k != 3:  # one loss on cv1 -> host; cv0 is on board and not counted
            ev.on_rx("host", "cv1", k, now_wall=100 + t + 0.02)
    m = ev.snapshot(101.0)
    assert m.evaluated == 10 and m.no_truth == 0
    assert m.vehicle_rmse_m == pytest.approx(0.3, abs=1e-5)
    assert m.object_rmse_m == pytest.approx(0.4, abs=1e-5)
    assert (m.objects_fused, m.objects_matched, m.obstacles_truth) == (3, 2, 2)
    assert m.e2e_latency_ms_p50 == pytest.approx(50.0, abs=0.01)
    assert m.tx_bytes_per_s == {"cv0": 380 * 10 / 5.0, "cv1": 400 * 10 / 5.0}
    assert m.tx_bytes_per_msg == {"cv0": 380.0, "cv1": 400.0}
    assert m.delivered_fraction == pytest.approx(5 / 6)  # sent by 100.5: k = 0..5, k = 3 lost
    s = ev.summary()
    assert s["vehicle_rmse_by_id_m"]["cv0"] == pytest.approx(0.3, abs=1e-5)
    assert s["tx_msgs_total"] == {"cv0": 10, "cv1": 10}


def test_evaluator_steady_state_leaves_the_burn_in_out() -> None:
    """Before burnin_s the vehicle is 2 m off (a cold start), after it 0.1 m: steady state sees only the
    latter, the whole run both; coverage and false tracks count from the burn-in on."""
    ev = Evaluator("f", burnin_s=1.0)
    for k in range(20):
        t = k * 0.1
        ev.on_truth(_truth(t, (0.0, 0.0), [(0.0, 0.0), (20.0, 0.0)]))
        off, objects = (2.0, [(0.0, 0.3)]) if t < 1.0 else (0.1, [(0.0, 0.3), (60.0, 0.0)])
        ev.on_fused(_fused(t, (off, 0.0), objects), None, None, now_wall=100 + t)
    s = ev.summary()
    assert s["burnin_s"] == 1.0
    assert s["vehicle_rmse_steady_m"] == pytest.approx(0.1) and s["vehicle_rmse_steady_by_id_m"] == {
        "cv0": pytest.approx(0.1)
    }
    assert s["vehicle_rmse_m"] == pytest.approx(np.sqrt((10 * 4.0 + 10 * 0.01) / 20))
    assert s["object_rmse_steady_m"] == pytest.approx(0.3)
    assert s["object_coverage_steady"] == pytest.approx(0.5)  # one of the two obstacles, every frame
    assert s["false_track_fraction_steady"] == pytest.approx(0.5)  # the object at (60, 0) matches nothing


def test_a_vehicles_fused_track_breaks_where_it_was_absent() -> None:
    """The picture does not draw a chord across a gap in a vehicle's fused poses."""
    ev = Evaluator("f")
    empty = _fused(0.1, (0, 0), []).model_copy(
        update={"vehicle_ids": [], "vehicle_pose": np.zeros((0, 6)), "vehicle_pose_cov": np.zeros((0, 21))}
    )
    for k, fused in enumerate([_fused(0.0, (0, 0), []), empty, empty, _fused(0.3, (9, 0), [])]):
        ev.on_truth(_truth(0.1 * k, (0, 0), []))
        ev.on_fused(fused, None, None, now_wall=10.0 + k)
    ev.snapshot(20.0)
    txy = np.array(ev.tracks_fused["cv0"])
    assert txy.shape == (3, 3) and np.isnan(txy[1, 1:]).all() and txy[2, 1] == 9  # one break, then on


def test_evaluator_waits_for_truth_then_gives_up() -> None:
    ev = Evaluator("f")
    ev.on_fused(_fused(1.0, (0, 0), []), None, None, now_wall=10.0)
    assert ev.evaluated == 0
    ev.on_truth(_truth(1.0, (0.1, 0), []))
    ev.snapshot(10.5)
    assert ev.evaluated == 1
    ev.on_fused(
        _fused(0.5, (0, 0), []), None, None, now_wall=11.0
    )  # older than any truth kept? no truth at 0.5
    ev.snapshot(11.0)
    assert ev.no_truth == 1


def test_match_objects_gates() -> None:
    ti, fi = match_objects(
        np.array([[0.0, 0.0, 0], [10, 0, 0]]), np.array([[0.5, 0, 0], [30, 0, 0]]), gate_m=3.0
    )
    assert ti.tolist() == [0] and fi.tolist() == [0]
    assert match_objects(np.zeros((0, 3)), np.zeros((2, 3)))[0].size == 0


def test_ellipse_params() -> None:
    w, h, ang = ellipse_params(np.diag([4.0, 1.0]), n_sigma=2.0)
    assert (w, h) == pytest.approx((8.0, 4.0))
    assert abs(ang) % 180 == pytest.approx(0.0, abs=1e-9)


def test_the_fusion_loop_survives_a_payload_that_breaks_the_core(monkeypatch) -> None:
    """ingest refuses bad input itself; should a defect make it raise, the loop reports the error,
    counts the payload as ``ingest_error`` and keeps fusing (it used to die with the first one)."""
    import queue

    from mapcontainer.fusion import Container
    from mapcontainer.host import HostSetup
    from schemas import encode
    from services.host.worker import fusion_loop
    from unit.test_fusion_container import prior

    real = Container.ingest

    def ingest(self, payload, t_recv):
        if payload == b"boom":
            raise OverflowError("a defect")
        return real(self, payload, t_recv)

    monkeypatch.setattr(Container, "ingest", ingest)
    setup = HostSetup(fleet="f", known_senders=("cv0",))
    inbox, outbox = queue.Queue(), queue.Queue()
    th = threading.Thread(target=fusion_loop, args=(setup, inbox, outbox), daemon=True)
    th.start()
    assert outbox.get(timeout=60)[0] == "ready"
    inbox.put(("ingest", b"boom", 0.0))
    error = outbox.get(timeout=30)
    fused = []
    for k in range(3):
        inbox.put(("ingest", encode(prior(seq=k, t=0.1 * k)), 0.1 * k))
        fused.append(outbox.get(timeout=30))
    inbox.put(("stop",))
    th.join(timeout=10)
    assert error[0] == "error" and "OverflowError: a defect" in error[1]
    assert [(item[0], round(item[2], 1)) for item in fused] == [("fused", 0.0), ("fused", 0.1), ("fused", 0.2)]
    assert [r[:2] for r in fused[0][-1]] == [(False, "ingest_error"), (True, None)] and not th.is_alive()


@pytest.mark.parametrize("pub_wall_ns", [1, 10**18 * 9])
def test_a_forged_publish_time_is_left_out_of_the_latency_and_counted(pub_wall_ns: int) -> None:
    """t_wall_ns = 1 in a fused state's attachment made a latency of -1e12 ms, which no EvalMetrics
    accepts: the evaluator's thread died on its next snapshot."""
    ev = Evaluator("f")
    ev.on_truth(_truth(0.0, (0.0, 0.0), []))
    ev.on_fused(_fused(0.0, (0.1, 0.0), []), pub_wall_ns=pub_wall_ns, t_meas_wall_ns=10**18, now_wall=5.0)
    ev.on_truth(_truth(0.1, (0.0, 0.0), []))
    ev.on_fused(_fused(0.1, (0.1, 0.0), []), pub_wall_ns=10**18 + 150_000_000, t_meas_wall_ns=10**18, now_wall=5.1)
    m = ev.snapshot(5.2)
    assert m.evaluated == 2 and m.e2e_latency_ms_p50 == pytest.approx(150.0)
    assert ev.summary()["latency_refused"] == 1


def test_the_evaluator_counts_at_most_max_sources_senders() -> None:
    from services.evaluator.core import MAX_SOURCES

    ev = Evaluator("f")
    for i in range(MAX_SOURCES + 50):
        ev.on_tx(f"s{i}", 0, 100, now_wall=1.0)
        ev.on_rx("host", f"s{i}", 0, now_wall=1.01)
    ev.on_rx("host", "never-sent", 0, now_wall=1.02)
    assert len(ev.tx_msgs_total) == MAX_SOURCES and ev.summary()["sources_refused"] == 50
    assert all(key[1] != "never-sent" for key in ev._rx_seen)


def test_a_host_that_does_not_keep_up_says_so() -> None:
    assert fused_lag(10.0, 9.8, time_scale=1.0, max_lag_s=1.0) is None
    why = fused_lag(10.0, 7.9, time_scale=1.0, max_lag_s=1.0)
    assert why is not None and "2.1 s" in why and "not keeping up" in why
    assert fused_lag(10.0, 7.9, time_scale=4.0, max_lag_s=1.0) is None  # 2.1 scenario s are 0.5 wall s
    assert fused_lag(None, 7.9, 1.0, 1.0) is None and fused_lag(10.0, None, 1.0, 1.0) is None


def test_a_lagging_host_names_the_cause() -> None:
    """The probe's lag of 1.8 billion seconds named no cause: the reason lists what the host sees."""
    causes = lag_causes(180.0, 100.0, 40, 2, "cv1", {"stale": 300, "flood": 5}, {"stale": 28, "flood": 5})
    assert causes == [
        "solves take 180 ms, frames come every 100 ms",
        "40 messages wait for the fusion worker",
        "the world's clock changed 2 times, last in a message of cv1",
        "refused since the last fused state: 272 stale",
    ]
    why = fused_lag(10.0, 7.9, 1.0, 1.0, causes)
    assert why.startswith("the fused output trails the world by 2.1 s") and "272 stale" in why
    assert lag_causes(50.0, 100.0, 0, 0, None, {"stale": 3}, {"stale": 3}) == []


def test_the_evaluators_traces_stay_bounded_over_any_run_length() -> None:
    """The evaluator grew 2.5 MB a minute: a trace keeps its newest points at full rate and thins the older
    ones, still spread over the whole run; an obstacle gone for OBSTACLE_GONE_S loses its trace."""
    from services.evaluator.core import OBSTACLE_GONE_S, Trace

    import tracemalloc

    tracemalloc.start()
    tr = Trace(width=1, recent=100, older=400)
    made = tracemalloc.get_traced_memory()[0]
    for k in range(100_000):
        tr.append((k,))
    grown = tracemalloc.get_traced_memory()[0] - made
    tracemalloc.stop()
    pts = list(tr.array()[:, 0])
    assert len(tr) <= 500 and pts == sorted(pts) and pts[-100:] == list(range(99_900, 100_000))
    assert pts[0] < 1_000 and tr.last()[0] == 99_999  # the run's start is still drawn
    assert grown < 1_000  # its memory is the one it was made with (the soak's evaluator grew 15 MB in 45 min)
    ev = Evaluator("f", plot_every_s=0.1)
    ev = Evaluator("f", plot_every_s=0.1)
    ev.on_truth(_truth(0.0, [0.0, 0.0], [[5.0, 0.0]]))
    assert list(ev.truth_obstacles) == [1]
    later = _truth(OBSTACLE_GONE_S + 1.0, [0.0, 0.0], [[5.0, 0.0]])
    later = later.model_copy(update={"obstacle_id": np.array([2], np.uint32)})
    ev.on_truth(later)
    assert list(ev.truth_obstacles) == [2]


def test_a_frames_wall_time_is_on_the_epoch_its_truth_was_sent_with() -> None:
    """The evaluator measured a fused state's latency from its frame's wall time on the newest epoch: for a
    frame from before a pause of the adaptive clock the latency came out short by the pause. The frame's
    own truth says when it was."""
    from services.evaluator.app import FrameWallTimes

    e0, pause = 10**18, 2 * 10**9
    frames = FrameWallTimes(keep=3)
    env = dict(fleet="f", sender="world", t_sent=0.0, vehicle_ids=[], time_scale=0.5)
    for k, epoch in ((0, e0), (1, e0), (2, e0 + pause)):
        frames.record(GroundTruth(seq=k, t_meas=0.1 * k, epoch_wall_ns=epoch, **env))
    assert frames.get(0.1) == e0 + 200_000_000  # 0.1 s of scenario at half speed: 0.2 s after the epoch
    assert frames.get(0.2) == e0 + pause + 400_000_000
    frames.record(GroundTruth(seq=3, t_meas=0.3, epoch_wall_ns=e0 + pause, **env))
    assert frames.get(0.0) is None and frames.get(0.3) is not None  # the oldest frames are let go
    frames.record(GroundTruth(seq=4, t_meas=0.4, **env | {"time_scale": None}))  # no clock: nothing to keep
    assert frames.get(0.4) is None
