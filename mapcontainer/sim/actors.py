"""Actors: vehicles that follow lane centre lines and pedestrians that walk walkable paths.

Every actor's reference point is the centre of its footprint on the ground (the body origin of
a connected vehicle); its extent is an oriented box standing on the ground.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from schemas import ObjectClass

from ..hdmap.model import Polyline

__all__ = ["ActorState", "BodyMotion", "LaneFollower", "PathWalker", "box_corners"]

_YAW_BASE_M = 1.0  # yaw from the chord over +-1 m: smooth across the polyline's 1 m vertices
_ARC_MEMO = 8  # instants a LaneFollower remembers its arc for (a state asks for three)


@dataclass(frozen=True)
class ActorState:
    """The true state of one actor at one instant (map frame)."""

    id: str
    cls: ObjectClass
    p_map: np.ndarray  # (3,) footprint centre on the ground
    yaw: float
    v_map: np.ndarray  # (3,)
    yaw_rate: float
    size: np.ndarray  # (3,) length, width, height
    body: np.ndarray = field(default_factory=lambda: np.zeros(3))  # heave (m), roll, pitch (rad) about nominal

    @property
    def speed(self) -> float:
        return float(np.hypot(self.v_map[0], self.v_map[1]))

    @property
    def pose(self) -> np.ndarray:
        """[x, y, z, roll, pitch, yaw] of the body: the footprint centre raised by the heave, with the
        body's roll and pitch (flat ground: zero for a rigid body)."""
        dz, roll, pitch = self.body
        return np.array([self.p_map[0], self.p_map[1], self.p_map[2] + dz, roll, pitch, self.yaw])


class BodyMotion:
    """Heave, roll and pitch of a body about nominal: per axis a static offset plus a dynamic part, a sum
    of ``n`` sinusoids at 0.5-1.5 Hz (suspension modes) with random phases. ``static`` and ``dynamic``
    are 1-sigmas (3,) over (heave m, roll rad, pitch rad); deterministic in t for a given rng."""

    def __init__(self, static, dynamic, rng: np.random.Generator, n: int = 3):
        self.offset = rng.normal(0.0, 1.0, 3) * np.asarray(static, dtype=float)
        self.freq = rng.uniform(0.5, 1.5, (3, n))
        self.phase = rng.uniform(0.0, 2 * np.pi, (3, n))
        self.amp = np.asarray(dynamic, dtype=float)[:, None] * np.sqrt(2.0 / n)  # variance n a^2 / 2

    def __call__(self, t: float) -> np.ndarray:
        return self.offset + np.sum(self.amp * np.sin(2 * np.pi * self.freq * t + self.phase), axis=1)


class _PathActor:
    """State from an arc-length function s(t) along a polyline (subclasses define s(t))."""

    cls: ObjectClass

    def __init__(self, actor_id: str, line: Polyline, size):
        self.id = actor_id
        self.line = line
        self.size = np.asarray(size, dtype=float)
        self.body: Callable[[float], np.ndarray] | None = None  # heave, roll, pitch at t (None: rigid)

    def arc(self, t: float) -> tuple[float, float]:
        """Arc length and signed speed along the line at time t."""
        raise NotImplementedError

    def state(self, t: float, dt: float = 0.05) -> ActorState:
        s, v = self.arc(t)
        s_a, v_a = self.arc(t - dt)
        s_b, v_b = self.arc(t + dt)
        # One polyline lookup: the position, and the chords over +-_YAW_BASE_M at t, t - dt and t + dt.
        b = _YAW_BASE_M
        p = self.line.point_at(np.array([s, s + b, s - b, s_a + b, s_a - b, s_b + b, s_b - b]))
        yaw, yaw_a, yaw_b = (_chord_yaw(p[i] - p[i + 1], vi) for i, vi in ((1, v), (3, v_a), (5, v_b)))
        yaw_rate = float(np.angle(np.exp(1j * (yaw_b - yaw_a)))) / (2 * dt)
        heading = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        body = np.zeros(3) if self.body is None else self.body(t)
        return ActorState(self.id, self.cls, p[0], yaw, heading * abs(v), yaw_rate, self.size, body)


def _chord_yaw(d: np.ndarray, v: float) -> float:
    """Heading of a chord d along the line, for motion with signed speed v (backwards: reversed)."""
    if v < 0:
        d = -d
    return float(np.arctan2(d[1], d[0]))


class LaneFollower(_PathActor):
    """A vehicle on a lane centre line: s(t) = s0 + v t + (A T / 2 pi) (sin(2 pi t / T + phase) - sin(phase)).

    Its speed v + A cos(2 pi t / T + phase) varies slowly around v (never negative if A <= v). With a
    ``leader`` (the vehicle ahead in the same lane) it keeps ``min_gap_m`` behind it (centre to centre):
    s(t) = min(s_free(t), s_leader(t) + leader_offset_m - min_gap_m), at the leader's speed while it
    follows. On a ring the front vehicle follows the last one a lap ahead (``leader_offset_m``, the lane's
    length), by that one's free motion (``leader_free``), which ends the chain.
    """

    cls = ObjectClass.VEHICLE

    def __init__(self, actor_id, line, s0, speed, amp, period, phase, size):
        super().__init__(actor_id, line, size)
        self.s0, self.v, self.amp, self.period, self.phase = s0, speed, min(amp, speed), period, phase
        self.leader: LaneFollower | None = None
        self.leader_offset_m = 0.0
        self.leader_free = False
        self.min_gap_m = 0.0
        self._arcs: dict[float, tuple[float, float]] = {}  # arc(t) of the last few t asked for

    def free_arc(self, t: float) -> tuple[float, float]:
        """Arc length and speed without a leader."""
        w = 2 * np.pi / self.period
        s = self.s0 + self.v * t + self.amp / w * (np.sin(w * t + self.phase) - np.sin(self.phase))
        return float(s), float(self.v + self.amp * np.cos(w * t + self.phase))

    def arc(self, t: float) -> tuple[float, float]:
        """Arc length and speed at t. Remembered for the last few t: a vehicle's arc needs its leader's,
        which needs its own leader's, so a lane of n vehicles would cost n^2 / 2 evaluations per instant."""
        if (hit := self._arcs.get(t)) is not None:
            return hit
        s, v = self.free_arc(t)
        if self.leader is not None:
            s_lead, v_lead = self.leader.free_arc(t) if self.leader_free else self.leader.arc(t)
            s_lead += self.leader_offset_m
            if s > s_lead - self.min_gap_m:
                s, v = s_lead - self.min_gap_m, v_lead
        if len(self._arcs) >= _ARC_MEMO:
            self._arcs.pop(next(iter(self._arcs)))
        self._arcs[t] = (s, v)
        return s, v


class PathWalker(_PathActor):
    """A pedestrian: loops along a closed path, walks to and fro along an open one (a crossing)."""

    cls = ObjectClass.PEDESTRIAN

    def __init__(self, actor_id, line, s0, speed, direction, size=(0.6, 0.6, 1.75)):
        super().__init__(actor_id, line, size)
        self.s0, self.v = s0, speed * direction

    def arc(self, t: float) -> tuple[float, float]:
        s = self.s0 + self.v * t
        if self.line.closed:
            return s, self.v
        # Triangle wave between the two ends of the crossing.
        L = self.line.length
        phase = np.mod(s, 2 * L)
        return (float(phase), self.v) if phase < L else (float(2 * L - phase), -self.v)


def box_corners(state: ActorState) -> np.ndarray:
    """The 8 corners (8, 3) of an actor's box in the map frame."""
    length, w, h = state.size
    x = np.array([1, 1, -1, -1, 1, 1, -1, -1]) * length / 2
    y = np.array([1, -1, -1, 1, 1, -1, -1, 1]) * w / 2
    z = np.array([0, 0, 0, 0, 1, 1, 1, 1]) * h
    c, s = np.cos(state.yaw), np.sin(state.yaw)
    return np.column_stack([c * x - s * y, s * x + c * y, z]) + state.p_map
