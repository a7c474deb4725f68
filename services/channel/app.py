"""Channel service: the V2X link emulator as an application-level relay (docs/architecture.md, "The V2X channel").

Subscribes ``mc/{fleet}/v2x/tx/*/prior`` and ``.../raw``. For every receiver ``dst`` (``--receiver``,
repeatable) the Zenoh callback only calls ``Channel.send(src, dst, payload, now)`` under a lock
(``now``: wall-clock seconds since the service started) and wakes the scheduler. The scheduler
thread sleeps until ``Channel.next_arrival()`` or a new message, takes ``deliver(now)`` and
republishes each delivery on ``mc/{fleet}/v2x/rx/{dst}/{src}/prior`` (or ``raw``) with the sender's
attachment (the world's clock) plus ``t_wall_ns``. A receiver can have on-board sources
(``--receiver host=cv0``: the host runs on cv0, whose messages reach it without the radio) —
those are not relayed to it. The host's downlink (``mc/{fleet}/v2x/tx/{hid}/downlink/{vid}``, one
message per vehicle) goes over link hid->vid to that vehicle alone, on ``mc/{fleet}/v2x/rx/{vid}/{hid}/downlink``.

The processing latency in the health status is the scheduler's lateness: the time a delivery is
published minus the time the link model said it arrives (about 0.5 ms in the prototype).

With a geometric radio profile (``--network its-g5``, ``cv2x-mode4``: :mod:`mapcontainer.radio`) the
relay also subscribes the world's truth (``mc/{fleet}/sim/truth``) and tells the link where every
vehicle is (``Relay.observe``, on the relay's wall clock); a receiver sits at its first on-board
source (``--receiver host=cv0``: the host's radio is cv0's). Every vehicle's message is one broadcast
on the air, relayed to a receiver or not, so it loads the medium; the health figures add the radio
drops by cause and each vehicle's channel busy ratio (``cbr.<vehicle>.mean``).
"""

from __future__ import annotations

import argparse
import threading
import time
from collections import OrderedDict

from pydantic import Field

from mapcontainer.admission import Gate
from mapcontainer.security import CA_NAME, VERIFY_WINDOW_S, Verifier, load_certificate, unwrap
from schemas import GroundTruth
from schemas.codec import Rejection
from schemas.topics import topic

from ..runtime import (
    CountingPublisher,
    Received,
    Service,
    ServiceSettings,
    SimClock,
    add_service_args,
    make_attachment,
    service_settings_from_args,
    setup_logging,
    topic_gate,
)

__all__ = ["ChannelSettings", "Relay", "main", "parse_args", "parse_receivers"]

KINDS = ("prior", "raw")  # broadcast to every receiver; the downlink goes to its one vehicle (Relay.offer_to)
DOWNLINK_TARGETS = 64  # the vehicles one host's downlink may serve at the full rate


class ChannelSettings(ServiceSettings):
    network: str = "dsrc"
    seed: int = 0
    receivers: dict[str, list[str]] = Field(
        default_factory=lambda: {"host": []}, description="receiver id -> its on-board sources (not relayed)"
    )
    stale_input_s: float | None = None  # an idle channel is not unhealthy
    scenario: str | None = Field(None, description="whose map's buildings a geometric radio profile uses")
    time_scale: float = Field(
        1.0, ge=SimClock.TIME_SCALE_MIN, le=SimClock.TIME_SCALE_MAX, description="the world's: senders' rates scale"
    )
    keys: str | None = Field(None, description="the fleet's keys directory: relay only verified messages")


def parse_receivers(specs: list[str] | None) -> dict[str, list[str]]:
    """``["host=cv0", "rsu"]`` -> ``{"host": ["cv0"], "rsu": []}``."""
    out: dict[str, list[str]] = {}
    for spec in specs or ["host"]:
        dst, _, local = spec.partition("=")
        out[dst] = [x for x in local.split(",") if x]
    return out


def parse_args(argv: list[str] | None = None) -> ChannelSettings:
    p = argparse.ArgumentParser(prog="python -m services.channel", description=__doc__.splitlines()[0])
    p.add_argument(
        "--network", default="dsrc", help="network profile (configs/network/NAME.yaml) or a YAML path"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--receiver",
        action="append",
        default=None,
        help="receiver id, optionally with on-board sources: host=cv0 (repeatable; default host)",
    )
    p.add_argument("--time-scale", type=float, default=1.0, help="the world's (senders' rates scale with it)")
    p.add_argument(
        "--scenario", default=None, help="the world's scenario: its map's buildings block a geometric radio profile"
    )
    p.add_argument("--keys", default=None, help="the fleet's keys directory (its CA): relay verified messages only")
    add_service_args(p, "channel", default_id="channel")
    a = p.parse_args(argv)
    base = service_settings_from_args(a).model_dump()
    base["stale_input_s"] = None
    return ChannelSettings(
        **base,
        network=a.network,
        seed=a.seed,
        receivers=parse_receivers(a.receiver),
        time_scale=a.time_scale,
        scenario=a.scenario,
        keys=a.keys,
    )


class Relay:
    """Thread-safe glue between Zenoh callbacks and the Channel core, with a wall clock.

    ``offer`` is called from callbacks (short: a lock, ``send`` per receiver, a notify);
    ``run`` is the scheduler loop. Attachments are kept by (src, payload hash) until delivery, the first
    one offered for a payload: a copy of a message offered later with another attachment changes nothing
    (the probe's copies of genuine priors with ``epoch_wall_ns = 1`` rewrote the clock of the originals).
    """

    MAX_PENDING = 4096

    def __init__(self, channel, receivers: dict[str, list[str]], clock=time.monotonic):
        self.channel = channel
        self.receivers = receivers
        self.radio = hasattr(channel, "observe_truth")  # a geometric link (mapcontainer.radio.RadioChannel)
        if self.radio:
            for dst, onboard in receivers.items():
                if onboard:
                    channel.place(dst, onboard[0])
        self._clock = clock
        self._t0 = clock()
        self._cond = threading.Condition()
        self._meta: OrderedDict[tuple[str, int], tuple[str, dict]] = OrderedDict()
        self.offered = 0
        self.accepted = 0

    def now(self) -> float:
        return self._clock() - self._t0

    def offer(self, kind: str, src: str, payload: bytes, attachment: dict) -> None:
        with self._cond:
            now = self.now()
            self._meta.setdefault((src, hash(payload)), (kind, attachment))
            while len(self._meta) > self.MAX_PENDING:
                self._meta.popitem(last=False)
            if self.radio:
                self.channel.on_air(src, payload, now)  # a broadcast: on the air whoever it is relayed to
            for dst, onboard in self.receivers.items():
                if src == dst or src in onboard:
                    continue
                self.offered += 1
                self.accepted += bool(self.channel.send(src, dst, payload, now))
            self._cond.notify()

    def offer_to(self, kind: str, src: str, dst: str, payload: bytes, attachment: dict) -> None:
        """One message for one receiver (the host's downlink to a vehicle) over link src->dst."""
        with self._cond:
            now = self.now()
            self._meta.setdefault((src, hash(payload)), (kind, attachment))
            while len(self._meta) > self.MAX_PENDING:
                self._meta.popitem(last=False)
            self.offered += 1
            self.accepted += bool(self.channel.send(src, dst, payload, now))
            self._cond.notify()

    def observe(self, truth) -> None:
        """The world's truth: where the vehicles are now (a geometric link only)."""
        if self.radio:
            with self._cond:
                self.channel.observe_truth(truth, t=self.now())

    def due(self, stop: threading.Event, max_wait_s: float = 0.2):
        """Block until something is due (or ``max_wait_s``): [(delivery, kind, attachment, lateness_s)]."""
        with self._cond:
            nxt = self.channel.next_arrival()
            wait = max_wait_s if nxt is None else min(max_wait_s, nxt - self.now())
            if wait > 0 and not stop.is_set():
                self._cond.wait(wait)
            now = self.now()
            out = []
            for d in self.channel.deliver(now):
                kind, att = self._meta.get((d.src, hash(d.payload)), ("prior", {}))
                out.append((d, kind, att, now - d.t_arrive))
            return out

    def stats(self) -> dict:
        with self._cond:
            st = self.channel.stats()
        st.pop("links", None)
        settled = st.get("offered_msgs", 0) - st.get("in_flight_msgs", 0)  # a message in flight is not lost yet
        delivered = st.get("delivered_msgs", 0) - st.get("duplicated_msgs", 0)
        st["delivered_fraction"] = delivered / settled if settled else 1.0
        return st


def main(s: ChannelSettings) -> int:
    from mapcontainer.channel import load_profile
    from mapcontainer.radio import make_channel

    log = setup_logging("channel", s.id, s.log_level)
    log.info("settings: %s", s.model_dump_json())
    profile = load_profile(s.network)
    hdmap = None
    if s.scenario is not None and getattr(profile, "radio", None) is not None:
        from mapcontainer.sim.config import load_scenario
        from mapcontainer.sim.maps import world_map

        hdmap = world_map(load_scenario(s.scenario))  # the world's own map: buildings are physics, not the HD map
    relay = Relay(make_channel(profile, s.seed, hdmap), s.receivers)
    # signed fleets: a message is verified before it costs its sender's budget (mapcontainer.admission.Gate)
    verifier = Verifier(load_certificate(s.keys, CA_NAME), window_s=VERIFY_WINDOW_S) if s.keys else None
    gate_lock = threading.Lock()
    log.info("profile %s: %s", profile.name, profile.description)

    with Service("channel", s, figures=relay.stats, keys=s.keys) as svc:
        pubs: dict[tuple[str, str, str], CountingPublisher] = {}

        def publisher(kind: str, dst: str, src: str) -> CountingPublisher:
            key = (kind, dst, src)
            if key not in pubs:
                pubs[key] = svc.publisher(topic(f"{kind}_rx").key(fleet=s.fleet, dst=dst, src=src))
            return pubs[key]

        def on_tx(kind: str):
            tx = topic(f"{kind}_tx")
            if kind == "downlink":  # one message per vehicle and frame from one host: its budget is per target
                rate = 2.0 * (tx.rate_hz or 10.0) * max(s.time_scale, 1.0) * DOWNLINK_TARGETS
                gate = Gate(verifier, rate, rate)
            else:
                gate = topic_gate(tx.name, verifier, s.time_scale)  # a flooding source loses its own excess only

            def cb(msg: Received) -> None:
                where = tx.parse(msg.key)
                if where is None:  # Zenoh's * also matches chunks such as cv1.x that no rx key can hold
                    svc.metrics.reject("bad_key", f"{msg.key} is not a {tx.name} key of ours", log)
                    return
                with gate_lock:
                    out = gate.admit(msg.payload, where["src"], time.monotonic(), time.time())
                if isinstance(out, Rejection):
                    svc.metrics.reject(out.reason, f"{tx.name} from {where['src']}: {out.detail}", log)
                elif kind == "downlink":  # to its one vehicle
                    relay.offer_to(kind, where["src"], where["dst"], msg.payload, msg.attachment)
                else:  # relayed as it came: the receiver verifies the signature again, end to end
                    relay.offer(kind, where["src"], msg.payload, msg.attachment)

            return cb

        for kind in (*KINDS, "downlink"):
            svc.subscribe(topic(f"{kind}_tx").pattern(fleet=s.fleet), on_tx(kind))

        if relay.radio:

            # the world's truth places the radios: believed only when the world signed it (signed fleets);
            # a verifier of its own, since Zenoh calls this from another thread than the relay's gate
            truth_verifier = Verifier(load_certificate(s.keys, CA_NAME), window_s=VERIFY_WINDOW_S) if s.keys else None

            def on_truth(msg: Received) -> None:
                inner = unwrap(msg.payload, truth_verifier, time.time(), "world")
                if isinstance(inner, Rejection):
                    svc.metrics.reject(inner.reason, f"truth on {msg.key}: {inner.detail}", log)
                    return
                truth = svc.decode_or_reject(inner, GroundTruth)
                if truth is not None:
                    relay.observe(truth)

            svc.subscribe(topic("truth").key(fleet=s.fleet), on_truth)

        def schedule() -> None:
            while not svc.stop_requested.is_set():
                for d, kind, att, late in relay.due(svc.stop_requested):
                    att = {**att, "t_wall_ns": time.time_ns(), "link_latency_s": d.latency}
                    publisher(kind, d.dst, d.src).put(d.payload, attachment=make_attachment(**att))
                    svc.metrics.latency.add(max(late, 0.0))

        svc.spawn(schedule, "scheduler")
        svc.wait()
        with relay._cond:
            relay._cond.notify_all()
    return 0
