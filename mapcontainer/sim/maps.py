"""The world's map of a scenario: the procedural ring road, or the SUMO network the traffic drives on."""

from __future__ import annotations

import functools
from pathlib import Path

from ..hdmap.generator import generate_map
from ..hdmap.model import HDMap
from ..hdmap.sumo import PlacementRule
from .config import ScenarioConfig

__all__ = ["world_map"]


def world_map(sc: ScenarioConfig) -> HDMap:
    """The true map of scenario ``sc`` (what the cameras see): ``generate_map(sc.map)``, or with SUMO traffic
    the import of ``traffic.net`` (landmarks by ``traffic.landmarks``, or from the POIs of ``traffic.pois``),
    so the vehicles localize against the network they drive on. Same scenario: the same map."""
    sumo = sc.sumo
    if sumo is None:
        return generate_map(sc.map)
    pois = None if sumo.pois is None else str(sumo.pois)
    mtimes = tuple(Path(p).stat().st_mtime_ns for p in (sumo.net, pois) if p is not None)
    return _imported(str(sumo.net), pois, sumo.landmarks.model_dump_json(), mtimes)


@functools.lru_cache(maxsize=8)
def _imported(net: str, pois: str | None, rule_json: str, mtimes: tuple[int, ...]) -> HDMap:
    """The imported network (cached per process: a World, the evaluator and the map export share it)."""
    from ..hdmap.sumo import import_sumo

    return import_sumo(Path(net), PlacementRule.model_validate_json(rule_json), pois).hdmap
