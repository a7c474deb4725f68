"""A deterministic (seeded) world: actors on an HD map and each connected vehicle's sensors."""

from .config import ScenarioConfig, SensorConfig, list_scenarios, load_scenario
from .errors import ERROR_SOURCES, enabled_error_sources, published_map, with_error_sources, with_traffic
from .world import FrameDebug, Tick, World

__all__ = [
    "ERROR_SOURCES",
    "FrameDebug",
    "ScenarioConfig",
    "SensorConfig",
    "Tick",
    "World",
    "enabled_error_sources",
    "list_scenarios",
    "load_scenario",
    "published_map",
    "with_error_sources",
    "with_traffic",
]
