"""The vectorized HD map: model, procedural generator, GeoJSON file format, spatial queries, and map import
(SUMO, Lanelet2: ``read_any_map``; their readers come from the optional ``roads`` extra, imported on use)."""

from .errors import MapFileError, MissingExtraError
from .formats import read_any_map
from .generator import MapSpec, generate_map
from .imported import ImportedMap
from .io import MapOrigin, load_map, save_map
from .model import HDMap, JunctionArea, LaneCenterline, LaneLine, PointFeature, PoleFeature, Polyline, WalkableArea
from .query import MapIndex

__all__ = [
    "HDMap",
    "ImportedMap",
    "JunctionArea",
    "LaneCenterline",
    "LaneLine",
    "MapFileError",
    "MapIndex",
    "MapOrigin",
    "MapSpec",
    "MissingExtraError",
    "PointFeature",
    "PoleFeature",
    "Polyline",
    "WalkableArea",
    "generate_map",
    "load_map",
    "read_any_map",
    "save_map",
]
