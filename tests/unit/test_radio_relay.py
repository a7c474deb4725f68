"""The channel relay with a geometric radio profile: positions from the world's truth, broadcasts, figures."""

from __future__ import annotations

import threading

import numpy as np

from mapcontainer.channel import load_profile
from mapcontainer.radio import RadioChannel, make_channel
from schemas import GroundTruth
from services.channel.app import Relay, parse_args
from services.runtime.metrics import flatten_figures


def _truth(t: float, xs: dict[str, float], obstacles: dict[int, float]) -> GroundTruth:
    n = len(obstacles)
    return GroundTruth(
        fleet="f",
        sender="world",
        seq=int(t * 10),
        t_meas=t,
        t_sent=t,
        vehicle_ids=list(xs),
        vehicle_pose=np.array([[x, 0, 0, 0, 0, 0] for x in xs.values()], float).reshape(-1, 6),
        vehicle_v_map=np.zeros((len(xs), 3)),
        obstacle_id=np.array(list(obstacles), dtype=np.uint32),
        obstacle_cls=np.full(n, 2, np.uint8),  # vehicles
        obstacle_p_map=np.array([[x, 0.2, 0] for x in obstacles.values()], float).reshape(-1, 3),
        obstacle_v_map=np.zeros((n, 3)),
        obstacle_yaw=np.zeros(n),
    )


def test_relay_places_the_host_at_its_vehicle_and_learns_positions_from_truth():
    clk = [0.0]
    ch = make_channel(load_profile("its-g5"), 3)
    assert isinstance(ch, RadioChannel)
    relay = Relay(ch, {"host": ["cv0"]}, clock=lambda: clk[0])
    assert relay.radio
    stop = threading.Event()
    got = []
    for k in range(30):
        clk[0] = 0.1 * k
        relay.observe(_truth(5.0 + 0.1 * k, {"cv0": 0.0, "cv1": 40.0, "cv2": 900.0}, {7: 20.0}))
        relay.offer("prior", "cv0", b"own" * 100, {})  # on board the host: on the air, not relayed
        relay.offer("prior", "cv1", b"near" * 100, {"k": k})
        relay.offer("prior", "cv2", b"far" * 100, {})
        clk[0] += 0.05
        got += relay.due(stop, max_wait_s=0.0)
    srcs = [d.src for d, *_ in got]
    assert "cv1" in srcs and "cv2" not in srcs  # 900 m away: below the sensing threshold
    st = relay.stats()
    assert st["radio_drops"]["sensing"] == 30 and st["offered_msgs"] == 60
    assert {"cv0", "cv1", "cv2"} <= set(st["cbr"]) and st["link_states"]["nlosv"] > 0
    flat = flatten_figures(st)
    assert 0 < flat["cbr.cv0.mean"] < 1 and "radio_drops.sensing" in flat
    # every delivery waited at least the modelled access delay: the air time of its 400 bytes
    assert all(d.latency > 4e-4 for d, *_ in got)


def test_channel_service_takes_a_scenario_for_the_buildings():
    s = parse_args(["--network", "its-g5", "--scenario", "blindspot-occluded", "--receiver", "host=cv0"])
    assert s.scenario == "blindspot-occluded" and s.receivers == {"host": ["cv0"]}
    assert parse_args([]).scenario is None


def test_the_downlink_goes_to_its_one_vehicle():
    """Relay.offer_to: the host's downlink over link host->vid only (not broadcast to the receivers)."""
    from mapcontainer.channel import Channel

    clk = [0.0]
    relay = Relay(Channel(load_profile("ideal"), 1), {"host": ["cv0"]}, clock=lambda: clk[0])
    relay.offer_to("downlink", "host", "cv1", b"for cv1", {"k": 1})
    got = relay.due(threading.Event(), max_wait_s=0.0)
    assert [(d.src, d.dst, d.payload, kind, att) for d, kind, att, _ in got] == [
        ("host", "cv1", b"for cv1", "downlink", {"k": 1})
    ]
    assert relay.offered == relay.accepted == 1
