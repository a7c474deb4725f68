"""The vectorized HD map: model, procedural generator, GeoJSON file format and spatial queries."""

from .generator import MapSpec, generate_map
from .io import MapOrigin, load_map, save_map
from .model import HDMap, JunctionArea, LaneCenterline, LaneLine, PointFeature, PoleFeature, Polyline, WalkableArea
from .query import MapIndex

__all__ = [
    "HDMap",
    "JunctionArea",
    "LaneCenterline",
    "LaneLine",
    "MapIndex",
    "MapOrigin",
    "MapSpec",
    "PointFeature",
    "PoleFeature",
    "Polyline",
    "WalkableArea",
    "generate_map",
    "load_map",
    "save_map",
]
