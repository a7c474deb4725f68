"""The simulated world: actors on an HD map, and each connected vehicle's sensors, tick by tick.

Two maps: ``true_map`` is the world (what the cameras see, where the actors drive); ``hdmap`` is the
map the vehicles and the host carry (:func:`~mapcontainer.sim.errors.published_map`: the true one with
the scenario's map error drawn for the seed). The traffic is the scenario's, varied per run from the
seed when ``traffic`` is on (:mod:`.traffic`), or SUMO's on the network the map is imported from
(``traffic.source: sumo``, :mod:`.sumo`); every noise and error stream is drawn from the seed, each
from a stream of its own.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from schemas import (
    CameraInfo,
    GnssFix,
    GroundTruth,
    ObjectObservations,
    Odometry,
    SensorFrame,
)

from .. import geometry as geo
from .. import lanemask
from ..hdmap.model import HDMap
from .actors import ActorState, BodyMotion, LaneFollower, PathWalker
from .config import ScenarioConfig
from .errors import published_map, vehicle_error_streams
from .maps import world_map
from .scene import ActorBoxes
from .sensors import Camera, CameraObservation, Gnss, ObjectDetector
from .sensors import Odometry as OdometrySensor
from .traffic import Traffic, draw_traffic

if TYPE_CHECKING:
    from .sumo import SumoTraffic

__all__ = ["FrameDebug", "Tick", "World"]


@dataclass(frozen=True)
class FrameDebug:
    """What the simulator knows about one sensor frame beyond the message (for tests and plots)."""

    camera: CameraObservation
    object_truth_ids: list[str | None]  # per detection; None for a false alarm


@dataclass(frozen=True)
class Tick:
    k: int
    t: float
    truth: GroundTruth
    states: dict[str, ActorState]
    frames: dict[str, SensorFrame]
    debug: dict[str, FrameDebug]


class _VehicleSensors:
    """One vehicle's sensors: noise from ``seed``'s children, errors from ``errors``' children."""

    def __init__(self, world: World, seed: np.random.SeedSequence, errors: np.random.SeedSequence):
        cfg = world.scenario.sensors
        cam_ss, gnss_ss, odo_ss, det_ss = seed.spawn(4)
        calib_rng, bias_rng, confusion_rng, clock_rng = (np.random.default_rng(ss) for ss in errors.spawn(4))
        clutter = cfg.clutter.enabled
        self.camera = Camera(
            cfg.camera, world.true_map, np.random.default_rng(cam_ss), calib_rng, clutter, cull=world.cull
        )
        self.gnss = Gnss(cfg.gnss, np.random.default_rng(gnss_ss))
        self.odometry = OdometrySensor(cfg.odometry, np.random.default_rng(odo_ss))
        # The object detector looks through the same camera: its body-frame positions carry the extrinsic error.
        T_rep_true = self.camera.T_body_cam_reported @ geo.inverse(self.camera.T_body_cam)
        self.detector = ObjectDetector(
            cfg.detector,
            cfg.camera.mount_xyz_m,
            np.random.default_rng(det_ss),
            bias_rng,
            confusion_rng,
            T_rep_true,
            clutter,
        )
        z = clock_rng.normal()
        self.clock_offset_s = float(z * cfg.clock.offset_sigma_s) if cfg.clock.enabled else 0.0
        intr = self.camera.reported_intr
        self.camera_info = CameraInfo(
            fx=intr.fx,
            fy=intr.fy,
            cx=intr.cx,
            cy=intr.cy,
            width=intr.width,
            height=intr.height,
            T_body_cam=self.camera.T_body_cam_reported,
        )


def _follow(followers: list[LaneFollower], specs, gap_m: float, lane_lengths: list[float]) -> None:
    """Each vehicle follows the next one ahead in its lane (by start position); the front one follows the
    last one a lap ahead (its free motion, which ends the chain)."""
    for lane in {sp.lane for sp in specs}:
        order = sorted((i for i, sp in enumerate(specs) if sp.lane == lane), key=lambda i: specs[i].s0_m)
        if len(order) < 2:
            continue
        for behind, ahead in zip(order, [*order[1:], order[0]], strict=True):
            followers[behind].leader = followers[ahead]
            followers[behind].min_gap_m = gap_m
        followers[order[-1]].leader_offset_m = lane_lengths[lane]
        followers[order[-1]].leader_free = True


class World:
    """A scenario with its maps, actors and the connected vehicles' sensors, for one seed.

    ``true_map``: the world the cameras see and the actors drive in. ``hdmap``: the map the vehicles and
    the host carry (the published map: ``true_map`` with the scenario's map error). ``traffic``: the
    actors of this run. ``cull`` False: every sensor looks at every actor and map feature instead of
    those within its reach (the same frames, at a cost growing with the square of the actors and with
    the map: a check of the culling).
    """

    def __init__(self, scenario: ScenarioConfig, seed: int, fleet: str = "sim", cull: bool = True):
        self.scenario = scenario
        self.cull = cull
        self.seed = seed
        self.fleet = fleet
        self.true_map: HDMap = world_map(scenario)
        self.hdmap: HDMap = published_map(scenario, seed, self.true_map)
        self.dt = 1.0 / scenario.sensors.rate_hz
        self.sumo: SumoTraffic | None = None
        self._bodies: dict[str, BodyMotion] = {}
        if scenario.sumo is not None:
            self._init_sumo(scenario, seed)
            return
        lanes = [c.polyline for c in self.true_map.centerlines]
        areas = [w.polyline for w in self.true_map.walkable]
        self.traffic: Traffic | None = draw_traffic(
            scenario, seed, [a.length for a in areas], [a.length for a in lanes]
        )

        def follower(actor_id: str, spec) -> LaneFollower:
            return LaneFollower(
                actor_id,
                lanes[spec.lane],
                spec.s0_m,
                spec.speed_mps,
                spec.speed_amp_mps,
                spec.speed_period_s,
                spec.speed_phase_rad,
                (spec.length_m, spec.width_m, spec.height_m),
            )

        tr = self.traffic
        n_ov = len(tr.obstacle_vehicles)
        self.connected = [follower(f"cv{i}", s) for i, s in enumerate(tr.connected)]
        obstacles = [follower(str(i + 1), s) for i, s in enumerate(tr.obstacle_vehicles)]
        if scenario.traffic.enabled and scenario.traffic.min_gap_m > 0:
            vehicles, specs = [*self.connected, *obstacles], [*tr.connected, *tr.obstacle_vehicles]
            _follow(vehicles, specs, scenario.traffic.min_gap_m, [a.length for a in lanes])
        obstacles += [
            PathWalker(str(n_ov + i + 1), areas[p.area], p.s0_m, p.speed_mps, p.direction)
            for i, p in enumerate(tr.pedestrians)
        ]
        self.obstacles = obstacles
        self._vehicle_ids = [a.id for a in self.connected]
        self._init_sensors(scenario, seed)
        for a in self.connected:
            a.body = self._bodies.get(a.id)

    def _init_sumo(self, scenario: ScenarioConfig, seed: int) -> None:
        """Actors from SUMO (:class:`~.sumo.SumoTraffic`): no procedural actors or drawn traffic."""
        from .sumo import SumoTraffic

        self.traffic = None
        self.connected, self.obstacles = [], []
        self.sumo = SumoTraffic(scenario.sumo, self.true_map, self.dt, seed)
        self._vehicle_ids = self.sumo.vehicle_ids
        self._init_sensors(scenario, seed)

    def _init_sensors(self, scenario: ScenarioConfig, seed: int) -> None:
        """Each connected vehicle's sensors, error streams and body motion (by index: cv0 first)."""
        n_cv = len(self._vehicle_ids)
        root = np.random.SeedSequence(seed)
        errors = vehicle_error_streams(seed, n_cv)
        self._sensors = {
            vid: _VehicleSensors(self, ss, es)
            for vid, ss, es in zip(self._vehicle_ids, root.spawn(n_cv), errors, strict=True)
        }
        self._last_k: dict[str, int] = {}  # the last frame each vehicle's sensors measured
        b = scenario.sensors.body
        static = (b.heave_static_m, b.roll_static_rad, b.pitch_static_rad)
        dynamic = (b.heave_dynamic_m, b.roll_dynamic_rad, b.pitch_dynamic_rad)
        if any(static) or any(dynamic):  # spawned after the sensors' streams: those stay as they were
            for vid, ss in zip(self._vehicle_ids, root.spawn(n_cv), strict=True):
                self._bodies[vid] = BodyMotion(static, dynamic, np.random.default_rng(ss))
        self._seq = 0

    @property
    def vehicle_ids(self) -> list[str]:
        return list(self._vehicle_ids)

    def close(self) -> None:
        """Release what the World holds outside Python (SUMO's simulation); idempotent."""
        if self.sumo is not None:
            self.sumo.close()

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def camera(self, vid: str) -> Camera:
        return self._sensors[vid].camera

    def detector(self, vid: str) -> ObjectDetector:
        return self._sensors[vid].detector

    def clock_offset_s(self, vid: str) -> float:
        """How far vehicle ``vid``'s time stamps are ahead of true time (s)."""
        return self._sensors[vid].clock_offset_s

    def states(self, t: float) -> dict[str, ActorState]:
        """Every actor at time t, connected vehicles first. With SUMO: at the step nearest t (a step that
        SUMO has not reached yet is simulated; one more than :data:`~.sumo.KEEP_STEPS` behind is refused)."""
        if self.sumo is not None:
            bodies = self._bodies
            return self.sumo.states(int(round(t / self.dt)), lambda v, t: bodies[v](t) if v in bodies else None)
        return {a.id: a.state(t) for a in [*self.connected, *self.obstacles]}

    def truth(self, k: int, t: float, states: dict[str, ActorState]) -> GroundTruth:
        cv_ids = set(self._vehicle_ids)
        cv = [states[v] for v in self._vehicle_ids]
        ob = [s for i, s in states.items() if i not in cv_ids]
        return GroundTruth(
            fleet=self.fleet,
            sender="world",
            seq=k,
            t_meas=t,
            t_sent=t,
            vehicle_ids=[s.id for s in cv],
            vehicle_pose=np.array([s.pose for s in cv]).reshape(-1, 6),
            vehicle_v_map=np.array([s.v_map for s in cv]).reshape(-1, 3),
            obstacle_id=np.array([int(s.id) for s in ob], dtype=np.uint32),
            obstacle_cls=np.array([s.cls for s in ob], dtype=np.uint8),
            obstacle_p_map=np.array([s.p_map for s in ob]).reshape(-1, 3),
            obstacle_v_map=np.array([s.v_map for s in ob]).reshape(-1, 3),
            obstacle_yaw=np.array([s.yaw for s in ob]),
        )

    def boxes(self, states: dict[str, ActorState]) -> ActorBoxes:
        """Every actor's box of ``states`` (in their order), indexed by range unless the World is built
        with ``cull=False``: what every vehicle's sensors of one tick look at."""
        return ActorBoxes(list(states.values()), index=self.cull)

    def sense(
        self, k: int, t: float, vid: str, states: dict[str, ActorState], boxes: ActorBoxes | None = None
    ) -> tuple[SensorFrame, FrameDebug]:
        """One sensor frame of vehicle ``vid`` at frame k, after its last one (the sensors' error
        processes only run forward; ValueError otherwise). ``boxes``: :meth:`boxes` of ``states``
        (made here if None; :meth:`tick` makes it once for every vehicle)."""
        last = self._forward(vid, k)
        sensors = self._sensors[vid]
        me = states[vid]
        boxes = self.boxes(states) if boxes is None else boxes
        me_idx = boxes.index(vid)
        cam = sensors.camera.observe(me.pose, boxes, skip=me_idx)
        png = lanemask.encode(cam.lane_mask)  # 1-bit PNG: about 2.3 kB
        skipped = 1 if last is None else k - last  # frames since the last one sensed (1 when in order)
        self._last_k[vid] = k
        p_gnss, sh, sv = sensors.gnss.measure(t, me.p_map, self.dt * skipped)
        speed, yaw_rate = sensors.odometry.measure(me.speed, me.yaw_rate)
        p_obj, cov_obj, cls_obj, ids = sensors.detector.observe(me, boxes, t, skip=me_idx)
        t_vehicle = t + sensors.clock_offset_s  # the frame is stamped by the vehicle's clock
        frame = SensorFrame(
            fleet=self.fleet,
            sender=vid,
            seq=k,
            t_meas=t_vehicle,
            t_sent=t_vehicle,
            camera=sensors.camera_info,
            points_uv=cam.points_uv,
            points_cls=cam.points_cls,
            poles_uv=cam.poles_uv,
            lane_mask_png=png,
            gnss=GnssFix(p_map=p_gnss, sigma_h_m=sh, sigma_v_m=sv),
            odometry=Odometry(speed=speed, yaw_rate=yaw_rate),
            objects=ObjectObservations.from_metres(p_obj, cov_obj, cls_obj),
        )
        return frame, FrameDebug(cam, ids)

    def _forward(self, vid: str, k: int) -> int | None:
        """The last frame vehicle ``vid`` sensed (None: none yet); ValueError unless k comes after it."""
        last = self._last_k.get(vid)
        if last is not None and k <= last:
            raise ValueError(
                f"{vid}: frame {k} is not after its last frame {last}: a World senses forward in time only"
                " (a new World starts again)"
            )
        return last

    def tick(self, k: int) -> Tick:
        """Everything at frame k (t = k dt). Call with increasing k (sensor state advances; ValueError
        otherwise); frames left out are never sensed (an overloaded live world drops them), the sensors'
        error processes advance over the time elapsed since the last frame."""
        for vid in self.vehicle_ids:  # before anything moves
            self._forward(vid, k)
        t = k * self.dt
        states = self.states(t)
        boxes = self.boxes(states)
        frames, debug = {}, {}
        for vid in self.vehicle_ids:
            frames[vid], debug[vid] = self.sense(k, t, vid, states, boxes)
        return Tick(k, t, self.truth(k, t, states), states, frames, debug)

    def run(self, duration_s: float) -> Iterator[Tick]:
        """The frames of the next ``duration_s``: from frame 0 on a new World, from the frame after the
        last one sensed on a World that has run before."""
        k0 = max(self._last_k.values(), default=-1) + 1
        for k in range(k0, k0 + int(round(duration_s / self.dt))):
            yield self.tick(k)
