"""The simulated world: actors on an HD map, and each connected vehicle's sensors, tick by tick.

Trajectories depend only on the scenario (as in the paper's Monte Carlo runs, where the same
traffic is observed with independent noise); every noise stream is drawn from the seed.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from schemas import (
    CameraInfo,
    GnssFix,
    GroundTruth,
    ObjectObservations,
    Odometry,
    SensorFrame,
)

from .. import lanemask
from ..hdmap.generator import generate_map
from ..hdmap.model import HDMap
from .actors import ActorState, BodyMotion, LaneFollower, PathWalker
from .config import ScenarioConfig
from .sensors import Camera, CameraObservation, Gnss, ObjectDetector
from .sensors import Odometry as OdometrySensor

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
    def __init__(self, world: World, seed: np.random.SeedSequence):
        cfg = world.scenario.sensors
        cam_ss, gnss_ss, odo_ss, det_ss = seed.spawn(4)
        self.camera = Camera(cfg.camera, world.hdmap, np.random.default_rng(cam_ss))
        self.gnss = Gnss(cfg.gnss, np.random.default_rng(gnss_ss))
        self.odometry = OdometrySensor(cfg.odometry, np.random.default_rng(odo_ss))
        self.detector = ObjectDetector(cfg.detector, cfg.camera.mount_xyz_m, np.random.default_rng(det_ss))
        intr = self.camera.intr
        self.camera_info = CameraInfo(
            fx=intr.fx,
            fy=intr.fy,
            cx=intr.cx,
            cy=intr.cy,
            width=intr.width,
            height=intr.height,
            T_body_cam=self.camera.T_body_cam,
        )


class World:
    """A scenario with its map, actors and the connected vehicles' sensors, for one seed."""

    def __init__(self, scenario: ScenarioConfig, seed: int, fleet: str = "sim"):
        self.scenario = scenario
        self.seed = seed
        self.fleet = fleet
        self.hdmap: HDMap = generate_map(scenario.map)
        self.dt = 1.0 / scenario.sensors.rate_hz
        lanes = [c.polyline for c in self.hdmap.centerlines]
        areas = [w.polyline for w in self.hdmap.walkable]

        def follower(actor_id: str, spec, i: int, n: int) -> LaneFollower:
            phase = 2 * np.pi * i / max(n, 1)
            return LaneFollower(
                actor_id,
                lanes[spec.lane],
                spec.s0_m,
                spec.speed_mps,
                spec.speed_amp_mps,
                spec.speed_period_s,
                phase,
                (spec.length_m, spec.width_m, spec.height_m),
            )

        n_cv, n_ov = len(scenario.connected), len(scenario.obstacle_vehicles)
        self.connected = [follower(f"cv{i}", s, i, n_cv) for i, s in enumerate(scenario.connected)]
        obstacles = [follower(str(i + 1), s, i, n_ov) for i, s in enumerate(scenario.obstacle_vehicles)]
        obstacles += [
            PathWalker(str(n_ov + i + 1), areas[p.area], p.s0_m, p.speed_mps, p.direction)
            for i, p in enumerate(scenario.pedestrians)
        ]
        self.obstacles = obstacles
        root = np.random.SeedSequence(seed)
        self._sensors = {
            a.id: _VehicleSensors(self, ss) for a, ss in zip(self.connected, root.spawn(n_cv), strict=True)
        }
        self._last_k: dict[str, int] = {}  # the last frame each vehicle's sensors measured
        b = scenario.sensors.body
        static = (b.heave_static_m, b.roll_static_rad, b.pitch_static_rad)
        dynamic = (b.heave_dynamic_m, b.roll_dynamic_rad, b.pitch_dynamic_rad)
        if any(static) or any(dynamic):  # spawned after the sensors' streams: those stay as they were
            for a, ss in zip(self.connected, root.spawn(n_cv), strict=True):
                a.body = BodyMotion(static, dynamic, np.random.default_rng(ss))
        self._seq = 0

    @property
    def vehicle_ids(self) -> list[str]:
        return [a.id for a in self.connected]

    def camera(self, vid: str) -> Camera:
        return self._sensors[vid].camera

    def states(self, t: float) -> dict[str, ActorState]:
        return {a.id: a.state(t) for a in [*self.connected, *self.obstacles]}

    def truth(self, k: int, t: float, states: dict[str, ActorState]) -> GroundTruth:
        cv = [states[a.id] for a in self.connected]
        ob = [states[a.id] for a in self.obstacles]
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

    def sense(self, k: int, t: float, vid: str, states: dict[str, ActorState]) -> tuple[SensorFrame, FrameDebug]:
        """One sensor frame of vehicle ``vid`` at frame k, after its last one (the sensors' error
        processes only run forward; ValueError otherwise)."""
        last = self._forward(vid, k)
        sensors = self._sensors[vid]
        me = states[vid]
        others = [s for i, s in states.items() if i != vid]
        cam = sensors.camera.observe(me.pose, others)
        png = lanemask.encode(cam.lane_mask)  # 1-bit PNG: about 2.3 kB
        skipped = 1 if last is None else k - last  # frames since the last one sensed (1 when in order)
        self._last_k[vid] = k
        p_gnss, sh, sv = sensors.gnss.measure(t, me.p_map, self.dt * skipped)
        speed, yaw_rate = sensors.odometry.measure(me.speed, me.yaw_rate)
        p_obj, cov_obj, cls_obj, ids = sensors.detector.observe(me, others, others + [me])
        frame = SensorFrame(
            fleet=self.fleet,
            sender=vid,
            seq=k,
            t_meas=t,
            t_sent=t,
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
        frames, debug = {}, {}
        for vid in self.vehicle_ids:
            frames[vid], debug[vid] = self.sense(k, t, vid, states)
        return Tick(k, t, self.truth(k, t, states), states, frames, debug)

    def run(self, duration_s: float) -> Iterator[Tick]:
        """The frames of the next ``duration_s``: from frame 0 on a new World, from the frame after the
        last one sensed on a World that has run before."""
        k0 = max(self._last_k.values(), default=-1) + 1
        for k in range(k0, k0 + int(round(duration_s / self.dt))):
            yield self.tick(k)
