"""SUMO network import: a network netconvert builds from plain nodes and edges, the sample networks that
sumolib and eclipse-sumo ship, and every file the importer must refuse."""

from __future__ import annotations

import gzip
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sumolib = pytest.importorskip("sumolib")  # the roads extra; CI installs it (.ci/run), so these run there
sumo = pytest.importorskip("sumo")

from mapcontainer.hdmap.errors import MapFileError, MissingExtraError  # noqa: E402
from mapcontainer.hdmap.io import load_map, save_map  # noqa: E402
from mapcontainer.hdmap.model import Polyline  # noqa: E402
from mapcontainer.hdmap.sumo import DOUBLE_LINE_GAP_M, ROAD_CLASSES, STOP_LINE_WIDTH_M, PlacementRule, import_sumo  # noqa: E402

NODES = """<nodes>
  <node id="C" x="0" y="0" type="traffic_light"/>
  <node id="W" x="-120" y="0" type="priority"/>
  <node id="E" x="120" y="0" type="priority"/>
  <node id="N" x="0" y="100" type="priority"/>
  <node id="S" x="0" y="-100" type="priority"/>
  <node id="F" x="-120" y="80" type="priority"/>
  <node id="G" x="-200" y="0" type="priority"/>
</nodes>"""
# W-C: one lane each way; N-C: two lanes each way; C-E: a one-way road of two lanes; C-S: one lane each
# way; W-F and W-G: one-lane two-way roads without signals (W is an unsignalised junction of three roads).
EDGES = """<edges>
  <edge id="WC" from="W" to="C" numLanes="1" speed="13.0"/>
  <edge id="CW" from="C" to="W" numLanes="1" speed="13.0"/>
  <edge id="NC" from="N" to="C" numLanes="2" speed="13.0"/>
  <edge id="CN" from="C" to="N" numLanes="2" speed="13.0"/>
  <edge id="CE" from="C" to="E" numLanes="2" speed="13.0"/>
  <edge id="SC" from="S" to="C" numLanes="1" speed="13.0"/>
  <edge id="CS" from="C" to="S" numLanes="1" speed="13.0"/>
  <edge id="WF" from="W" to="F" numLanes="1" speed="13.0"/>
  <edge id="FW" from="F" to="W" numLanes="1" speed="13.0"/>
  <edge id="WG" from="W" to="G" numLanes="1" speed="13.0"/>
  <edge id="GW" from="G" to="W" numLanes="1" speed="13.0"/>
</edges>"""
OFFSET = np.array([200.0, 100.0])  # netconvert moves the network so that its lower-left corner is (0, 0)


def _netconvert() -> Path:
    return Path(sumo.SUMO_HOME) / "bin" / "netconvert"


@pytest.fixture(scope="module")
def net_file(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("net")
    (d / "n.nod.xml").write_text(NODES)
    (d / "e.edg.xml").write_text(EDGES)
    out = d / "cross.net.xml"
    subprocess.run(
        [str(_netconvert()), "-n", "n.nod.xml", "-e", "e.edg.xml", "--sidewalks.guess", "--crossings.guess",
         "--no-turnarounds", "-o", out.name],
        cwd=d, check=True, capture_output=True, timeout=60,
    )  # fmt: skip
    return out


@pytest.fixture(scope="module")
def net(net_file):
    return sumolib.net.readNet(str(net_file), withInternal=True, withPrograms=True, withPedestrianConnections=True)


@pytest.fixture(scope="module")
def imported(net_file):
    return import_sumo(net_file)


def _road_lanes(edge) -> list:
    """Lanes for road vehicles, outer first (the importer's definition, :data:`ROAD_CLASSES`)."""
    lanes = sorted(edge.getLanes(), key=lambda ln: ln.getIndex())
    return [ln for ln in lanes if set(ln.getPermissions()) - {"pedestrian"} and any(map(ln.allows, ROAD_CLASSES))]


def _area(shape) -> bool:
    """A junction shape that is an area: at least 3 distinct points."""
    return len({(round(x, 6), round(y, 6)) for x, y, *_ in shape}) >= 3


def test_counts_match_sumolibs_view(imported, net) -> None:
    hd = imported.hdmap
    normal = [e for e in net.getEdges(withInternal=False) if e.getFunction() == ""]
    assert len(hd.centerlines) == sum(len(_road_lanes(e)) for e in normal) == 14
    sidewalks = sum(1 for e in normal for ln in e.getLanes() if set(ln.getPermissions()) == {"pedestrian"})
    crossings = [e for e in net.getEdges() if e.getFunction() == "crossing"]
    walking = [e for e in net.getEdges() if e.getFunction() == "walkingarea"]
    kinds = [w.kind for w in hd.walkable]
    assert kinds.count("crossing") == len(crossings) > 0
    assert kinds.count("sidewalk") == sidewalks + len(walking)
    shaped = [n for n in net.getNodes() if n.getType() not in ("dead_end", "internal") and _area(n.getShape())]
    assert len(hd.junctions) == len(shaped) == 2  # C and W; the others are dead ends
    approaches = {c[0].getEdge().getID() for t in net.getTrafficLights() for c in t.getConnections()}
    approaches = {e for e in approaches if net.getEdge(e).getFunction() == ""}
    assert approaches == {"WC", "NC", "SC"}
    assert hd.feature_counts()["traffic_light"] == 3


def test_lane_line_kinds(imported, net) -> None:
    hd = imported.hdmap
    # Outer edges: one per edge (11). Dashed: between the two lanes of NC, CN and CE. Between directions:
    # WC/CW, SC/CS, WF/FW and WG/GW single solid lines, NC/CN a double line; CE (one way) ends in a solid line.
    # Stop lines on the three approaches to the signal.
    kinds = [ln.kind for ln in hd.lane_lines]
    assert kinds.count("dashed") == 3
    assert kinds.count("solid") == 11 + 4 + 2 + 1 + 3
    bars = [ln for ln in hd.lane_lines if ln.width_m == STOP_LINE_WIDTH_M]
    widths = sorted(round(float(np.linalg.norm(np.diff(ln.points[:, :2], axis=0))), 1) for ln in bars)
    lane_w = net.getEdge("WC").getLane(1).getWidth()
    assert widths == pytest.approx([lane_w, lane_w, 2 * lane_w], abs=0.05)  # WC, SC one lane; NC two
    # The double line: two solid lines DOUBLE_LINE_GAP_M apart around the boundary of NC and CN.
    inner = _road_lanes(net.getEdge("NC"))[-1]
    shape = np.array(inner.getShape3D())
    mid = shape.mean(axis=0)
    boundary_offsets = []
    for ln in hd.lane_lines:
        pl = Polyline(ln.points)
        d = float(np.linalg.norm(pl.point_at(pl.project(mid))[:2] - mid[:2]))
        if abs(d - inner.getWidth() / 2) < 0.5:
            boundary_offsets.append((ln.kind, abs(d - inner.getWidth() / 2)))
    double = [k for k, gap in boundary_offsets if abs(gap - DOUBLE_LINE_GAP_M / 2) < 0.01]
    assert double == ["solid", "solid"]
    assert [k for k, gap in boundary_offsets if gap < 0.01] == ["dashed"]  # between NC's own two lanes


def test_coordinates_are_the_networks_own(imported, net, net_file) -> None:
    """Shapes stay in network coordinates (input + netOffset), as SUMO writes them."""
    assert np.allclose(net.getLocationOffset(), OFFSET)
    centre = imported.hdmap.junctions[0]  # "C" sorts first
    assert np.allclose(centre.polygon.mean(axis=0), OFFSET, atol=3.0)
    lane = _road_lanes(net.getEdge("WC"))[0]
    assert any(np.allclose(c.points[:, :2], np.array(lane.getShape())) for c in imported.hdmap.centerlines)
    assert imported.origin is None  # no projection in a network built from plain x, y


def test_traffic_lights_stand_at_the_stop_lines(imported, net) -> None:
    rule = PlacementRule()
    lights = [p.p_map for p in imported.hdmap.points if p.cls == "traffic_light"]
    for eid in ("WC", "NC", "SC"):
        lane = _road_lanes(net.getEdge(eid))[0]  # the outer road lane (lane 0 is the sidewalk)
        stop = np.array(lane.getShape())[-1]
        expected = lane.getWidth() / 2 + rule.curb_offset_m
        d = min(np.linalg.norm(p[:2] - stop) for p in lights)
        assert d == pytest.approx(expected, abs=0.05)
    assert all(p[2] == pytest.approx(rule.traffic_light_height_m) for p in lights)


def test_left_hand_traffic_puts_the_curb_on_the_left(tmp_path) -> None:
    (tmp_path / "n.nod.xml").write_text(NODES)
    (tmp_path / "e.edg.xml").write_text(EDGES)
    subprocess.run(
        [str(_netconvert()), "-n", "n.nod.xml", "-e", "e.edg.xml", "--lefthand", "-o", "lh.net.xml"],
        cwd=tmp_path, check=True, capture_output=True, timeout=60,
    )  # fmt: skip
    hd = import_sumo(tmp_path / "lh.net.xml").hdmap
    net = sumolib.net.readNet(str(tmp_path / "lh.net.xml"))
    for eid in ("WC", "NC", "SC"):  # the traffic light of each approach stands left of its outer lane's end
        shape = np.array(_road_lanes(net.getEdge(eid))[0].getShape())
        t, end = shape[-1] - shape[-2], shape[-1]
        light = min((p.p_map for p in hd.points if p.cls == "traffic_light"), key=lambda p: np.linalg.norm(p[:2] - end))
        v = light[:2] - end
        assert t[0] * v[1] - t[1] * v[0] > 0


def test_placement_is_seeded_and_follows_the_rule(net_file) -> None:
    a, b = import_sumo(net_file, PlacementRule(seed=3)), import_sumo(net_file, PlacementRule(seed=3))
    c = import_sumo(net_file, PlacementRule(seed=4))
    bases = lambda m: np.array([p.base for p in m.hdmap.poles])  # noqa: E731
    assert np.array_equal(bases(a), bases(b))
    assert bases(a).shape != bases(c).shape or not np.allclose(bases(a), bases(c))
    lamps = a.hdmap.poles
    assert all(p.top[2] - p.base[2] == pytest.approx(8.0) for p in lamps)
    # 35 m apart along each edge's outer edge, none within 3 m of its ends: between L/35 - 2 and L/35 + 1 per edge.
    lengths = [_road_lanes(e)[0].getLength() for e in sumolib.net.readNet(str(net_file)).getEdges()]
    assert sum(int(x / 35) - 2 for x in lengths) <= len(lamps) <= sum(int(x / 35) + 1 for x in lengths)
    rule = PlacementRule(seed=3, lamp_spacing_m=20.0)
    assert len(import_sumo(net_file, rule).hdmap.poles) > len(lamps)
    # Signs: a speed-limit sign after the start of every edge (all are >= 40 m) and a right-of-way sign on the
    # approaches to W, the unsignalised junction of three roads (from C, F and G).
    assert a.hdmap.feature_counts()["sign"] == 11 + 3


def test_pois_of_an_additional_file_replace_the_rule(net_file, tmp_path) -> None:
    add = tmp_path / "pois.add.xml"
    add.write_text(
        '<additional>\n'
        '  <poi id="l1" type="street_lamp" color="1,1,0" layer="0" x="100" y="105">\n'
        '    <param key="height" value="6"/>\n'
        '  </poi>\n'
        '  <poi id="l2" type="lamp" color="1,1,0" layer="0" lane="WC_1" pos="20"/>\n'
        '  <poi id="t" type="tree" color="0,1,0" layer="0" x="10" y="10"/>\n'
        '</additional>\n'
    )  # fmt: skip
    m = import_sumo(net_file, additional=add)
    assert m.hdmap.feature_counts() == {"lamp": 2, "traffic_light": 3, "sign": 14}
    first = m.hdmap.poles[0]
    assert np.allclose(first.base, [100, 105, 0]) and first.top[2] == pytest.approx(6.0)
    assert any("1 POIs of other types" in n for n in m.notes)


def test_gzipped_and_plain_give_the_same_map(net_file, imported, tmp_path) -> None:
    gz = tmp_path / "cross.net.xml.gz"
    gz.write_bytes(gzip.compress(net_file.read_bytes()))
    other = import_sumo(gz).hdmap
    assert len(other.lane_lines) == len(imported.hdmap.lane_lines)
    assert all(
        np.array_equal(a.points, b.points) for a, b in zip(other.lane_lines, imported.hdmap.lane_lines, strict=True)
    )


def test_geojson_round_trip_keeps_junctions(imported, tmp_path) -> None:
    path = save_map(imported.hdmap, tmp_path / "m.geojson")
    back = load_map(path)
    assert len(back.junctions) == len(imported.hdmap.junctions)
    assert all(
        np.array_equal(a.polygon, b.polygon) for a, b in zip(back.junctions, imported.hdmap.junctions, strict=True)
    )
    assert back.feature_counts() == imported.hdmap.feature_counts()


def test_a_projected_network_has_a_geodetic_origin() -> None:
    pytest.importorskip("pyproj")  # the roads extra
    path = Path(sumo.__file__).parent / "tools/game/bs3d/bs.net.xml"
    m = import_sumo(path)
    # The network's (0, 0) is the lower-left corner of its UTM bounding box; its WGS84 bounding box is
    # origBoundary="10.525796,52.269679,10.549189,52.288860". Rotated by the grid convergence, the corner lies
    # tens of metres from the lon/lat box's corner, inside the box widened by 0.001 degrees.
    assert 52.269679 - 1e-3 < m.origin.lat_deg < 52.288860 and 10.525796 - 1e-3 < m.origin.lon_deg < 10.549189
    assert any("deg from true north" in n for n in m.notes)


SAMPLES = {
    "rilsa1": ("sumolib", "scenario/scenarios/RiLSA1/rilsa1.net.xml"),
    "cross": ("sumo", "tools/game/cross/cross.net.xml"),
    "ingolstadt.gz": ("sumo", "tools/game/fkk_in/ingolstadt.net.xml.gz"),
}


@pytest.mark.parametrize("sample", sorted(SAMPLES))
def test_shipped_sample_networks(sample: str) -> None:
    pkg, rel = SAMPLES[sample]
    path = Path((sumolib if pkg == "sumolib" else sumo).__file__).parent / rel
    net = sumolib.net.readNet(str(path), withInternal=True, withPrograms=True)
    hd = import_sumo(path).hdmap
    normal = [e for e in net.getEdges(withInternal=False) if e.getFunction() == ""]
    assert len(hd.centerlines) == sum(len(_road_lanes(e)) for e in normal) > 0
    tls_edges = {(t.getID(), c[0].getEdge().getID()) for t in net.getTrafficLights() if t.getPrograms()
                 for c in t.getConnections() if c[0].getEdge().getFunction() == ""}  # fmt: skip
    assert hd.feature_counts()["traffic_light"] == len(tls_edges) > 0
    shaped = [n for n in net.getNodes() if n.getType() not in ("dead_end", "internal") and _area(n.getShape())]
    assert len(hd.junctions) == len(shaped) > 0


def _gzip_truncated(p: Path, net_file: Path) -> None:
    p.write_bytes(gzip.compress(net_file.read_bytes())[:400])


def _gzip_bad_crc(p: Path, net_file: Path) -> None:
    data = bytearray(gzip.compress(net_file.read_bytes()))
    data[-8] ^= 0xFF  # the CRC32 of the trailer
    p.write_bytes(bytes(data))


BAD = {
    "missing": (None, "no such file"),
    "empty": (lambda p, n: p.write_bytes(b""), "empty"),
    "not_xml": (lambda p, n: p.write_text("edge,lane\n1,2\n"), "not XML"),
    "not_a_net": (lambda p, n: p.write_text('<osm version="0.6"/>'), "not a SUMO network"),
    "no_roads": (
        lambda p, n: p.write_text(
            '<net version="1.9"><location netOffset="0,0" '
            'convBoundary="0,0,1,1" origBoundary="0,0,1,1" projParameter="!"/></net>'
        ),
        "no roads",
    ),  # fmt: skip
    "gzip_truncated": (_gzip_truncated, "corrupt gzip"),
    "gzip_bad_crc": (_gzip_bad_crc, "corrupt gzip"),
    "xml_broken_later": (lambda p, n: p.write_text(n.read_text()[:3000]), "not well-formed XML"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_unreadable_files_are_refused_with_a_clear_error(case: str, tmp_path: Path, net_file: Path) -> None:
    make, words = BAD[case]
    path = tmp_path / ("bad.net.xml.gz" if "gzip" in case else "bad.net.xml")
    if make is not None:
        make(path, net_file)
    with pytest.raises(MapFileError) as info:
        import_sumo(path)
    assert words in str(info.value)
    assert str(path) in str(info.value)
    assert "\n" not in str(info.value)


def test_missing_extra_names_it(monkeypatch, net_file) -> None:
    monkeypatch.setitem(sys.modules, "sumolib", None)  # import sumolib now raises ImportError
    with pytest.raises(MissingExtraError, match=r"map-container\[roads\]"):
        import_sumo(net_file)


def test_an_imported_map_serves_the_map_readers(imported, net) -> None:
    """The spatial index and the map-error model take an imported map as they take the ring road."""
    from mapcontainer.hdmap.perturb import MapError, perturb_map
    from mapcontainer.hdmap.query import MapIndex

    hd = imported.hdmap
    index = MapIndex(hd)
    light = next(p for p in hd.points if p.cls == "traffic_light")
    points, _ = index.landmarks_in_range(light.p_map, 1.0)
    assert [p.id for p in points] == [light.id]
    centre = net.getEdge("WC").getLane(1).getShape3D()[0]
    assert index.nearest_lane_height(np.array(centre)) == pytest.approx(0.0)
    assert len(index.lane_samples_in_range(np.array(centre), 10.0)) > 0
    noisy = perturb_map(hd, MapError(landmark_sigma_m=(0.05, 0.02), line_sigma_m=0.05), np.random.SeedSequence(1))
    assert noisy.feature_counts() == hd.feature_counts() and len(noisy.junctions) == len(hd.junctions)
