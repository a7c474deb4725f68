"""The live channel relay with a geometric radio profile: it learns positions from the world's truth."""

from __future__ import annotations

import time

import pytest

from schemas import VehiclePrior, decode
from schemas.topics import topic
from services.health import fleet_health

pytestmark = pytest.mark.integration


def test_the_relay_places_vehicles_from_truth_and_reports_the_radio(rendezvous, fleet_name, spawn, watch_liveliness):
    """world -> vehicle cv1 -> channel (its-g5 on paper-urban's buildings) -> v2x/rx/host/cv1/prior."""
    session, endpoint = rendezvous
    alive = watch_liveliness(session, topic("alive").pattern(fleet=fleet_name))
    common = ["--fleet", fleet_name, "--connect", endpoint]
    spawn("services.channel", *common, "--network", "its-g5", "--scenario", "paper-urban", "--receiver", "host=cv0")
    spawn("services.vehicle", *common, "--id", "cv1")
    for role, sid in (("channel", "channel"), ("vehicle", "cv1")):
        alive.wait_alive(topic("alive").key(fleet=fleet_name, role=role, id=sid), timeout=60)
    got = []
    sub = session.declare_subscriber(
        topic("prior_rx").pattern(fleet=fleet_name, dst="host"), lambda s: got.append(s.payload.to_bytes())
    )
    spawn("services.world", *common, "--vehicles", "2", "--duration", "3", "--wait-subscribers", "3")
    deadline = time.monotonic() + 60
    while len(got) < 3 and time.monotonic() < deadline:
        time.sleep(0.05)
    sub.undeclare()
    assert len(got) >= 3
    prior = decode(got[-1], VehiclePrior)
    assert prior and prior.sender == "cv1"
    channel = {(v.role, v.id): v for v in fleet_health(session, fleet_name, timeout_s=2.0)}[("channel", "channel")]
    fig = channel.status.figures
    # the first prior may race the first truth message (then it goes by the base latency, counted)
    assert fig["unlocated_msgs"] <= 1 and fig["offered_msgs"] >= 3
    assert fig["link_states.los"] + fig["link_states.nlosv"] + fig["link_states.nlos"] > 0
    assert 0 < fig["cbr.cv1.mean"] < 1 and fig["delivered_fraction"] > 0.9
    assert channel.status.state == "ok"
