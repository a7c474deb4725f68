"""The topic registry: every key expression, the model it carries and its nominal rate.

Publishers, subscribers, the health CLI and the docs all read this one table. Templates use
``{fleet}`` (the run's namespace) and role placeholders; :meth:`Topic.key` fills them and
:meth:`Topic.pattern` turns the unfilled ones into Zenoh ``*`` chunks.
"""

from __future__ import annotations

import re
import string
from dataclasses import dataclass

from pydantic import BaseModel

from .codec import MAX_MESSAGE_BYTES
from .models import (
    MAX_MASK_BYTES,
    EvalMetrics,
    FusedState,
    GroundTruth,
    HealthStatus,
    PoseDownlink,
    RawObservations,
    SensorFrame,
    VehiclePrior,
)

__all__ = ["TOPICS", "Topic", "is_chunk", "max_bytes", "topic"]

_CHUNK = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


@dataclass(frozen=True)
class Topic:
    name: str
    template: str
    model: type[BaseModel] | None  # None: a liveliness token, no payload
    rate_hz: float | None  # nominal publish rate per key; None: on demand
    description: str
    # Payloads larger than this are refused before anything reads them (subscribers check the size Zenoh
    # reports before copying the bytes out): about four times the largest message the topic can carry.
    max_bytes: int = MAX_MESSAGE_BYTES

    @property
    def fields(self) -> tuple[str, ...]:
        return tuple(f for _, f, _, _ in string.Formatter().parse(self.template) if f)

    def key(self, **values: str) -> str:
        """The concrete key expression; every placeholder must be given a single safe chunk."""
        missing = set(self.fields) - values.keys()
        if missing:
            raise ValueError(f"topic {self.name!r} needs {sorted(missing)}")
        for k, v in values.items():
            if not is_chunk(v):
                raise ValueError(f"{k}={v!r} is not a valid key chunk (letters, digits, '_' or '-')")
        return self.template.format(**values)

    def pattern(self, **values: str) -> str:
        """A key expression with ``*`` for every placeholder not given (for subscribers)."""
        filled = {f: values.get(f, "*") for f in self.fields}
        for k, v in values.items():
            if not is_chunk(v):
                raise ValueError(f"{k}={v!r} is not a valid key chunk")
        return self.template.format(**filled)

    def parse(self, key: str) -> dict[str, str] | None:
        """The placeholders of a concrete ``key`` of this topic (``{"fleet": ..., "src": ...}``), or None
        when the key is not one of this topic's or a placeholder's chunk is not one :meth:`key` accepts
        (Zenoh's ``*`` matches chunks such as ``cv1.x`` that our keys never hold)."""
        parts, want = str(key).split("/"), self.template.split("/")
        if len(parts) != len(want):
            return None
        out: dict[str, str] = {}
        for got, t in zip(parts, want, strict=True):
            if t.startswith("{") and t.endswith("}"):
                if not is_chunk(got):
                    return None
                out[t[1:-1]] = got
            elif got != t:
                return None
        return out


_KIB = 1024
_OBSERVATIONS_BYTES = MAX_MASK_BYTES + 512 * _KIB  # a lane mask at its limit, the detections and a signature
_STATE_BYTES = 1024 * _KIB  # up to MAX_OBJECTS vehicles and objects with their covariances

TOPICS: tuple[Topic, ...] = (
    Topic("sensors", "mc/{fleet}/sim/{vid}/sensors", SensorFrame, 10.0,
          "world -> vehicle: one camera frame with GNSS, odometry and object detections (on-board bus)",
          _OBSERVATIONS_BYTES),
    Topic("truth", "mc/{fleet}/sim/truth", GroundTruth, 10.0, "world -> evaluator: ground truth", _STATE_BYTES),
    Topic("prior_tx", "mc/{fleet}/v2x/tx/{src}/prior", VehiclePrior, 10.0,
          "vehicle -> channel emulator: distributed-mode prior", 256 * _KIB),
    Topic("raw_tx", "mc/{fleet}/v2x/tx/{src}/raw", RawObservations, 10.0,
          "vehicle -> channel emulator: centralized-mode raw observations", _OBSERVATIONS_BYTES),
    Topic("prior_rx", "mc/{fleet}/v2x/rx/{dst}/{src}/prior", VehiclePrior, 10.0,
          "channel emulator -> receiver {dst}: a prior from {src} after the link model", 256 * _KIB),
    Topic("raw_rx", "mc/{fleet}/v2x/rx/{dst}/{src}/raw", RawObservations, 10.0,
          "channel emulator -> receiver {dst}: raw observations from {src} after the link model",
          _OBSERVATIONS_BYTES),
    Topic("downlink_tx", "mc/{fleet}/v2x/tx/{src}/downlink/{dst}", PoseDownlink, 10.0,
          "host {src} -> channel emulator: what the other vehicles know about vehicle {dst}'s pose (the downlink)",
          16 * _KIB),
    Topic("downlink_rx", "mc/{fleet}/v2x/rx/{dst}/{src}/downlink", PoseDownlink, 10.0,
          "channel emulator -> vehicle {dst}: the downlink of host {src} after the link model", 16 * _KIB),
    Topic("fused", "mc/{fleet}/host/{hid}/fused", FusedState, 10.0, "host -> anyone: the fused environment",
          _STATE_BYTES),
    Topic("metrics", "mc/{fleet}/eval/metrics", EvalMetrics, 1.0,
          "evaluator -> anyone: live RMSE, end-to-end latency, bytes/s per vehicle, delivered fraction",
          64 * _KIB),
    Topic("health", "mc/{fleet}/health/{role}/{id}", HealthStatus, 1.0,
          "every service: periodic status put, and a queryable on the same key", 64 * _KIB),
    Topic("alive", "mc/{fleet}/alive/{role}/{id}", None, None, "every service: liveliness token", 0),
)

_BY_NAME = {t.name: t for t in TOPICS}


def is_chunk(value: str) -> bool:
    """``value`` can fill a placeholder (a fleet, vehicle or host id): letters, digits, '_' or '-'."""
    return bool(_CHUNK.fullmatch(str(value)))


def max_bytes(key: str) -> int:
    """The size bound of the topic whose template ``key`` (a key or a subscriber's pattern, ``*`` chunks
    allowed) belongs to; the codec's MAX_MESSAGE_BYTES for a key of no topic."""
    parts = str(key).split("/")
    for t in TOPICS:
        want = t.template.split("/")
        if len(want) == len(parts) and all(
            w == p or (w.startswith("{") and (p == "*" or is_chunk(p))) for w, p in zip(want, parts, strict=True)
        ):
            return t.max_bytes
    return MAX_MESSAGE_BYTES


def topic(name: str) -> Topic:
    try:
        return _BY_NAME[name]
    except KeyError:
        raise KeyError(f"unknown topic {name!r}; known: {sorted(_BY_NAME)}") from None
