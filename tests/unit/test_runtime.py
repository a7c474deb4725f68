"""services.runtime: rate counters, latency percentiles, health status building, Zenoh config building."""

from __future__ import annotations

import msgpack
import pytest

from schemas import HealthStatus, decode, encode
from services.health import ServiceView, exit_code, format_table, split_key
from services.runtime import (
    STATES,
    LatencySamples,
    RateCounter,
    ServiceMetrics,
    SimClock,
    ZenohSettings,
    build_health,
    build_zenoh_config,
    flatten_figures,
    make_attachment,
    read_attachment,
)


class FakeClock:
    def __init__(self, t: float = 100.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


# ------------------------------------------------------------------------------ counters


def test_rate_counter_counts_over_the_sliding_window() -> None:
    clk = FakeClock()
    rc = RateCounter(window_s=2.0, clock=clk)
    clk.t += 10.0  # older than the window: the span is the full window
    for _ in range(20):  # 10 Hz for 2 s, 100 bytes each
        rc.add(100)
        clk.t += 0.1
    rate, bps = rc.rates()
    assert rate == pytest.approx(10.0, rel=0.06)
    assert bps == pytest.approx(1000.0, rel=0.06)
    assert rc.total == 20 and rc.total_bytes == 2000
    clk.t += 5.0  # silence: everything leaves the window
    assert rc.rates() == (0.0, 0.0)
    assert rc.idle_s() == pytest.approx(5.1)


def test_rate_counter_young_counter_is_not_underreported() -> None:
    clk = FakeClock()
    rc = RateCounter(window_s=5.0, clock=clk)
    for _ in range(10):
        rc.add(10)
        clk.t += 0.1
    rate, _ = rc.rates()  # 10 events in 1 s of life: 10/s, not 10/5 = 2/s
    assert rate == pytest.approx(10.0, rel=0.01)
    assert RateCounter(1.0).idle_s() is None


def test_rate_counter_rejects_a_bad_window() -> None:
    with pytest.raises(ValueError, match="window_s"):
        RateCounter(0)


def test_latency_percentiles_in_ms() -> None:
    lat = LatencySamples(maxlen=1000)
    assert lat.percentiles_ms() == [None, None]
    for i in range(1, 101):
        lat.add(i * 1e-3)
    p50, p99 = lat.percentiles_ms((50, 99))
    assert p50 == pytest.approx(50.5)
    assert p99 == pytest.approx(99.01)


# ------------------------------------------------------------------------------ health


def test_flatten_figures() -> None:
    fig = flatten_figures(
        {"a": 1, "b": {"c": 2.5, "d": True}, "mode": "map_matching", "n": None, "x": float("nan")}
    )
    assert fig == {"a": 1.0, "b.c": 2.5, "b.d": 1.0, "mode.map_matching": 1.0}


def test_build_health_round_trips_through_the_codec() -> None:
    m = ServiceMetrics(window_s=5.0)
    for _ in range(3):
        m.msgs_in.add(200)
    m.msgs_out.add(50)
    m.latency.add(0.002)
    m.reject("malformed", "bad bytes")
    m.reject("malformed", "bad bytes")
    m.reject("queue_full")
    h = build_health(
        fleet="f1",
        role="vehicle",
        sid="cv0",
        seq=7,
        uptime_s=12.5,
        metrics=m,
        state="degraded",
        note="input stalled",
        figures={"inliers": 12, "loc": {"mode": "fallback"}},
        now_wall_s=1000.0,
    )
    assert isinstance(h, HealthStatus)
    assert (h.role, h.sender, h.seq, h.state, h.uptime_s) == ("vehicle", "cv0", 7, "degraded", 12.5)
    assert h.msgs_in_per_s > 0 and h.bytes_in_per_s == pytest.approx(3 * 200 * h.msgs_in_per_s / 3)
    assert h.latency_ms_p50 == pytest.approx(2.0)
    assert h.rejects == {"malformed": 2, "queue_full": 1}
    assert h.last_error == "input stalled"
    assert h.figures == {"inliers": 12.0, "loc.mode.fallback": 1.0}
    back = decode(encode(h), HealthStatus)
    assert back == h


def test_build_health_rejects_an_unknown_state() -> None:
    with pytest.raises(ValueError, match="state"):
        build_health(fleet="f", role="r", sid="i", seq=0, uptime_s=0, metrics=ServiceMetrics(), state="meh")


def _view(role, sid, state, alive=True, status=True, note=None, rejects=None):
    st = None
    if status:
        st = build_health(
            fleet="f",
            role=role,
            sid=sid,
            seq=1,
            uptime_s=1,
            metrics=ServiceMetrics(),
            state=state if state in STATES else "ok",
            note=note,
        )
        if rejects:
            st.rejects.update(rejects)
    return ServiceView(role, sid, alive, state, st)


def test_health_exit_codes() -> None:
    assert exit_code([]) == 2
    assert exit_code([_view("world", "world", "missing", alive=False, status=False)]) == 2
    assert exit_code([_view("world", "world", "ok"), _view("host", "host", "ok")]) == 0
    assert exit_code([_view("world", "world", "ok"), _view("host", "host", "degraded")]) == 1
    assert exit_code([_view("world", "world", "ok"), _view("host", "host", "missing", False, False)]) == 1
    assert exit_code([_view("world", "world", "unresponsive", True, False)]) == 1
    # a cold start's expected period and a run whose input ended are healthy
    assert exit_code([_view("world", "world", "starting"), _view("vehicle", "cv1", "starting")]) == 0
    assert exit_code([_view("host", "host", "finished"), _view("evaluator", "evaluator", "ok")]) == 0
    assert exit_code([_view("host", "host", "finished"), _view("vehicle", "cv1", "degraded")]) == 1


def test_health_table_fits_100_columns_and_says_why() -> None:
    long_reason = "misbehaviour (detections not fused): " + "; ".join(
        f"cv{i} seen 3.2 m from where it says it is, more than its covariance allows" for i in range(8)
    )
    views = [
        _view("host", "host", "degraded", note=long_reason, rejects={"stale": 20, "flood": 3}),
        _view("vehicle", "cv1", "starting", note="searching for its pose"),
        _view("vehicle", "cv0", "ok", rejects={"stale": 2}),
        _view("world", "world", "missing", alive=False, status=False),
    ]
    table = format_table(views, "a-long-fleet-name")
    assert max(len(line) for line in table.splitlines()) <= 100
    rows = {line.split()[0]: line for line in table.splitlines()[2:]}
    assert rows["host"].split()[1] == "degraded" and "misbehaviour (detections" in rows["host"]
    assert rows["host"].endswith("...")
    assert rows["vehicle/cv1"].split()[1] == "starting" and rows["vehicle/cv1"].endswith("searching for its pose")
    assert rows["vehicle/cv0"].endswith("rejected stale 2")
    assert rows["world"].split()[1] == "missing" and rows["world"].endswith("no health token")


def test_health_table_and_json() -> None:
    views = [_view("world", "world", "ok"), _view("host", "host", "missing", False, False)]
    table = format_table(views, "f")
    assert "world" in table and "missing" in table
    js = views[0].to_json()
    assert js["role"] == "world" and js["state"] == "ok" and "uptime_s" in js and "figures" in js
    assert split_key("mc/f/alive/vehicle/cv0") == ("vehicle", "cv0")
    with pytest.raises(ValueError):
        split_key("mc/f")


# ------------------------------------------------------------------------------ zenoh config


def test_peer_config_is_the_verified_recipe() -> None:
    conf = build_zenoh_config(ZenohSettings(connect=["tcp/127.0.0.1:7000"]))
    assert conf["mode"] == "peer"
    assert conf["listen"]["endpoints"] == ["tcp/127.0.0.1:0"]
    assert conf["connect"] == {
        "endpoints": ["tcp/127.0.0.1:7000"],
        "timeout_ms": 3000,
        "exit_on_failure": True,
    }
    assert conf["scouting"]["multicast"]["enabled"] is False
    assert conf["scouting"]["gossip"]["autoconnect_strategy"]["peer"]["to_peer"] == "greater-zid"
    assert 1000 <= conf["transport"]["link"]["tx"]["lease"] <= 2000
    assert "adminspace" not in conf


def test_client_and_router_configs() -> None:
    client = build_zenoh_config(ZenohSettings(mode="client", connect=["tcp/10.0.0.1:7447"]))
    assert client["mode"] == "client" and "listen" not in client
    router = build_zenoh_config(ZenohSettings(mode="router", connect=["tcp/10.0.0.2:7447"], adminspace=True))
    assert router["listen"]["endpoints"] == ["tcp/0.0.0.0:7447"]
    assert router["scouting"]["delay"] == 0
    assert router["adminspace"] == {"enabled": True}
    assert "gossip" not in router["scouting"]


def test_configs_are_accepted_by_zenoh() -> None:
    import json

    import zenoh

    for s in (
        ZenohSettings(),
        ZenohSettings(mode="client", connect=["tcp/127.0.0.1:1"]),
        ZenohSettings(mode="router"),
    ):
        conf = zenoh.Config.from_json5(json.dumps(build_zenoh_config(s)))
        assert json.loads(conf.get_json("mode")) == (s.mode or "peer")


def test_settings_validate() -> None:
    with pytest.raises(ValueError):
        ZenohSettings(lease_ms=10)
    with pytest.raises(ValueError):
        ZenohSettings(mode="satellite")


# ------------------------------------------------------------------------------ clock and attachments


def test_sim_clock_maps_scenario_time_to_wall_time() -> None:
    c = SimClock()
    assert c.now() is None and c.wall_ns(1.0) is None and not c.known
    assert not c.update({"epoch_wall_ns": "x"})
    for bad_scale in (float("inf"), float("nan"), True, 0, -1.0, 1e-300, 1e6):  # would stop, overflow or run away
        assert not c.update({"epoch_wall_ns": 1, "time_scale": bad_scale}) and not c.known
    assert not c.update({"epoch_wall_ns": True, "time_scale": 1.0})
    for bad_epoch in (0, -5, 2**64 - 1):
        assert not c.update({"epoch_wall_ns": bad_epoch, "time_scale": 1.0}) and not c.known
    assert c.update({"epoch_wall_ns": 1_000_000_000, "time_scale": 0.5})
    assert c.wall_ns(2.0) == 5_000_000_000  # 2 s of scenario at half speed: 4 s of wall time
    assert c.now(5_000_000_000) == pytest.approx(2.0)


def test_attachment_round_trip_and_garbage() -> None:
    raw = make_attachment(t_wall_ns=123, epoch_wall_ns=None, time_scale=1.0)
    assert read_attachment(raw) == {"t_wall_ns": 123, "time_scale": 1.0}
    assert read_attachment(b"\xc1\xff") == {}
    assert read_attachment(None) == {}
    assert read_attachment(make_attachment()) == {}
    # keys that are not names (bytes) are dropped: the channel passes the fields on as keywords
    odd = msgpack.packb({b"k": 1, "t_wall_ns": 5}, use_bin_type=True)
    assert read_attachment(odd) == {"t_wall_ns": 5}
    assert read_attachment(make_attachment(**read_attachment(odd), link_latency_s=0.02)) == {
        "t_wall_ns": 5,
        "link_latency_s": 0.02,
    }


def test_a_payload_over_its_topics_bound_is_refused_before_its_bytes_are_copied() -> None:
    """The probe's 8 MiB nested payload on a prior key: refused as too_large from the length Zenoh reports;
    the bytes are never copied out and the callback never runs. A prior of normal size goes through."""
    from types import SimpleNamespace

    from schemas.topics import max_bytes, topic
    from services.runtime import Service, ServiceSettings

    class Payload:
        def __init__(self, n: int) -> None:
            self.n = n

        def __len__(self) -> int:
            return self.n

        def to_bytes(self) -> bytes:
            if self.n > 1_000_000:
                raise AssertionError("an oversized payload was copied")
            return bytes(self.n)

    callbacks = {}
    svc = Service("host", ServiceSettings(fleet="f", id="host"))
    svc.session = SimpleNamespace(declare_subscriber=lambda key, cb: callbacks.setdefault(key, cb))
    got = []
    key = topic("prior_rx").pattern(fleet="f", dst="host")
    svc.subscribe(key, got.append)
    sample = SimpleNamespace(key_expr="mc/f/v2x/rx/host/cv1/prior", attachment=None, payload=Payload(8 * 2**20))
    callbacks[key](sample)
    assert got == [] and svc.metrics.rejects == {"too_large": 1}
    callbacks[key](SimpleNamespace(key_expr=sample.key_expr, attachment=None, payload=Payload(600)))
    assert len(got) == 1 and len(got[0].payload) == 600
    assert max_bytes(key) == topic("prior_rx").max_bytes == 256 * 1024
    assert max_bytes("mc/f/sim/cv0/sensors") > 4 * 2**20  # a lane mask at its limit still fits


def test_the_clock_comes_from_a_message_and_its_changes_are_counted() -> None:
    from schemas import VehiclePrior

    c = SimClock()
    fields = {"fleet": "f", "seq": 0, "t_meas": 0.0, "t_sent": 0.0, "pose": [0.0] * 6, "v_map": [0.0] * 3}
    cov = {"pose_cov": [1.0, 0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 1.0, 0, 1.0]}
    quality = {"quality": {"mode": "map_matching"}}
    plain = VehiclePrior(sender="cv0", **fields, **cov, **quality)
    assert not c.update(plain) and c.stamp(plain) is plain  # no clock in it, none to stamp
    assert c.update(VehiclePrior(sender="cv0", epoch_wall_ns=10**18, time_scale=1.0, **fields, **cov, **quality))
    assert c.changes == 0 and c.stamp(plain).epoch_wall_ns == 10**18
    # an older epoch (a message relayed from before a pause of the adaptive clock, or a liar) is not taken
    assert c.update({"sender": "cv1", "epoch_wall_ns": 1, "time_scale": 1.0})
    assert (c.epoch_wall_ns, c.changes) == (10**18, 0)
    # a later one is the same clock after a pause; another time scale is another clock, counted with its sender
    assert c.update({"sender": "cv1", "epoch_wall_ns": 10**18 + 5, "time_scale": 1.0, "t_next": 2.0})
    assert (c.epoch_wall_ns, c.changes, c.t_next) == (10**18 + 5, 0, 2.0)
    assert c.now(10**18 + 5 + 10**10) == 2.0  # capped at the next frame's time while the world is paused
    assert c.update({"sender": "cv2", "epoch_wall_ns": 10**18, "time_scale": 0.5})
    assert (c.changes, c.changed_by, c.time_scale, c.t_next) == (1, "cv2", 0.5, None)


def test_a_pause_moves_the_epoch_on_but_a_forged_later_epoch_does_not() -> None:
    """The adaptive clock's pause moves the world's epoch forward; an epoch that would put the present before
    times already seen (one signed message an hour ahead) is counted with its sender and not taken."""
    s, e0 = 10**9, 10**18
    c = SimClock()
    assert c.update({"sender": "cv0", "epoch_wall_ns": e0, "time_scale": 1.0, "t_meas": 5.0, "t_next": 5.1}, e0 + 5 * s)
    assert c.t_seen == 5.0
    # the world paused 2 s, then sent frame 5.1 on its new epoch: taken, and the present is 5.1 s again
    paused = e0 + 2 * s
    msg = {"sender": "cv0", "epoch_wall_ns": paused, "time_scale": 1.0, "t_meas": 5.1, "t_next": 5.2}
    assert c.update(msg, paused + int(5.12 * s))
    assert c.epoch_wall_ns == paused and c.now(paused + int(5.12 * s)) == pytest.approx(5.12)
    # a liar's epoch an hour later: the present would be an hour back; counted, not taken
    liar = {"sender": "cv3", "epoch_wall_ns": paused + 3600 * s, "time_scale": 1.0, "t_meas": 5.2}
    assert c.update(liar, paused + int(5.3 * s))
    assert (c.epoch_wall_ns, c.changes, c.changed_by) == (paused, 1, "cv3")
    assert c.now(paused + int(5.3 * s)) == pytest.approx(5.2)  # capped at the next frame until it is out
    # a message from the future (on the clock in force) does not count as a time seen
    assert c.update({"sender": "cv3", "epoch_wall_ns": paused, "time_scale": 1.0, "t_meas": 1e6}, paused + 6 * s)
    assert c.t_seen == 5.2


def test_a_late_message_of_the_old_time_scale_does_not_turn_a_changed_clock_back() -> None:
    """A message relayed late from before a change of time scale (sent on the old clock, its time older than
    what the new clock already stamped) flipped the clock back to the old scale and counted a change. It is
    from the past of the clock in force: ignored. A message on another scale that is not older is a change."""
    s, e0 = 10**9, 10**18
    c = SimClock()
    assert c.update({"sender": "world", "epoch_wall_ns": e0, "time_scale": 1.0, "t_meas": 9.9}, e0 + int(9.9 * s))
    e1 = e0 - 10 * s  # the world went on at half speed from t = 10 s, at wall time e0 + 10 s
    assert c.update({"sender": "world", "epoch_wall_ns": e1, "time_scale": 0.5, "t_meas": 10.0}, e0 + 10 * s)
    assert (c.time_scale, c.changes) == (0.5, 1)
    late = {"sender": "cv1", "epoch_wall_ns": e0, "time_scale": 1.0, "t_meas": 9.9}  # relayed from before
    assert c.update(late, e0 + int(10.2 * s))
    assert (c.epoch_wall_ns, c.time_scale, c.changes) == (e1, 0.5, 1)
    again = {"sender": "world", "epoch_wall_ns": e0, "time_scale": 1.0, "t_meas": 10.2}  # a change back: taken
    assert c.update(again, e0 + int(10.2 * s))
    assert (c.epoch_wall_ns, c.time_scale, c.changes) == (e0, 1.0, 2)
