"""One scenario in one process on a simulated clock: world -> vehicles -> bytes -> channel -> host.

The same core classes and the same byte encoding as the live services, so accuracy and bandwidth
figures carry over; deterministic for a seed. Several host *views* can be fed from one run: each
view is a host container that listens to a subset of the senders (e.g. the ego alone, or everyone),
which isolates what cooperation adds without simulating the world twice.

Time: at every camera frame t_k the vehicles handle their sensor frames and send at t_k; the host
vehicle's own message reaches its container directly (as in the paper, the container runs on the
ego vehicle), the others go through the channel model; every delivery with arrival time <= t_k is
ingested, then each view fuses at t_k.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from schemas import FusedState, GroundTruth, encode
from schemas.arrays import cov_from_upper

from . import geometry as geo
from .channel import Channel, NetworkProfile, load_profile
from .fusion import FusionParams
from .host import make_host
from .metrics import match_objects
from .sim import World, load_scenario
from .sim.config import ScenarioConfig
from .vehicle import Mode, VehicleAgent

__all__ = ["PipelineResult", "TickRecord", "View", "relative_errors", "run_pipeline"]

HOST_ID = "host"


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
    priors: dict[str, np.ndarray]  # vid -> self-localized pose (distributed mode)
    prior_covs: dict[str, np.ndarray]  # vid -> 6x6
    fused: dict[str, FusedState]  # view name -> fused state at t


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
    deliveries: list[tuple[str, float, float]] = field(default_factory=list)  # (src, t_sent, t_arrive) received


def run_pipeline(
    scenario: str | ScenarioConfig = "paper-urban",
    seed: int = 0,
    duration_s: float | None = None,
    mode: Mode = "distributed",
    network: str | NetworkProfile = "ideal",
    views: tuple[View, ...] = (View("cooperative"),),
    fusion: FusionParams | None = None,
    fleet: str = "sim",
) -> PipelineResult:
    """Run one episode and return per-frame records for evaluation."""
    sc = load_scenario(scenario) if isinstance(scenario, str) else scenario
    profile = load_profile(network) if isinstance(network, str) else network
    world = World(sc, seed=seed, fleet=fleet)
    ego = world.vehicle_ids[0]
    agents = {v: VehicleAgent(world.hdmap, v, fleet, mode) for v in world.vehicle_ids}
    channel = Channel(profile, seed=seed)
    hosts = {
        view.name: make_host(
            world.hdmap,
            fusion or FusionParams(),
            fleet,
            HOST_ID,
            mode,
            known_senders=set(view.senders or world.vehicle_ids),
        )
        for view in views
    }
    listeners = {view.name: set(view.senders or world.vehicle_ids) for view in views}
    duration = sc.duration_s if duration_s is None else duration_s
    result = PipelineResult(sc.name, seed, mode, profile.name, ego, duration_s=duration)

    for tick in world.run(duration):
        t = tick.t
        rec = TickRecord(t, tick.truth, {}, {}, {}, {})
        for vid, frame in tick.frames.items():
            msg = agents[vid].handle(t, frame)
            payload = encode(msg)
            rec.gnss[vid] = np.asarray(frame.gnss.p_map, dtype=float)
            if mode == "distributed":
                rec.priors[vid] = np.asarray(msg.pose, dtype=float)
                rec.prior_covs[vid] = cov_from_upper(msg.pose_cov)
            if vid == ego:
                for name, host in hosts.items():
                    if vid in listeners[name]:
                        host.ingest(payload, t)
            else:
                result.tx_bytes[vid] += len(payload)
                result.tx_msgs[vid] += 1
                channel.send(vid, HOST_ID, payload, t)
        for d in channel.deliver(t):
            result.deliveries.append((d.src, d.t_sent, d.t_arrive))
            for name, host in hosts.items():
                if d.src in listeners[name]:
                    host.ingest(d.payload, d.t_arrive)
        for name, host in hosts.items():
            rec.fused[name] = host.fuse(t)
        result.records.append(rec)
    result.channel_stats = channel.stats()
    result.host_stats = {name: host.stats() for name, host in hosts.items()}
    return result


def relative_errors(fused: FusedState, truth: GroundTruth, ego: str, radius_m: float):
    """Errors (N, 2) of target positions in the ego's body frame (the paper's rms2) for true targets
    within ``radius_m`` of the ego, using the fused ego pose and fused target positions."""
    if ego not in fused.vehicle_ids or ego not in truth.vehicle_ids:
        return np.zeros((0, 2)), 0
    T_true = geo.pose_to_matrix(np.asarray(truth.vehicle_pose[truth.vehicle_ids.index(ego)], float))
    T_hat = geo.pose_to_matrix(np.asarray(fused.vehicle_pose[fused.vehicle_ids.index(ego)], float))
    p_true_map = np.asarray(truth.obstacle_p_map, float)
    near = np.linalg.norm(p_true_map[:, :2] - T_true[:2, 3], axis=1) <= radius_m
    ti, fi = match_objects(fused.object_p_map, truth.obstacle_p_map)
    keep = near[ti]
    ti, fi = ti[keep], fi[keep]
    rel_true = geo.transform_points(geo.inverse(T_true), p_true_map[ti])
    rel_hat = geo.transform_points(geo.inverse(T_hat), np.asarray(fused.object_p_map, float)[fi])
    return (rel_hat - rel_true)[:, :2], int(near.sum())
