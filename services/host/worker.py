"""The host loop (:class:`mapcontainer.host.HostLoop`) fed through queues, run in a worker process.

GTSAM holds the GIL for a whole solve (docs/architecture.md, "The host"), so the container runs in a
process started with the ``spawn`` context (never ``fork`` after a Zenoh session is open: docs/architecture.md,
"Processes and Zenoh"), and the host service's main process only does Zenoh I/O. The same loop runs in
a thread with ``--inline`` (for comparison and debugging). What is fused, and when, is the core's
(``build_host(setup)``): this module only moves items between the queues and the loop, on this
process's monotonic clock.

Protocol (tuples on the queues):
  inbox:  ("ingest", payload: bytes, t_recv: float) | ("stop",)
  outbox: ("ready", pid) | ("error", text)
          | ("fused", payload: bytes, t: float, solve_s: float, stats: dict, solved, downlinks, results)
          | ("results", results)
  results: [(accepted: bool, reason: str | None, ingest_s: float), ...]
  solved: {"tol": the frame tolerance passed to fuse, "inputs": [[sender, seq, t_recv], ...]}: every payload
          ingested since the previous solve, in order (the host publishes it in the fused state's attachment,
          so that a recording can be re-fused exactly: mapcontainer.recording.replay)
  downlinks: [(vehicle id, PoseDownlink bytes), ...] after the solve when the set-up asks for the downlink
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

from mapcontainer.host import HostSetup
from schemas import encode

__all__ = ["fusion_loop", "fusion_process"]


def fusion_process(setup: HostSetup, inbox, outbox, parent_pid: int) -> None:
    """The worker process's entry point: Ctrl-C and SIGINT go to the service, which sends ("stop",)."""
    from mapcontainer.fusion.blas import limit_blas_threads

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    limit_blas_threads(1)  # small dense solves: one BLAS thread is faster and steadier here
    fusion_loop(setup, inbox, outbox, parent_pid)


def fusion_loop(setup: HostSetup, inbox, outbox, parent_pid: int | None = None) -> None:
    """Run the host loop (:func:`mapcontainer.host.build_host`) until ("stop",) arrives or the parent is gone."""
    from mapcontainer.host import build_host

    try:
        host = build_host(setup)
    except Exception:
        outbox.put(("error", traceback.format_exc()))
        return
    outbox.put(("ready", os.getpid()))
    results: list[tuple[bool, str | None, float]] = []
    last_flush = time.monotonic()
    while True:
        deadline = host.next_deadline()
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
            t0 = time.perf_counter()
            try:
                r = host.receive(item[1], item[2], time.monotonic())
            except Exception:  # a defect, not bad input (ingest refuses that): report it, keep fusing
                outbox.put(("error", traceback.format_exc()))
                results.append((False, "ingest_error", time.perf_counter() - t0))
                continue
            results.append((r.accepted, r.reason, time.perf_counter() - t0))
        try:
            fused = host.step(time.monotonic())
        except Exception:
            outbox.put(("error", traceback.format_exc()))
            fused = None
        if fused is not None:
            solved = {"tol": fused.tolerance_s, "inputs": fused.inputs}
            down = [(m.target, encode(m)) for m in host.downlink(fused.t)] if setup.downlink else []
            outbox.put(("fused", fused.payload(), fused.t, fused.wall_s, host.stats(), solved, down, results))
            results = []
            last_flush = time.monotonic()
        if results and time.monotonic() - last_flush > 0.5:
            outbox.put(("results", results))
            results, last_flush = [], time.monotonic()
