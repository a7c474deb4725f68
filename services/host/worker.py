"""The fusion loop: the host container's core, fed through queues, run in a worker process.

GTSAM holds the GIL for a whole solve (docs/architecture.md, "The host"), so the container runs in a
process started with the ``spawn`` context (never ``fork`` after a Zenoh session is open: docs/architecture.md,
"Processes and Zenoh"), and the host service's main process only does Zenoh I/O. The same loop runs in
a thread with ``--inline`` (for comparison and debugging).

Protocol (tuples on the queues):
  inbox:  ("ingest", payload: bytes, t_recv: float) | ("stop",)
  outbox: ("ready", pid) | ("error", text)
          | ("fused", payload: bytes, t: float, solve_s: float, stats: dict, solved, results)
          | ("results", results)
  results: [(accepted: bool, reason: str | None, ingest_s: float), ...]
  solved: {"tol": the frame tolerance passed to fuse, "inputs": [[sender, seq, t_recv], ...]}: every payload
          ingested since the previous solve, in order (the host publishes it in the fused state's attachment,
          so that a recording can be re-fused exactly: mapcontainer.recording.replay)
The loop solves once per camera frame, at the frame's ``t_meas`` (so the evaluator compares the
state with the ground truth of that very frame), when :class:`mapcontainer.fusion.gate.FrameGate`
releases it: the same gate decides when :func:`mapcontainer.pipeline.run_pipeline` solves, there on
simulated arrival times, here on this process's monotonic clock (``max_wait_s`` is wall seconds).
"""

from __future__ import annotations

import os
import queue
import signal
import time
import traceback
from typing import Any

__all__ = ["FusionSpec", "fusion_loop", "fusion_process", "make_core"]

FusionSpec = dict[str, Any]  # scenario, mode, fleet, host_id, known_senders, params, max_wait_s, reference


def make_core(spec: FusionSpec):
    """The host's core: ``mapcontainer.host.make_host`` (distributed or centralized container)."""
    from mapcontainer.fusion import FusionParams
    from mapcontainer.host import make_host
    from mapcontainer.sim.config import load_scenario
    from mapcontainer.sim.errors import published_map

    params = FusionParams(**spec["params"]) if spec.get("params") else FusionParams()
    known = set(spec["known_senders"]) if spec.get("known_senders") else None
    # the centralized mode localizes against the run's published map (the vehicles' own, HD-map error included)
    hdmap = published_map(load_scenario(spec["scenario"]), spec.get("seed", 0))
    return make_host(hdmap, params, spec["fleet"], spec["host_id"], spec["mode"], known_senders=known)


def _stats(core) -> dict:
    fn = getattr(core, "stats", None)
    try:
        return dict(fn()) if fn else {}
    except Exception as e:  # figures only
        return {"stats_error": str(e)}


def _envelope(peek, payload: bytes) -> tuple[str, float] | None:
    """(sender, t_meas) of an accepted payload, for the frame gate (``peek``: schemas.codec.peek)."""
    obj = peek(payload)  # the container has accepted it; this is only for choosing the solve time
    sender, t = obj.get("sender"), obj.get("t_meas")
    return (sender, float(t)) if isinstance(sender, str) and isinstance(t, int | float) else None


def fusion_process(spec: FusionSpec, inbox, outbox, parent_pid: int) -> None:
    """The worker process's entry point: Ctrl-C and SIGINT go to the service, which sends ("stop",)."""
    from mapcontainer.fusion import limit_blas_threads

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    limit_blas_threads(1)  # small dense solves: one BLAS thread is faster and steadier here
    fusion_loop(spec, inbox, outbox, parent_pid)


def __getattr__(name: str):
    """``FrameGate`` lives in mapcontainer.fusion.gate: imported on use, since importing
    mapcontainer.fusion loads the solver, which the host's main process never needs."""
    if name == "FrameGate":
        from mapcontainer.fusion.gate import FrameGate

        return FrameGate
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def fusion_loop(spec: FusionSpec, inbox, outbox, parent_pid: int | None = None) -> None:
    """Run until ("stop",) arrives or the parent process is gone."""
    from mapcontainer.fusion.gate import MAX_WAIT_S, FrameGate
    from schemas.codec import encode, peek

    try:
        core = make_core(spec)
    except Exception:
        outbox.put(("error", traceback.format_exc()))
        return
    outbox.put(("ready", os.getpid()))
    gate = FrameGate(
        set(spec["known_senders"] or ()) or None, spec.get("max_wait_s", MAX_WAIT_S), reference=spec.get("reference")
    )
    results: list[tuple[bool, str | None, float]] = []
    inputs: list[list] = []  # [sender, seq, t_recv] of every payload ingested since the last solve
    last_flush = time.monotonic()
    while True:
        deadline = gate.next_deadline()
        wait = 0.2 if deadline is None else min(0.2, max(0.0, deadline - time.monotonic()))
        try:
            items = [inbox.get(timeout=wait)] if wait > 0 else []
        except queue.Empty:
            items = []
            if parent_pid is not None and os.getppid() != parent_pid:
                return
        while True:  # take everything that is waiting: ingest all, then solve at most once
            try:
                items.append(inbox.get_nowait())
            except queue.Empty:
                break
        for item in items:
            if item[0] == "stop":
                return
            head = peek(item[1])
            if isinstance(head.get("sender"), str) and isinstance(head.get("seq"), int):
                inputs.append([head["sender"], head["seq"], float(item[2])])
            t0 = time.perf_counter()
            try:
                r = core.ingest(item[1], item[2])
            except Exception:  # a defect, not bad input (ingest refuses that): report it, keep fusing
                outbox.put(("error", traceback.format_exc()))
                results.append((False, "ingest_error", time.perf_counter() - t0))
                continue
            accepted = bool(getattr(r, "accepted", r))
            if accepted:
                head = _envelope(peek, item[1])
                if head is not None:
                    gate.arrived(head[0], head[1], time.monotonic())
            results.append((accepted, getattr(r, "reason", None), time.perf_counter() - t0))
        t = gate.due(time.monotonic())
        if t is not None:
            t0 = time.perf_counter()
            try:
                payload = encode(core.fuse(t, gate.tolerance_s))
            except Exception:
                outbox.put(("error", traceback.format_exc()))
                payload = None
            solve_s = time.perf_counter() - t0
            if payload is not None:
                stats = {**_stats(core), "frames_complete": gate.complete, "frames_timed_out": gate.timed_out}
                outbox.put(("fused", payload, t, solve_s, stats, {"tol": gate.tolerance_s, "inputs": inputs}, results))
                results, inputs = [], []
                last_flush = time.monotonic()
        if results and time.monotonic() - last_flush > 0.5:
            outbox.put(("results", results))
            results, last_flush = [], time.monotonic()
