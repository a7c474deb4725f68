"""Lanelet2 OSM maps: our exporter's files through lanelet2's own loader and back, a hand-written map with the
line types and tags a user's map has, and every file the importer must refuse."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

lanelet2 = pytest.importorskip("lanelet2")  # the roads extra; CI installs it (.ci/run), so these run there

from lanelet2.core import TrafficLight, TrafficSign  # noqa: E402
from lanelet2.io import Origin  # noqa: E402
from lanelet2.projection import LocalCartesianProjector  # noqa: E402

from mapcontainer.hdmap import MapSpec, generate_map  # noqa: E402
from mapcontainer.hdmap.errors import MapFileError, MissingExtraError  # noqa: E402
from mapcontainer.hdmap.io import MapOrigin  # noqa: E402
from mapcontainer.hdmap.lanelet import DOUBLE_LINE_GAP_M, export_lanelet2, import_lanelet2  # noqa: E402
from mapcontainer.hdmap.model import HDMap, LaneCenterline, LaneLine  # noqa: E402

ORIGIN = MapOrigin(48.1, 11.5, 500.0)
TOL_M = 1e-3  # OSM files hold lat/lon with 11 decimals: about 1e-6 m; a millimetre is the stated tolerance


def _gap(points: np.ndarray, lines: list[np.ndarray]) -> float:
    """The largest distance from one of ``points`` (N, 3) to the nearest segment of ``lines`` (polylines)."""
    a = np.vstack([x[:-1] for x in lines])
    d = np.vstack([np.diff(x, axis=0) for x in lines])
    q = np.asarray(points)[:, None, :]
    t = np.clip(np.einsum("nij,ij->ni", q - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0.0, 1.0)
    return float(np.max(np.min(np.linalg.norm(a + t[..., None] * d - q, axis=2), axis=1)))


@pytest.fixture(scope="module")
def ring() -> HDMap:
    return generate_map(MapSpec())


@pytest.fixture(scope="module")
def exported(ring, tmp_path_factory) -> tuple[Path, dict]:
    path = tmp_path_factory.mktemp("ll2") / "ring.osm"
    return path, export_lanelet2(ring, path, ORIGIN)


def test_lanelet2_loads_the_export_without_errors(ring, exported) -> None:
    path, info = exported
    projector = LocalCartesianProjector(Origin(ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.alt_m))
    llmap, errors = lanelet2.io.loadRobust(str(path), projector)
    assert errors == []
    types = [ls.attributes["type"] for ls in llmap.lineStringLayer]
    assert types.count("line_thin") == len(ring.lane_lines)
    assert types.count("pole") == len(ring.poles)
    assert types.count("traffic_light") == ring.feature_counts()["traffic_light"]
    assert types.count("traffic_sign") == ring.feature_counts()["sign"]
    regs = list(llmap.regulatoryElementLayer)
    assert sum(isinstance(r, TrafficLight) for r in regs) == ring.feature_counts()["traffic_light"]
    assert sum(isinstance(r, TrafficSign) for r in regs) == ring.feature_counts()["sign"]
    # Each closed centre line of the ring is two lanelets end to end, each referring to its regulatory elements.
    assert len(llmap.laneletLayer) == 2 * len(ring.centerlines) == info["lanelets"]
    assert sum(len(ll.regulatoryElements) for ll in llmap.laneletLayer) == len(ring.points)
    assert len(llmap.areaLayer) == len(ring.walkable)


def test_round_trip_keeps_lines_and_landmarks(ring, exported) -> None:
    path, _ = exported
    back = import_lanelet2(path, ORIGIN).hdmap
    assert len(back.lane_lines) == len(ring.lane_lines)
    for a, b in zip(ring.lane_lines, back.lane_lines, strict=True):
        assert (a.kind, a.closed) == (b.kind, b.closed)
        assert a.points.shape == b.points.shape
        assert np.max(np.abs(a.points - b.points)) < TOL_M
    assert back.feature_counts() == ring.feature_counts()
    for a, b in zip(ring.points, back.points, strict=True):
        assert a.cls == b.cls and np.max(np.abs(a.p_map - b.p_map)) < TOL_M
    for a, b in zip(ring.poles, back.poles, strict=True):
        assert np.max(np.abs(a.base - b.base)) < TOL_M and np.max(np.abs(a.top - b.top)) < TOL_M
    # Centre lines: lanelet2 computes its own between the bounds; each of ours lies on one of them within 1 cm.
    assert len(back.centerlines) == 2 * len(ring.centerlines)
    for c in ring.centerlines:
        assert _gap(c.points, [b.points for b in back.centerlines]) < 0.01
    assert [w.kind for w in back.walkable] == [w.kind for w in ring.walkable]
    for a, b in zip(ring.walkable, back.walkable, strict=True):  # lanelet2 may reverse a ring: compare as sets
        ring_b = np.column_stack([b.polygon, np.zeros(len(b.polygon))])
        assert _gap(np.column_stack([a.polygon, np.zeros(len(a.polygon))]), [ring_b]) < TOL_M
        assert len(a.polygon) == len(b.polygon)


def test_lanelet_bounds_are_the_painted_lines(tmp_path) -> None:
    """A straight two-lane road: its lanelets' bounds are our lane lines, with their line types, not virtual lines."""
    x = np.linspace(0.0, 100.0, 11)

    def line(y: float) -> np.ndarray:
        return np.column_stack([x, np.full_like(x, y), np.zeros_like(x)])

    lines = [LaneLine(1, line(-3.5), "solid"), LaneLine(2, line(0.0), "dashed"), LaneLine(3, line(3.5), "solid")]
    centres = [LaneCenterline(4, line(-1.75), width_m=3.5), LaneCenterline(5, line(1.75)[::-1].copy(), width_m=3.5)]
    hd = HDMap("road", lane_lines=lines, centerlines=centres)
    path = tmp_path / "road.osm"
    info = export_lanelet2(hd, path, ORIGIN)
    assert info["lanelet_bounds_painted"] == 4
    projector = LocalCartesianProjector(Origin(ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.alt_m))
    llmap, errors = lanelet2.io.loadRobust(str(path), projector)
    assert errors == []
    lls = sorted(llmap.laneletLayer, key=lambda ll: ll.centerline[0].y)
    # Both lanes have the dashed line on their left and a solid edge on their right (right-hand traffic).
    assert [ll.leftBound.attributes["subtype"] for ll in lls] == ["dashed", "dashed"]
    assert [ll.rightBound.attributes["subtype"] for ll in lls] == ["solid", "solid"]
    assert all(ll.leftBound.attributes["type"] == "line_thin" for ll in lls)
    back = import_lanelet2(path, ORIGIN).hdmap
    assert [c.width_m for c in back.centerlines] == pytest.approx([3.5, 3.5], abs=1e-3)
    assert _gap(hd.centerlines[0].points, [back.centerlines[0].points, back.centerlines[1].points]) < TOL_M


# A map as a user's tools write it: nodes by lat/lon, a solid_solid centre line, a curbstone, a stop line, a lamp
# as a tagged node, a traffic sign referred to by a regulatory element, a crosswalk lanelet.
USER_MAP = """<?xml version="1.0"?>
<osm version="0.6" generator="hand">
  <node id="1" lat="48.1" lon="11.5"/>
  <node id="2" lat="48.1" lon="11.501"/>
  <node id="3" lat="48.10003" lon="11.5"/>
  <node id="4" lat="48.10003" lon="11.501"/>
  <node id="5" lat="48.10006" lon="11.5"/>
  <node id="6" lat="48.10006" lon="11.501"/>
  <node id="7" lat="48.10008" lon="11.5002"><tag k="type" v="pole"/><tag k="height" v="7.5"/></node>
  <node id="8" lat="48.10008" lon="11.5005"><tag k="ele" v="2.0"/></node>
  <node id="9" lat="48.10008" lon="11.500504"><tag k="ele" v="2.0"/></node>
  <node id="10" lat="48.10001" lon="11.50095"/>
  <node id="11" lat="48.10002" lon="11.50095"/>
  <way id="20"><nd ref="1"/><nd ref="2"/><tag k="type" v="curbstone"/><tag k="subtype" v="high"/></way>
  <way id="21"><nd ref="3"/><nd ref="4"/><tag k="type" v="line_thin"/><tag k="subtype" v="solid_solid"/></way>
  <way id="22"><nd ref="5"/><nd ref="6"/><tag k="type" v="line_thin"/><tag k="subtype" v="dashed"/></way>
  <way id="23"><nd ref="8"/><nd ref="9"/><tag k="type" v="traffic_sign"/><tag k="subtype" v="de205"/>
    <tag k="height" v="0.6"/></way>
  <way id="24"><nd ref="10"/><nd ref="11"/><tag k="type" v="stop_line"/></way>
  <relation id="30"><member type="way" ref="21" role="left"/><member type="way" ref="20" role="right"/>
    <member type="relation" ref="40" role="regulatory_element"/>
    <tag k="type" v="lanelet"/><tag k="subtype" v="road"/></relation>
  <relation id="40"><member type="way" ref="23" role="refers"/>
    <tag k="type" v="regulatory_element"/><tag k="subtype" v="traffic_sign"/></relation>
</osm>
"""


def test_a_users_map(tmp_path) -> None:
    path = tmp_path / "user.osm"
    path.write_text(USER_MAP)
    m = import_lanelet2(path, MapOrigin(48.1, 11.5), projector="utm")
    hd = m.hdmap
    # curbstone: 1 solid; solid_solid: 2 solid; dashed: 1; stop line: 1 solid.
    assert sorted(ln.kind for ln in hd.lane_lines) == ["dashed", "solid", "solid", "solid", "solid"]
    ys = sorted(float(ln.points[0, 1]) for ln in hd.lane_lines if ln.kind == "solid" and ln.points[0, 0] < 1)
    assert ys[2] - ys[1] == pytest.approx(DOUBLE_LINE_GAP_M, abs=1e-3)  # the double line's two lines
    assert hd.feature_counts() == {"lamp": 1, "traffic_light": 0, "sign": 1}
    lamp = hd.poles[0]
    assert lamp.top[2] - lamp.base[2] == pytest.approx(7.5)
    assert hd.points[0].p_map[2] == pytest.approx(2.3, abs=1e-3)  # the sign's bottom at 2 m, 0.6 m high
    assert len(hd.centerlines) == 1
    assert hd.centerlines[0].width_m == pytest.approx(3.34, abs=0.05)  # 0.00003 degrees of latitude
    assert m.origin == MapOrigin(48.1, 11.5)
    # Without an origin, the first node is the origin: the curbstone starts at (0, 0).
    m2 = import_lanelet2(path)
    assert np.allclose(m2.hdmap.lane_lines[0].points[0, :2], 0.0, atol=1e-6)
    assert any("first node" in n for n in m2.notes)


BAD = {
    "missing": (None, "no such file"),
    "empty": (b"", "empty"),
    "not_xml": (b"lat,lon\n1,2\n", "not XML"),
    "not_osm": (b'<net version="1.9"/>', "not an OSM"),
    "no_elements": (b'<osm version="0.6"/>', "empty"),
    "truncated": (b'<osm version="0.6"><node id="1" lat="49" lon="8"/><way id="2"><nd ref=', "lanelet2 cannot load"),
    "nothing_usable": (
        b'<osm version="0.6"><node id="1" lat="49" lon="8"/><way id="2"><nd ref="1"/><nd ref="99"/>'
        b'<tag k="type" v="line_thin"/></way></osm>',
        "nothing in the map",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_unreadable_files_are_refused_with_a_clear_error(case: str, tmp_path: Path) -> None:
    data, words = BAD[case]
    path = tmp_path / "bad.osm"
    if data is not None:
        path.write_bytes(data)
    with pytest.raises(MapFileError) as info:
        import_lanelet2(path, ORIGIN)
    assert words in str(info.value) and str(path) in str(info.value)


def test_missing_extra_names_it(monkeypatch, tmp_path) -> None:
    path = tmp_path / "user.osm"
    path.write_text(USER_MAP)
    monkeypatch.setitem(sys.modules, "lanelet2", None)
    with pytest.raises(MissingExtraError, match=r"map-container\[roads\]"):
        import_lanelet2(path, ORIGIN)
