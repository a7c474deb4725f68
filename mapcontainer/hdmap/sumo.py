"""Import a SUMO road network (``.net.xml``, plain or gzipped) into an :class:`HDMap`, through sumolib.

Everything stays in the network's own frame: SUMO stores every shape already shifted by
``netOffset`` (network x = projected x + netOffset), so the map's coordinates are the network's
coordinates unchanged; the geodetic position of the map origin (0, 0) is known only when the network
has a projection and pyproj is installed (``convertXY2LonLat(0, 0)``, sumolib's own conversion); the axes
are then the projection's grid axes (UTM: y differs from true north by the grid convergence, which the
import notes), not exactly east and north.
The import rules, in short (details in ``mapcontainer/hdmap/README.md``):

* lanes: a lane that allows only pedestrians is a sidewalk; one that allows any road vehicle
  (:data:`ROAD_CLASSES`) is a road lane; other lanes (rail, none allowed) are left out;
* lane lines from the road lanes of every normal edge, each lane's centre shape offset by half its
  width: solid at the road's outer edge, dashed between lanes of one direction; between the two
  directions one solid line when each has one lane, a double solid line otherwise, written once
  (by the edge of the smaller id) when the opposite edge's boundary lies within
  :data:`SHARED_BOUNDARY_M`; a road without an opposite edge (one way, or a median) ends in a solid line;
* stop lines: a solid bar across the road lanes' ends on every approach to a signal or a stop junction;
* lane centre lines: each road lane's shape, in its driving direction, with its width;
* walkable areas: sidewalk lanes and crossings as strips around their shapes (walking path = the
  shape), walking areas (the corners joining them) as their polygons with their principal axis as path;
* junction areas: every junction with a polygon shape (dead ends and internal junctions have none);
* traffic lights: one per approach (incoming road edge) of every signal with a signal program, at
  its stop line, beside the outer lane's edge (:class:`PlacementRule`);
* lamps and signs: by :class:`PlacementRule` (seeded), unless an additional file's POIs give that class.
"""

from __future__ import annotations

import gzip
import xml.etree.ElementTree as ET
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.sax import SAXException

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .errors import MapFileError, require
from .geometry2d import dedup, distance_to_polyline, offset_polyline, principal_axis, strip_outline
from .imported import ImportedMap
from .io import MapOrigin
from .model import HDMap, JunctionArea, LaneCenterline, LaneLine, PointFeature, PoleFeature, Polyline, WalkableArea

__all__ = [
    "ROAD_CLASSES",
    "SHARED_BOUNDARY_M",
    "SIGNED_JUNCTIONS",
    "STOP_JUNCTIONS",
    "STOP_LINE_WIDTH_M",
    "PlacementRule",
    "import_sumo",
    "sniff_sumo",
]

ROAD_CLASSES = (
    "passenger", "private", "taxi", "bus", "coach", "delivery", "truck", "trailer", "emergency",
    "motorcycle", "moped", "bicycle", "evehicle", "authority",
)  # fmt: skip
SIGNED_JUNCTIONS = ("priority", "priority_stop", "allway_stop", "zipper")  # right of way told by signs
STOP_JUNCTIONS = ("priority_stop", "allway_stop")  # approaches with a painted stop line, besides signals
STOP_LINE_WIDTH_M = 0.3
SHARED_BOUNDARY_M = 0.5  # two directions' inner boundaries this close are one painted line
DOUBLE_LINE_GAP_M = 0.24  # centre-to-centre distance of the two lines of a double line
_GZIP_MAGIC = b"\x1f\x8b"


class PlacementRule(BaseModel):
    """Where the importer puts landmarks that a network does not contain (metres, seeded).

    Along every normal edge with road lanes, on its right-hand side (the left in a left-hand network),
    ``curb_offset_m`` beyond the outer road lane's edge:

    * lamps every ``lamp_spacing_m``, the first at a phase drawn uniformly in [0, spacing) per edge,
      none closer than ``end_margin_m`` to the edge's ends;
    * a sign ``sign_after_start_m`` after the start of every edge at least ``sign_min_edge_m`` long
      (a speed-limit sign after each junction), moved by U(-``sign_jitter_m``, +``sign_jitter_m``);
    * a sign ``end_margin_m`` before the end of every edge arriving at a junction of three or more roads whose
      right of way signs tell (:data:`SIGNED_JUNCTIONS`: priority, stop, all-way stop, zipper; not a signal, not
      right-before-left, which has no signs);
    * a traffic light at the stop line (the end of the outer road lane) of every approach to a signal.

    The random draws come from ``numpy.random.default_rng(seed)`` taken in the order of sorted edge ids,
    so the same network and rule give the same map.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    seed: int = Field(0, ge=0)
    curb_offset_m: float = Field(1.0, ge=0)
    lamp_spacing_m: float = Field(35.0, gt=1)
    lamp_height_m: float = Field(8.0, gt=1)
    end_margin_m: float = Field(3.0, ge=0)
    sign_after_start_m: float = Field(10.0, ge=0)
    sign_min_edge_m: float = Field(40.0, ge=0)
    sign_jitter_m: float = Field(2.0, ge=0)
    sign_height_m: float = Field(2.2, gt=0.5)
    traffic_light_height_m: float = Field(5.0, gt=1)


# ---------------------------------------------------------------------------------- reading the file


def sniff_sumo(path: Path) -> dict[str, str]:
    """The attributes of a SUMO network file's root ``<net>`` element; MapFileError for anything else.

    Checks, in order: the file exists and is a file, it is not empty, gzip data decompresses, it is
    XML, and its root element is ``net``. Reads only the file's start (the whole file when gzipped, to find
    corrupt data before sumolib does).
    """
    if not path.exists():
        raise MapFileError(f"{path}: no such file")
    if not path.is_file():
        raise MapFileError(f"{path}: not a file")
    with path.open("rb") as fh:
        head = fh.read(2)
    if not head:
        raise MapFileError(f"{path}: the file is empty")
    gzipped = head == _GZIP_MAGIC
    if gzipped:
        try:
            with gzip.open(path, "rb") as fh:
                while fh.read(1 << 20):
                    pass
        except (OSError, EOFError, zlib.error) as exc:
            raise MapFileError(f"{path}: corrupt gzip data ({exc})") from None
    opener = gzip.open if gzipped else open
    try:
        with opener(path, "rb") as fh:
            if not fh.read(1):
                raise MapFileError(f"{path}: the file is empty (once decompressed)")
            fh.seek(0)
            _, root = next(ET.iterparse(fh, events=("start",)))
    except ET.ParseError as exc:
        raise MapFileError(f"{path}: not XML ({exc})") from None
    except StopIteration:
        raise MapFileError(f"{path}: no XML element in the file") from None
    if root.tag != "net":
        raise MapFileError(f"{path}: not a SUMO network (root element <{root.tag}>, expected <net>)")
    return dict(root.attrib)


def _read_net(path: Path):
    sumolib = require("sumolib", "Reading a SUMO network")
    try:
        return sumolib.net.readNet(str(path), withInternal=True, withPrograms=True, withPedestrianConnections=True)
    except SAXException as exc:
        raise MapFileError(f"{path}: not well-formed XML ({exc})") from None
    except (OSError, EOFError, zlib.error) as exc:
        raise MapFileError(f"{path}: cannot be read ({exc})") from None
    except (KeyError, ValueError, IndexError, AttributeError, TypeError) as exc:
        raise MapFileError(f"{path}: not a valid SUMO network ({type(exc).__name__}: {exc})") from None


# ---------------------------------------------------------------------------------- classification


def _is_sidewalk(lane) -> bool:
    perms = lane.getPermissions()
    return bool(perms) and set(perms) <= {"pedestrian"}


def _is_road(lane) -> bool:
    return any(lane.allows(c) for c in ROAD_CLASSES)


def _shape(lane) -> np.ndarray:
    return dedup(np.asarray(lane.getShape3D(), dtype=float))


@dataclass
class _Edge:
    """A normal edge's road lanes (outer first) and sidewalk lanes, with the side its outer edge is on."""

    edge: Any
    road: list
    sidewalks: list
    outer: float  # -1: the outer edge is on the right of the driving direction (right-hand traffic), +1: left

    @property
    def id(self) -> str:
        return self.edge.getID()

    def boundary(self, k: int) -> np.ndarray:
        """Boundary k of the road lanes: 0 the outer edge, k between road lanes k-1 and k, len(road) the inner edge."""
        if k < len(self.road):
            lane = self.road[k]
            return offset_polyline(_shape(lane), self.outer * lane.getWidth() / 2)
        lane = self.road[-1]
        return offset_polyline(_shape(lane), -self.outer * lane.getWidth() / 2)


def _edges(net, lefthand: bool) -> dict[str, _Edge]:
    out = {}
    for e in sorted(net.getEdges(withInternal=False), key=lambda e: e.getID()):
        if e.getFunction() != "":
            continue
        lanes = sorted(e.getLanes(), key=lambda ln: ln.getIndex())
        lanes = [ln for ln in lanes if len(_shape(ln)) >= 2]
        road = [ln for ln in lanes if not _is_sidewalk(ln) and _is_road(ln)]
        walk = [ln for ln in lanes if _is_sidewalk(ln)]
        out[e.getID()] = _Edge(e, road, walk, +1.0 if lefthand else -1.0)
    return out


def _opposite(ed: _Edge, edges: dict[str, _Edge]) -> _Edge | None:
    """The edge of the other direction between the same two junctions whose inner boundary meets ours."""
    mine = ed.boundary(len(ed.road))
    mid = mine[len(mine) // 2, :2]
    best, best_d = None, np.inf
    for other in ed.edge.getToNode().getOutgoing():
        o = edges.get(other.getID())
        if o is None or not o.road or other.getToNode() is not ed.edge.getFromNode():
            continue
        d = distance_to_polyline(mid, o.boundary(len(o.road)))
        if d < best_d:
            best, best_d = o, d
    return best if best_d <= SHARED_BOUNDARY_M else None


# ---------------------------------------------------------------------------------- the import


class _Ids:
    def __init__(self) -> None:
        self._next = 1

    def __call__(self) -> int:
        self._next += 1
        return self._next - 1


def _lane_lines(edges: dict[str, _Edge], hd: HDMap, new_id: _Ids) -> None:
    for ed in edges.values():
        if not ed.road:
            continue
        n = len(ed.road)
        hd.lane_lines.append(LaneLine(new_id(), ed.boundary(0), "solid"))
        for k in range(1, n):
            hd.lane_lines.append(LaneLine(new_id(), ed.boundary(k), "dashed"))
        opp = _opposite(ed, edges)
        inner = ed.boundary(n)
        if opp is None:
            hd.lane_lines.append(LaneLine(new_id(), inner, "solid"))
        elif ed.id < opp.id:
            if n == 1 and len(opp.road) == 1:
                hd.lane_lines.append(LaneLine(new_id(), inner, "solid"))
            else:
                for side in (-0.5, 0.5):
                    line = offset_polyline(inner, side * DOUBLE_LINE_GAP_M)
                    hd.lane_lines.append(LaneLine(new_id(), line, "solid", width_m=0.12))


def _walkable(net, edges: dict[str, _Edge], hd: HDMap, new_id: _Ids, notes: list[str]) -> None:
    for ed in edges.values():
        for lane in ed.sidewalks:
            shape = _shape(lane)
            poly = strip_outline(shape, lane.getWidth())
            hd.walkable.append(WalkableArea(new_id(), "sidewalk", poly, shape))
    special = sorted(
        (e for e in net.getEdges() if e.getFunction() in ("crossing", "walkingarea")), key=lambda e: e.getID()
    )
    skipped = 0
    for e in special:
        for lane in e.getLanes():
            shape = _shape(lane)
            if e.getFunction() == "crossing" and len(shape) >= 2:
                hd.walkable.append(WalkableArea(new_id(), "crossing", strip_outline(shape, lane.getWidth()), shape))
            elif e.getFunction() == "walkingarea" and len(shape) >= 3:
                poly = shape[:-1, :2] if np.allclose(shape[0, :2], shape[-1, :2]) else shape[:, :2]
                if len(poly) < 3:
                    skipped += 1
                    continue
                try:
                    path = principal_axis(poly, z=float(shape[:, 2].mean()))
                except ValueError:  # all its points in one place
                    skipped += 1
                    continue
                hd.walkable.append(WalkableArea(new_id(), "sidewalk", poly, path))
            else:
                skipped += 1
    if skipped:
        notes.append(f"{skipped} crossing or walking-area lanes without a usable shape left out")


def _junctions(net, hd: HDMap, new_id: _Ids) -> None:
    for node in sorted(net.getNodes(), key=lambda n: n.getID()):
        if node.getType() in ("internal", "dead_end"):
            continue
        shape = node.getShape3D()
        if not shape or len(shape) < 3:
            continue
        pts = dedup(np.asarray(shape, dtype=float))
        if len(pts) > 1 and np.allclose(pts[0, :2], pts[-1, :2]):
            pts = pts[:-1]
        if len(pts) < 3:
            continue
        hd.junctions.append(JunctionArea(new_id(), pts[:, :2].copy(), float(pts[:, 2].mean())))


def _stop_lines(net, edges: dict[str, _Edge], hd: HDMap, new_id: _Ids) -> None:
    """A solid bar across the ends of the road lanes of every approach to a signal or a stop junction."""
    stops = {eid for _, eid in _signal_approaches(net, edges)}
    stops |= {eid for eid, ed in edges.items() if ed.road and ed.edge.getToNode().getType() in STOP_JUNCTIONS}
    for eid in sorted(stops):
        ed = edges[eid]
        a, b = ed.boundary(0)[-1], ed.boundary(len(ed.road))[-1]
        if np.linalg.norm(b[:2] - a[:2]) > 0.1:
            hd.lane_lines.append(LaneLine(new_id(), np.stack([a, b]), "solid", width_m=STOP_LINE_WIDTH_M))


def _signal_approaches(net, edges: dict[str, _Edge]) -> list[tuple[str, str]]:
    """(signal id, incoming road edge id) of every approach to a traffic light that has a signal program."""
    out = set()
    for tls in net.getTrafficLights():
        if not tls.getPrograms():
            continue
        for in_lane, _out, _link in tls.getConnections():
            ed = edges.get(in_lane.getEdge().getID())
            if ed is not None and ed.road:
                out.add((tls.getID(), ed.id))
    return sorted(out)


def _at(ed: _Edge, s: float, rule: PlacementRule) -> np.ndarray:
    """The ground point ``curb_offset_m`` beyond the outer road edge, ``s`` metres along it (clamped)."""

    line = ed.boundary(0)
    pl = Polyline(line)
    p, t = pl.point_at(s), pl.tangent_at(s)
    n = np.array([-t[1], t[0], 0.0])
    n /= max(np.linalg.norm(n), 1e-12)
    return p + n * ed.outer * rule.curb_offset_m


def _placed_landmarks(net, edges: dict[str, _Edge], rule: PlacementRule, classes: set[str], hd: HDMap, new_id: _Ids):

    up = np.array([0.0, 0.0, 1.0])
    if "traffic_light" in classes:
        for _tls, eid in _signal_approaches(net, edges):
            ed = edges[eid]
            end = Polyline(ed.boundary(0)).length
            hd.points.append(
                PointFeature(new_id(), "traffic_light", _at(ed, end, rule) + up * rule.traffic_light_height_m)
            )
    rng = np.random.default_rng(rule.seed)
    for ed in edges.values():
        if not ed.road:
            continue
        length = Polyline(ed.boundary(0)).length
        phase = rng.uniform(0.0, rule.lamp_spacing_m)
        jitter = rng.uniform(-rule.sign_jitter_m, rule.sign_jitter_m)
        if "lamp" in classes:
            for s in np.arange(phase, length - rule.end_margin_m, rule.lamp_spacing_m):
                if s < rule.end_margin_m:
                    continue
                base = _at(ed, s, rule)
                hd.poles.append(PoleFeature(new_id(), "lamp", base, base + up * rule.lamp_height_m))
        if "sign" not in classes:
            continue
        if length >= rule.sign_min_edge_m:
            base = _at(ed, rule.sign_after_start_m + jitter, rule)
            hd.points.append(PointFeature(new_id(), "sign", base + up * rule.sign_height_m))
        node = ed.edge.getToNode()
        roads = {
            e.getID()
            for e in (*node.getIncoming(), *node.getOutgoing())
            if e.getID() in edges and edges[e.getID()].road
        }
        neighbours = {e.getFromNode().getID() for e in node.getIncoming() if e.getID() in roads}
        neighbours |= {e.getToNode().getID() for e in node.getOutgoing() if e.getID() in roads}
        if node.getType() in SIGNED_JUNCTIONS and len(neighbours) >= 3:
            base = _at(ed, length - rule.end_margin_m, rule)
            hd.points.append(PointFeature(new_id(), "sign", base + up * rule.sign_height_m))


POI_CLASSES = {
    "lamp": ("lamp", "street_lamp", "streetlamp", "street_light", "streetlight", "light_pole"),
    "traffic_light": ("traffic_light", "traffic_signals", "traffic_signal", "trafficlight"),
    "sign": ("sign", "traffic_sign", "road_sign", "stop", "give_way"),
}


def _poi_class(poi_type: str) -> str | None:
    t = poi_type.lower().replace(".", "_").replace("-", "_")
    for cls, names in POI_CLASSES.items():
        if any(t == n or t.endswith("_" + n) or t.endswith(":" + n) for n in names):
            return cls
    return None


def _poi_landmarks(net, path: Path, rule: PlacementRule, notes: list[str]):
    """Landmarks from the POIs of an additional file: {class: [(x, y, z, height)]}."""
    require("sumolib", "Reading POIs of a SUMO additional file")
    from sumolib.geomhelper import positionAtShapeOffset
    from sumolib.shapes.poi import read as read_pois

    if not path.is_file():
        raise MapFileError(f"{path}: no such file")
    try:
        pois = read_pois(str(path))
    except SAXException as exc:
        raise MapFileError(f"{path}: not well-formed XML ({exc})") from None
    except (KeyError, ValueError) as exc:
        raise MapFileError(f"{path}: a POI lacks an attribute or has a bad value ({exc})") from None
    found: dict[str, list[np.ndarray]] = {"lamp": [], "traffic_light": [], "sign": []}
    unknown = 0
    for poi in pois:
        cls = _poi_class(poi.type or "")
        if cls is None:
            unknown += 1
            continue
        if poi.lane is not None:
            try:
                x, y = positionAtShapeOffset(net.getLane(poi.lane).getShape(), poi.pos)
            except KeyError:
                raise MapFileError(f"{path}: POI {poi.id!r} is on lane {poi.lane!r}, which the network lacks") from None
        elif poi.lonLat:
            try:
                x, y = net.convertLonLat2XY(poi.x, poi.y)
            except (RuntimeError, ImportError) as exc:
                raise MapFileError(
                    f"{path}: POI {poi.id!r} is given in lon/lat, needing the net's projection and pyproj ({exc})"
                ) from None
        else:
            x, y = poi.x, poi.y
        default = {"lamp": rule.lamp_height_m, "traffic_light": rule.traffic_light_height_m, "sign": rule.sign_height_m}
        height = float(poi.attributes.get("height", default[cls]))
        found[cls].append(np.array([x, y, 0.0, height]))
    if unknown:
        notes.append(
            f"{unknown} POIs of other types ignored (known: {sorted(n for v in POI_CLASSES.values() for n in v)})"
        )
    return found


def import_sumo(
    path: Path | str, rule: PlacementRule | None = None, additional: Path | str | None = None
) -> ImportedMap:
    """Read a SUMO network into an HD map (module docstring); MapFileError for a file it cannot read.

    ``additional``: a SUMO additional file whose POIs (types in :data:`POI_CLASSES`, with an optional
    ``height`` param) give lamps, traffic lights and signs: a class found there replaces the placement rule's.
    """
    path = Path(path)
    rule = rule or PlacementRule()
    root = sniff_sumo(path)
    net = _read_net(path)
    lefthand = root.get("lefthand", "false").lower() == "true"
    edges = _edges(net, lefthand)
    if not any(ed.road or ed.sidewalks for ed in edges.values()):
        raise MapFileError(f"{path}: the SUMO network has no roads (no normal edge with a road or sidewalk lane)")

    name = path.name.removesuffix(".gz").removesuffix(".xml").removesuffix(".net")
    hd = HDMap(name=name)
    notes: list[str] = []
    new_id = _Ids()
    _lane_lines(edges, hd, new_id)
    _stop_lines(net, edges, hd, new_id)
    for ed in edges.values():
        for lane in ed.road:
            hd.centerlines.append(LaneCenterline(new_id(), _shape(lane), width_m=float(lane.getWidth())))
    _walkable(net, edges, hd, new_id, notes)
    _junctions(net, hd, new_id)

    classes = {"lamp", "traffic_light", "sign"}
    if additional is not None:
        up = np.array([0.0, 0.0, 1.0])
        found = _poi_landmarks(net, Path(additional), rule, notes)
        for cls, rows in found.items():
            if not rows:
                continue
            classes.discard(cls)
            for r in rows:
                if cls == "lamp":
                    hd.poles.append(PoleFeature(new_id(), "lamp", r[:3], r[:3] + up * r[3]))
                else:
                    hd.points.append(PointFeature(new_id(), cls, r[:3] + up * r[3]))
        notes.append(f"from POIs: {', '.join(c for c in sorted(found) if found[c]) or 'nothing'}")
    _placed_landmarks(net, edges, rule, classes, hd, new_id)
    if classes:
        notes.append(f"placed by the rule (seed {rule.seed}): {', '.join(sorted(classes))}")

    dx, dy = net.getLocationOffset()
    notes.append(f"network coordinates (netOffset {dx:g}, {dy:g} already in every shape, as SUMO writes them)")
    origin = None
    if net.hasGeoProj():
        try:
            lon, lat = net.convertXY2LonLat(0.0, 0.0)
            origin = MapOrigin(float(lat), float(lon), 0.0)
            gamma = net.getGeoProj().get_factors(lon, lat).meridian_convergence
            notes.append(f"axes: the projection's grid, y {gamma:.2f} deg from true north at the origin (not ENU)")
        except (RuntimeError, ImportError):
            notes.append("the network has a projection but pyproj is not installed: no geodetic origin")
    return ImportedMap(hd, origin, f"sumo:{path}", notes)
