"""Lanelet2 OSM maps: import into an :class:`HDMap` and export from one, through the ``lanelet2`` package.

A Lanelet2 file holds WGS84 positions; a projector with an origin makes them metric. ``local`` is
lanelet2's ``LocalCartesianProjector`` (east-north-up at the origin: our map frame exactly), ``utm`` its
``UtmProjector`` (UTM metres minus the origin's, as Autoware uses). Without an origin the import takes
the file's first node as the origin.

Import (what maps to what; details in ``mapcontainer/hdmap/README.md``):

=============================================== ===========================================================
Lanelet2                                        HD map
=============================================== ===========================================================
line string ``line_thin``/``line_thick``        lane line, ``subtype`` solid / dashed; ``solid_solid``,
                                                ``solid_dashed``, ``dashed_solid``, ``dashed_dashed``: two lines
                                                :data:`DOUBLE_LINE_GAP_M` apart (the first named on the left)
line string ``curbstone``, ``road_border``,     a solid lane line (the road's visible edge, a painted bar)
``stop_line``
line string ``traffic_light`` (or referred to   a traffic light at the line's midpoint raised by half its
by a traffic-light regulatory element)          ``height`` tag (the line is the housing's bottom edge)
line string ``traffic_sign`` (or referred to    a sign, the same way
by a traffic-sign regulatory element)
line string or point ``pole``/``street_lamp``   a lamp: a vertical line's lowest and highest points; a point
                                                or a flat line's first point plus its ``height`` (8 m default)
lanelet ``crosswalk`` / ``walkway``             a crossing / sidewalk: the polygon of its bounds, path its centre line
other lanelets                                  a lane centre line (lanelet2's centerline), width the mean bound gap
area ``crosswalk`` / ``walkway``                a crossing / sidewalk: its outer polygon, path its principal axis
area ``intersection``                           a junction area
=============================================== ===========================================================

Export writes what the import reads back: lane lines as ``line_thin`` solid/dashed line strings (a closed
line repeats its first node), each centre line as a ``road`` lanelet whose bounds are lane lines that run
at half the lane width beside it along its whole length, or ``virtual`` lines at that offset where none
does, a closed centre line as two lanelets end to end (lanelet2 finds no centre line between closed
bounds; they come back as two open centre lines), traffic lights and signs as 0.3 m
line strings (tag ``height``) referred to by regulatory elements attached to the nearest lanelet, lamps
as vertical ``pole`` line strings, walkable areas and junctions as areas (except self-intersecting outlines, which
lanelet2 refuses to load: they are counted in ``areas_not_written``).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np

from .errors import MapFileError, require
from .geometry2d import distance_to_polyline, is_simple_polygon, offset_polyline, principal_axis
from .imported import ImportedMap
from .io import MapOrigin
from .model import HDMap, JunctionArea, LaneCenterline, LaneLine, PointFeature, PoleFeature, Polyline, WalkableArea

__all__ = ["DEFAULT_ORIGIN", "PROJECTORS", "export_lanelet2", "import_lanelet2", "sniff_osm"]

PROJECTORS = ("local", "utm")
DEFAULT_ORIGIN = MapOrigin(49.0, 8.4, 0.0)  # Karlsruhe, lanelet2's own examples: for maps that carry none
DOUBLE_LINE_GAP_M = 0.24
LAMP_HEIGHT_M = 8.0
HOUSING_WIDTH_M = 0.3  # exported traffic lights and signs: the housing's bottom edge
HOUSING_HEIGHT_M = 0.7
_BOUND_TOL_M = 0.3  # a lane line is a lanelet's bound when it stays this close to half a lane width off
_LINE_KINDS = {"solid": ["solid"], "dashed": ["dashed"], "solid_solid": ["solid", "solid"],
               "solid_dashed": ["solid", "dashed"], "dashed_solid": ["dashed", "solid"],
               "dashed_dashed": ["dashed", "dashed"]}  # fmt: skip
_EDGE_TYPES = ("curbstone", "road_border", "stop_line")
_POLE_TYPES = ("pole", "street_lamp", "lamp")


def sniff_osm(path: Path) -> None:
    """MapFileError unless ``path`` is a non-empty XML file whose root element is ``osm``."""
    if not path.exists():
        raise MapFileError(f"{path}: no such file")
    if not path.is_file():
        raise MapFileError(f"{path}: not a file")
    if path.stat().st_size == 0:
        raise MapFileError(f"{path}: the file is empty")
    try:
        with path.open("rb") as fh:
            _, root = next(ET.iterparse(fh, events=("start",)))
    except ET.ParseError as exc:
        raise MapFileError(f"{path}: not XML ({exc})") from None
    except StopIteration:
        raise MapFileError(f"{path}: no XML element in the file") from None
    if root.tag != "osm":
        raise MapFileError(f"{path}: not an OSM (Lanelet2) map (root element <{root.tag}>, expected <osm>)")


def _first_node_origin(path: Path) -> MapOrigin:
    for _, el in ET.iterparse(path, events=("start",)):
        if el.tag == "node" and "lat" in el.attrib and "lon" in el.attrib:
            return MapOrigin(float(el.attrib["lat"]), float(el.attrib["lon"]), 0.0)
    raise MapFileError(f"{path}: the OSM file has no node with lat and lon")


def _projector(origin: MapOrigin, projector: str):
    require("lanelet2", "Reading or writing a Lanelet2 map")
    from lanelet2.io import Origin
    from lanelet2.projection import LocalCartesianProjector, UtmProjector

    if projector not in PROJECTORS:
        raise ValueError(f"projector must be one of {PROJECTORS}, got {projector!r}")
    o = Origin(origin.lat_deg, origin.lon_deg, origin.alt_m)
    return LocalCartesianProjector(o) if projector == "local" else UtmProjector(o)


def _xyz(points) -> np.ndarray:
    return np.array([[p.x, p.y, p.z] for p in points], dtype=float).reshape(-1, 3)


def _attr(prim, key: str, default: str = "") -> str:
    attrs = prim.attributes
    return str(attrs[key]) if key in attrs else default


def _height(prim, default: float) -> float:
    try:
        return float(_attr(prim, "height", str(default)))
    except ValueError:
        return default


def _line_points(ls) -> tuple[np.ndarray, bool]:
    """A line string's points and whether it is closed (its last node is its first)."""
    ids = [p.id for p in ls]
    pts = _xyz(ls)
    if len(ids) > 2 and ids[0] == ids[-1]:
        return pts[:-1], True
    return pts, False


def import_lanelet2(path: Path | str, origin: MapOrigin | None = None, projector: str = "local") -> ImportedMap:
    """Read a Lanelet2 OSM map into an HD map (module docstring); MapFileError for a file it cannot read."""
    path = Path(path)
    sniff_osm(path)
    lanelet2 = require("lanelet2", "Reading a Lanelet2 map")
    from lanelet2.core import TrafficLight, TrafficSign

    notes: list[str] = []
    if origin is None:
        origin = _first_node_origin(path)
        notes.append(f"no origin given: the first node's ({origin.lat_deg:.7f}, {origin.lon_deg:.7f})")
    try:
        llmap, errors = lanelet2.io.loadRobust(str(path), _projector(origin, projector))
    except RuntimeError as exc:  # lanelet2's loader reports a file it cannot parse this way
        raise MapFileError(f"{path}: lanelet2 cannot load it ({exc})") from None
    problems = [e.strip(" \t-") for e in errors if not e.startswith("Errors oc")]  # without the header line
    if problems:
        notes.append(f"lanelet2 reported {len(problems)} problems, the first: {problems[0]}")
    if not (len(llmap.laneletLayer) or len(llmap.lineStringLayer) or len(llmap.pointLayer)):
        raise MapFileError(f"{path}: the Lanelet2 map is empty (no lanelets, line strings or points)")

    hd = HDMap(name=path.name.removesuffix(".osm"))
    ids = iter(range(1, 10**9))
    lights: set[int] = set()
    signs: set[int] = set()
    for reg in llmap.regulatoryElementLayer:
        if isinstance(reg, TrafficLight):
            lights |= {x.id for x in reg.trafficLights}
        elif isinstance(reg, TrafficSign):
            signs |= {x.id for x in reg.trafficSigns()}
    up = np.array([0.0, 0.0, 1.0])
    for ls in sorted(llmap.lineStringLayer, key=lambda x: x.id):
        kind, sub = _attr(ls, "type"), _attr(ls, "subtype")
        pts, closed = _line_points(ls)
        if len(pts) < 1:
            continue
        if kind == "traffic_light" or ls.id in lights:
            mid = pts.mean(axis=0) + up * _height(ls, 0.0) / 2
            hd.points.append(PointFeature(next(ids), "traffic_light", mid))
        elif kind == "traffic_sign" or ls.id in signs:
            mid = pts.mean(axis=0) + up * _height(ls, 0.0) / 2
            hd.points.append(PointFeature(next(ids), "sign", mid))
        elif kind in _POLE_TYPES:
            lo, hi = pts[np.argmin(pts[:, 2])], pts[np.argmax(pts[:, 2])]
            if hi[2] - lo[2] < 0.5:
                lo, hi = pts[0], pts[0] + up * _height(ls, LAMP_HEIGHT_M)
            hd.poles.append(PoleFeature(next(ids), "lamp", lo, hi))
        elif len(pts) >= 2 and kind in ("line_thin", "line_thick"):
            kinds = _LINE_KINDS.get(sub or "solid")
            if kinds is None:
                notes.append(f"line string {ls.id}: unknown {kind} subtype {sub!r}, read as solid")
                kinds = ["solid"]
            width = 0.3 if kind == "line_thick" else 0.15
            if len(kinds) == 1:
                hd.lane_lines.append(LaneLine(next(ids), pts, kinds[0], closed=closed, width_m=width))
            else:
                for side, k in zip((0.5, -0.5), kinds, strict=True):
                    line = offset_polyline(pts, side * DOUBLE_LINE_GAP_M)
                    hd.lane_lines.append(LaneLine(next(ids), line, k, closed=closed, width_m=width))
        elif len(pts) >= 2 and kind in _EDGE_TYPES:
            hd.lane_lines.append(LaneLine(next(ids), pts, "solid", closed=closed, width_m=0.3))
    for p in sorted(llmap.pointLayer, key=lambda x: x.id):
        kind = _attr(p, "type")
        xyz = np.array([p.x, p.y, p.z], dtype=float)
        if kind in _POLE_TYPES:
            hd.poles.append(PoleFeature(next(ids), "lamp", xyz, xyz + up * _height(p, LAMP_HEIGHT_M)))
        elif kind == "traffic_light":
            hd.points.append(PointFeature(next(ids), "traffic_light", xyz))
        elif kind == "traffic_sign":
            hd.points.append(PointFeature(next(ids), "sign", xyz))
    for ll in sorted(llmap.laneletLayer, key=lambda x: x.id):
        left, right = _xyz(ll.leftBound), _xyz(ll.rightBound)
        centre = _xyz(ll.centerline)
        if len(centre) < 2:
            continue
        sub = _attr(ll, "subtype", "road")
        if sub in ("crosswalk", "walkway"):
            poly = np.vstack([left[:, :2], right[::-1, :2]])
            hd.walkable.append(WalkableArea(next(ids), "crossing" if sub == "crosswalk" else "sidewalk", poly, centre))
            continue
        width = float(np.mean([np.min(np.linalg.norm(right[:, :2] - q[:2], axis=1)) for q in left]))
        hd.centerlines.append(LaneCenterline(next(ids), centre, width_m=max(width, 0.5)))
    for area in sorted(llmap.areaLayer, key=lambda x: x.id):
        sub = _attr(area, "subtype")
        ring = _xyz(area.outerBoundPolygon())
        if len(ring) > 1 and np.allclose(ring[0], ring[-1]):
            ring = ring[:-1]
        if len(ring) < 3:
            continue
        if sub in ("crosswalk", "walkway"):
            path_ = principal_axis(ring, z=float(ring[:, 2].mean()))
            hd.walkable.append(
                WalkableArea(next(ids), "crossing" if sub == "crosswalk" else "sidewalk", ring[:, :2], path_)
            )
        elif sub == "intersection":
            hd.junctions.append(JunctionArea(next(ids), ring[:, :2], float(ring[:, 2].mean())))
    if not (hd.lane_lines or hd.centerlines or hd.points or hd.poles or hd.walkable or hd.junctions):
        why = f" (lanelet2: {problems[0]})" if problems else ""
        raise MapFileError(f"{path}: nothing in the map is a lane line, lanelet, landmark or area{why}")
    return ImportedMap(hd, origin, f"lanelet2:{path} ({projector} projector)", notes)


# ---------------------------------------------------------------------------------- export


def _signed_offsets(line: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Signed distance (left positive) of the centre line's vertices' nearest points on ``line``, and NaN
    where the nearest point is an end of the line ahead or behind the vertex (the line does not reach beside it)."""
    a, b = line[:-1, :2], line[1:, :2]
    d = b - a
    out = np.empty(len(centre))
    tangents = np.gradient(centre[:, :2], axis=0)
    for i, q in enumerate(centre[:, :2]):
        t = np.clip(np.einsum("ij,ij->i", q - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0, 1)
        foot = a + t[:, None] * d
        k = int(np.argmin(np.linalg.norm(foot - q, axis=1)))
        v = foot[k] - q
        tan = tangents[i] / max(np.linalg.norm(tangents[i]), 1e-12)
        out[i] = tan[0] * v[1] - tan[1] * v[0]  # the z of tan x v: positive when the line is on the left
        at_end = (k == 0 and t[0] == 0) or (k == len(a) - 1 and t[-1] == 1)
        if at_end and abs(np.dot(tan, v)) > _BOUND_TOL_M:
            out[i] = np.nan
    return out


def export_lanelet2(
    hdmap: HDMap, path: Path | str, origin: MapOrigin | None = None, projector: str = "local"
) -> dict[str, Any]:
    """Write ``hdmap`` as a Lanelet2 OSM file (module docstring); returns counts of what it wrote."""
    lanelet2 = require("lanelet2", "Writing a Lanelet2 map")
    from lanelet2.core import (
        Area,
        AttributeMap,
        Lanelet,
        LaneletMap,
        LineString3d,
        Point3d,
        TrafficLight,
        TrafficSign,
        TrafficSignsWithType,
        getId,
    )

    path = Path(path)
    origin = origin or DEFAULT_ORIGIN
    m = LaneletMap()

    def points(xyz) -> list:
        return [Point3d(getId(), float(p[0]), float(p[1]), float(p[2])) for p in np.asarray(xyz, dtype=float)]

    def linestring(xyz, closed: bool = False, **attrs) -> Any:
        pts = points(xyz)
        if closed:
            pts.append(pts[0])
        return LineString3d(getId(), pts, AttributeMap(attrs))

    lines = []
    for ln in hdmap.lane_lines:
        ls = linestring(ln.points, ln.closed, type="line_thin", subtype=ln.kind)
        m.add(ls)
        lines.append((ln, ls))
    lanelets = []
    painted_bounds = 0
    pieces = []
    for c in hdmap.centerlines:
        if c.closed:  # lanelet2 finds no centre line between closed bounds: two lanelets, end to end
            ring = np.vstack([c.points, c.points[:1]])
            half = len(c.points) // 2
            pieces += [(ring[: half + 1], c.width_m, False), (ring[half:], c.width_m, False)]
        else:
            pieces.append((c.points, c.width_m, True))
    for centre, width, whole in pieces:
        bounds = []
        for side in (+1, -1):
            bound = None
            if whole:
                mid = centre[len(centre) // 2, :2]
                for ln, ls in lines:
                    if ln.closed or distance_to_polyline(mid, ln.points) > width + 2 * _BOUND_TOL_M:
                        continue  # a quick test before the vertex-by-vertex one
                    off = _signed_offsets(ln.points, centre)
                    if np.all(np.isfinite(off)) and np.all(np.abs(off - side * width / 2) < _BOUND_TOL_M):
                        along = np.dot(ln.points[-1, :2] - ln.points[0, :2], centre[-1, :2] - centre[0, :2])
                        bound = ls if along > 0 else ls.invert()
                        painted_bounds += 1
                        break
            if bound is None:
                bound = linestring(offset_polyline(centre, side * width / 2), type="virtual")
            bounds.append(bound)
        ll = Lanelet(getId(), bounds[0], bounds[1], AttributeMap({"type": "lanelet", "subtype": "road"}))
        lanelets.append((centre, ll))
    up = np.array([0.0, 0.0, 1.0])

    def nearest_lanelet(p: np.ndarray):
        if not lanelets:
            return None
        d = [np.min(np.linalg.norm(centre[:, :2] - p[:2], axis=1)) for centre, _ in lanelets]
        return lanelets[int(np.argmin(d))][1]

    for f in hdmap.points:
        bottom = f.p_map - up * HOUSING_HEIGHT_M / 2
        ends = np.stack([bottom - [HOUSING_WIDTH_M / 2, 0, 0], bottom + [HOUSING_WIDTH_M / 2, 0, 0]])
        if f.cls == "traffic_light":
            ls = linestring(ends, type="traffic_light", subtype="red_yellow_green", height=str(HOUSING_HEIGHT_M))
            reg = TrafficLight(getId(), AttributeMap(), [ls])
        else:
            ls = linestring(ends, type="traffic_sign", subtype="unknown", height=str(HOUSING_HEIGHT_M))
            reg = TrafficSign(getId(), AttributeMap(), TrafficSignsWithType([ls], "unknown"))
        ll = nearest_lanelet(f.p_map)
        if ll is not None:
            ll.addRegulatoryElement(reg)
        else:
            m.add(reg)
    for f in hdmap.poles:
        m.add(linestring(np.stack([f.base, f.top]), type="pole", subtype="street_lamp"))
    for _, ll in lanelets:
        m.add(ll)
    skipped = 0
    for w in hdmap.walkable:
        if not is_simple_polygon(w.polygon):
            skipped += 1
            continue
        z = float(np.mean(w.path[:, 2]))
        ring = linestring(np.column_stack([w.polygon, np.full(len(w.polygon), z)]), closed=True, type="virtual")
        m.add(Area(getId(), [ring], [], AttributeMap({"subtype": "crosswalk" if w.kind == "crossing" else "walkway"})))
    for j in hdmap.junctions:
        if not is_simple_polygon(j.polygon):
            skipped += 1
            continue
        ring = linestring(np.column_stack([j.polygon, np.full(len(j.polygon), j.z)]), closed=True, type="virtual")
        m.add(Area(getId(), [ring], [], AttributeMap({"subtype": "intersection"})))
    errors = lanelet2.io.writeRobust(str(path), m, _projector(origin, projector))
    if errors:
        raise RuntimeError(f"lanelet2 could not write {path}: {'; '.join(errors)}")
    return {
        "out": str(path),
        "origin": vars(origin),
        "projector": projector,
        "line_strings": len(m.lineStringLayer),
        "lanelets": len(m.laneletLayer),
        "lanelet_bounds_painted": painted_bounds,
        "regulatory_elements": len(m.regulatoryElementLayer),
        "areas": len(m.areaLayer),
        "areas_not_written": skipped,
    }


def polyline_gap(a: np.ndarray, b: np.ndarray) -> float:
    """The largest distance (x, y, z) from a vertex of ``a`` to the polyline ``b``: a one-sided Hausdorff distance."""
    pl = Polyline(b)
    return float(max(np.linalg.norm(pl.point_at(pl.project(p)) - p) for p in a))
