"""One scenario in one process on a simulated clock: world -> vehicles -> bytes -> channel -> host.

The same core classes and the same byte encoding as the live services, so accuracy and bandwidth
figures carry over; deterministic for a seed. Several host *views* can be fed from one run: each
view is a host container that listens to a subset of the senders (e.g. the ego alone, or everyone),
which isolates what cooperation adds without simulating the world twice.

Time: at every camera frame t_k the vehicles handle their sensor frames and send at t_k; the host
vehicle's own message reaches its container directly at t_k (as in the paper, the container runs on
the ego vehicle), the others go through the channel model and arrive when it says. Each view
ingests every message at its arrival time, in arrival order, and solves frame t_k when its
:class:`~mapcontainer.fusion.gate.FrameGate` releases it, exactly as the live host does: once every
sender of the view has delivered its message for t_k, or ``max_wait_s`` after the first of them
arrived (the view then fuses at t_k with everything that has arrived by that release time;
``TickRecord.released`` says when). A frame the gate drops (a newer one was complete first) has no
fused state for that view, as the live host publishes none. On an ideal channel every message
arrives at t_k and each view fuses at t_k with all of frame k.

Start (``start``): "cold" — every vehicle initialises its localizer from GNSS, the map's driving
directions and the camera (a vehicle switched on at t = 0; it may take frames, or fail, to lock
on). "warm" — every vehicle starts from a known pose, modelling a vehicle that was already
localized before the run (its last estimate): the true pose at t = 0 plus Gaussian noise with the
standard deviations of :data:`WARM_START_SIGMA` (drawn from a stream seeded by ``seed`` alone,
separate from the world's and the channel's, so the sensor noise of a seed is the same in both
starts), and that noise's covariance passed as ``initial_pose``.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from schemas import FusedState, GroundTruth, Rejection, body_pose_cov, encode

from . import geometry as geo
from .channel import NetworkProfile, load_profile
from .faults import FaultInjector
from .fusion import FusionParams
from .fusion.gate import MAX_WAIT_S
from .host import Fused, HostSetup, build_host
from .onboard import DownlinkParams
from .radio import RadioChannel, make_channel
from .radio.cpm import CpmRules
from .sim import Tick, World, load_scenario
from .sim.config import ScenarioConfig
from .vehicle import Mode, VehicleAgent

__all__ = [
    "SIGNING_EPOCH_S",
    "WARM_START_SIGMA",
    "PipelineResult",
    "Start",
    "TickRecord",
    "View",
    "run_pipeline",
    "warm_start_poses",
]

HOST_ID = "host"

Start = Literal["cold", "warm"]
# Warm start: 1-sigma error of the pose a vehicle starts from, over [x, y, z, roll, pitch, yaw]
# (m, m, m, rad, rad, rad): 0.3 m horizontal per axis, 0.1 m height, 0.5 deg roll and pitch, 1 deg yaw.
WARM_START_SIGMA = np.array([0.3, 0.3, 0.1, np.deg2rad(0.5), np.deg2rad(0.5), np.deg2rad(1.0)])
_WARM_START_STREAM = 0x5741524D  # "WARM": spawn key of the warm-start noise stream


def warm_start_poses(
    truth: dict[str, np.ndarray], seed: int, sigma: np.ndarray = WARM_START_SIGMA
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Initial (pose, covariance) per vehicle: the true pose plus N(0, diag(sigma^2)) noise.

    ``truth``: vehicle id -> true pose (6,) at t = 0. Deterministic for (seed, vehicle order); each
    vehicle draws from its own child stream of SeedSequence((seed, "WARM")), so adding a vehicle does
    not change the others' draws. The yaw is wrapped to (-pi, pi].
    """
    sigma = np.asarray(sigma, dtype=float)
    if sigma.shape != (6,) or np.any(sigma <= 0) or not np.all(np.isfinite(sigma)):
        raise ValueError(f"sigma must be 6 positive finite numbers, got {sigma}")
    cov = np.diag(sigma**2)
    streams = np.random.SeedSequence([int(seed), _WARM_START_STREAM]).spawn(len(truth))
    out = {}
    for (vid, pose), ss in zip(truth.items(), streams, strict=True):
        p = np.asarray(pose, dtype=float) + np.random.default_rng(ss).normal(0.0, sigma)
        p[5] = float(geo.wrap_angle(p[5]))
        out[vid] = (p, cov.copy())
    return out


@dataclass(frozen=True)
class View:
    """A host container fed with the messages of ``senders`` (None: every connected vehicle)."""

    name: str
    senders: tuple[str, ...] | None = None


@dataclass
class TickRecord:
    """Everything the experiments evaluate at one frame."""

    t: float
    truth: GroundTruth
    gnss: dict[str, np.ndarray]  # vid -> GNSS fix p_map
    priors: dict[str, np.ndarray]  # vid -> the pose the vehicle sends (its filtered estimate; distributed mode)
    prior_covs: dict[str, np.ndarray]  # vid -> 6x6, of the body pose (schemas.body_pose_cov)
    fused: dict[str, FusedState]  # view name -> fused state at t
    loc_mode: dict[str, str] = field(default_factory=dict)  # vid -> "map_matching" | "fallback" (distributed)
    onboard: dict[str, np.ndarray] = field(default_factory=dict)  # vid -> the vehicle's filtered pose (distributed)
    onboard_covs: dict[str, np.ndarray] = field(default_factory=dict)  # vid -> 6x6
    # vid -> this frame's map matching alone (the baseline "map matching per frame"; the filtered pose in fallback)
    per_frame: dict[str, np.ndarray] = field(default_factory=dict)
    per_frame_covs: dict[str, np.ndarray] = field(default_factory=dict)  # vid -> 6x6, of the body pose
    released: dict[str, float] = field(default_factory=dict)  # view name -> when its gate released this frame
    # vid -> what the vehicle did with the host's downlink this frame (Onboard.status; downlink runs only)
    downlink: dict[str, str] = field(default_factory=dict)


@dataclass
class PipelineResult:
    scenario: str
    seed: int
    mode: str
    network: str
    ego: str
    records: list[TickRecord] = field(default_factory=list)
    tx_bytes: dict[str, int] = field(default_factory=lambda: defaultdict(int))  # vid -> bytes offered to V2X
    tx_msgs: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    channel_stats: dict = field(default_factory=dict)
    host_stats: dict[str, dict] = field(default_factory=dict)
    duration_s: float = 0.0
    start: str = "cold"
    deliveries: list[tuple[str, float, float]] = field(default_factory=list)  # (src, t_sent, t_arrive) received
    signing: bool = False
    tx_message_bytes: dict[str, int] = field(default_factory=lambda: defaultdict(int))  # the messages, unsigned
    security_rejected: dict[str, int] = field(default_factory=lambda: defaultdict(int))  # by the hosts' verifiers
    gate_stats: dict[str, dict[str, int]] = field(default_factory=dict)  # view -> frames complete / timed out
    # view -> CPU seconds (this thread's) of its host: verify, ingest (decode, buffer; centralized: localize
    # every vehicle) and fuse, the host's whole work; and each fuse call's CPU milliseconds
    host_cpu_s: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    fuse_cpu_ms: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    # the downlink (``downlink=True``): vid -> bytes and messages the host put on the air for it (signed if
    # signing; the ego's own go on board, not counted), and what each vehicle did with what arrived
    downlink: bool = False
    rx_bytes: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    rx_msgs: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    downlink_counts: dict[str, dict[str, int]] = field(default_factory=dict)


def run_pipeline(
    scenario: str | ScenarioConfig = "paper-urban",
    seed: int = 0,
    duration_s: float | None = None,
    mode: Mode = "distributed",
    network: str | NetworkProfile = "ideal",
    views: tuple[View, ...] = (View("cooperative"),),
    fusion: FusionParams | None = None,
    fleet: str = "sim",
    start: Start = "cold",
    signing: bool = False,
    max_wait_s: float = MAX_WAIT_S,
    cpm_rules: bool = False,
    downlink: bool = False,
    downlink_params: DownlinkParams | None = None,
) -> PipelineResult:
    """Run one episode and return per-frame records for evaluation.

    ``start``: how the vehicles' localizers start (module docstring): "cold" from GNSS (default),
    "warm" from the true pose at t = 0 plus seeded noise of :data:`WARM_START_SIGMA`. Warm start
    acts on the vehicles' own localizers, so it needs ``mode="distributed"`` (in centralized mode
    the host localizes every vehicle from its raw observations).

    ``signing``: every message goes on the air as the live fleet sends it, signed by its vehicle
    (:class:`~mapcontainer.security.Signer`, credentials from a CA made for the run), and each host view
    verifies it before ingesting it; Unix time in the signatures is ``SIGNING_EPOCH_S`` + scenario time.
    ``tx_bytes`` are then the signed bytes, ``tx_message_bytes`` the messages inside.

    ``cpm_rules``: every vehicle but the ego thins the objects of the prior it sends with the ETSI CPM
    inclusion rules (:class:`~mapcontainer.radio.cpm.CpmRules`; distributed mode).

    ``downlink``: after each solve the first view's host sends every vehicle what the others know about it
    (:meth:`~mapcontainer.host.HostLoop.downlink`) through the channel (the ego's on board), signed when
    ``signing``; each vehicle fuses what has arrived by its next frame (:mod:`~mapcontainer.onboard`), and the
    records' ``onboard`` poses are its on-board estimate. Distributed mode only. ``downlink_params``: how the
    vehicles use it (:class:`~mapcontainer.onboard.DownlinkParams`).

    ``max_wait_s``: scenario seconds a view's frame waits for its late senders (the FrameGate's; the
    live host's ``--max-wait`` is wall seconds, i.e. ``max_wait * time_scale`` scenario seconds).
    """
    if start not in ("cold", "warm"):
        raise ValueError(f"start must be 'cold' or 'warm', got {start!r}")
    if start == "warm" and mode != "distributed":
        raise ValueError("start='warm' sets the vehicles' own localizers: it needs mode='distributed'")
    sc = load_scenario(scenario) if isinstance(scenario, str) else scenario
    profile = load_profile(network) if isinstance(network, str) else network
    world = World(sc, seed=seed, fleet=fleet)
    ego = world.vehicle_ids[0]
    initial: dict[str, tuple[np.ndarray, np.ndarray] | None] = dict.fromkeys(world.vehicle_ids)
    if start == "warm":
        states0 = world.states(0.0)  # a pure function of time: does not advance the sensors
        initial.update(warm_start_poses({v: np.asarray(states0[v].pose, float) for v in world.vehicle_ids}, seed))
    agents = {
        v: VehicleAgent(world.hdmap, v, fleet, mode, initial_pose=initial[v], downlink=downlink_params)
        for v in world.vehicle_ids
    }
    faults = {v: FaultInjector(v, sc.faults) for v in world.vehicle_ids}
    if mode != "distributed" and any(faults.values()):
        raise ValueError("faults act on a vehicle's priors: they need mode='distributed'")
    if downlink and (mode != "distributed" or not views):
        raise ValueError("the downlink is fused by the vehicles' own localizers and sent by a host view: it needs "
                         "mode='distributed' and a view")
    if cpm_rules and mode != "distributed":
        raise ValueError("cpm_rules thin the objects of a vehicle's prior: they need mode='distributed'")
    cpm = {v: CpmRules() for v in world.vehicle_ids[1:]} if cpm_rules else {}
    channel = make_channel(profile, seed, world.hdmap)  # a RadioChannel for a radio profile
    radio = isinstance(channel, RadioChannel)
    if radio:
        channel.place(HOST_ID, ego)  # the container runs on the ego
    listeners = {view.name: set(view.senders or world.vehicle_ids) for view in views}
    hosts = {  # the container runs on the ego: its clock times the frames
        view.name: build_host(
            HostSetup(
                fleet=fleet,
                host_id=HOST_ID,
                mode=mode,
                known_senders=tuple(sorted(listeners[view.name])),
                local=(ego,),
                max_wait_s=max_wait_s,
                params=fusion or FusionParams(),
            ),
            world.hdmap,  # the centralized host localizes against the vehicles' (published) map
        )
        for view in views
    }
    signers, verifiers = (
        _security(world.vehicle_ids, [view.name for view in views], HOST_ID if downlink else None)
        if signing
        else ({}, {})
    )
    duration = sc.duration_s if duration_s is None else duration_s
    result = PipelineResult(sc.name, seed, mode, profile.name, ego, duration_s=duration, start=start, signing=signing)
    result.downlink = downlink
    down_view = views[0].name if views else None  # the host that sends the downlink
    carried: list = []  # uplink deliveries taken from the channel early (with the downlink's), for ``advance``

    def send_downlink(f: Fused) -> None:
        """The host's downlink after a solve, on the air to each vehicle (on board to the ego)."""
        t_sent = f.t if f.released is None else f.released
        for msg in hosts[down_view].downlink(t_sent):
            message = encode(msg)
            payload = (
                signers[f"{HOST_ID}->{msg.target}"].sign(message, SIGNING_EPOCH_S + t_sent) if signing else message
            )
            if msg.target == ego:
                take_downlink(ego, payload, t_sent)
            else:
                result.rx_bytes[msg.target] += len(payload)
                result.rx_msgs[msg.target] += 1
                channel.send(HOST_ID, msg.target, payload, t_sent)

    def take_downlink(vid: str, payload: bytes, t_arrive: float) -> None:
        if signing:
            out = verifiers[f"vehicle:{vid}"].verify(payload, SIGNING_EPOCH_S + t_arrive, expected_sender=HOST_ID)
            if isinstance(out, Rejection):
                result.security_rejected[out.reason] += 1
                return
            payload = out.payload
        agents[vid].receive_downlink(payload)

    def downlinks_until(t_end: float) -> None:
        """Hand the vehicles the downlinks that have arrived by ``t_end`` (uplinks kept for ``advance``)."""
        for d in channel.deliver(t_end):
            if d.dst == HOST_ID:
                carried.append(d)
            else:
                take_downlink(d.dst, d.payload, d.t_arrive)

    records: dict[int, TickRecord] = {}  # frame index k (t = k dt) -> its record

    def ingest(name: str, src: str, payload: bytes, t_arrive: float) -> None:
        """Into view ``name``'s host loop (its gate hears of what the core accepts)."""
        c0 = time.thread_time()
        if signing:
            out = verifiers[name].verify(payload, SIGNING_EPOCH_S + t_arrive, expected_sender=src)
            if isinstance(out, Rejection):
                result.security_rejected[out.reason] += 1
                result.host_cpu_s[name] += time.thread_time() - c0
                return
            payload = out.payload
        hosts[name].receive(payload, t_arrive)
        result.host_cpu_s[name] += time.thread_time() - c0

    def released(name: str, f: Fused) -> None:
        rec = records[int(round(f.t / world.dt))]  # the frame's time is the ego's clock: ms off t_k
        rec.fused[name] = f.state
        result.host_cpu_s[name] += f.cpu_s
        result.fuse_cpu_ms[name].append(1e3 * f.cpu_s)
        rec.released[name] = f.released
        if downlink and name == down_view:
            send_downlink(f)

    def timeouts(until: float) -> None:
        """Release what times out by ``until`` (a deadline falls before an arrival at the same instant)."""
        for name, host in hosts.items():
            for f in host.timeouts(until):
                released(name, f)

    def advance(t_end: float, onboard: list[tuple[str, bytes]]) -> None:
        """Every arrival up to ``t_end`` in time order (on-board messages at ``t_end``, before the
        channel's of the same instant), each view's gate asked after each."""
        events = [(t_end, 0, i, src, payload) for i, (src, payload) in enumerate(onboard)]
        if downlink:
            downlinks_until(t_end)
        arrived = [*carried, *channel.deliver(t_end)]
        carried.clear()
        for i, d in enumerate(arrived):
            result.deliveries.append((d.src, d.t_sent, d.t_arrive))
            events.append((d.t_arrive, 1, i, d.src, d.payload))
        events.sort(key=lambda e: e[:3])
        for t_arrive, _, _, src, payload in events:
            timeouts(t_arrive)
            for name in hosts:
                if src in listeners[name]:
                    ingest(name, src, payload, t_arrive)
                    if (f := hosts[name].step(t_arrive)) is not None:
                        released(name, f)
        timeouts(t_end)

    t_last = 0.0
    for tick in _closing(world, duration):
        t = t_last = tick.t
        rec = TickRecord(t, tick.truth, {}, {}, {}, {})
        if radio:
            channel.observe_truth(tick.truth)
        onboard: list[tuple[str, bytes]] = []
        if downlink:
            downlinks_until(t)  # what has arrived by this frame
        for vid, frame in tick.frames.items():
            msg = agents[vid].handle(t, frame)
            if isinstance(msg, Rejection):  # the simulator's own frames: a bug, not bad input
                raise RuntimeError(f"{vid} refused its frame at {t:.2f} s: {msg.reason}: {msg.detail}")
            rec.gnss[vid] = np.asarray(frame.gnss.p_map, dtype=float)
            if mode == "distributed":
                rec.priors[vid] = np.asarray(msg.pose, dtype=float)
                rec.prior_covs[vid] = body_pose_cov(msg)
                rec.loc_mode[vid] = msg.quality.mode
                res, est = agents[vid].last_result, agents[vid].onboard
                if est is not None:  # None until the localizer has initialised
                    rec.onboard[vid] = np.asarray(est.pose, dtype=float)  # the own estimate, with the downlink
                    rec.onboard_covs[vid] = np.asarray(est.cov, dtype=float)
                    if downlink:
                        rec.downlink[vid] = est.status
                    if res.pose_frame is not None:
                        bias = res.cov_filtered - res.cov_camera  # the error every frame repeats
                        rec.per_frame[vid], rec.per_frame_covs[vid] = res.pose_frame, res.cov_frame + bias
                    else:
                        rec.per_frame[vid], rec.per_frame_covs[vid] = rec.onboard[vid], rec.onboard_covs[vid]
            if vid in cpm:
                msg = cpm[vid].filter(msg)
            for m in faults[vid].apply(msg) if faults[vid] else [msg]:
                message = encode(m)
                payload = signers[vid].sign(message, SIGNING_EPOCH_S + t) if signing else message
                if vid == ego:
                    onboard.append((vid, payload))
                    if radio:
                        channel.on_air(vid, payload, t)  # the ego broadcasts too: it loads the medium
                else:
                    result.tx_bytes[vid] += len(payload)
                    result.tx_message_bytes[vid] += len(message)
                    result.tx_msgs[vid] += 1
                    channel.send(vid, HOST_ID, payload, t)
        records[int(round(t / world.dt))] = rec
        result.records.append(rec)
        advance(t, onboard)
    advance(t_last + max_wait_s, [])  # the last frames: their late messages and time-outs
    result.channel_stats = channel.stats()
    result.host_stats = {name: host.core.stats() for name, host in hosts.items()}
    result.downlink_counts = {v: dict(a.downlink.counts) for v, a in agents.items()} if downlink else {}
    result.gate_stats = {n: {"complete": h.gate.complete, "timed_out": h.gate.timed_out} for n, h in hosts.items()}
    return result


def _closing(world: World, duration_s: float) -> Iterator[Tick]:
    """The World's frames of ``duration_s``; what it holds outside Python (SUMO) released after the last."""
    try:
        yield from world.run(duration_s)
    finally:
        world.close()


SIGNING_EPOCH_S = 1.8e9  # Unix time of scenario time 0 in the pipeline's signatures (a fixed date in 2027)


def _security(vehicles: list[str], views: list[str], host: str | None = None) -> tuple[dict, dict]:
    """A CA made for the run, a Signer per vehicle and a Verifier per host view; with ``host`` (the downlink)
    the host's Signer per vehicle (keyed "<host>-><id>": a Signer sends its certificate once a second, with the
    first message it signs, and every vehicle's verifier must get it) and a Verifier per vehicle ("vehicle:<id>")."""
    from .security import Signer, Verifier, issue, make_ca

    now = SIGNING_EPOCH_S - 3600.0
    ca = make_ca("pipeline-ca", now=now, validity_s=30 * 86400.0)
    signers = {v: Signer(issue(ca, v, 30 * 86400.0, now)) for v in vehicles}
    if host is not None:
        host_credentials = issue(ca, host, 30 * 86400.0, now)
        signers.update({f"{host}->{v}": Signer(host_credentials) for v in vehicles})
    readers = [*views, *(f"vehicle:{v}" for v in vehicles)] if host is not None else views
    return signers, {name: Verifier(ca.certificate, window_s=5.0) for name in readers}
