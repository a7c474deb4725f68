"""Host service: the fusion container fed from Zenoh, fused state out at 10 Hz.

Subscribes ``mc/{fleet}/v2x/rx/{hid}/*/prior`` (and ``.../raw`` in centralized mode) and, for
on-board sources (``--local cv0``: the container runs on the ego vehicle, whose own messages do not
cross the radio), ``mc/{fleet}/v2x/tx/{src}/prior`` directly. Every payload is handed to the fusion
loop with its receive time in scenario seconds (from the world's clock carried in the
attachments); the loop solves once per camera frame (10 Hz), when every known sender's message for
the frame is in or ``--max-wait`` seconds after its first one (``mapcontainer.fusion.gate.FrameGate``), and the
service publishes the FusedState on ``mc/{fleet}/host/{hid}/fused`` and, with ``--downlink``, each vehicle's
PoseDownlink on ``mc/{fleet}/v2x/tx/{hid}/downlink/{vid}`` (signed like the fused state; the channel
emulator relays it to that vehicle). The attachment carries the
world's clock, ``t_wall_ns``, the solve time ``t_fused`` and frame tolerance ``tol``, and ``inputs``: the
``[sender, seq, t_recv]`` of every payload the container ingested since its previous solve, in order, which
makes a recording re-fusable exactly (``mapc replay --refuse``).

The container is ``mapcontainer.host.build_host`` of the host's own flags (``add_host_args``: ``--mode``,
``--map``, ``--local``, ``--known-senders``, ``--max-wait``, ``--params``); its HD map is a file
(``--map``, any format ``mapc map`` reads), which the centralized host needs and the distributed one does not.

GTSAM holds the GIL for a whole solve, so by default the container runs in a worker process
(``multiprocessing`` spawn context, started before the Zenoh session is opened) and this
process only moves bytes: subscriber callbacks never wait for a solve. ``--inline`` runs the
same loop in a thread instead (for measuring the difference).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import queue
import threading
import time
from pathlib import Path
from typing import Any

from pydantic import Field, model_validator

from mapcontainer.admission import Gate
from mapcontainer.host import HostSetup, add_host_args, host_setup_from_args
from mapcontainer.security import CA_NAME, VERIFY_WINDOW_S, Signer, Verifier, load_certificate, load_credentials
from schemas import FusedState, PoseDownlink
from schemas.codec import Rejection, peek, with_fields
from schemas.topics import is_chunk, topic

from ..runtime import (
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
from .worker import fusion_loop, fusion_process

__all__ = ["HostSettings", "fused_lag", "fusion_stall", "lag_causes", "main", "parse_args"]

FRAME_PERIOD_S = 0.1  # scenario seconds between camera frames: the host solves once per frame


class HostSettings(ServiceSettings):
    """The service's settings: transport and health here, the container's own set-up in ``host`` (its
    ``max_wait_s`` in wall seconds; its ``local`` senders are read from their tx topic)."""

    host: HostSetup
    inline: bool = False
    inbox: int = 2000
    time_scale: float = Field(
        1.0, ge=SimClock.TIME_SCALE_MIN, le=SimClock.TIME_SCALE_MAX, description="the world's: senders' rates scale"
    )
    keys: str | None = Field(None, description="directory of the fleet's keys: accept signed messages only")
    standby_for: str | None = Field(
        None, description="a warm standby of this host id: same input, publishes only while that host is gone"
    )
    max_fused_lag_s: float = Field(
        1.0, gt=0, description="degraded when the fused output trails the world's clock by more (wall seconds)"
    )

    @model_validator(mode="after")
    def _one_fleet(self) -> HostSettings:
        if self.host.fleet != self.fleet:
            raise ValueError(f"the container's fleet {self.host.fleet!r} is not the service's {self.fleet!r}")
        if self.host.max_wait_s > 2:
            raise ValueError(f"max_wait_s is at most 2 wall seconds, got {self.host.max_wait_s}")
        if self.host.mode == "centralized" and self.host.map_file is None:
            raise ValueError("the centralized host localizes the vehicles against an HD map: give --map FILE")
        if self.host.map_file is not None and not Path(self.host.map_file).is_file():
            raise ValueError(f"--map {self.host.map_file}: no such file")
        return self


def parse_args(argv: list[str] | None = None) -> HostSettings:
    p = argparse.ArgumentParser(prog="python -m services.host", description=__doc__.splitlines()[0])
    add_host_args(p)
    p.add_argument("--inline", action="store_true", help="run the solver in a thread, not a worker process")
    p.add_argument("--time-scale", type=float, default=1.0, help="the world's (senders' rates scale with it)")
    p.add_argument("--keys", default=None, help="directory of the fleet's keys (its CA): accept signed messages only")
    p.add_argument(
        "--standby-for",
        default=None,
        help="run as the warm standby of this host id: fuse its input, publish its fused state while it is gone",
    )
    add_service_args(p, "host", default_id="host")
    a = p.parse_args(argv)
    base = service_settings_from_args(a)
    return HostSettings(
        **base.model_dump(),
        host=host_setup_from_args(a, base.fleet, base.id),
        inline=a.inline,
        time_scale=a.time_scale,
        standby_for=a.standby_for,
        keys=a.keys,
    )


def fusion_stall(
    since_fused_s: float,
    input_idle_s: float | None,
    rejects: dict[str, int],
    rejects_at_fused: dict[str, int],
    stall_s: float | None,
) -> str | None:
    """Why the host is degraded although its input flows, or None: messages kept arriving (the last
    one at most ``stall_s`` ago) but no fused state was published for more than ``stall_s`` seconds,
    typically because the container refused them all (e.g. stale: the vehicles' clocks or latency put
    them outside the window). The reason names the rejections counted since the last fused state.
    (Input that stops altogether is the generic "input stalled" of every service.)"""
    if stall_s is None or since_fused_s <= stall_s or input_idle_s is None or input_idle_s > stall_s:
        return None
    why = _refused_since(rejects, rejects_at_fused) or "none"
    return f"input is flowing but nothing was fused for {since_fused_s:.1f} s (rejected since then: {why})"


def fused_lag(
    t_input: float | None, t_fused: float | None, time_scale: float, max_lag_s: float, causes: list[str] | None = None
) -> str | None:
    """Why the host is degraded although it fuses, or None: its newest fused state (scenario time
    ``t_fused``) trails its newest input (received at scenario time ``t_input``) by more than ``max_lag_s``
    wall seconds, so it does not keep up with its input (a solve slower than the frames, e.g. under a
    flood). Measured against the input, not the world's clock: when the input ends (the world finished,
    a replay ended) there is nothing left to keep up with. The reason names the ``causes`` seen
    (:func:`lag_causes`); with none, the host does not keep up with its input."""
    if t_input is None or t_fused is None:
        return None
    lag_s = (t_input - t_fused) / time_scale
    if lag_s <= max_lag_s:
        return None
    why = "; ".join(causes) if causes else "not keeping up"
    return f"the fused output trails the world by {lag_s:.1f} s (more than {max_lag_s:g} s): {why}"


def lag_causes(
    solve_ms: float,
    period_ms: float,
    inbox: int,
    clock_changes: int,
    clock_changed_by: str | None,
    rejects: dict[str, int],
    rejects_at_fused: dict[str, int],
) -> list[str]:
    """What can make the fused output trail the world, as far as the host sees: solves slower than the
    frames, a backlog for the fusion worker, a world clock that changed under it (a restarted world, or a
    signed sender whose clock disagrees), and the inputs refused since its last fused state."""
    out = []
    if solve_ms > period_ms:
        out.append(f"solves take {solve_ms:.0f} ms, frames come every {period_ms:.0f} ms")
    if inbox > 0:
        out.append(f"{inbox} messages wait for the fusion worker")
    if clock_changes:
        by = f", last in a message of {clock_changed_by}" if clock_changed_by else ""
        out.append(f"the world's clock changed {clock_changes} times{by}")
    counts = _refused_since(rejects, rejects_at_fused)
    if counts:
        out.append(f"refused since the last fused state: {counts}")
    return out


def _refused_since(rejects: dict[str, int], then: dict[str, int]) -> str:
    """The rejections counted since ``then``, most first ("272 stale, 3 flood"); empty if none."""
    new = {r: n - then.get(r, 0) for r, n in rejects.items() if n > then.get(r, 0)}
    return ", ".join(f"{n} {r}" for r, n in sorted(new.items(), key=lambda kv: -kv[1]))


def main(s: HostSettings) -> int:
    log = setup_logging("host", s.id, s.log_level)
    log.info("settings: %s", s.model_dump_json())
    hid = s.standby_for or s.id  # a standby receives and publishes as the host it stands in for
    verifier = Verifier(load_certificate(s.keys, CA_NAME), window_s=VERIFY_WINDOW_S) if s.keys else None
    credentials = load_credentials(s.keys, s.id) if s.keys else None
    signer = Signer(credentials) if credentials else None  # the fused state is signed too
    gate_lock = threading.Lock()  # the verifier is shared by the topics' gates
    # The worker starts before the Zenoh session exists (never fork after opening one; spawn anyway).
    if s.inline:
        inbox: Any = queue.Queue(maxsize=s.inbox)
        outbox: Any = queue.Queue()
        worker: Any = threading.Thread(target=fusion_loop, args=(s.host, inbox, outbox), daemon=True, name="fusion")
    else:
        ctx = mp.get_context("spawn")
        inbox, outbox = ctx.Queue(maxsize=s.inbox), ctx.Queue()
        worker = ctx.Process(
            target=fusion_process, args=(s.host, inbox, outbox, os.getpid()), daemon=True, name=f"fusion-{s.id}"
        )
    worker.start()
    first = None
    while first is None:  # the core imports GTSAM and builds its graph: seconds
        try:
            first = outbox.get(timeout=0.5)
        except queue.Empty:
            if not worker.is_alive():
                log.error("the fusion worker died while starting (exit code %s)", getattr(worker, "exitcode", None))
                return 1
    if first[0] != "ready":
        log.error("the fusion core did not start:\n%s", first[1])
        return 1
    log.info("fusion core ready (%s)", "thread" if s.inline else f"worker process {first[1]}")

    clock = SimClock()
    fig: dict[str, Any] = {
        "fused_published": 0,
        "downlink_sent": 0,
        "downlink_bytes": 0,
        "solve_ms": 0.0,
        "worker_alive": 1.0,
        "inbox": 0,
    }
    core_stats: dict[str, Any] = {"stats": {}}  # replaced whole, never mutated: the health thread reads it
    t0_mono = time.monotonic()
    warned = threading.Event()

    def figures() -> dict[str, Any]:
        try:
            fig["inbox"] = inbox.qsize()
        except NotImplementedError:  # macOS multiprocessing queues
            pass
        return {**{k: v for k, v in core_stats["stats"].items() if k != "flagged_why"}, **fig}

    # the last publish (monotonic), the rejections until then, and its scenario time
    fused_at: dict[str, Any] = {"t": time.monotonic(), "rejects": {}, "t_meas": None}
    newest_input: dict[str, float | None] = {"t": None}  # the newest input's receive time (scenario s)
    rc = 0
    with Service("host", s, figures=figures, keys=s.keys) as svc:

        def check() -> tuple[str, str | None]:
            if not worker.is_alive():
                return "failed", "the fusion worker is gone"
            why = fusion_stall(
                time.monotonic() - fused_at["t"],
                svc.metrics.msgs_in.idle_s(),
                dict(svc.metrics.rejects),
                fused_at["rejects"],
                s.stale_input_s,
            )
            if why is None and time.monotonic() - fused_at["t"] < 5.0:  # fusing: does it keep up?
                causes = lag_causes(
                    fig["solve_ms"],
                    FRAME_PERIOD_S / s.time_scale * 1e3,
                    int(figures().get("inbox", 0)),
                    clock.changes,
                    clock.changed_by,
                    dict(svc.metrics.rejects),
                    fused_at["rejects"],
                )
                why = fused_lag(newest_input["t"], fused_at.get("t_meas"), s.time_scale, s.max_fused_lag_s, causes)
            flagged = core_stats["stats"].get("flagged_why") or {}
            if why is None and flagged:
                why = "misbehaviour (detections not fused): " + "; ".join(
                    f"{v} {w}" for v, w in sorted(flagged.items())
                )
            return ("degraded", why) if why else ("ok", None)

        svc.health_check = check
        fused_pub = svc.publisher(topic("fused").key(fleet=s.fleet, hid=hid))
        primary = None  # a standby: set while the host it stands in for is alive
        if s.standby_for:
            primary = svc.watch_alive(topic("alive").key(fleet=s.fleet, role="host", id=s.standby_for))

        def on_msg(msg: Received, where: dict[str, str], gate: Gate, name: str) -> None:
            src = where["src"]  # the key's sender: anyone can publish on it, so it proves nothing
            with gate_lock:  # signed: verified before any budget, the inner message undecoded until then
                out = gate.admit(msg.payload, src, time.monotonic(), time.time())
            if isinstance(out, Rejection):
                svc.metrics.reject(out.reason, f"{name} from {src}: {out.detail}", log)
                return
            head = peek(out.payload)
            sender = head.get("sender")
            if verifier is None and sender is not None and sender != src:  # signed: the verifier checked it
                svc.metrics.reject("sender_mismatch", f"a message of {sender!r} on {src}'s key", log)
                return
            clock.update(head)  # the world's clock from the message (a verified one on a signed fleet)
            t_recv = clock.now(msg.t_recv_wall_ns)
            if t_recv is not None:  # on the world's clock, which the fused states' times are on
                newest_input["t"] = t_recv if newest_input["t"] is None else max(newest_input["t"], t_recv)
            else:
                if not warned.is_set():
                    warned.set()
                    log.warning("no world clock in the messages; receive times are seconds since start")
                t_recv = time.monotonic() - t0_mono
            try:
                inbox.put_nowait(("ingest", out.payload, t_recv))
            except queue.Full:
                svc.metrics.reject("queue_full", f"fusion inbox full ({s.inbox})", log)

        def subscriber(name: str):
            """on_msg for the keys of topic ``name``: the source from the key, one gate per topic."""
            tp, gate = topic(name), topic_gate(name, verifier, s.time_scale)

            def cb(msg: Received) -> None:
                where = tp.parse(msg.key)
                if where is None:
                    svc.metrics.reject("bad_key", f"{msg.key} is not a {name} key of ours", log)
                else:
                    on_msg(msg, where, gate, name)

            return cb

        kind = "prior" if s.host.mode == "distributed" else "raw"
        svc.subscribe(topic(f"{kind}_rx").pattern(fleet=s.fleet, dst=hid), subscriber(f"{kind}_rx"))
        for src in s.host.local:
            svc.subscribe(topic(f"{kind}_tx").key(fleet=s.fleet, src=src), subscriber(f"{kind}_tx"))

        down_pubs: dict[str, Any] = {}
        # a Signer per vehicle: a Signer sends its certificate with the first message it signs in a second,
        # and each vehicle reads only its own downlink, so one shared Signer would leave some without it
        down_signers: dict[str, Signer] = {}

        def send_downlink(vid: str, payload: bytes) -> None:
            """The downlink to ``vid``, through the channel emulator, signed like the fused state."""
            if not is_chunk(vid):
                return
            pub = down_pubs.get(vid)
            if pub is None:
                pub = down_pubs[vid] = svc.publisher(topic("downlink_tx").key(fleet=s.fleet, src=hid, dst=vid))
            payload = with_fields(payload, PoseDownlink, **clock.fields())
            if credentials is not None:
                payload = down_signers.setdefault(vid, Signer(credentials)).sign(payload, time.time())
            pub.put(payload, attachment=make_attachment(t_wall_ns=time.time_ns(), **clock.fields()))
            fig["downlink_sent"] += 1
            fig["downlink_bytes"] += len(payload)

        def drain() -> None:
            nonlocal rc
            while not svc.stop_requested.is_set():
                try:
                    item = outbox.get(timeout=0.2)
                except queue.Empty:
                    if not worker.is_alive():
                        log.error("the fusion worker exited (exit code %s)", getattr(worker, "exitcode", None))
                        fig["worker_alive"] = 0.0
                        rc = 1
                        svc.stop()
                    continue
                if item[0] == "error":
                    svc.metrics.error(item[1].strip().splitlines()[-1])
                    log.error("fusion error:\n%s", item[1])
                    continue
                results = item[-1]
                if item[0] == "fused":
                    _, payload, t, solve_s, stats, solved, downlinks, results = item
                    active = primary is None or not primary.is_set()
                    if active:
                        payload = with_fields(payload, FusedState, **clock.fields())  # the clock, under the signature
                        if signer is not None:
                            payload = signer.sign(payload, time.time())
                        fused_pub.put(
                            payload,
                            attachment=make_attachment(t_wall_ns=time.time_ns(), t_fused=t, **solved, **clock.fields()),
                        )
                        fig["fused_published"] += 1
                        for vid, down in downlinks:
                            send_downlink(vid, down)
                    if primary is not None:
                        fig["standby_active"] = float(active)
                    svc.metrics.latency.add(solve_s)
                    fig["solve_ms"] = solve_s * 1e3
                    was = core_stats["stats"].get("flagged_why") or {}
                    now = stats.get("flagged_why") or {}
                    for v in sorted(now.keys() - was.keys()):
                        log.warning("flagged %s at t=%.2f: %s", v, t, now[v])
                    for v in sorted(was.keys() - now.keys()):
                        log.info("%s no longer flagged at t=%.2f", v, t)
                    core_stats["stats"] = stats
                for accepted, reason, _ in results:
                    if not accepted:
                        svc.metrics.reject(reason or "rejected", "by the container", log)
                if item[0] == "fused":
                    fused_at.update(t=time.monotonic(), rejects=dict(svc.metrics.rejects), t_meas=item[2])

        svc.spawn(drain, "drain")
        svc.wait()
    try:
        inbox.put(("stop",), timeout=1.0)
    except queue.Full:
        pass
    worker.join(timeout=5.0)
    if not s.inline:
        if worker.is_alive():
            worker.terminate()
        inbox.cancel_join_thread()  # do not wait on bytes nobody will read
    return rc
