"""A deterministic (seeded) world: actors on an HD map and each connected vehicle's sensors."""

from .config import ScenarioConfig, SensorConfig, list_scenarios, load_scenario
from .world import FrameDebug, Tick, World

__all__ = ["FrameDebug", "ScenarioConfig", "SensorConfig", "Tick", "World", "list_scenarios", "load_scenario"]
