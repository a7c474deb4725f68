"""The vectorized HD map: model, procedural generator, GeoJSON file format and spatial queries."""

from .generator import MapSpec, generate_map
from .model import HDMap, LaneCenterline, LaneLine, PointFeature, PoleFeature, Polyline, WalkableArea

__all__ = [
    "HDMap",
    "LaneCenterline",
    "LaneLine",
    "MapSpec",
    "PointFeature",
    "PoleFeature",
    "Polyline",
    "WalkableArea",
    "generate_map",
]
