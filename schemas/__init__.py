"""Map Container's wire contract: message models, the msgpack codec and the topic registry."""

from .codec import REASONS, Rejection, decode, encode
from .models import (
    SCHEMA_VERSION,
    CameraInfo,
    Envelope,
    FusedState,
    GnssFix,
    GroundTruth,
    HealthStatus,
    LandmarkClass,
    LocalizationQuality,
    ObjectClass,
    ObjectObservations,
    Observations,
    Odometry,
    RawObservations,
    SensorFrame,
    VehiclePrior,
)

__all__ = [
    "REASONS",
    "SCHEMA_VERSION",
    "CameraInfo",
    "Envelope",
    "FusedState",
    "GnssFix",
    "GroundTruth",
    "HealthStatus",
    "LandmarkClass",
    "LocalizationQuality",
    "ObjectClass",
    "ObjectObservations",
    "Observations",
    "Odometry",
    "RawObservations",
    "Rejection",
    "SensorFrame",
    "VehiclePrior",
    "decode",
    "encode",
]
