"""The HD map file format: a GeoJSON FeatureCollection in **local map coordinates**.

Coordinates are the map frame — local ENU, metres, z up — **not WGS84 longitude/latitude**, so
GIS tools must not reproject them. The collection's top-level ``"properties"`` member says so and
may carry the geodetic origin of the map frame::

    {
      "type": "FeatureCollection",
      "name": "<map name>",
      "properties": {
        "format": "mapcontainer-hdmap", "version": 1,
        "crs": "local-enu-m",            # x east, y north, z up, metres from "origin"
        "crs_note": "coordinates are local ENU metres ... not WGS84",   # for humans
        "origin": {"lat_deg": ..., "lon_deg": ..., "alt_m": ...} | null
      },
      "features": [ ... one Feature per map element ... ]
    }

Features (``properties.kind`` says which element; ``id`` is an int unique in the map):

========== ====================================== ===========================================================
kind       geometry                               other properties
========== ====================================== ===========================================================
point      Point [x, y, z]                        ``cls``: "traffic_light" | "sign"
pole       LineString [base, top], 3-D            ``cls``: "lamp"
lane_line  LineString, 3-D, >= 2 positions        ``line_kind``: "solid" | "dashed", ``closed``, ``dash_m``,
                                                  ``gap_m``, ``width_m``
centerline LineString, 3-D, >= 2 positions        ``closed``, ``width_m`` (driving direction = point order)
walkable   Polygon [[ [x, y], ... ]] (one ring,   ``area_kind``: "sidewalk" | "crossing", ``closed``,
           2-D, first position repeated last)     ``path``: walking centre line [[x, y, z], ...] (>= 2)
junction   Polygon, as walkable                   ``z``: the junction's height (m)
========== ====================================== ===========================================================

The ``junction`` kind came after the first maps were written: a map without junction areas is the same
file as before, and a reader that does not know the kind refuses a file that has one, naming it.

Polyline vertices are stored exactly as the model holds them; ``closed: true`` means the last
vertex connects back to the first (no repeated vertex needed). A polygon ring repeats its first
position at the end, as GeoJSON requires, and the loader drops that repetition. Lengths
(``dash_m``, ``gap_m``, ``width_m``) are positive metres. Floats are written with ``repr`` precision,
so ``load_map(save_map(m))`` reproduces every coordinate exactly; the file has one feature per line so
that map diffs stay readable. Feature order is: points, poles, lane lines, centre lines, walkable areas.
:func:`load_map` validates everything and raises ``ValueError`` naming the offending feature (index,
kind and id) for a malformed file; properties it does not know are ignored (room for additions).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .model import (
    POINT_CLASSES,
    POLE_CLASSES,
    HDMap,
    JunctionArea,
    LaneCenterline,
    LaneLine,
    PointFeature,
    PoleFeature,
    WalkableArea,
)

__all__ = [
    "FORMAT", "VERSION", "MapOrigin", "load_map", "load_origin",
    "map_from_geojson", "map_to_geojson", "save_map",
]

FORMAT = "mapcontainer-hdmap"
VERSION = 1
CRS = "local-enu-m"
CRS_NOTE = "coordinates are local ENU metres (x east, y north, z up) from origin, not WGS84"

LINE_KINDS = ("solid", "dashed")
AREA_KINDS = ("sidewalk", "crossing")


@dataclass(frozen=True)
class MapOrigin:
    """Geodetic position of the map frame's origin (WGS84 degrees, metres above the ellipsoid)."""

    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0


# ---------------------------------------------------------------------------------- writing


def _coords(a: np.ndarray) -> list:
    return np.asarray(a, dtype=float).tolist()


def _feature(geometry: dict[str, Any], properties: dict[str, Any]) -> dict[str, Any]:
    return {"type": "Feature", "geometry": geometry, "properties": properties}


def map_to_geojson(hdmap: HDMap, origin: MapOrigin | None = None) -> dict[str, Any]:
    """The GeoJSON FeatureCollection (a dict) of ``hdmap``; see the module docstring."""
    feats: list[dict[str, Any]] = []
    for f in hdmap.points:
        geom = {"type": "Point", "coordinates": _coords(f.p_map)}
        feats.append(_feature(geom, {"kind": "point", "id": f.id, "cls": f.cls}))
    for f in hdmap.poles:
        feats.append(
            _feature(
                {"type": "LineString", "coordinates": _coords(np.stack([f.base, f.top]))},
                {"kind": "pole", "id": f.id, "cls": f.cls},
            )
        )
    for f in hdmap.lane_lines:
        feats.append(
            _feature(
                {"type": "LineString", "coordinates": _coords(f.points)},
                {
                    "kind": "lane_line", "id": f.id, "line_kind": f.kind, "closed": bool(f.closed),
                    "dash_m": float(f.dash_m), "gap_m": float(f.gap_m), "width_m": float(f.width_m),
                },
            )
        )
    for f in hdmap.centerlines:
        feats.append(
            _feature(
                {"type": "LineString", "coordinates": _coords(f.points)},
                {"kind": "centerline", "id": f.id, "closed": bool(f.closed), "width_m": float(f.width_m)},
            )
        )
    for f in hdmap.walkable:
        ring = np.vstack([f.polygon, f.polygon[:1]])
        feats.append(
            _feature(
                {"type": "Polygon", "coordinates": [_coords(ring)]},
                {
                    "kind": "walkable", "id": f.id, "area_kind": f.kind, "closed": bool(f.closed),
                    "path": _coords(f.path),
                },
            )
        )
    for f in hdmap.junctions:
        ring = np.vstack([f.polygon, f.polygon[:1]])
        feats.append(
            _feature({"type": "Polygon", "coordinates": [_coords(ring)]}, {"kind": "junction", "id": f.id, "z": f.z})
        )
    props: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "crs": CRS,
        "crs_note": CRS_NOTE,
        "origin": None if origin is None else asdict(origin),
    }
    return {"type": "FeatureCollection", "name": hdmap.name, "properties": props, "features": feats}


def save_map(hdmap: HDMap, path: Path | str, origin: MapOrigin | None = None) -> Path:
    """Write ``hdmap`` as a GeoJSON file (see the module docstring); returns the path.

    Raises ValueError for non-finite coordinates (JSON has no NaN).
    """
    path = Path(path)
    doc = map_to_geojson(hdmap, origin)
    features = doc.pop("features")
    head = json.dumps(doc, allow_nan=False, separators=(",", ":"))[:-1]  # without the closing brace
    # One feature per line keeps diffs of map files readable.
    body = ",\n".join(json.dumps(f, allow_nan=False, separators=(",", ":")) for f in features)
    path.write_text(f'{head},"features":[\n{body}\n]}}\n', encoding="utf-8")
    return path


# ---------------------------------------------------------------------------------- reading


class _Bad(ValueError):
    """A problem inside one feature; re-raised with the feature's index, kind and id."""


def _get(d: dict[str, Any], key: str, types: type | tuple[type, ...], what: str) -> Any:
    if key not in d:
        raise _Bad(f"missing {what} {key!r}")
    value = d[key]
    if isinstance(value, bool) and bool not in (types if isinstance(types, tuple) else (types,)):
        raise _Bad(f"{what} {key!r} must not be a boolean, got {value!r}")
    if not isinstance(value, types):
        raise _Bad(f"{what} {key!r} has type {type(value).__name__}, got {value!r}"[:200])
    return value


def _number(props: dict[str, Any], key: str, positive: bool = True) -> float:
    value = float(_get(props, key, (int, float), "property"))
    if not math.isfinite(value) or (positive and value <= 0):
        want = "a finite positive" if positive else "a finite"
        raise _Bad(f"property {key!r} must be {want} number, got {value!r}")
    return value


def _choice(props: dict[str, Any], key: str, allowed: tuple[str, ...]) -> str:
    value = _get(props, key, str, "property")
    if value not in allowed:
        raise _Bad(f"property {key!r} is {value!r}, expected one of {list(allowed)}")
    return value


def _array(value: Any, dim: int, what: str, min_rows: int = 1) -> np.ndarray:
    """A finite float array (N, dim) with N >= min_rows from nested JSON lists."""
    def is_number(x: Any) -> bool:
        return isinstance(x, int | float) and not isinstance(x, bool)

    if not isinstance(value, list) or not all(
        isinstance(row, list) and len(row) == dim and all(is_number(x) for x in row) for row in value
    ):
        raise _Bad(f"{what} must be a list of [{', '.join('xyz'[:dim])}] number lists")
    arr = np.array(value, dtype=float).reshape(-1, dim)
    if len(arr) < min_rows:
        raise _Bad(f"{what} needs at least {min_rows} positions, got {len(arr)}")
    if not np.all(np.isfinite(arr)):
        raise _Bad(f"{what} holds non-finite values")
    return arr


def _geometry(feat: dict[str, Any], gtype: str) -> Any:
    geom = _get(feat, "geometry", dict, "member")
    if geom.get("type") != gtype:
        raise _Bad(f"geometry must be a {gtype}, got {geom.get('type')!r}")
    return _get(geom, "coordinates", list, "geometry member")


def _parse_feature(feat: Any) -> tuple[str, Any]:
    """(kind, map element) of one GeoJSON Feature, or _Bad."""
    if not isinstance(feat, dict) or feat.get("type") != "Feature":
        raise _Bad("not a GeoJSON Feature object")
    props = _get(feat, "properties", dict, "member")
    kind = _choice(props, "kind", ("point", "pole", "lane_line", "centerline", "walkable", "junction"))
    fid = _get(props, "id", int, "property")
    if kind == "point":
        p = _array([_geometry(feat, "Point")], 3, "Point coordinates")[0]
        return kind, PointFeature(fid, _choice(props, "cls", POINT_CLASSES), p)
    if kind == "pole":
        ends = _array(_geometry(feat, "LineString"), 3, "pole LineString", min_rows=2)
        if len(ends) != 2:
            raise _Bad(f"pole LineString must have exactly 2 positions (base, top), got {len(ends)}")
        return kind, PoleFeature(fid, _choice(props, "cls", POLE_CLASSES), ends[0], ends[1])
    if kind == "lane_line":
        pts = _array(_geometry(feat, "LineString"), 3, "lane_line LineString", min_rows=2)
        return kind, LaneLine(
            fid, pts, _choice(props, "line_kind", LINE_KINDS), closed=_get(props, "closed", bool, "property"),
            dash_m=_number(props, "dash_m"), gap_m=_number(props, "gap_m"), width_m=_number(props, "width_m"),
        )
    if kind == "centerline":
        pts = _array(_geometry(feat, "LineString"), 3, "centerline LineString", min_rows=2)
        return kind, LaneCenterline(
            fid, pts, closed=_get(props, "closed", bool, "property"), width_m=_number(props, "width_m")
        )
    rings = _geometry(feat, "Polygon")
    if len(rings) != 1:
        raise _Bad(f"{kind} Polygon must have exactly one ring (no holes), got {len(rings)}")
    ring = _array(rings[0], 2, f"{kind} Polygon ring", min_rows=4)
    if not np.array_equal(ring[0], ring[-1]):
        raise _Bad(f"{kind} Polygon ring must end with its first position")
    if kind == "junction":
        return kind, JunctionArea(fid, ring[:-1], _number(props, "z", positive=False))
    path = _array(_get(props, "path", list, "property"), 3, "walkable path", min_rows=2)
    area_kind = _choice(props, "area_kind", AREA_KINDS)
    return kind, WalkableArea(fid, area_kind, ring[:-1], path, closed=_get(props, "closed", bool, "property"))


def _check_header(doc: Any) -> dict[str, Any]:
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection":
        raise ValueError("not a GeoJSON FeatureCollection")
    props = doc.get("properties")
    if not isinstance(props, dict) or props.get("format") != FORMAT:
        raise ValueError(f"properties.format must be {FORMAT!r} (a Map Container HD map)")
    version = props.get("version")
    if type(version) is not int or version != VERSION:
        raise ValueError(f"unsupported map format version {version!r}; this reader knows {VERSION}")
    if props.get("crs") != CRS:
        raise ValueError(f"properties.crs must be {CRS!r} (local ENU metres), got {props.get('crs')!r}")
    if not isinstance(doc.get("name"), str):
        raise ValueError("the collection needs a string 'name'")
    if not isinstance(doc.get("features"), list):
        raise ValueError("the collection needs a 'features' list")
    return props


def map_from_geojson(doc: Any) -> HDMap:
    """Parse and validate a GeoJSON FeatureCollection (a dict); ValueError names the bad feature."""
    _check_header(doc)
    hd = HDMap(name=doc["name"])
    lists = {"point": hd.points, "pole": hd.poles, "lane_line": hd.lane_lines, "centerline": hd.centerlines,
             "walkable": hd.walkable, "junction": hd.junctions}
    seen: dict[int, int] = {}
    for i, feat in enumerate(doc["features"]):
        props = feat.get("properties") if isinstance(feat, dict) else None
        label = f"feature {i}"
        if isinstance(props, dict):
            label += f" (kind={props.get('kind')!r}, id={props.get('id')!r})"
        try:
            kind, element = _parse_feature(feat)
        except _Bad as exc:
            raise ValueError(f"{label}: {exc}") from None
        if element.id in seen:
            raise ValueError(f"{label}: id {element.id} is already used by feature {seen[element.id]}")
        seen[element.id] = i
        lists[kind].append(element)
    return hd


def load_map(path: Path | str) -> HDMap:
    """Read and validate a map written by :func:`save_map`; ValueError for a malformed file."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    try:
        return map_from_geojson(doc)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def load_origin(path: Path | str) -> MapOrigin | None:
    """The geodetic origin stored in a map file, or None if the file has none."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    try:
        origin = _check_header(doc).get("origin")
        if origin is None:
            return None
        if not isinstance(origin, dict):
            raise _Bad(f"origin must be an object or null, got {origin!r}")
        lat = _number(origin, "lat_deg", positive=False)
        lon = _number(origin, "lon_deg", positive=False)
        alt = _number(origin, "alt_m", positive=False) if "alt_m" in origin else 0.0
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise ValueError(f"{path}: origin lat/lon out of range: {lat}, {lon}")
    return MapOrigin(lat, lon, alt)
