"""Scenario and sensor configuration (validated; loaded from configs/)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, PositiveInt, model_validator

from ..config import ConfigError, deep_merge, find_preset, list_presets, load_yaml_model, read_yaml, validate_model
from ..faults import Fault
from ..hdmap.generator import MapSpec

__all__ = [
    "BodyConfig",
    "CameraConfig",
    "DetectorConfig",
    "GnssConfig",
    "OdometryConfig",
    "PedestrianSpec",
    "ScenarioConfig",
    "SensorConfig",
    "VehicleSpec",
    "list_scenarios",
    "load_scenario",
    "scale_scenario",
]


Pos = Annotated[float, Field(gt=0)]
NonNeg = Annotated[float, Field(ge=0)]
Probability = Annotated[float, Field(ge=0, le=1)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class CameraConfig(_Strict):
    """Pinhole camera and its landmark / lane detectors. Values and their meaning: configs/sensors/*.yaml."""

    width: PositiveInt
    height: PositiveInt
    f_px: Pos
    mount_xyz_m: tuple[float, float, float]
    pitch_rad: float
    range_m: Pos
    pixel_sigma_px: NonNeg
    p_detect_near: Probability
    p_detect_far: Probability
    min_depth_m: Pos
    clutter_points_per_frame: NonNeg
    clutter_poles_per_frame: NonNeg
    lane_range_m: Pos
    lane_marking_width_m: Pos
    lane_pixel_sigma_px: NonNeg
    lane_dropout: Probability


class GnssConfig(_Strict):
    """A low-cost GNSS receiver: white noise, a Gauss-Markov bias and urban multipath jumps."""

    white_sigma_m: NonNeg
    vertical_sigma_m: NonNeg
    bias_sigma_m: NonNeg
    bias_tau_s: Pos
    multipath_rate_per_s: NonNeg
    multipath_jump_m: tuple[NonNeg, NonNeg]
    multipath_duration_s: tuple[NonNeg, NonNeg]
    reported_sigma_h_m: Pos
    reported_sigma_v_m: Pos


class OdometryConfig(_Strict):
    """Wheel speed and gyro yaw rate with noise, scale error and bias."""

    speed_sigma_mps: NonNeg
    speed_scale_sigma: NonNeg
    yaw_rate_sigma_radps: NonNeg
    yaw_rate_bias_sigma_radps: NonNeg


class DetectorConfig(_Strict):
    """Object detector: body-frame positions with range-dependent noise, misses and false alarms."""

    range_m: Pos
    fov_deg: float = Field(gt=0, le=360)
    sigma_radial_m: tuple[NonNeg, NonNeg]
    sigma_tangential_m: tuple[NonNeg, NonNeg]
    sigma_vertical_m: Pos
    p_detect_near: Probability
    p_detect_far: Probability
    false_alarms_per_frame: NonNeg


class BodyConfig(_Strict):
    """How the body the sensors ride on moves about its nominal attitude and height on the road.

    Per vehicle: a static offset (load, tyres) plus a dynamic part (suspension: a sum of sinusoids at
    0.5-1.5 Hz with seeded phases), each a 1-sigma. Zero everywhere: a rigid body on a flat road.
    """

    heave_static_m: NonNeg = 0.0
    heave_dynamic_m: NonNeg = 0.0
    roll_static_rad: NonNeg = 0.0
    roll_dynamic_rad: NonNeg = 0.0
    pitch_static_rad: NonNeg = 0.0
    pitch_dynamic_rad: NonNeg = 0.0


class SensorConfig(_Strict):
    """All sensors of a connected vehicle (configs/sensors/NAME.yaml)."""

    rate_hz: Pos
    camera: CameraConfig
    gnss: GnssConfig
    odometry: OdometryConfig
    detector: DetectorConfig
    body: BodyConfig = BodyConfig()


class VehicleSpec(_Strict):
    """A vehicle driving along a lane centre line."""

    lane: int = Field(0, ge=0, description="index into the map's centre lines")
    s0_m: float = Field(0.0, description="start position along the lane (arc length)")
    speed_mps: float = Field(10.0, ge=0)
    speed_amp_mps: float = Field(1.0, ge=0, description="amplitude of a slow sinusoidal speed change")
    speed_period_s: float = Field(20.0, gt=0)
    length_m: float = Field(4.6, gt=0)
    width_m: float = Field(1.9, gt=0)
    height_m: float = Field(1.5, gt=0)


class PedestrianSpec(_Strict):
    """A pedestrian walking along a walkable area's path (loops on sidewalks, to and fro on crossings)."""

    area: int = Field(0, ge=0, description="index into the map's walkable areas")
    s0_m: float = 0.0
    speed_mps: float = Field(1.3, ge=0)
    direction: Literal[1, -1] = 1


class ScenarioConfig(_Strict):
    name: str
    description: str = ""
    map: MapSpec = MapSpec()
    sensors: SensorConfig
    connected: list[VehicleSpec] = Field(min_length=1)
    obstacle_vehicles: list[VehicleSpec] = Field(default_factory=list)
    pedestrians: list[PedestrianSpec] = Field(default_factory=list)
    duration_s: float = Field(30.0, gt=0, description="default episode length")
    faults: list[Fault] = Field(default_factory=list, description="misbehaving vehicles (mapcontainer.faults)")

    @model_validator(mode="after")
    def _indices(self):
        lanes = 2 * self.map.lanes_per_direction
        areas = 2 + self.map.crossings
        for v in [*self.connected, *self.obstacle_vehicles]:
            if v.lane >= lanes:
                raise ValueError(f"lane {v.lane} does not exist: the map has {lanes} lanes")
        for p in self.pedestrians:
            if p.area >= areas:
                raise ValueError(f"walkable area {p.area} does not exist: the map has {areas}")
        return self


def list_scenarios() -> list[str]:
    """Names of the scenario presets (``scenarios/`` of the built-in and the user's config directories)."""
    return list(list_presets("scenarios"))


def load_scenario(name_or_path: str | Path, overrides: dict[str, Any] | None = None) -> ScenarioConfig:
    """A preset by name (configs/scenarios/NAME.yaml) or a YAML file by path.

    The scenario's ``sensors`` entry may be a mapping of overrides on top of the sensor profile
    named by ``sensor_profile`` (default: configs/sensors/default.yaml).
    """
    path = Path(name_or_path)
    if not path.suffix:
        path = find_preset("scenarios", str(name_or_path), "scenario")
    data = read_yaml(path)
    profile = data.pop("sensor_profile", "default")
    if not isinstance(profile, str):
        raise ConfigError(f"{path}: sensor_profile must be the name of a sensor profile, got {profile!r}")
    sensors = read_yaml(find_preset("sensors", profile, "sensor profile"))
    own = data.get("sensors") or {}
    if not isinstance(own, dict):
        raise ConfigError(f"{path}: sensors must be a mapping of overrides, got {type(own).__name__}")
    data["sensors"] = deep_merge(sensors, own)
    if overrides:
        data = deep_merge(data, overrides)
    return validate_model(ScenarioConfig, data, path)


def load_sensor_config(name: str = "default") -> SensorConfig:
    return load_yaml_model(SensorConfig, find_preset("sensors", name, "sensor profile"))


def scale_scenario(sc: ScenarioConfig, vehicles: int | None) -> ScenarioConfig:
    """The scenario with ``vehicles`` connected vehicles (None: as defined).

    Fewer than defined: the first ones. More: extra vehicles are spread evenly over the ring's
    lanes and around it, at about the defined vehicles' mean speed (0.9x to 1.1x).
    """
    if vehicles is None or vehicles == len(sc.connected):
        return sc
    if vehicles < 1:
        raise ValueError(f"vehicles must be at least 1, got {vehicles}")
    connected = list(sc.connected[:vehicles])
    n_extra = vehicles - len(connected)
    if n_extra > 0:
        lanes = 2 * sc.map.lanes_per_direction
        speed = sum(v.speed_mps for v in sc.connected) / len(sc.connected)
        ring_m = 2 * (sc.map.length_m + sc.map.width_m)  # roughly the ring's length; s wraps anyway
        for i in range(n_extra):
            connected.append(
                VehicleSpec(
                    lane=i % lanes,
                    s0_m=(i + 0.5) * ring_m / n_extra,
                    speed_mps=speed * (0.9 + 0.2 * ((i * 7) % 5) / 4),
                )
            )
    data = sc.model_dump()
    data["connected"] = [v.model_dump() for v in connected]
    return ScenarioConfig.model_validate(data)
