"""World service: ``World(load_scenario(name), seed, fleet)`` paced to wall clock x ``--time-scale``.

Publishes each vehicle's SensorFrame on ``mc/{fleet}/sim/{vid}/sensors`` and GroundTruth on
``mc/{fleet}/sim/truth``. Frame k is computed ahead, then published at its due wall time
``epoch + k dt / time_scale``; every message carries the clock in its envelope (``epoch_wall_ns``,
``time_scale``, ``t_next``), the attachment a copy of it and the publish time (``t_wall_ns``).

With ``--time-scale auto`` (the adaptive clock) the world waits, before each frame, for the vehicles'
messages of the previous one and for the host, pausing its clock (the epoch moves on), so every frame is
processed whatever the load. At a fixed time scale, if frames take longer than their period (an
overloaded machine), the world drops frames instead of falling behind: once a frame is due before it was
even computed, it skips to the frame due next, as an overloaded sensor pipeline does, and its state turns
degraded while it does (``skipped_frames``). Publishing ever staler frames instead would make every prior
older than the host's window, and nothing would be fused. The lag behind the clock is a health figure
too, degraded beyond ``--max-lag``. Frames dropped in the first ``startup_s`` of scenario time after the
world starts (or resumes) leave it *starting*, not degraded, while they count: every process of the fleet
is starting then, and the vehicles' cold starts take the machine.

With ``--state-file`` the clock is kept in a file: a restarted world resumes the same timeline
(at the frame now due, with fresh sensor noise state) instead of starting again at t = 0.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

from pydantic import Field

from mapcontainer.security import Signer, inner_payload, load_credentials
from mapcontainer.sim.config import load_scenario
from mapcontainer.sim.world import World
from schemas import encode
from schemas.codec import peek
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
    time_scale_arg,
    write_json,
)
from .core import Pacer, Progress, scale_scenario

__all__ = ["WorldSettings", "main", "parse_args"]


class WorldSettings(ServiceSettings):
    scenario: str = "paper-urban"
    seed: int = 0
    vehicles: int | None = Field(None, ge=1, description="connected vehicles (None: the scenario's)")
    time_scale: float = Field(
        1.0, ge=SimClock.TIME_SCALE_MIN, le=SimClock.TIME_SCALE_MAX, description="scenario seconds per wall second"
    )
    duration_s: float | None = Field(None, gt=0, description="scenario seconds to run; None: until stopped")
    wait_subscribers_s: float = Field(10.0, ge=0, description="wait this long for the vehicles' subscribers")
    start_delay_s: float = Field(0.2, ge=0, description="wall seconds between the clock's epoch and now")
    max_lag_s: float = Field(0.5, gt=0, description="degraded when publishing this far behind the clock")
    adaptive: bool = Field(
        False, description="--time-scale auto: the clock pauses while a vehicle or the host is behind (time_scale 1)"
    )
    auto_wait_s: float = Field(
        2.0, gt=0, description="adaptive: wait at most this long (wall s) for a frame's services"
    )
    host_slack_s: float = Field(
        0.5, ge=0, description="adaptive: the host's fused state may trail by this (scenario s)"
    )
    startup_s: float = Field(
        3.0, ge=0, description="frames dropped this soon (scenario s) after the start leave it starting, not degraded"
    )
    state_file: str | None = None
    stale_input_s: float | None = None  # the world has no input
    keys: str | None = Field(None, description="the fleet's keys directory: the ground truth is signed as world")


def parse_args(argv: list[str] | None = None) -> WorldSettings:
    p = argparse.ArgumentParser(prog="python -m services.world", description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="paper-urban")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--vehicles", type=int, default=None)
    p.add_argument("--time-scale", type=time_scale_arg, default=1.0, help="scenario seconds per wall second, or auto")
    p.add_argument("--duration", type=float, default=None, help="scenario seconds; default: until stopped")
    p.add_argument("--wait-subscribers", type=float, default=10.0)
    p.add_argument("--state-file", default=None, help="keep the clock here; a restart resumes the timeline")
    p.add_argument("--keys", default=None, help="the fleet's keys directory: sign the ground truth (as world)")
    add_service_args(p, "world", default_id="world")
    a = p.parse_args(argv)
    base = service_settings_from_args(a).model_dump()
    base["stale_input_s"] = None
    return WorldSettings(
        **base,
        scenario=a.scenario,
        seed=a.seed,
        vehicles=a.vehicles,
        time_scale=1.0 if a.time_scale == "auto" else a.time_scale,
        adaptive=a.time_scale == "auto",
        duration_s=a.duration,
        wait_subscribers_s=a.wait_subscribers,
        state_file=a.state_file,
        keys=a.keys,
    )


def _load_clock(path: str | None, s: WorldSettings) -> int | None:
    """The epoch of a previous run of this world (same scenario, seed, scale), if any."""
    if not path or not os.path.exists(path):
        return None
    try:
        st = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    same = (st.get("scenario"), st.get("seed"), st.get("time_scale"), st.get("vehicles")) == (
        s.scenario,
        s.seed,
        s.time_scale,
        s.vehicles,
    )
    return int(st["epoch_wall_ns"]) if same and isinstance(st.get("epoch_wall_ns"), int) else None


def _save_clock(s: WorldSettings, epoch_wall_ns: int, fig: dict | None = None) -> None:
    """The clock in the state file: a restarted world resumes its timeline, the launcher reads scenario time
    from it, and the run's report how the clock went (``fig``: the scale achieved, pauses, frames dropped)."""
    doc = {"epoch_wall_ns": epoch_wall_ns, "scenario": s.scenario, "seed": s.seed, "time_scale": s.time_scale}
    keep = ("achieved_time_scale", "paused_s", "waits_timed_out", "skipped_frames", "k")
    write_json(
        Path(s.state_file), {**doc, "vehicles": s.vehicles, **{k: (fig or {})[k] for k in keep if k in (fig or {})}}
    )


def _follow_progress(svc: Service, s: WorldSettings, vehicle_ids: list[str], dt: float):
    """Adaptive clock: (Progress fed from the vehicles' V2X messages and the hosts' fused states, the vehicles
    alive, whether a host is alive); (None, None, None) at a fixed time scale."""
    if not s.adaptive:
        return None, None, None
    progress = Progress(vehicle_ids, dt, s.host_slack_s)
    tx = {name: topic(name) for name in ("prior_tx", "raw_tx")}

    def on_tx(msg: Received) -> None:
        for tp in tx.values():
            where = tp.parse(msg.key)
            if where is not None:
                t = peek(inner_payload(msg.payload)).get("t_meas")
                if isinstance(t, float | int):
                    progress.sent(where["src"], float(t))

    def on_fused(msg: Received) -> None:
        t = peek(inner_payload(msg.payload)).get("t_meas")  # signed fleets: the state inside the signature
        if isinstance(t, float | int):
            progress.fused(float(t))

    for tp in tx.values():
        svc.subscribe(tp.pattern(fleet=s.fleet), on_tx, count=False)  # progress, not the world's input
    svc.subscribe(topic("fused").pattern(fleet=s.fleet), on_fused, count=False)
    vehicles = svc.watch_tokens(topic("alive").pattern(fleet=s.fleet, role="vehicle"))
    hosts = svc.watch_tokens(topic("alive").pattern(fleet=s.fleet, role="host"))
    return progress, (lambda: {k.rsplit("/", 1)[-1] for k in list(vehicles)}), (lambda: bool(hosts))


def main(s: WorldSettings) -> int:
    log = setup_logging("world", s.id, s.log_level)
    log.info("settings: %s", s.model_dump_json())
    sc = scale_scenario(load_scenario(s.scenario), s.vehicles)
    world = World(sc, seed=s.seed, fleet=s.fleet)
    signer = Signer(load_credentials(s.keys, "world")) if s.keys else None  # truth's sender is "world"
    fig: dict[str, float] = {
        "k": 0,
        "t": 0.0,
        "lag_s": 0.0,
        "late_frames": 0,
        "skipped_frames": 0,
        "vehicles": len(world.vehicle_ids),
        "tick_ms": 0.0,
    }
    if s.adaptive:  # the scale achieved, the clock's pauses, and waits that timed out
        fig.update(achieved_time_scale=0.0, paused_s=0.0, waits_timed_out=0)
    waited = {"late": [], "t": -math.inf}  # adaptive: who was behind when a wait timed out, and when

    skipping = {"t": -math.inf, "starting": False}  # monotonic time of the last skip; whether in the start

    def check() -> tuple[str, str | None]:
        if time.monotonic() - waited["t"] < s.rate_window_s:
            return "degraded", f"the clock went on without {', '.join(waited['late'])} (waited {s.auto_wait_s:g} s)"
        if fig["lag_s"] > s.max_lag_s:
            return "degraded", f"{fig['lag_s']:.2f} s behind the clock (frames take {fig['tick_ms']:.0f} ms)"
        if time.monotonic() - skipping["t"] < s.rate_window_s:
            period_ms = world.dt / s.time_scale * 1e3
            return "starting" if skipping["starting"] else "degraded", (
                f"dropping frames to keep up ({fig['skipped_frames']:.0f} so far): frames take "
                f"{fig['tick_ms']:.0f} ms, the period is {period_ms:.0f} ms"
            )
        return "ok", None

    with world, Service("world", s, figures=lambda: fig, health_check=check, keys=s.keys) as svc:
        pubs = {vid: svc.publisher(topic("sensors").key(fleet=s.fleet, vid=vid)) for vid in world.vehicle_ids}
        truth_pub = svc.publisher(topic("truth").key(fleet=s.fleet))
        svc.ready()
        if s.wait_subscribers_s > 0 and not svc.wait_matching(pubs.values(), s.wait_subscribers_s):
            missing = [v for v, p in pubs.items() if not p.matching]
            log.warning("no subscriber yet for %s after %.1f s; starting anyway", missing, s.wait_subscribers_s)
        epoch = _load_clock(s.state_file, s)
        if epoch is None:
            epoch = time.time_ns() + int(s.start_delay_s * 1e9)
            if s.state_file:
                _save_clock(s, epoch)
        pacer = Pacer(epoch, world.dt, s.time_scale)
        k = pacer.first_k_at(time.time_ns())
        t_start = pacer.t(k)
        progress, alive_vehicles, host_alive = _follow_progress(svc, s, world.vehicle_ids, world.dt)
        wall0, saved = time.time_ns(), {"t": time.monotonic()}

        def paused(ns: int) -> None:
            """The adaptive clock stood still ``ns``: count it, and keep the moved epoch in the state file (a
            restarted world resumes on it, and the launcher reads scenario time from it), at most every 0.5 s."""
            if ns <= 0:
                return
            fig["paused_s"] += ns * 1e-9
            if s.state_file and time.monotonic() - saved["t"] > 0.5:
                _save_clock(s, pacer.epoch_wall_ns, fig)
                saved["t"] = time.monotonic()

        if k:
            log.info("resuming the timeline at frame %d (t = %.1f s)", k, pacer.t(k))
        log.info(
            "publishing %d vehicles at %.1f Hz x %.2f from epoch %d",
            len(pubs),
            1 / world.dt,
            s.time_scale,
            epoch,
        )
        while not svc.stop_requested.is_set():
            t = pacer.t(k)
            if s.duration_s is not None and t >= s.duration_s - 1e-9:
                log.info("duration %.1f s reached", s.duration_s)
                break
            c0 = time.perf_counter()
            tick = world.tick(k)
            fig["tick_ms"] = (time.perf_counter() - c0) * 1e3
            if progress is not None and k > 0 and pacer.t(k - 1) >= t_start:
                late = progress.wait_for(pacer.t(k - 1), s.auto_wait_s, alive_vehicles, host_alive)
                if late:
                    fig["waits_timed_out"] += 1
                    waited.update(late=late, t=time.monotonic())
                paused(pacer.pause(k, time.time_ns()))  # the clock stood still while they caught up
                fig["achieved_time_scale"] = round((t - t_start) / max((time.time_ns() - wall0) * 1e-9, 1e-9), 3)
            due = pacer.due_wall_ns(k)
            if svc.wait(max(0.0, (due - time.time_ns()) * 1e-9)):
                break
            now = time.time_ns()
            lag = (now - due) * 1e-9
            if lag > world.dt / s.time_scale:
                fig["late_frames"] += 1
            # the clock travels inside the messages, signed with them; encoded now, after any pause moved the epoch
            c0 = time.perf_counter()
            clock = {"epoch_wall_ns": pacer.epoch_wall_ns, "time_scale": s.time_scale, "t_next": pacer.t(k + 1)}
            payloads = {vid: encode(f.model_copy(update=clock)) for vid, f in tick.frames.items()}
            truth = encode(tick.truth.model_copy(update=clock))
            if signer is not None:
                truth = signer.sign(truth, time.time())
            fig["tick_ms"] += (time.perf_counter() - c0) * 1e3
            att = make_attachment(t_wall_ns=now, **clock)  # instrumentation (recordings); never believed
            for vid, payload in payloads.items():
                pubs[vid].put(payload, attachment=att)
            truth_pub.put(truth, attachment=att)
            fig.update(k=k, t=t, lag_s=max(lag, 0.0))
            svc.metrics.latency.add(fig["tick_ms"] * 1e-3)
            k += 1
            due_next = pacer.first_k_at(time.time_ns())  # the first frame not due yet
            if due_next > k and progress is not None:  # adaptive: the clock waits for the world too
                paused(pacer.pause(k, time.time_ns()))
            elif due_next > k:  # frame k is due already, before it is computed: skip to the next one
                fig["skipped_frames"] += due_next - k
                skipping.update(t=time.monotonic(), starting=pacer.t(k) < t_start + s.startup_s)
                k = due_next
        if s.state_file:
            _save_clock(s, pacer.epoch_wall_ns, fig)
    return 0
