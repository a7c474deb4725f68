"""Vehicle service: sensors in, V2X message out.

Subscribes ``mc/{fleet}/sim/{vid}/sensors``; frames wait in a backlog (``mapcontainer.vehicle.FrameBacklog``)
for one worker thread that calls ``VehicleAgent.handle(t, frame)`` on the newest and publishes the result on
``mc/{fleet}/v2x/tx/{vid}/prior`` (distributed) or ``.../raw`` (centralized). The attachment passes
the world's clock on and adds ``t_capture_wall_ns`` (when the world published the frame).

Frames are handled in order, and the newest one waiting is the one matched: when the vehicle cannot keep
up (a frame's work took longer than the frame period), the frames that arrived meanwhile are stale, counted
as ``skipped`` and not matched or sent; in distributed mode the worker still passes their odometry and GNSS
fix to the localizer, in order (``VehicleAgent.skip``), so that no stretch of the path goes unmeasured and
the track is kept (tests/integration/test_vehicle_agent.py: a vehicle that can match one frame in three
keeps its lock). Its priors are then at most one frame period plus one frame's work old.

The host's downlink (distributed mode): ``mc/{fleet}/v2x/rx/{vid}/*/downlink`` (PoseDownlink, through the
channel emulator; on a signed fleet verified against the host id in the key) is kept by the Zenoh callback
and handed to the agent by the frame worker before its next frame (``VehicleAgent.receive_downlink``): the
agent is only ever used from that one thread.

Health (distributed mode, ``VehicleAgent.health``): degraded while the vehicle does not know where it
is -- from the first frame after a gap longer than ``health.gap_s`` (a freeze, frames lost), a restart
or a reset of its localizer, and in any phase of the localizer but tracking, until it has been
map-matched while tracking for ``health.relocalized_s`` -- and while tracking without a map match for
more than ``health.unlocalized_s`` (its priors are then GNSS-grade); all in scenario seconds
(:mod:`mapcontainer.localization.health`).
"""

from __future__ import annotations

import argparse
import threading
import time
from typing import Literal

from pydantic import Field

from mapcontainer.faults import FaultInjector
from mapcontainer.localization.health import PoseHealthParams
from mapcontainer.security import CA_NAME, VERIFY_WINDOW_S, Signer, Verifier, load_certificate, load_credentials, unwrap
from mapcontainer.sim.config import load_scenario
from mapcontainer.sim.errors import published_map
from mapcontainer.vehicle import FrameBacklog
from schemas import Rejection, SensorFrame, encode
from schemas.topics import topic

from ..runtime import (
    Received,
    Service,
    ServiceSettings,
    SimClock,
    add_service_args,
    make_attachment,
    service_settings_from_args,
    setup_logging,
)

__all__ = ["VehicleSettings", "main", "parse_args"]


class VehicleSettings(ServiceSettings):
    scenario: str = "paper-urban"  # the HD map comes from the scenario's map spec and the seed
    seed: int = Field(0, ge=0, description="the run's seed: the HD map's error is drawn from it (as the world's)")
    mode: Literal["distributed", "centralized"] = "distributed"
    health: PoseHealthParams = Field(default_factory=PoseHealthParams, description="when the pose health is degraded")
    keys: str | None = Field(None, description="directory of the fleet's keys: sign every V2X message (None: unsigned)")


def parse_args(argv: list[str] | None = None) -> VehicleSettings:
    p = argparse.ArgumentParser(prog="python -m services.vehicle", description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="paper-urban", help="scenario whose HD map the vehicle carries")
    p.add_argument(
        "--seed", type=int, default=0, help="the run's seed (the world's): the HD map's error is drawn from it"
    )
    p.add_argument("--mode", choices=["distributed", "centralized"], default="distributed")
    p.add_argument("--keys", default=None, help="directory of the fleet's keys (mapc keys init): sign what is sent")
    add_service_args(p, "vehicle")
    a = p.parse_args(argv)
    return VehicleSettings(
        **service_settings_from_args(a).model_dump(),
        scenario=a.scenario,
        seed=a.seed,
        mode=a.mode,
        keys=a.keys,
    )


def main(s: VehicleSettings) -> int:
    from mapcontainer.vehicle import VehicleAgent

    log = setup_logging("vehicle", s.id, s.log_level)
    log.info("settings: %s", s.model_dump_json())
    scenario = load_scenario(s.scenario)
    hdmap = published_map(scenario, s.seed)  # the in-process pipeline's map for this scenario and seed
    agent = VehicleAgent(hdmap, s.id, s.fleet, mode=s.mode, health=s.health)
    faults = FaultInjector(s.id, scenario.faults)  # the scenario's faults of this vehicle, if any
    signer = Signer(load_credentials(s.keys, s.id)) if s.keys else None  # ConfigError: exit 2 at start
    if faults:
        log.warning("this vehicle misbehaves as configured: %s", [f.model_dump() for f in faults.faults])
    clock = SimClock()
    figures_fn = getattr(agent, "figures", None) or getattr(agent, "stats", None)
    extra = {"sent": 0.0, "last_msg_bytes": 0.0, "skipped": 0.0}  # skipped: frames given to agent.skip

    def check() -> tuple[str, str | None]:
        return agent.health() if s.mode == "distributed" else ("ok", None)

    with Service(
        "vehicle", s, figures=lambda: {**(figures_fn() if figures_fn else {}), **extra}, health_check=check, keys=s.keys
    ) as svc:
        kind = "prior_tx" if s.mode == "distributed" else "raw_tx"
        pub = svc.publisher(topic(kind).key(fleet=s.fleet, src=s.id))

        def frame_of(msg: Received) -> tuple[SensorFrame, float] | None:
            """The sample's frame and the time to handle it at (the world's clock now; the frame's own
            time until that clock is known), or None if it was refused."""
            frame = svc.decode_or_reject(msg.payload, SensorFrame)
            if frame is None:
                return None
            if frame.sender != s.id:
                svc.metrics.reject("wrong_sender", f"frame from {frame.sender} on {msg.key}", log)
                return None
            clock.update(frame)  # the world's clock, from the frame itself (never from an attachment)
            t_now = clock.now()
            return frame, frame.t_meas if t_now is None else t_now

        def refused(out: object) -> bool:
            if isinstance(out, Rejection):
                svc.metrics.reject(out.reason, out.detail[:200], log)
                return True
            return False

        downlinks: list[bytes] = []  # verified downlinks, for the frame worker
        down_lock = threading.Lock()
        down_verifier = Verifier(load_certificate(s.keys, CA_NAME), window_s=VERIFY_WINDOW_S) if s.keys else None

        def on_downlink(msg: Received) -> None:
            where = topic("downlink_rx").parse(msg.key)
            if where is None or where["dst"] != s.id:
                svc.metrics.reject("bad_key", f"{msg.key} is not a downlink for {s.id}", log)
                return
            inner = unwrap(msg.payload, down_verifier, time.time(), where["src"])
            if isinstance(inner, Rejection):
                svc.metrics.reject(inner.reason, f"downlink on {msg.key}: {inner.detail}", log)
                return
            with down_lock:
                downlinks.append(inner)
                del downlinks[:-4]  # only the newest counts

        def take_downlinks() -> None:
            with down_lock:
                got, downlinks[:] = list(downlinks), []
            for payload in got:
                reason = agent.receive_downlink(payload)
                if reason is not None:
                    svc.metrics.reject(f"downlink_{reason}", "downlink refused by the vehicle", log)

        def on_frame(msg: Received) -> None:
            got = frame_of(msg)
            if got is None:
                return
            take_downlinks()
            out = agent.handle(got[1], got[0])
            if refused(out):
                return
            for m in faults.apply(out) if faults and s.mode == "distributed" else [out]:
                m = clock.stamp(m)  # the clock travels inside the message, under its signature
                payload = encode(m) if signer is None else signer.sign(encode(m), time.time())
                pub.put(
                    payload,
                    attachment=make_attachment(
                        t_wall_ns=time.time_ns(),
                        t_capture_wall_ns=msg.attachment.get("t_wall_ns"),
                        **clock.fields(),
                    ),
                )
                extra["sent"] += 1
                extra["last_msg_bytes"] = float(len(payload))

        def on_skipped_frame(msg: Received) -> None:
            got = frame_of(msg)
            if got is not None and not refused(agent.skip(got[1], got[0])):
                extra["skipped"] += 1

        backlog: FrameBacklog[Received] = FrameBacklog()

        def work() -> None:
            """The newest frame waiting is matched; the stale ones before it are skipped (their odometry kept)."""
            while not svc.stop_requested.is_set():
                got = backlog.take(timeout_s=0.2)
                if got is None:
                    continue
                stale, newest = got
                for msg in stale:
                    svc.metrics.reject("skipped", "a newer frame is waiting: handled in part", log)
                    run(on_skipped_frame if s.mode == "distributed" else count_skipped, msg)
                t0 = time.perf_counter()
                run(on_frame, newest)
                svc.metrics.latency.add(time.perf_counter() - t0)
                for _ in range(backlog.pop_dropped()):
                    svc.metrics.reject("queue_full", f"more than {backlog.max_waiting} frames waiting: dropped", log)

        def count_skipped(msg: Received) -> None:
            extra["skipped"] += 1

        def run(handler, msg: Received) -> None:
            try:
                handler(msg)
            except Exception as e:
                svc.metrics.error(f"{type(e).__name__}: {e}")
                log.exception("frame handler failed on %s", msg.key)

        if s.mode == "distributed":
            svc.subscribe(topic("downlink_rx").pattern(fleet=s.fleet, dst=s.id), on_downlink)
        svc.spawn(work, "frames")
        svc.subscribe(topic("sensors").key(fleet=s.fleet, vid=s.id), backlog.put)
        svc.wait()
    return 0
