"""The world's map of a scenario: the generated ring road, or the map file of ``map: {format, path}``."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from ..hdmap.generator import generate_map
from ..hdmap.model import HDMap
from .config import MapFile, ScenarioConfig

__all__ = ["crop_map", "map_bounds", "world_map"]


def world_map(sc: ScenarioConfig) -> HDMap:
    """The true map of scenario ``sc`` (what the cameras see): ``generate_map(sc.map)``, or the import of the map
    file (a SUMO network with landmarks by ``map.landmarks`` or from the POIs of ``map.pois``; a Lanelet2 map; our
    GeoJSON), cropped to ``map.bounds`` when given. With SUMO traffic the map is the network the vehicles drive on.
    Same scenario: the same map."""
    mf = sc.map_file
    if mf is None:
        return generate_map(sc.map)
    files = [mf.file] + ([mf.pois] if mf.pois is not None else [])
    mtimes = tuple(Path(p).stat().st_mtime_ns for p in files)
    return _imported(mf.model_dump_json(), str(mf.file), mtimes)


@functools.lru_cache(maxsize=8)
def _imported(spec_json: str, file: str, mtimes: tuple[int, ...]) -> HDMap:
    """The imported map (cached per process: a World, the evaluator and the map export share it)."""
    from ..hdmap.formats import read_any_map
    from ..hdmap.io import MapOrigin

    mf = MapFile.model_validate_json(spec_json)
    origin = None if mf.origin is None else MapOrigin(*mf.origin)
    hd = read_any_map(file, mf.format, rule=mf.landmarks, additional=mf.pois, origin=origin).hdmap
    return hd if mf.bounds is None else crop_map(hd, mf.bounds)


def _inside(xy, bounds) -> bool:
    xy = np.asarray(xy, dtype=float).reshape(-1, np.shape(xy)[-1])[:, :2]
    x0, y0, x1, y1 = bounds
    return bool(np.any((xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)))


def crop_map(hd: HDMap, bounds: tuple[float, float, float, float]) -> HDMap:
    """The elements of ``hd`` with at least one vertex in ``bounds`` = (xmin, ymin, xmax, ymax), whole (lines are
    not cut: a lane line that leaves the box goes on to its end); ids as they were."""
    return HDMap(
        name=hd.name,
        points=[f for f in hd.points if _inside(f.p_map, bounds)],
        poles=[f for f in hd.poles if _inside(f.base, bounds)],
        lane_lines=[ln for ln in hd.lane_lines if _inside(ln.points, bounds)],
        centerlines=[c for c in hd.centerlines if _inside(c.points, bounds)],
        walkable=[w for w in hd.walkable if _inside(w.polygon, bounds)],
        junctions=[j for j in hd.junctions if _inside(j.polygon, bounds)],
    )


def map_bounds(hd: HDMap) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) of the map's lane centre lines and walkable areas (m)."""
    pts = [c.points[:, :2] for c in hd.centerlines] + [w.polygon[:, :2] for w in hd.walkable]
    if not pts:
        raise ValueError(f"map {hd.name!r} has no centre line or walkable area")
    xy = np.concatenate(pts)
    return (float(xy[:, 0].min()), float(xy[:, 1].min()), float(xy[:, 0].max()), float(xy[:, 1].max()))
