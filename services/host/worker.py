"""The fusion loop: the host container's core, fed through queues, run in a worker process.

GTSAM holds the GIL for a whole solve (DESIGN.md §5), so the container runs in a process started
with the ``spawn`` context (never ``fork`` after a Zenoh session is open: ZENOH.md), and the host
service's main process only does Zenoh I/O. The same loop runs in a thread with ``--inline``
(for comparison and debugging).

Protocol (tuples on the queues):
  inbox:  ("ingest", payload: bytes, t_recv: float) | ("stop",)
  outbox: ("ready", pid) | ("error", text)
          | ("fused", payload: bytes, t: float, solve_s: float, stats: dict, results)
          | ("results", results)
  results: [(accepted: bool, reason: str | None, ingest_s: float), ...]
The loop solves once per camera frame, at the frame's ``t_meas`` (as pipeline.py does, so the
evaluator compares the state with the ground truth of that very frame), when :class:`FrameGate`
says the frame is ready.
"""

from __future__ import annotations

import os
import queue
import signal
import time
import traceback
from typing import Any

__all__ = ["FrameGate", "FusionSpec", "fusion_loop", "fusion_process", "make_core"]

FusionSpec = dict[str, Any]  # scenario, mode, fleet, host_id, known_senders, params, max_wait_s (picklable)


def make_core(spec: FusionSpec):
    """The host's core: ``mapcontainer.host.make_host`` (distributed or centralized container)."""
    from mapcontainer.fusion import FusionParams
    from mapcontainer.hdmap.generator import generate_map
    from mapcontainer.host import make_host
    from mapcontainer.sim.config import load_scenario

    params = FusionParams(**spec["params"]) if spec.get("params") else FusionParams()
    known = set(spec["known_senders"]) if spec.get("known_senders") else None
    hdmap = generate_map(load_scenario(spec["scenario"]).map)  # the centralized mode localizes against it
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


class FrameGate:
    """When to solve: once per camera frame, when the frame is complete or has waited long enough.

    Frames are keyed by ``t_meas``. The frame ``t`` is *ready* when every expected sender has
    delivered its message for ``t`` (the known senders; without a list, those heard from in the last
    ``active_s``), or ``max_wait_s`` (wall) after its first message arrived. :meth:`due` returns the
    newest ready frame newer than the last one solved; older unsolved frames are then dropped (their
    messages are in the container and count in the next solve). Solving a frame before a vehicle's
    message for it has arrived would publish that vehicle's previous pose as its pose at ``t`` (about
    v * 0.1 s off), so the gate trades up to ``max_wait_s`` of latency for simultaneous states.
    """

    def __init__(self, expected: set[str] | None, max_wait_s: float, active_s: float = 2.0):
        if max_wait_s < 0:
            raise ValueError(f"max_wait_s must be >= 0, got {max_wait_s}")
        self.expected = set(expected) if expected else None
        self.max_wait_s = max_wait_s
        self.active_s = active_s
        self._frames: dict[int, tuple[float, float, set[str]]] = {}  # key -> (t_meas, first arrival, senders)
        self._heard: dict[str, float] = {}
        self._last_key: int | None = None
        self.timed_out = 0
        self.complete = 0

    def arrived(self, sender: str, t_meas: float, now: float) -> None:
        self._heard[sender] = now
        key = int(round(t_meas * 1000))
        if self._last_key is not None and key <= self._last_key:
            return
        frame = self._frames.setdefault(key, (t_meas, now, set()))
        frame[2].add(sender)

    def _expected(self, now: float) -> set[str]:
        if self.expected is not None:
            return self.expected
        return {s for s, t in self._heard.items() if now - t <= self.active_s}

    def due(self, now: float) -> float | None:
        expected = self._expected(now)
        ready = None
        for key, (t, first, senders) in self._frames.items():
            full = expected <= senders
            if full or now - first >= self.max_wait_s:
                if ready is None or key > ready[0]:
                    ready = (key, t, full)
        if ready is None:
            return None
        key, t, full = ready
        self.complete += full
        self.timed_out += not full
        self._last_key = key
        self._frames = {k: v for k, v in self._frames.items() if k > key}
        return t

    def next_deadline(self) -> float | None:
        return min((first + self.max_wait_s for _, first, _ in self._frames.values()), default=None)


def fusion_loop(spec: FusionSpec, inbox, outbox, parent_pid: int | None = None) -> None:
    """Run until ("stop",) arrives or the parent process is gone."""
    from schemas.codec import encode, peek

    try:
        core = make_core(spec)
    except Exception:
        outbox.put(("error", traceback.format_exc()))
        return
    outbox.put(("ready", os.getpid()))
    gate = FrameGate(set(spec["known_senders"] or ()) or None, spec.get("max_wait_s", 0.1))
    results: list[tuple[bool, str | None, float]] = []
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
                payload = encode(core.fuse(t))
            except Exception:
                outbox.put(("error", traceback.format_exc()))
                payload = None
            solve_s = time.perf_counter() - t0
            if payload is not None:
                stats = {**_stats(core), "frames_complete": gate.complete, "frames_timed_out": gate.timed_out}
                outbox.put(("fused", payload, t, solve_s, stats, results))
                results = []
                last_flush = time.monotonic()
        if results and time.monotonic() - last_flush > 0.5:
            outbox.put(("results", results))
            results, last_flush = [], time.monotonic()
