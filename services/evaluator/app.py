"""Evaluator service: live RMSE, end-to-end latency, bytes/s per vehicle and delivered fraction.

Subscribes ground truth, every host's fused state, the vehicles' ``v2x/tx`` (bytes each vehicle
sends) and the channel's ``v2x/rx`` (what arrived); the figures are defined in
:mod:`services.evaluator.core`. Once a second it publishes :class:`schemas.EvalMetrics` on the
registry's ``metrics`` topic (``mc/{fleet}/eval/metrics``). It streams ``eval_frames.csv`` (one row
per scored fused state, :func:`mapcontainer.evaluation.frame_row`) to ``--out`` as it goes, and on stop
writes ``eval_summary.json``, ``birdseye.png`` (truth vs fused, covariance ellipses) and ``errors.png``
(error over scenario time) there (:mod:`services.evaluator.plot`).
Callbacks only enqueue; one worker thread decodes and evaluates. With ``--keys`` (a signed fleet) it
believes only ground truth signed by the world and fused states signed by their host (or its standby),
counting what it refuses by reason in its health, and signs its metrics.
"""

from __future__ import annotations

import argparse
import csv
import queue
import time
from collections import OrderedDict
from pathlib import Path

from pydantic import Field

from mapcontainer.security import (
    CA_NAME,
    VERIFY_WINDOW_S,
    Signer,
    Verifier,
    fused_signers,
    inner_payload,
    load_certificate,
    load_credentials,
    unwrap,
)
from mapcontainer.sim.config import load_scenario
from schemas import FusedState, GroundTruth, encode
from schemas.codec import Rejection, peek
from schemas.topics import topic

from ..channel.app import parse_receivers
from ..runtime import (
    Received,
    Service,
    ServiceSettings,
    SimClock,
    add_service_args,
    service_settings_from_args,
    setup_logging,
    write_json,
)
from .core import Evaluator

__all__ = ["EvaluatorSettings", "frames_writer", "main", "parse_args"]


class EvaluatorSettings(ServiceSettings):
    scenario: str | None = "paper-urban"  # for the map in the picture; None: no map
    out: str | None = None
    receivers: dict[str, list[str]] = Field(default_factory=lambda: {"host": []})
    window_s: float = 5.0
    burnin_s: float = Field(5.0, ge=0, description="scenario seconds left out of the steady-state figures")
    stale_input_s: float | None = None
    keys: str | None = Field(
        None, description="the fleet's keys directory: believe signed truth and fused states only, sign the metrics"
    )


def parse_args(argv: list[str] | None = None) -> EvaluatorSettings:
    p = argparse.ArgumentParser(prog="python -m services.evaluator", description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="paper-urban", help="for the map in the picture")
    p.add_argument("--out", default=None, help="directory for eval_summary.json, birdseye.png and errors.png")
    p.add_argument("--receiver", action="append", default=None, help="as for the channel: host=cv0")
    p.add_argument("--window", type=float, default=5.0, help="seconds of the sliding window")
    p.add_argument("--burnin", type=float, default=5.0, help="scenario seconds not in the steady-state figures")
    p.add_argument(
        "--keys", default=None, help="the fleet's keys directory: verify truth and fused states, sign the metrics"
    )
    add_service_args(p, "evaluator", default_id="evaluator")
    a = p.parse_args(argv)
    base = service_settings_from_args(a).model_dump()
    base["stale_input_s"] = None
    return EvaluatorSettings(
        **base,
        scenario=a.scenario,
        out=a.out,
        receivers=parse_receivers(a.receiver),
        window_s=a.window,
        burnin_s=a.burnin,
        keys=a.keys,
    )


def frames_writer(path: Path):
    """``(file, writerow)``: the per-frame rows' CSV, its header written; rows go to the file as they come
    (a run of any length keeps none of them in memory)."""
    from mapcontainer.evaluation import frame_row_fields

    f = path.open("w", newline="")  # noqa: SIM115 - closed by main after the run
    w = csv.DictWriter(f, fieldnames=frame_row_fields())
    w.writeheader()
    return f, w.writerow


def _seq(payload: bytes) -> int | None:
    """The sequence number of a V2X message, signed or not (unverified: it only counts deliveries)."""
    seq = peek(inner_payload(payload)).get("seq")  # {} for what is not our message: bytes, not a delivery
    return seq if isinstance(seq, int) else None



class FrameWallTimes:
    """The wall time of each recent frame of the world, on the epoch its truth was sent with.

    The end-to-end latency of a fused state is measured from its frame's wall time. The clock's newest
    epoch gives the wrong one for a frame from before a pause of the adaptive clock (the epoch moved on by
    the pause, so the latency came out short by it); the truth of the frame says when the frame was.
    """

    def __init__(self, keep: int = 600) -> None:
        self._ns: OrderedDict[float, int] = OrderedDict()
        self._keep = keep

    def record(self, truth: GroundTruth) -> None:
        if truth.epoch_wall_ns is None or not truth.time_scale:
            return
        self._ns[round(truth.t_meas, 6)] = truth.epoch_wall_ns + int(round(truth.t_meas / truth.time_scale * 1e9))
        while len(self._ns) > self._keep:
            self._ns.popitem(last=False)

    def get(self, t_meas: float) -> int | None:
        return self._ns.get(round(t_meas, 6))

def main(s: EvaluatorSettings) -> int:
    log = setup_logging("evaluator", s.id, s.log_level)
    log.info("settings: %s", s.model_dump_json())
    scenario = load_scenario(s.scenario) if s.scenario else None  # an unknown name: ConfigError at start
    hdmap = None
    if scenario is not None and s.out:  # the pictures' map, read now: at the stop there is only a grace period
        from mapcontainer.sim.maps import world_map

        hdmap = world_map(scenario)
    onboard = {k: set(v) for k, v in s.receivers.items()}
    frames_f, sink = None, None
    if s.out:
        Path(s.out).mkdir(parents=True, exist_ok=True)
        frames_f, sink = frames_writer(Path(s.out) / "eval_frames.csv")
    ev = Evaluator(
        s.fleet, evaluator_id=s.id, window_s=s.window_s, onboard=onboard, burnin_s=s.burnin_s, frame_sink=sink
    )
    clock = SimClock()
    # signed fleets: truth from the world, fused states from their host (or its standby), each verified
    verifier = Verifier(load_certificate(s.keys, CA_NAME), window_s=VERIFY_WINDOW_S) if s.keys else None
    signer = Signer(load_credentials(s.keys, s.id)) if s.keys else None
    work: queue.Queue[tuple[str, Received]] = queue.Queue(maxsize=10_000)
    latest: dict = {"figures": {}}  # replaced whole, never mutated: the health thread reads it

    with Service("evaluator", s, figures=lambda: latest["figures"], keys=s.keys) as svc:
        pub = svc.publisher(topic("metrics").key(fleet=s.fleet), drop=True)

        def enqueue(kind: str):
            def cb(msg: Received) -> None:
                try:
                    work.put_nowait((kind, msg))
                except queue.Full:
                    svc.metrics.reject("queue_full", "evaluator falls behind", log)

            return cb

        svc.subscribe(topic("truth").key(fleet=s.fleet), enqueue("truth"))
        svc.subscribe(topic("fused").pattern(fleet=s.fleet), enqueue("fused"))
        for kind in ("prior", "raw"):
            svc.subscribe(topic(f"{kind}_tx").pattern(fleet=s.fleet), enqueue(f"{kind}_tx"))
            svc.subscribe(topic(f"{kind}_rx").pattern(fleet=s.fleet), enqueue(f"{kind}_rx"))

        frame_wall = FrameWallTimes()

        def believed(msg: Received, model, senders):
            """The message, verified (signed fleets) and decoded; None, counted, if it is refused."""
            inner = unwrap(msg.payload, verifier, time.time(), senders)
            if isinstance(inner, Rejection):
                svc.metrics.reject(inner.reason, f"{model.__name__} on {msg.key}: {inner.detail}", log)
                return None
            return svc.decode_or_reject(inner, model)

        def process(kind: str, msg: Received) -> None:
            now = time.time()
            if kind == "truth":
                truth = believed(msg, GroundTruth, "world")
                if truth is not None:
                    clock.update(truth)  # the world's clock, from the message
                    frame_wall.record(truth)
                    ev.on_truth(truth)
            elif kind == "fused":
                where = topic("fused").parse(msg.key)
                fused = believed(msg, FusedState, fused_signers(where["hid"])) if where else None
                if fused is not None:
                    clock.update(fused)
                    pub_ns = msg.attachment.get("t_wall_ns")
                    pub_ns = pub_ns if isinstance(pub_ns, int) and pub_ns > 0 else msg.t_recv_wall_ns
                    meas_ns = frame_wall.get(fused.t_meas)  # when the frame was, on its own epoch
                    ev.on_fused(fused, pub_ns, clock.wall_ns(fused.t_meas) if meas_ns is None else meas_ns, now)
            else:  # a V2X topic: who sent it (and to whom) is in its key
                where = topic(kind).parse(msg.key)
                if where is None:
                    svc.metrics.reject("bad_key", f"{msg.key} is not a {kind} key of ours", log)
                elif kind.endswith("_tx"):
                    ev.on_tx(where["src"], _seq(msg.payload), len(msg.payload), now)
                else:
                    ev.on_rx(where["dst"], where["src"], _seq(msg.payload), now)

        def loop() -> None:
            next_pub = time.monotonic() + 1.0
            while not svc.stop_requested.is_set():
                try:
                    kind, msg = work.get(timeout=max(0.0, min(0.2, next_pub - time.monotonic())))
                    t0 = time.perf_counter()
                    process(kind, msg)
                    svc.metrics.latency.add(time.perf_counter() - t0)
                except queue.Empty:
                    pass
                except Exception as exc:  # one message the evaluator cannot score must not end the run
                    svc.metrics.reject("unscorable", f"{kind} on {msg.key}: {type(exc).__name__}: {exc}", log)
                if time.monotonic() >= next_pub:
                    next_pub += 1.0
                    if frames_f is not None:
                        frames_f.flush()
                    try:
                        m = ev.snapshot(time.time())
                    except Exception as exc:  # figures that do not validate: report, keep evaluating
                        svc.metrics.error(f"snapshot: {type(exc).__name__}: {exc}")
                        log.exception("could not make the metrics snapshot")
                        continue
                    latest["figures"] = {
                        k: v
                        for k, v in m.model_dump().items()
                        if isinstance(v, int | float) and k not in ("seq", "t_wall")
                    }
                    pub.put(encode(m) if signer is None else signer.sign(encode(m), time.time()))

        svc.spawn(loop, "evaluate")
        svc.wait()
    # the session is closed: write the run's outputs
    if s.out:
        out = Path(s.out)
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "eval_summary.json", ev.summary())
        frames_f.close()
        try:
            from .plot import render_birdseye, render_errors

            render_birdseye(out / "birdseye.png", ev, hdmap, f"fleet {s.fleet}: {s.scenario}")
            render_errors(out / "errors.png", ev, f"fleet {s.fleet}: {s.scenario}")
        except Exception:  # the pictures are a convenience; the summary is already written
            log.exception("could not draw the run's pictures")
        log.info("wrote %s", out / "eval_summary.json")
    return 0
