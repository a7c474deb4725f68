"""HD map: generator counts and determinism, GeoJSON file round trip and validation, Polyline."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapcontainer.hdmap import (
    HDMap,
    LaneCenterline,
    LaneLine,
    MapSpec,
    PointFeature,
    PoleFeature,
    Polyline,
    WalkableArea,
    generate_map,
)
from mapcontainer.hdmap.io import MapOrigin, load_map, load_origin, map_to_geojson, save_map


def assert_maps_equal(a: HDMap, b: HDMap) -> None:
    """Every feature, every scalar and every array (np.array_equal, same dtype) of two maps."""
    assert a.name == b.name
    for group in ("points", "poles", "lane_lines", "centerlines", "walkable"):
        fa, fb = getattr(a, group), getattr(b, group)
        assert len(fa) == len(fb), group
        for x, y in zip(fa, fb, strict=True):
            assert type(x) is type(y)
            for name, vx in vars(x).items():
                vy = getattr(y, name)
                if isinstance(vx, np.ndarray):
                    assert isinstance(vy, np.ndarray) and vx.dtype == vy.dtype, f"{group} {x.id} {name}"
                    assert vx.shape == vy.shape and np.array_equal(vx, vy), f"{group} {x.id} {name}"
                else:
                    assert type(vx) is type(vy) and vx == vy, f"{group} {x.id} {name}: {vx!r} != {vy!r}"


def small_map() -> HDMap:
    """A hand-made map touching every feature type and option (open/closed, solid/dashed)."""
    return HDMap(
        name="small",
        points=[
            PointFeature(1, "traffic_light", np.array([0.1 + 0.2, -1e-9, 5.0])),
            PointFeature(2, "sign", np.array([-12.345678901234567, 3.0, 2.2])),
        ],
        poles=[PoleFeature(3, "lamp", np.array([1.0, 2.0, 0.0]), np.array([1.0, 2.0, 8.0]))],
        lane_lines=[
            LaneLine(4, np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.25], [80.0, 10.0, 0.5]]), "dashed",
                     closed=False, dash_m=2.5, gap_m=5.5, width_m=0.12),
            LaneLine(5, np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [10.0, 10.0, 0.0]]), "solid",
                     closed=True),
        ],
        centerlines=[
            LaneCenterline(6, np.array([[0.0, 1.75, 0.0], [50.0, 1.75, 0.0]]), closed=False, width_m=3.25)
        ],
        walkable=[
            WalkableArea(7, "crossing", np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 9.0], [0.0, 9.0]]),
                         np.array([[2.0, 0.0, 0.0], [2.0, 9.0, 0.0]])),
            WalkableArea(8, "sidewalk", np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 0.0]]),
                         np.array([[0.5, 0.0, 0.0], [0.5, 1.0, 0.0], [0.2, 0.5, 0.0]]), closed=True),
        ],
    )


# -------------------------------------------------------------------------------- generator


def test_default_map_has_the_papers_landmarks() -> None:
    hd = generate_map(MapSpec())
    assert hd.feature_counts() == {"lamp": 14, "traffic_light": 4, "sign": 4}
    assert len(hd.points) == 8 and len(hd.poles) == 14
    assert len(hd.lane_lines) == 5  # 2 lanes per direction: 3 solid + 2 dashed
    assert sorted(line.kind for line in hd.lane_lines) == ["dashed", "dashed", "solid", "solid", "solid"]
    assert len(hd.centerlines) == 4
    assert sorted(w.kind for w in hd.walkable) == ["crossing", "crossing", "sidewalk", "sidewalk"]
    ids = [f.id for group in (hd.points, hd.poles, hd.lane_lines, hd.centerlines, hd.walkable) for f in group]
    assert len(set(ids)) == len(ids)


def test_landmark_counts_follow_the_spec() -> None:
    hd = generate_map(MapSpec(lamps=6, traffic_lights=2, signs=9, lanes_per_direction=1))
    assert hd.feature_counts() == {"lamp": 6, "traffic_light": 2, "sign": 9}
    assert len(hd.lane_lines) == 3 and len(hd.centerlines) == 2


def test_poles_stand_upright_and_landmarks_off_the_road() -> None:
    spec = MapSpec()
    hd = generate_map(spec)
    for pole in hd.poles:
        assert pole.base[2] == 0.0 and pole.top[2] == pytest.approx(spec.lamp_height_m)
        np.testing.assert_allclose(pole.base[:2], pole.top[:2])
    road_edge = spec.lanes_per_direction * spec.lane_width_m
    centre = Polyline(hd.lane_lines[spec.lanes_per_direction].points, closed=True)
    for f in hd.points:
        nearest = centre.point_at(centre.project(f.p_map))
        assert np.linalg.norm(f.p_map[:2] - nearest[:2]) > road_edge


def test_generation_is_deterministic() -> None:
    assert_maps_equal(generate_map(MapSpec(seed=3)), generate_map(MapSpec(seed=3)))


def test_another_seed_moves_the_landmarks() -> None:
    a, b = generate_map(MapSpec(seed=1)), generate_map(MapSpec(seed=2))
    assert not np.array_equal(np.array([p.base for p in a.poles]), np.array([p.base for p in b.poles]))


# ------------------------------------------------------------------------------- file format


@pytest.mark.parametrize("make", [lambda: generate_map(MapSpec()), small_map], ids=["generated", "small"])
def test_save_load_round_trip_is_exact(tmp_path: Path, make) -> None:
    hd = make()
    path = save_map(hd, tmp_path / "map.geojson")
    back = load_map(path)
    assert_maps_equal(hd, back)
    assert back.feature_counts() == hd.feature_counts()
    # Saving what was loaded writes the same bytes.
    assert save_map(back, tmp_path / "again.geojson").read_bytes() == path.read_bytes()


def test_file_is_geojson_in_local_enu_metres(tmp_path: Path) -> None:
    path = save_map(small_map(), tmp_path / "m.geojson")
    doc = json.loads(path.read_text())
    assert doc["type"] == "FeatureCollection"
    assert doc["properties"]["crs"] == "local-enu-m" and "not WGS84" in doc["properties"]["crs_note"]
    kinds = [f["properties"]["kind"] for f in doc["features"]]
    assert kinds == ["point", "point", "pole", "lane_line", "lane_line", "centerline", "walkable", "walkable"]
    geoms = [f["geometry"]["type"] for f in doc["features"]]
    assert geoms == ["Point"] * 2 + ["LineString"] * 4 + ["Polygon"] * 2
    ring = doc["features"][6]["geometry"]["coordinates"][0]
    assert ring[0] == ring[-1] and len(ring) == 5  # GeoJSON rings repeat their first position
    lane = doc["features"][3]["properties"]
    assert lane == {"kind": "lane_line", "id": 4, "line_kind": "dashed", "closed": False,
                    "dash_m": 2.5, "gap_m": 5.5, "width_m": 0.12}


def test_origin_round_trip(tmp_path: Path) -> None:
    path = save_map(small_map(), tmp_path / "m.geojson", origin=MapOrigin(48.137154, 11.576124, 519.5))
    assert load_origin(path) == MapOrigin(48.137154, 11.576124, 519.5)
    assert load_origin(save_map(small_map(), tmp_path / "n.geojson")) is None


def test_save_refuses_non_finite_coordinates(tmp_path: Path) -> None:
    hd = HDMap("bad", points=[PointFeature(1, "sign", np.array([np.nan, 0.0, 0.0]))])
    with pytest.raises(ValueError):
        save_map(hd, tmp_path / "bad.geojson")


def _doc() -> dict[str, Any]:
    return map_to_geojson(small_map())


def _set(doc: dict[str, Any], index: int, path: tuple, value: Any) -> dict[str, Any]:
    node = doc["features"][index]
    for key in path[:-1]:
        node = node[key]
    if value is ...:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return doc


def geom(i: int, key: str, value: Any):
    """Mutation: set (or delete, with ``...``) geometry member ``key`` of feature ``i``."""
    return lambda d: _set(d, i, ("geometry", key), value)


def prop(i: int, key: str, value: Any):
    """Mutation: set (or delete, with ``...``) property ``key`` of feature ``i``."""
    return lambda d: _set(d, i, ("properties", key), value)


def header(**changes: Any):
    """Mutation of the collection's top-level ``properties``."""
    return lambda d: {**d, "properties": {**d["properties"], **changes}}


def _two_rings(d: dict[str, Any]) -> dict[str, Any]:
    return _set(d, 6, ("geometry", "coordinates"), d["features"][6]["geometry"]["coordinates"] * 2)


# (mutation of the document, expected words in the message)
MALFORMED = {
    "point_2d": (geom(0, "coordinates", [1.0, 2.0]), "feature 0 (kind='point', id=1)"),
    "point_wrong_geometry": (geom(1, "type", "LineString"), "feature 1"),
    "point_bad_class": (prop(0, "cls", "lamp"), "'cls'"),
    "point_string_coord": (geom(0, "coordinates", [1.0, "2", 3.0]), "feature 0"),
    "point_nan": (geom(0, "coordinates", [float("nan"), 0.0, 0.0]), "non-finite"),
    "pole_three_positions": (geom(2, "coordinates", [[0, 0, 0], [0, 0, 4], [0, 0, 8]]),
                             "feature 2 (kind='pole', id=3)"),
    "pole_no_geometry": (lambda d: _set(d, 2, ("geometry",), ...), "missing member 'geometry'"),
    "lane_bad_line_kind": (prop(3, "line_kind", "dotted"), "'line_kind'"),
    "lane_one_position": (geom(3, "coordinates", [[0.0, 0.0, 0.0]]), "at least 2"),
    "lane_closed_string": (prop(4, "closed", "yes"), "feature 4"),
    "lane_negative_width": (prop(3, "width_m", -0.1), "'width_m'"),
    "lane_missing_dash": (prop(3, "dash_m", ...), "missing property 'dash_m'"),
    "centerline_2d": (geom(5, "coordinates", [[0, 0], [1, 1]]), "feature 5"),
    "walkable_open_ring": (geom(6, "coordinates", [[[0, 0], [1, 0], [1, 1], [0, 1]]]), "first position"),
    "walkable_hole": (_two_rings, "one ring"),
    "walkable_no_path": (prop(7, "path", ...), "feature 7 (kind='walkable', id=8)"),
    "walkable_bad_kind": (prop(7, "area_kind", "park"), "'area_kind'"),
    "unknown_kind": (prop(1, "kind", "tree"), "'kind'"),
    "bool_id": (prop(1, "id", True), "boolean"),
    "string_id": (prop(1, "id", "2"), "'id'"),
    "duplicate_id": (prop(2, "id", 1), "already used by feature 0"),
    "not_a_feature": (lambda d: _set(d, 0, ("type",), "Thing"), "feature 0"),
    "no_properties": (lambda d: _set(d, 0, ("properties",), ...), "feature 0"),
    "not_a_collection": (lambda d: {**d, "type": "Feature"}, "FeatureCollection"),
    "wgs84_crs": (header(crs="EPSG:4326"), "crs"),
    "wrong_format": (header(format="other"), "format"),
    "future_version": (header(version=2), "version"),
    "features_not_a_list": (lambda d: {**d, "features": {}}, "features"),
    "top_level_list": (lambda d: [d], "FeatureCollection"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_load_rejects_malformed_files(tmp_path: Path, case: str) -> None:
    mutate, words = MALFORMED[case]
    path = tmp_path / f"{case}.geojson"
    path.write_text(json.dumps(mutate(_doc())))
    with pytest.raises(ValueError) as info:
        load_map(path)
    assert words in str(info.value)
    assert str(path) in str(info.value)


def test_load_rejects_invalid_json(tmp_path: Path) -> None:
    path = tmp_path / "broken.geojson"
    path.write_text('{"type": "FeatureCollection", "features": [')
    with pytest.raises(ValueError, match="not valid JSON"):
        load_map(path)


def test_load_rejects_a_bad_origin(tmp_path: Path) -> None:
    doc = _doc()
    doc["properties"]["origin"] = {"lat_deg": 123.0, "lon_deg": 0.0}
    path = tmp_path / "o.geojson"
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="out of range"):
        load_origin(path)


# ---------------------------------------------------------------------------------- Polyline


SQUARE = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [10.0, 10.0, 0.0], [0.0, 10.0, 0.0]])


def test_polyline_length_and_point_at() -> None:
    open_line = Polyline(SQUARE)
    closed = Polyline(SQUARE, closed=True)
    assert open_line.length == pytest.approx(30.0)
    assert closed.length == pytest.approx(40.0)
    np.testing.assert_allclose(closed.point_at(5.0), [5.0, 0.0, 0.0])
    np.testing.assert_allclose(closed.point_at(35.0), [0.0, 5.0, 0.0])
    np.testing.assert_allclose(closed.point_at(45.0), [5.0, 0.0, 0.0])  # wraps around
    np.testing.assert_allclose(open_line.point_at(45.0), [0.0, 10.0, 0.0])  # clamps at the end
    np.testing.assert_allclose(open_line.point_at(-3.0), [0.0, 0.0, 0.0])
    np.testing.assert_allclose(open_line.point_at([0.0, 15.0]), [[0.0, 0.0, 0.0], [10.0, 5.0, 0.0]])


def test_polyline_closed_drops_a_repeated_first_vertex() -> None:
    line = Polyline(np.vstack([SQUARE, SQUARE[:1]]), closed=True)
    assert len(line.points) == 4 and line.length == pytest.approx(40.0)


def test_polyline_tangent_at() -> None:
    closed = Polyline(SQUARE, closed=True)
    np.testing.assert_allclose(closed.tangent_at(5.0), [1.0, 0.0, 0.0])
    np.testing.assert_allclose(closed.tangent_at(15.0), [0.0, 1.0, 0.0])
    np.testing.assert_allclose(closed.tangent_at(35.0), [0.0, -1.0, 0.0])
    np.testing.assert_allclose(np.linalg.norm(closed.tangent_at(np.linspace(0, 40, 17)), axis=1), 1.0)


def test_polyline_project_is_the_inverse_of_point_at() -> None:
    closed = Polyline(SQUARE, closed=True)
    for s in (0.5, 7.0, 13.0, 27.5, 39.0):
        p = closed.point_at(s)
        assert closed.project(p) == pytest.approx(s)
    assert closed.project([5.0, -2.0, 3.0]) == pytest.approx(5.0)  # off the line, z ignored
    assert Polyline(SQUARE).project([-5.0, -5.0, 0.0]) == pytest.approx(0.0)


def test_polyline_sample_spacing() -> None:
    closed = Polyline(SQUARE, closed=True)
    pts = closed.sample(1.0)
    assert len(pts) == 40
    steps = np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1)
    np.testing.assert_allclose(steps, 1.0)
    open_pts = Polyline(SQUARE).sample(1.0)
    np.testing.assert_allclose(open_pts[[0, -1]], SQUARE[[0, -1]])


def test_polyline_rejects_too_few_points() -> None:
    with pytest.raises(ValueError):
        Polyline(np.zeros((1, 3)))
    with pytest.raises(ValueError):
        Polyline(np.zeros((3, 2)))


def test_dashed_painted_samples_skip_the_gaps() -> None:
    line = LaneLine(1, np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0]]), "dashed", dash_m=3.0, gap_m=6.0)
    x = line.painted_samples(0.5)[:, 0]
    assert np.all(np.mod(x, 9.0) < 3.0)
    assert len(x) == pytest.approx(100 / 9 * 6, abs=6)
    solid = LaneLine(2, line.points, "solid")
    assert len(solid.painted_samples(0.5)) == 200
