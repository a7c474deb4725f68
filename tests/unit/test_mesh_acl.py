"""The default fleet's access control lets each service declare what it uses (services/launcher/mesh.py).

A subscription the ACL does not grant fails silently: the service simply hears nothing. The world's
adaptive clock then had no vehicle to wait for (it heard no liveliness tokens and no transmit keys), and a
geometric radio in the channel relay no truth to place its radios by.
"""

from __future__ import annotations

from types import SimpleNamespace

import pytest

zenoh = pytest.importorskip("zenoh")

from schemas.topics import topic  # noqa: E402
from services.launcher.manifest import FleetParams  # noqa: E402
from services.launcher.mesh import _PUB, _SUB, _WATCH, _grants  # noqa: E402

FLEET = "f"


def _granted(role: str, ident: str, kind: tuple, key: str) -> bool:
    spec = SimpleNamespace(name=ident, role=role, id=ident)
    wanted = zenoh.KeyExpr(key)
    return any(
        pairs == kind and any(zenoh.KeyExpr(k).includes(wanted) for k in keys)
        for pairs, keys in _grants(spec, FleetParams(fleet=FLEET))
    )


def test_the_world_may_follow_what_its_adaptive_clock_waits_for() -> None:
    for name in ("prior_tx", "raw_tx"):
        assert _granted("world", "world", _SUB, topic(name).pattern(fleet=FLEET))
    assert _granted("world", "world", _SUB, topic("fused").pattern(fleet=FLEET))
    for role in ("vehicle", "host"):
        assert _granted("world", "world", _WATCH, topic("alive").pattern(fleet=FLEET, role=role))
    assert _granted("world", "world", _PUB, topic("truth").key(fleet=FLEET))
    assert not _granted("world", "world", _PUB, topic("fused").key(fleet=FLEET, hid="host"))  # reads, never puts


def test_the_channel_may_read_the_truth_that_places_its_radios_but_not_put_it() -> None:
    assert _granted("channel", "channel", _SUB, topic("truth").key(fleet=FLEET))
    assert _granted("channel", "channel", _SUB, topic("prior_tx").pattern(fleet=FLEET))
    assert not _granted("channel", "channel", _PUB, topic("truth").key(fleet=FLEET))


def test_the_downlink_host_puts_it_the_channel_relays_it_each_vehicle_reads_only_its_own() -> None:
    hid = FleetParams(fleet=FLEET).host_id
    assert _granted("host", hid, _PUB, topic("downlink_tx").key(fleet=FLEET, src=hid, dst="cv1"))
    assert not _granted("host", hid, _PUB, topic("downlink_tx").key(fleet=FLEET, src="other", dst="cv1"))
    assert not _granted("vehicle", "cv1", _PUB, topic("downlink_tx").key(fleet=FLEET, src=hid, dst="cv1"))
    assert _granted("channel", "channel", _SUB, topic("downlink_tx").pattern(fleet=FLEET))
    assert _granted("channel", "channel", _PUB, topic("downlink_rx").key(fleet=FLEET, dst="cv1", src=hid))
    assert _granted("vehicle", "cv1", _SUB, topic("downlink_rx").pattern(fleet=FLEET, dst="cv1"))
    assert not _granted("vehicle", "cv1", _SUB, topic("downlink_rx").pattern(fleet=FLEET, dst="cv2"))
    assert not _granted("vehicle", "cv1", _SUB, topic("downlink_rx").pattern(fleet=FLEET))  # not everyone's
