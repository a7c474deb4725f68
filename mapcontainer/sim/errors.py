"""The simulator's error sources: their switches, the published (erroneous) HD map and their streams.

Every source is configured in the sensor profile (configs/sensors/default.yaml documents each value,
its physical meaning and where the default comes from) and switched by its ``enabled`` flag:

=================  ==============================================  ===================================
source             what differs from the ideal simulation          configuration
=================  ==============================================  ===================================
map                the vehicles' and host's map vs the world's     sensors.hdmap
calibration        true camera vs the CameraInfo it reports        sensors.camera.calibration_error
detector           persistent detector error, reported sigmas off  sensors.detector.errors
class_confusion    a detection reports another class               sensors.detector.class_confusion
clock_offset       a vehicle's time stamps are off by a constant   sensors.clock
clutter            false landmarks and false objects               sensors.clutter
=================  ==============================================  ===================================

Traffic variation (``ScenarioConfig.traffic``) is not an error source; :func:`with_traffic` switches it.

Streams: every source draws from its own ``SeedSequence([seed, KEY])`` (per vehicle a child of it), never
from the sensors' noise streams, so switching one source leaves the others' draws as they were.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from ..hdmap.model import HDMap
from ..hdmap.perturb import MapError, perturb_map
from .config import ScenarioConfig
from .maps import world_map

__all__ = [
    "ERROR_SOURCES",
    "ERROR_STREAM",
    "MAP_STREAM",
    "enabled_error_sources",
    "published_map",
    "vehicle_error_streams",
    "with_error_sources",
    "with_traffic",
]

ERROR_SOURCES = ("map", "calibration", "detector", "class_confusion", "clock_offset", "clutter")

# Where each source's switch is in a scenario (a path of keys below the scenario).
_SWITCH: dict[str, tuple[str, ...]] = {
    "map": ("sensors", "hdmap"),
    "calibration": ("sensors", "camera", "calibration_error"),
    "detector": ("sensors", "detector", "errors"),
    "class_confusion": ("sensors", "detector", "class_confusion"),
    "clock_offset": ("sensors", "clock"),
    "clutter": ("sensors", "clutter"),
}

MAP_STREAM = 0x4D415045  # "MAPE": spawn key of the map error's stream
ERROR_STREAM = 0x45525253  # "ERRS": spawn key of the per-vehicle error streams (calibration, detector, clock)


def _section(data: dict, path: tuple[str, ...]) -> dict:
    for key in path:
        data = data[key]
    return data


def with_error_sources(sc: ScenarioConfig, on: Iterable[str]) -> ScenarioConfig:
    """``sc`` with exactly the error sources ``on`` switched on (at the scenario's values), all others off.

    ValueError for a name that is not in :data:`ERROR_SOURCES`. ``with_error_sources(sc, ())``: ideal
    sensors in the sense of this module (white noise, misses and GNSS error remain);
    ``with_error_sources(sc, ERROR_SOURCES)``: everything on.
    """
    on = set(on)
    unknown = on - set(ERROR_SOURCES)
    if unknown:
        raise ValueError(f"unknown error source(s) {sorted(unknown)}; known: {', '.join(ERROR_SOURCES)}")
    data = sc.model_dump()
    for name, path in _SWITCH.items():
        _section(data, path)["enabled"] = name in on
    return ScenarioConfig.model_validate(data)


def enabled_error_sources(sc: ScenarioConfig) -> tuple[str, ...]:
    """The error sources switched on in ``sc``, in the order of :data:`ERROR_SOURCES`."""
    data = sc.model_dump()
    return tuple(name for name in ERROR_SOURCES if _section(data, _SWITCH[name])["enabled"])


def with_traffic(sc: ScenarioConfig, enabled: bool) -> ScenarioConfig:
    """``sc`` with per-run traffic variation on or off (off: the actors exactly as the scenario lists them)."""
    return sc.model_copy(update={"traffic": sc.traffic.model_copy(update={"enabled": bool(enabled)})})


def map_error(sc: ScenarioConfig) -> MapError | None:
    """The scenario's map error model, or None when the source is off."""
    m = sc.sensors.hdmap
    if not m.enabled:
        return None
    return MapError(
        field_sigma_m=m.field_sigma_m,
        field_length_m=m.field_length_m,
        line_sigma_m=m.line_sigma_m,
        line_length_m=m.line_length_m,
        landmark_sigma_m=m.landmark_sigma_m,
        p_missing=m.p_missing,
        p_extra=m.p_extra,
    )


def published_map(sc: ScenarioConfig, seed: int, true_map: HDMap | None = None) -> HDMap:
    """The HD map the vehicles and the host of run ``seed`` carry: the world's map (:func:`.maps.world_map`,
    or ``true_map`` if given) with the scenario's map error drawn from ``SeedSequence([seed, MAP_STREAM])``;
    the world's map itself when the source is off. The in-process pipeline and the live services both
    call this, so they use the same map for a scenario and seed.
    """
    truth = world_map(sc) if true_map is None else true_map
    err = map_error(sc)
    if err is None:
        return truth
    return perturb_map(truth, err, np.random.SeedSequence([int(seed), MAP_STREAM]))


def vehicle_error_streams(seed: int, n: int) -> list[np.random.SeedSequence]:
    """One stream per connected vehicle (by index) for its calibration, detector and clock errors."""
    return np.random.SeedSequence([int(seed), ERROR_STREAM]).spawn(n)
