"""The host container in either architecture (paper, "Distributed Fusion Architecture"): its set-up, and the
one loop that every driver runs.

* distributed: vehicles localize themselves and send VehiclePriors; the
  :class:`~mapcontainer.fusion.Container` fuses them in its sliding-window factor graph.
* centralized: vehicles send RawObservations; the :class:`~mapcontainer.fusion.joint.JointHost` estimates
  every vehicle and object jointly from them (the accuracy reference), against the host's HD map.

Both are a :class:`~mapcontainer.fusion.hostcore.HostCore`. A :class:`HostSetup` says how a host runs;
:func:`build_host` makes its :class:`HostLoop`: the core plus the :class:`~mapcontainer.fusion.gate.FrameGate`
that decides when a frame is solved, time an argument everywhere. The drivers only move bytes and clocks:

* :func:`mapcontainer.pipeline.run_pipeline`: simulated arrival times, one loop per host view;
* ``services.host``: the live host, Zenoh receive times, the gate on the process's monotonic clock;
* :func:`mapcontainer.recording.replay.refuse`: a recording's inputs (the recorded input sets, or the
  recorded arrivals through the gate).

The host's map arrives as a map: a file in any format :func:`~mapcontainer.hdmap.formats.read_any_map`
reads (``HostSetup.map_file``), or an :class:`~mapcontainer.hdmap.model.HDMap` handed to :func:`build_host`.
Only the centralized host uses it (it localizes the vehicles); nothing here needs the simulator.

This module imports neither GTSAM nor the estimators until :func:`build_host` runs, so a process that only
configures a host (the host service's main process) stays light.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from schemas.codec import encode, peek
from schemas.models import FusedState, PoseDownlink

from .fusion.gate import MAX_WAIT_S, FrameGate
from .fusion.params import FusionParams

if TYPE_CHECKING:
    from .fusion.hostcore import HostCore, IngestResult
    from .hdmap.model import HDMap

__all__ = [
    "Fused",
    "HostLoop",
    "HostSetup",
    "add_host_args",
    "build_host",
    "host_setup_from_args",
    "load_host_map",
]

_EPS_S = 1e-9  # a deadline counts as reached at that very time (float rounding)


class HostSetup(BaseModel):
    """How a host container runs: everything :func:`build_host` needs, nothing about transport."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    fleet: str = Field(description="the fleet namespace: messages of another fleet are refused")
    host_id: str = Field("host", description="the sender id of the fused states")
    mode: Literal["distributed", "centralized"] = "distributed"
    known_senders: tuple[str, ...] | None = Field(
        None, description="the only senders taken, and the ones a frame waits for (None: anyone, the recently heard)"
    )
    local: tuple[str, ...] = Field(
        (), description="on-board senders (their messages do not cross the radio); the first one's clock times frames"
    )
    max_wait_s: float = Field(MAX_WAIT_S, ge=0, description="how long a frame waits for its late senders")
    params: FusionParams = Field(default_factory=FusionParams)
    map_file: str | None = Field(None, description="the HD map (any supported format); the centralized host needs one")
    downlink: bool = Field(
        False, description="after each solve, send every vehicle what the others know about it (HostLoop.downlink)"
    )

    @property
    def reference(self) -> str | None:
        """The sender whose frame times the host solves at (the vehicle it runs on), if any."""
        return self.local[0] if self.local else None


def load_host_map(path: str | Path) -> HDMap:
    """The HD map in ``path``: GeoJSON, SUMO network or Lanelet2 OSM (MapFileError if it cannot be read)."""
    from .hdmap.formats import read_any_map

    return read_any_map(path).hdmap


def build_host(setup: HostSetup, hdmap: HDMap | None = None) -> HostLoop:
    """The host of ``setup``: its core and its frame gate. ``hdmap`` (centralized mode): the map, else read from
    ``setup.map_file``; ValueError when the centralized host has neither."""
    if setup.mode == "distributed":
        from .fusion.container import Container

        core: HostCore = Container(setup.params, setup.fleet, setup.host_id, _known(setup))
    else:
        from .fusion.joint import JointHost

        if hdmap is None:
            if setup.map_file is None:
                raise ValueError("the centralized host localizes the vehicles against an HD map: give one (map_file)")
            hdmap = load_host_map(setup.map_file)
        core = JointHost(hdmap, setup.params, setup.fleet, setup.host_id, _known(setup))
    return HostLoop(core, FrameGate(_known(setup), setup.max_wait_s, reference=setup.reference))


def _known(setup: HostSetup) -> set[str] | None:
    return set(setup.known_senders) if setup.known_senders else None


@dataclass(frozen=True)
class Fused:
    """One solve: the fused state at ``t``, what it took in, and what it cost."""

    state: FusedState
    t: float
    tolerance_s: float
    # [sender, seq, t_recv] of every payload received since the previous solve, in order: with t and
    # tolerance_s, what re-fusing a recording exactly needs (the host service publishes it)
    inputs: list[list] = field(default_factory=list)
    wall_s: float = 0.0  # the solve's duration
    cpu_s: float = 0.0  # its CPU time in this thread
    released: float | None = None  # the gate's time that released it (None: solved at a time given, ``fuse``)

    def payload(self) -> bytes:
        return encode(self.state)


class HostLoop:
    """A host core behind its frame gate: ``receive`` payloads, ``step`` (or ``timeouts``) to solve what is due.

    Time is an argument: ``t_recv`` is the scenario time a payload arrived (the core's clock: staleness,
    the window), ``now`` the gate's clock (the driver's: simulated arrival times, a monotonic clock),
    ``t_recv`` when not given. Deterministic for a given sequence of calls.
    """

    def __init__(self, core: HostCore, gate: FrameGate):
        self.core = core
        self.gate = gate
        self._inputs: list[list] = []
        self._downlink_seq = 0

    def receive(self, payload: bytes, t_recv: float, now: float | None = None) -> IngestResult:
        """Into the core; an accepted message tells the gate its sender and frame. A defect of the core (it
        refuses bad input itself) propagates; the payload still counts as received for the next solve."""
        head = peek(payload)
        sender, seq, t_meas = head.get("sender"), head.get("seq"), head.get("t_meas")
        if isinstance(sender, str) and isinstance(seq, int):
            self._inputs.append([sender, seq, float(t_recv)])
        r = self.core.ingest(payload, t_recv)
        if r.accepted and isinstance(sender, str) and isinstance(t_meas, int | float):
            self.gate.arrived(sender, float(t_meas), t_recv if now is None else now)
        return r

    def next_deadline(self) -> float | None:
        """When the earliest pending frame times out (the gate's clock), None when none is pending."""
        return self.gate.next_deadline()

    def due(self, now: float) -> float | None:
        """The frame to solve at ``now`` (FrameGate.due), or None."""
        return self.gate.due(now)

    def step(self, now: float) -> Fused | None:
        """Solve the frame due at ``now``, if one is."""
        t = self.gate.due(now)
        return None if t is None else self._solve(t, self.gate.tolerance_s, now)

    def timeouts(self, until: float) -> list[Fused]:
        """Solve, in order, every frame that times out by ``until`` (a deadline at ``until`` included)."""
        out = []
        while (d := self.gate.next_deadline()) is not None and d <= until + _EPS_S:
            f = self.step(d)
            if f is None:
                break
            out.append(f)
        return out

    def fuse(self, t: float, tolerance_s: float | None = None) -> Fused:
        """Solve frame ``t`` now, whatever the gate says (re-fusion at recorded times); the gate forgets the
        frames up to it. ``tolerance_s``: the gate's when None."""
        tol = self.gate.tolerance_s if tolerance_s is None else float(tolerance_s)
        self.gate.solved(float(t))
        return self._solve(float(t), tol)

    def _solve(self, t: float, tolerance_s: float, now: float | None = None) -> Fused:
        w0, c0 = time.perf_counter(), time.thread_time()
        state = self.core.fuse(t, tolerance_s)
        cpu_s, wall_s = time.thread_time() - c0, time.perf_counter() - w0
        inputs, self._inputs = self._inputs, []
        return Fused(state, t, tolerance_s, inputs, wall_s, cpu_s, now)

    def downlink(self, t_sent: float) -> list[PoseDownlink]:
        """What the host owes each vehicle after a solve: what the others know about its pose, its own share
        removed (:mod:`mapcontainer.downlink`), one PoseDownlink per vehicle the others know something about.
        Empty for a core that cannot separate a vehicle's own share (the centralized host: its vehicles
        send raw observations and keep no estimate of their own to fuse it with)."""
        make = getattr(self.core, "downlink", None)
        if make is None:
            return []
        out = make(t_sent, self._downlink_seq)
        self._downlink_seq += len(out)
        return out

    def stats(self) -> dict[str, Any]:
        """The core's figures and the gate's frame counts (a core's figures failing leaves the reason)."""
        try:
            out = dict(self.core.stats())
        except Exception as e:  # figures only: never a reason to stop fusing
            out = {"stats_error": str(e)}
        return {**out, "frames_complete": self.gate.complete, "frames_timed_out": self.gate.timed_out}


# ---------------------------------------------------------------------------- command line


def add_host_args(p: argparse.ArgumentParser) -> None:
    """The host's own flags (the service adds its transport flags; a recording's host command line is read
    back with these)."""
    p.add_argument("--map", default=None, help="the HD map file (GeoJSON, SUMO .net.xml, Lanelet2 .osm); centralized")
    p.add_argument("--mode", choices=["distributed", "centralized"], default="distributed")
    p.add_argument("--max-wait", type=float, default=MAX_WAIT_S, help="seconds a frame waits for all senders")
    p.add_argument("--known-senders", default=None, help="comma-separated vehicle ids (default: anyone)")
    p.add_argument("--local", action="append", default=[], help="on-board source, e.g. cv0 (repeatable)")
    p.add_argument("--params", default=None, help="YAML file of FusionParams fields")
    p.add_argument(
        "--downlink",
        action=argparse.BooleanOptionalAction,
        default=HostSetup.model_fields["downlink"].default,
        help="send every vehicle what the others know about its pose (distributed mode)",
    )


def host_setup_from_args(a: argparse.Namespace, fleet: str, host_id: str) -> HostSetup:
    """The HostSetup of :func:`add_host_args`' flags; a bad ``--params`` file is a ConfigError naming it."""
    from .config import read_yaml, validate_model

    params = FusionParams() if a.params is None else validate_model(FusionParams, read_yaml(Path(a.params)), a.params)
    return HostSetup(
        fleet=fleet,
        host_id=host_id,
        mode=a.mode,
        known_senders=tuple(x for x in a.known_senders.split(",") if x) if a.known_senders else None,
        local=tuple(a.local),
        max_wait_s=a.max_wait,
        params=params,
        map_file=a.map,
        downlink=a.downlink,
    )
