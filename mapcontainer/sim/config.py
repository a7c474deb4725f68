"""Scenario and sensor configuration (validated; loaded from configs/)."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Discriminator, Field, PositiveInt, Tag, field_validator, model_validator

from ..config import ConfigError, deep_merge, find_preset, list_presets, load_yaml_model, read_yaml, validate_model
from ..faults import Fault
from ..hdmap.errors import EXTRA
from ..hdmap.generator import MapSpec
from ..hdmap.sumo import PlacementRule

__all__ = [
    "BodyConfig",
    "CalibrationErrorConfig",
    "CameraConfig",
    "ClassConfusionConfig",
    "ClockConfig",
    "ClutterConfig",
    "DetectorConfig",
    "DetectorErrorConfig",
    "MAP_FORMATS",
    "GnssConfig",
    "MapErrorConfig",
    "MapFile",
    "OdometryConfig",
    "PedestrianSpec",
    "ScenarioConfig",
    "SensorConfig",
    "SumoConnected",
    "SumoRandomTrips",
    "SumoTrafficConfig",
    "TrafficConfig",
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


class CalibrationErrorConfig(_Strict):
    """How far a vehicle's true camera is from the calibration it reports and believes (per vehicle, per
    run): a rotation vector and a translation of T_body_cam with these 1-sigmas per axis, focal lengths
    scaled by 1 + N(0, focal_sigma) each, the principal point moved by N(0, principal_point_sigma_px)
    per axis. The camera renders with the true calibration; CameraInfo carries the nominal one."""

    enabled: bool = False
    rotation_sigma_rad: NonNeg = 0.0
    translation_sigma_m: NonNeg = 0.0
    focal_sigma: NonNeg = 0.0
    principal_point_sigma_px: NonNeg = 0.0


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
    calibration_error: CalibrationErrorConfig = CalibrationErrorConfig()


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


class DetectorErrorConfig(_Strict):
    """What makes the detector's errors differ from the white noise its covariance describes.

    A share ``persistent_fraction`` of each axis' error variance is a first-order Gauss-Markov process per
    (observer, target) with correlation time ``tau_s`` (the rest stays white, so the total variance is the
    nominal one); the reported sigmas are off by a per-vehicle factor exp(N(0, reported_scale_sigma)), and
    the covariance is evaluated at the measured position (the detector does not know the true one).
    """

    enabled: bool = False
    persistent_fraction: Probability = 0.0
    tau_s: Pos = 1.0
    reported_scale_sigma: NonNeg = 0.0


class ClassConfusionConfig(_Strict):
    """A detection reports another class (uniform among the other object classes) with probability ``p``."""

    enabled: bool = False
    p: Probability = 0.0


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
    false_alarm_lifetime_s: NonNeg = 0.0
    errors: DetectorErrorConfig = DetectorErrorConfig()
    class_confusion: ClassConfusionConfig = ClassConfusionConfig()


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


class ClockConfig(_Strict):
    """A vehicle's clock: its time stamps (t_meas, t_sent) are off by a constant N(0, offset_sigma_s) drawn
    per vehicle per run."""

    enabled: bool = False
    offset_sigma_s: NonNeg = 0.0


class ClutterConfig(_Strict):
    """The switch of the false detections whose rates the camera and detector sections set
    (clutter_points_per_frame, clutter_poles_per_frame, false_alarms_per_frame); off: none."""

    enabled: bool = True


class MapErrorConfig(_Strict):
    """How the HD map the vehicles and the host carry differs from the world (drawn per run).

    Displacement = a smooth field shared by every feature (survey drift: 1-sigmas ``field_sigma_m``
    (horizontal per axis, vertical), squared-exponential correlation over ``field_length_m``) + for each
    lane line its own smooth field over ``line_length_m`` (horizontal 1-sigma ``line_sigma_m`` per axis)
    + for each landmark an independent offset ``landmark_sigma_m`` (horizontal per axis, vertical).
    Each landmark is missing from the map with probability ``p_missing``; Poisson(``p_extra`` x landmarks)
    landmarks that are not in the world are in the map.
    """

    enabled: bool = False
    field_sigma_m: tuple[NonNeg, NonNeg] = (0.0, 0.0)
    field_length_m: Pos = 30.0
    line_sigma_m: NonNeg = 0.0
    line_length_m: Pos = 15.0
    landmark_sigma_m: tuple[NonNeg, NonNeg] = (0.0, 0.0)
    p_missing: Probability = 0.0
    p_extra: NonNeg = 0.0


class SensorConfig(_Strict):
    """All sensors of a connected vehicle (configs/sensors/NAME.yaml)."""

    rate_hz: Pos
    camera: CameraConfig
    gnss: GnssConfig
    odometry: OdometryConfig
    detector: DetectorConfig
    body: BodyConfig = BodyConfig()
    clock: ClockConfig = ClockConfig()
    clutter: ClutterConfig = ClutterConfig()
    hdmap: MapErrorConfig = MapErrorConfig()


class VehicleSpec(_Strict):
    """A vehicle driving along a lane centre line."""

    lane: int = Field(0, ge=0, description="index into the map's centre lines")
    s0_m: float = Field(0.0, description="start position along the lane (arc length)")
    speed_mps: float = Field(10.0, ge=0)
    speed_amp_mps: float = Field(1.0, ge=0, description="amplitude of a slow sinusoidal speed change")
    speed_period_s: float = Field(20.0, gt=0)
    speed_phase_rad: float | None = Field(
        None, description="phase of the speed change (None: spread evenly over the scenario's vehicles)"
    )
    length_m: float = Field(4.6, gt=0)
    width_m: float = Field(1.9, gt=0)
    height_m: float = Field(1.5, gt=0)


class PedestrianSpec(_Strict):
    """A pedestrian walking along a walkable area's path (loops on sidewalks, to and fro on crossings)."""

    area: int = Field(0, ge=0, description="index into the map's walkable areas")
    s0_m: float = 0.0
    speed_mps: float = Field(1.3, ge=0)
    direction: Literal[1, -1] = 1


class TrafficConfig(_Strict):
    """How the traffic varies from run to run (drawn from the run's seed; off: exactly as listed).

    Vehicles: the start moves along the lane by N(0, s0_sigma_m) (truncated at 2 sigma); the mean speed is
    scaled by 1 + N(0, speed_sigma) (truncated at 2 sigma), the speed change's amplitude by
    U(speed_amp_scale) and its period by U(speed_period_scale), its phase moves by N(0, speed_phase_sigma_rad)
    (about pi: uniform). Vehicles in one lane start at least ``min_gap_m`` apart (centre to centre: a
    vehicle drawn closer to the one behind it is pushed forward). A ``platoon``
    draws all of that once for every vehicle (the scene moves together: order, gaps and relative phases
    kept) and moves each vehicle by a further N(0, gap_sigma_m) (truncated at 2 sigma). Otherwise each
    vehicle draws its own, and moves to the other lane of its direction with probability lane_swap_p.
    Pedestrians: speed N(pedestrian_speed_mps) clipped to pedestrian_speed_range_mps, direction reversed
    with probability pedestrian_reverse_p, start uniform along the path (pedestrian_s0_uniform) or as listed.
    """

    source: Literal["scenario"] = "scenario"
    enabled: bool = False
    platoon: bool = False
    s0_sigma_m: NonNeg = 0.0
    gap_sigma_m: NonNeg = 0.0
    speed_sigma: NonNeg = 0.0
    speed_amp_scale: tuple[NonNeg, NonNeg] = (1.0, 1.0)
    speed_period_scale: tuple[Pos, Pos] = (1.0, 1.0)
    speed_phase_sigma_rad: NonNeg = 0.0
    min_gap_m: NonNeg = 0.0
    lane_swap_p: Probability = 0.0
    pedestrian_speed_mps: tuple[Pos, NonNeg] = (1.3, 0.0)
    pedestrian_speed_range_mps: tuple[NonNeg, Pos] = (0.5, 2.5)
    pedestrian_reverse_p: Probability = 0.0
    pedestrian_s0_uniform: bool = False

    @model_validator(mode="after")
    def _ranges(self):
        for name in ("speed_amp_scale", "speed_period_scale", "pedestrian_speed_range_mps"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{name} must be (low, high) with low <= high, got {(lo, hi)}")
        return self


class SumoRandomTrips(_Strict):
    """Random trips from SUMO's ``tools/randomTrips.py``: ``vehicles`` vehicle trips and ``pedestrians`` person
    trips departing evenly over SUMO time [0, ``period_s``) (one every period_s / count seconds), between random
    edges at least ``min_distance_m`` apart (vehicles start and end at the network's fringe ``fringe_factor``
    times as often as inside it). ``seed``: the trips' seed; None draws them per run from the run's seed."""

    seed: int | None = Field(None, ge=0)
    vehicles: int = Field(ge=1, le=10000)
    pedestrians: int = Field(0, ge=0, le=10000)
    period_s: float = Field(60.0, gt=0, le=86400)
    min_distance_m: NonNeg = 100.0
    fringe_factor: float = Field(5.0, ge=1)


class SumoConnected(_Strict):
    """Which SUMO vehicles are the connected vehicles (cv0, cv1, ... in this order): the listed ``ids``, or the
    first ``first`` vehicles to depart (of vehicle type ``type`` when given)."""

    ids: list[str] | None = Field(None, min_length=1)
    first: int | None = Field(None, ge=1, le=256)
    type: str | None = None

    @model_validator(mode="after")
    def _one(self):
        if (self.ids is None) == (self.first is None):
            raise ValueError("give the connected vehicles as ids: [...] or as first: N (optionally with type:)")
        if self.ids is not None and self.type is not None:
            raise ValueError("type: selects among the first N to depart; with ids: it has no meaning")
        if self.ids is not None and len(set(self.ids)) != len(self.ids):
            raise ValueError(f"connected ids repeat: {self.ids}")
        return self

    @property
    def count(self) -> int:
        return len(self.ids) if self.ids is not None else int(self.first)


class SumoTrafficConfig(_Strict):
    """Traffic driven by SUMO in process (libsumo; the ``roads`` extra): :mod:`mapcontainer.sim.sumo`.

    The network SUMO drives is the scenario's map when that is ``map: {format: sumo, path: NET}`` (``net`` is then
    filled in from it); ``net`` names it only when the map is a Lanelet2 or GeoJSON file of the same network.
    Routes from ``routes`` (route files: vehicles, persons, flows, vehicle types) or ``random`` trips, plus
    ``additional`` files for SUMO (signal programs, vehicle types); the signals run the network's programs unless
    those replace them. SUMO steps at the sensor rate. Before t = 0 SUMO runs at least ``warmup_s`` and until
    every connected vehicle has departed (at most ``max_warmup_s``; a connected vehicle not departed by
    then is an error). A connected vehicle on the second last edge of its route gets a new destination (seeded,
    among the edges inside the map's extent), so it keeps driving; one that leaves the simulation all the same
    (teleported after ``time_to_teleport_s`` of standing, removed) stops the episode with an error. Relative
    paths are relative to the scenario file. ``enabled`` (per-run variation): on, SUMO's seed and the random
    trips' (unless ``random.seed``) are the run's seed; off, both are ``seed``.
    """

    source: Literal["sumo"]
    net: Path | None = None
    routes: list[Path] = Field(default_factory=list)
    random: SumoRandomTrips | None = None
    additional: list[Path] = Field(default_factory=list)
    connected: SumoConnected
    warmup_s: NonNeg = 10.0
    max_warmup_s: Pos = 300.0
    time_to_teleport_s: float = Field(300.0, description="SUMO's --time-to-teleport; -1: never teleport")
    lateral_resolution_m: Pos = Field(
        0.8, description="SUMO's sublane model (--lateral-resolution): continuous lane changes, none standing"
    )
    enabled: bool = True
    seed: int = Field(0, ge=0)

    @model_validator(mode="before")
    @classmethod
    def _moved(cls, data: Any) -> Any:
        if isinstance(data, dict):
            moved = [k for k in ("landmarks", "pois") if k in data]
            if moved:
                raise ValueError(
                    f"{', '.join(moved)} describe the map: give them in map: {{format: sumo, path: NET, "
                    f"{', '.join(f'{k}: ...' for k in moved)}}}"
                )
        return data

    @model_validator(mode="after")
    def _files(self):
        if not self.routes and self.random is None:
            raise ValueError("SUMO traffic needs routes: [FILE, ...] or random: {vehicles: N, ...}")
        nets = [self.net] if self.net is not None else []
        for what, paths in (("net", nets), ("routes", self.routes), ("additional", self.additional)):
            for p in paths:
                if not p.is_file():
                    raise ValueError(f"{what} file {p} does not exist")
        if self.random is not None and not self.routes and self.connected.first is not None:
            if self.connected.first > self.random.vehicles:
                raise ValueError(
                    f"connected.first = {self.connected.first} but random trips make only {self.random.vehicles}"
                    " vehicles"
                )
        if self.max_warmup_s < self.warmup_s:
            raise ValueError(f"max_warmup_s ({self.max_warmup_s:g}) is below warmup_s ({self.warmup_s:g})")
        return self


MAP_FORMATS = ("sumo", "lanelet2", "geojson")
"""The ``format`` of a map read from a file (``map: {format: ..., path: ...}``)."""

_FORMAT_PACKAGES = {"sumo": ("sumolib",), "lanelet2": ("lanelet2",), "geojson": ()}  # their readers' packages


def _installed(package: str) -> bool:
    try:
        return importlib.util.find_spec(package) is not None
    except (ImportError, ValueError):
        return False


def package_dir(package: str) -> Path:
    """The directory of the installed Python package ``package`` (without importing it); ValueError if it is not
    installed."""
    spec = importlib.util.find_spec(package) if _installed(package) else None
    locations = list(spec.submodule_search_locations or []) if spec is not None else []
    if not locations:
        raise ValueError(
            f"package {package!r} is not installed (the networks shipped with SUMO come with the optional extra"
            f" {EXTRA}: pip install 'map-container[{EXTRA}]', from a checkout pip install -e '.[{EXTRA}]')"
        )
    return Path(locations[0])


class MapFile(_Strict):
    """The scenario's map read from a file: a SUMO network (``.net.xml[.gz]``), a Lanelet2 OSM map or our GeoJSON
    (:func:`mapcontainer.hdmap.formats.read_any_map`; SUMO and Lanelet2 need the ``roads`` extra).

    ``path`` is relative to the scenario file's directory, or, with ``package``, to the directory of that installed
    Python package (``package: sumo``: the sample networks eclipse-sumo ships, without copying them). SUMO only:
    ``landmarks`` (the importer's placement rule for lamps and signs) or ``pois`` (an additional file of lamp, sign
    and traffic-light POIs). Lanelet2 only: ``origin`` (lat, lon in degrees of the map frame's origin; default the
    file's first node). ``bounds`` [xmin, ymin, xmax, ymax] (m, map frame): the part of the map the scenario uses;
    the map keeps the elements with a vertex inside, and with SUMO traffic the connected vehicles' new destinations
    are drawn inside it.
    """

    format: str
    path: Path
    package: str | None = None
    landmarks: PlacementRule = PlacementRule()
    pois: Path | None = None
    origin: tuple[float, float] | None = None
    bounds: tuple[float, float, float, float] | None = None

    @field_validator("format")
    @classmethod
    def _format(cls, v: str) -> str:
        if v not in MAP_FORMATS:
            raise ValueError(
                f"unknown map format {v!r}: map: {{format: {' | '.join(MAP_FORMATS)}, path: FILE}}, or map: without"
                " format for the generated ring road"
            )
        return v

    @property
    def file(self) -> Path:
        """The map file's path (resolved against ``package`` when given)."""
        return package_dir(self.package) / self.path if self.package is not None else self.path

    @model_validator(mode="after")
    def _check(self):
        missing = [p for p in _FORMAT_PACKAGES[self.format] if not _installed(p)]
        if missing:
            raise ValueError(
                f"a {self.format} map needs the Python package {missing[0]!r} of the optional extra {EXTRA}:"
                f" pip install 'map-container[{EXTRA}]' (from a checkout: pip install -e '.[{EXTRA}]')"
            )
        f = self.file
        if not f.is_file():
            where = f" (in package {self.package!r})" if self.package is not None else ""
            raise ValueError(f"map file {f}{where} does not exist")
        if self.format != "sumo" and (self.pois is not None or self.landmarks != PlacementRule()):
            raise ValueError(f"landmarks: and pois: place landmarks on a SUMO network; this map is {self.format}")
        if self.pois is not None and not self.pois.is_file():
            raise ValueError(f"pois file {self.pois} does not exist")
        if self.format != "lanelet2" and self.origin is not None:
            raise ValueError(f"origin: is the origin of a Lanelet2 map's frame; this map is {self.format}")
        if self.bounds is not None:
            x0, y0, x1, y1 = self.bounds
            if not (x0 < x1 and y0 < y1):
                raise ValueError(
                    f"bounds must be [xmin, ymin, xmax, ymax] with xmin < xmax, ymin < ymax: {self.bounds}"
                )
        return self


def _map_kind(v: Any) -> str:
    fmt = v.get("format") if isinstance(v, dict) else getattr(v, "format", None)
    return "procedural" if fmt is None else "file"


MapSection = Annotated[
    Annotated[MapSpec, Tag("procedural")] | Annotated[MapFile, Tag("file")],
    Discriminator(_map_kind),
]


def _traffic_kind(v: Any) -> str:
    source = v.get("source", "scenario") if isinstance(v, dict) else getattr(v, "source", "scenario")
    return "sumo" if source == "sumo" else "scenario"


Traffic = Annotated[
    Annotated[TrafficConfig, Tag("scenario")] | Annotated[SumoTrafficConfig, Tag("sumo")],
    Discriminator(_traffic_kind),
]


class ScenarioConfig(_Strict):
    """A scenario. The map is ``map:``: the generated ring road (:class:`MapSpec`, the default) or a file
    (:class:`MapFile`: ``{format: sumo | lanelet2 | geojson, path: ...}``). Actors come from the lists
    ``connected``, ``obstacle_vehicles`` and ``pedestrians`` on the ring road (varied per run by ``traffic``), or,
    with ``traffic.source: sumo``, from SUMO on the map's network (the lists are then left out)."""

    name: str
    description: str = ""
    map: MapSection = MapSpec()
    sensors: SensorConfig
    connected: list[VehicleSpec] = Field(default_factory=list)
    obstacle_vehicles: list[VehicleSpec] = Field(default_factory=list)
    pedestrians: list[PedestrianSpec] = Field(default_factory=list)
    duration_s: float = Field(30.0, gt=0, description="default episode length")
    faults: list[Fault] = Field(default_factory=list, description="misbehaving vehicles (mapcontainer.faults)")
    traffic: Traffic = TrafficConfig()

    @property
    def sumo(self) -> SumoTrafficConfig | None:
        """The SUMO traffic section, or None when the actors are the scenario's own."""
        return self.traffic if isinstance(self.traffic, SumoTrafficConfig) else None

    @property
    def map_file(self) -> MapFile | None:
        """The map's file section, or None for the generated ring road."""
        return self.map if isinstance(self.map, MapFile) else None

    @property
    def n_connected(self) -> int:
        return self.sumo.connected.count if self.sumo is not None else len(self.connected)

    @model_validator(mode="before")
    @classmethod
    def _sumo_net_from_map(cls, data: Any) -> Any:
        """With SUMO traffic on a SUMO map and no ``traffic.net``: the network is the map's file."""
        if not isinstance(data, dict):
            return data
        m, tr = data.get("map"), data.get("traffic")
        if isinstance(m, dict) and m.get("format") == "sumo" and isinstance(tr, dict) and tr.get("source") == "sumo":
            if tr.get("net") is None and m.get("path") is not None:
                try:
                    f = MapFile.model_validate(m).file
                except ValueError:
                    return data  # the map section's own error says what is wrong
                data = {**data, "traffic": {**tr, "net": str(f)}}
        return data

    @model_validator(mode="after")
    def _indices(self):
        mf = self.map_file
        if self.sumo is not None:
            listed = [k for k in ("connected", "obstacle_vehicles", "pedestrians") if getattr(self, k)]
            if listed:
                raise ValueError(f"with traffic.source: sumo the actors come from SUMO: leave out {', '.join(listed)}")
            if mf is None:
                raise ValueError(
                    "with traffic.source: sumo the map is the SUMO network: map: {format: sumo, path: NET.net.xml}"
                    " (traffic.net names the network only when map: is a Lanelet2 or GeoJSON file of it)"
                )
            if mf.format == "sumo" and self.sumo.net is not None and self.sumo.net.resolve() != mf.file.resolve():
                raise ValueError(
                    f"traffic.net ({self.sumo.net}) is not the map's network ({mf.file}): with a SUMO map leave it out"
                )
            if mf.format != "sumo" and self.sumo.net is None:
                raise ValueError(f"a {mf.format} map with SUMO traffic needs traffic.net: the SUMO network it drives")
            return self
        if mf is not None:
            raise ValueError(
                f"a {mf.format} map needs traffic: {{source: sumo, ...}}: the scenario's own actors (connected,"
                " obstacle_vehicles, pedestrians) drive the generated ring road"
            )
        if not self.connected:
            raise ValueError("connected: a scenario needs at least one connected vehicle")
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
    named by ``sensor_profile`` (default: configs/sensors/default.yaml). ``extends: NAME`` starts from
    the preset NAME's file and merges this one over it (mappings merged, lists replaced).
    """
    path = _scenario_path(name_or_path)
    data = _scenario_data(path, ())
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


def _scenario_path(name_or_path: str | Path) -> Path:
    path = Path(name_or_path)
    return path if path.suffix else find_preset("scenarios", str(name_or_path), "scenario")


def _scenario_data(path: Path, chain: tuple[Path, ...]) -> dict[str, Any]:
    """The scenario file's mapping with its ``extends:`` chain resolved (base first, this file over it)."""
    if path in chain:
        raise ConfigError(f"{path}: scenarios extend each other in a cycle: {' -> '.join(str(p) for p in chain)}")
    data = read_yaml(path)
    _resolve_paths(data, path.parent)
    base = data.pop("extends", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise ConfigError(f"{path}: extends must be the name of a scenario, got {base!r}")
    return deep_merge(_scenario_data(_scenario_path(base), (*chain, path)), data)


_SUMO_PATHS = ("net",)
_SUMO_PATH_LISTS = ("routes", "additional")


def _resolve_paths(data: dict[str, Any], base: Path) -> None:
    """The file names of a SUMO traffic section and of a file map made absolute, relative to the scenario file's
    directory ``base`` (in place; a map ``path`` with ``package:`` is the package's, absolute paths stay)."""

    def resolve(p: Any) -> Any:
        return str(base / p) if isinstance(p, str) and not Path(p).is_absolute() else p

    m = data.get("map")
    if isinstance(m, dict) and "format" in m:
        if "path" in m and m.get("package") is None:
            m["path"] = resolve(m["path"])
        if "pois" in m:
            m["pois"] = resolve(m["pois"])
    tr = data.get("traffic")
    if not isinstance(tr, dict) or tr.get("source") != "sumo":
        return
    for key in _SUMO_PATHS:
        if key in tr:
            tr[key] = resolve(tr[key])
    for key in _SUMO_PATH_LISTS:
        if isinstance(tr.get(key), list):
            tr[key] = [resolve(p) for p in tr[key]]


def load_sensor_config(name: str = "default") -> SensorConfig:
    return load_yaml_model(SensorConfig, find_preset("sensors", name, "sensor profile"))


def scale_scenario(sc: ScenarioConfig, vehicles: int | None) -> ScenarioConfig:
    """The scenario with ``vehicles`` connected vehicles (None: as defined).

    Fewer than defined: the first ones. More: extra vehicles are spread evenly over the ring's
    lanes and around it, at about the defined vehicles' mean speed (0.9x to 1.1x). A SUMO scenario: the
    first N SUMO vehicles to depart (or the first N listed ids).
    """
    if vehicles is None or vehicles == sc.n_connected:
        return sc
    if vehicles < 1:
        raise ValueError(f"vehicles must be at least 1, got {vehicles}")
    if sc.sumo is not None:
        return _scale_sumo(sc, vehicles)
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


def _scale_sumo(sc: ScenarioConfig, vehicles: int) -> ScenarioConfig:
    """A SUMO scenario with ``vehicles`` connected vehicles: the first N to depart; of listed ids the first N
    (ConfigError for more than listed)."""
    sel = sc.sumo.connected
    if sel.ids is not None:
        if vehicles > len(sel.ids):
            raise ConfigError(f"{sc.name} names {len(sel.ids)} connected SUMO vehicles, {vehicles} asked for")
        sel = sel.model_copy(update={"ids": sel.ids[:vehicles]})
    else:
        sel = sel.model_copy(update={"first": vehicles})
    data = sc.model_dump()
    data["traffic"]["connected"] = sel.model_dump()
    return validate_model(ScenarioConfig, data, sc.name)
