"""Faults and attacks of a connected vehicle, as configuration: what its outgoing V2X messages become.

A scenario (``faults:`` in its YAML) or a fleet run lists faults, each for one vehicle from
``start_s`` to ``end_s`` of scenario time (``end_s`` None: to the end). :class:`FaultInjector` turns the
message the vehicle's agent built into the messages that go on the air; the same injector runs in
the in-process pipeline and in the live vehicle service, so a fault is the same in both.

Kinds (each a model below, told apart by ``kind``):

* ``pose_bias`` — the reported pose is ``bias_m`` (map x, y) off; its covariance is not changed (a
  miscalibrated or lying localizer);
* ``ghost_objects`` — ``count`` objects that do not exist are added to every message, at fixed places in
  the body frame (a spoofed detector);
* ``drop_detections`` — the message carries no object detections (a blind or withholding detector);
* ``clock_offset`` — ``t_meas`` and ``t_sent`` are ``offset_s`` off (a vehicle with a wrong clock);
* ``frozen_clock`` — ``t_meas`` and ``t_sent`` stay at their value at ``start_s`` (a clock that stopped);
* ``replay`` — besides its own, the vehicle re-sends its message of ``delay_s`` ago, unchanged;
* ``impostor`` — besides its own, a copy of each message goes out claiming to be ``as_vehicle``,
  with the impostor's pose moved ``bias_m`` (a forger using another vehicle's identity).

Pure and deterministic.
"""

from __future__ import annotations

from collections import deque
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from schemas import ObjectClass, ObjectObservations, VehiclePrior
from schemas.models import NAME_PATTERN

__all__ = ["FAULT_KINDS", "Fault", "FaultInjector"]


class _Fault(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    vehicle: str = Field(pattern=NAME_PATTERN, description="the misbehaving vehicle")
    start_s: float = Field(0.0, ge=0, description="scenario time the fault starts")
    end_s: float | None = Field(None, gt=0, description="scenario time it ends (None: never)")

    def active(self, t: float) -> bool:
        return t >= self.start_s and (self.end_s is None or t < self.end_s)


class PoseBias(_Fault):
    kind: Literal["pose_bias"] = "pose_bias"
    bias_m: tuple[float, float] = Field(description="map-frame (x, y) offset of the reported pose (m)")


class GhostObjects(_Fault):
    kind: Literal["ghost_objects"] = "ghost_objects"
    count: int = Field(2, ge=1, le=64, description="objects added to every message")
    range_m: float = Field(15.0, gt=0, description="how far ahead the ghosts stand (m)")


class DropDetections(_Fault):
    kind: Literal["drop_detections"] = "drop_detections"


class ClockOffset(_Fault):
    kind: Literal["clock_offset"] = "clock_offset"
    offset_s: float = Field(description="added to t_meas and t_sent (s)")


class FrozenClock(_Fault):
    kind: Literal["frozen_clock"] = "frozen_clock"


class Replay(_Fault):
    kind: Literal["replay"] = "replay"
    delay_s: float = Field(1.0, gt=0, description="the message of this long ago is sent again (s)")


class Impostor(_Fault):
    kind: Literal["impostor"] = "impostor"
    as_vehicle: str = Field(pattern=NAME_PATTERN, description="the identity the copies claim")
    bias_m: tuple[float, float] = Field((5.0, 0.0), description="the forged copies' pose offset (m)")


Fault = Annotated[
    PoseBias | GhostObjects | DropDetections | ClockOffset | FrozenClock | Replay | Impostor,
    Field(discriminator="kind"),
]
FAULT_KINDS = ("pose_bias", "ghost_objects", "drop_detections", "clock_offset", "frozen_clock", "replay", "impostor")


class FaultInjector:
    """The faults of one vehicle applied to its outgoing messages (module doc)."""

    def __init__(self, vehicle_id: str, faults: list[Fault]):
        self.vehicle_id = vehicle_id
        self.faults = [f for f in faults if f.vehicle == vehicle_id]
        self._sent: deque[VehiclePrior] = deque()  # for replay: this vehicle's messages, newest last
        self._frozen_t: dict[int, float] = {}  # frozen_clock: the time each fault froze at

    def __bool__(self) -> bool:
        return bool(self.faults)

    def apply(self, msg: VehiclePrior) -> list[VehiclePrior]:
        """The messages that go out instead of ``msg`` (in order; possibly none, possibly several)."""
        if not self.faults:
            return [msg]
        t = float(msg.t_meas)
        out = msg
        extra: list[VehiclePrior] = []
        for i, f in enumerate(self.faults):
            if not f.active(t):
                continue
            if isinstance(f, PoseBias):
                out = _moved(out, f.bias_m)
            elif isinstance(f, GhostObjects):
                out = _with(out, objects=_with_ghosts(out.objects, f.count, f.range_m))
            elif isinstance(f, DropDetections):
                out = _with(out, objects=ObjectObservations())
            elif isinstance(f, ClockOffset):
                out = _with(out, t_meas=out.t_meas + f.offset_s, t_sent=out.t_sent + f.offset_s)
            elif isinstance(f, FrozenClock):
                frozen = self._frozen_t.setdefault(i, out.t_meas)
                out = _with(out, t_meas=frozen, t_sent=frozen)
            elif isinstance(f, Replay):
                old = [m for m in self._sent if m.t_meas <= t - f.delay_s]
                if old:
                    extra.append(old[-1])
            elif isinstance(f, Impostor):
                extra.append(_with(_moved(out, f.bias_m), sender=f.as_vehicle))
        self._sent.append(msg)
        keep_s = max((f.delay_s for f in self.faults if isinstance(f, Replay)), default=0.0) + 1.0
        while self._sent and self._sent[0].t_meas < t - keep_s:
            self._sent.popleft()
        return [out, *extra]


def _with(msg: VehiclePrior, **update) -> VehiclePrior:
    """``msg`` with fields replaced, validated as any message (a fault never makes an invalid message)."""
    return VehiclePrior.model_validate({**dict(msg), **update})


def _moved(msg: VehiclePrior, bias_m: tuple[float, float]) -> VehiclePrior:
    pose = np.asarray(msg.pose, dtype=float).copy()
    pose[:2] += bias_m
    return _with(msg, pose=pose)


def _with_ghosts(objs: ObjectObservations, count: int, range_m: float) -> ObjectObservations:
    """``objs`` and ``count`` vehicles that are not there, side by side ``range_m`` ahead (body frame)."""
    lateral = (np.arange(count) - (count - 1) / 2) * 3.0
    p = np.column_stack([np.full(count, range_m), lateral, np.full(count, 0.8)])
    cov = np.tile(np.diag([0.3, 0.2, 0.1]) ** 2, (count, 1, 1))
    ghosts = ObjectObservations.from_metres(p, cov, [int(ObjectClass.VEHICLE)] * count)
    if len(objs) == 0:
        return ghosts
    return ObjectObservations(
        p_body_cm=np.concatenate([objs.p_body_cm, ghosts.p_body_cm]),
        cov=np.concatenate([objs.cov, ghosts.cov]),
        cls=np.concatenate([objs.cls, ghosts.cls]),
    )
