"""The scenario's map: section: the generated ring road or a map file (format, path, package, bounds), its errors,
and the presets on networks shipped with SUMO (sumo-intersection, sumo-district) loading and building their world."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from mapcontainer.config import ConfigError
from mapcontainer.hdmap.generator import MapSpec
from mapcontainer.hdmap.io import save_map
from mapcontainer.sim import config as sim_config
from mapcontainer.sim.config import MapFile, load_scenario
from mapcontainer.sim.maps import crop_map, world_map

HAS_ROADS = all(importlib.util.find_spec(m) is not None for m in ("sumolib", "libsumo", "sumo"))
needs_roads = pytest.mark.skipif(not HAS_ROADS, reason="needs the roads extra (sumolib, libsumo, eclipse-sumo)")

RING_ACTORS = "connected: [{lane: 0}]\n"


def _load(tmp_path: Path, body: str, name: str = "s"):
    path = tmp_path / f"{name}.yaml"
    path.write_text(f"name: {name}\n{body}")
    return load_scenario(path)


@pytest.fixture
def geojson(tmp_path) -> Path:
    """A GeoJSON map file (the generated ring road's)."""
    from mapcontainer.hdmap.generator import generate_map

    path = tmp_path / "ring.geojson"
    save_map(generate_map(MapSpec()), path)
    return path


def test_the_generated_ring_road_stays_the_default(tmp_path):
    sc = _load(tmp_path, RING_ACTORS)
    assert sc.map == MapSpec() and sc.map_file is None
    assert load_scenario("paper-urban").map_file is None


@pytest.mark.parametrize(
    ("section", "message"),
    [
        ("{format: shapefile, path: ring.geojson}", r"unknown map format 'shapefile'.*sumo \| lanelet2 \| geojson"),
        ("{format: geojson, path: nowhere.geojson}", r"map file .*nowhere.geojson does not exist"),
        ("{format: geojson}", r"map.path: Field required"),
        ("{format: geojson, path: ring.geojson, bounds: [10, 0, 5, 1]}", "xmin < xmax"),
        ("{format: geojson, path: ring.geojson, origin: [49, 8]}", "origin: is the origin of a Lanelet2 map"),
        ("{format: geojson, path: ring.geojson, landmarks: {seed: 3}}", "place landmarks on a SUMO network"),
        ("{format: geojson, path: x.geojson, package: no_such_package_xyz}", "'no_such_package_xyz' is not installed"),
        ("{length_m: 10}", "length_m"),
    ],
)
def test_bad_map_sections_are_refused_naming_the_problem(tmp_path, geojson, section, message):
    with pytest.raises(ConfigError, match=message):
        _load(tmp_path, f"map: {section}\ntraffic: {{source: sumo, routes: [r.xml], connected: {{first: 1}}}}\n")


def test_a_format_whose_reader_is_not_installed_names_the_extra(tmp_path, monkeypatch):
    (tmp_path / "n.net.xml").write_text("<net/>")
    real = sim_config._installed
    monkeypatch.setattr(sim_config, "_installed", lambda p: p not in ("sumolib", "lanelet2") and real(p))
    for fmt, pkg, file in (("sumo", "sumolib", "n.net.xml"), ("lanelet2", "lanelet2", "n.net.xml")):
        with pytest.raises(ConfigError, match=rf"a {fmt} map needs the Python package '{pkg}'.*\[roads\]"):
            _load(tmp_path, f"map: {{format: {fmt}, path: {file}}}\n" + RING_ACTORS)


def test_a_map_file_needs_sumo_traffic_and_sumo_traffic_a_sumo_map(tmp_path, geojson):
    with pytest.raises(ConfigError, match=r"a geojson map needs traffic: \{source: sumo"):
        _load(tmp_path, "map: {format: geojson, path: ring.geojson}\n" + RING_ACTORS)
    (tmp_path / "r.xml").write_text("<routes/>")
    sumo_traffic = "traffic: {source: sumo, routes: [r.xml], connected: {first: 1}}\n"
    with pytest.raises(ConfigError, match=r"the map is the SUMO network: map: \{format: sumo"):
        _load(tmp_path, sumo_traffic)
    with pytest.raises(ConfigError, match="needs traffic.net"):
        _load(tmp_path, "map: {format: geojson, path: ring.geojson}\n" + sumo_traffic)
    with pytest.raises(ConfigError, match=r"landmarks, pois describe the map: give them in map:"):
        _load(tmp_path, "traffic: {source: sumo, routes: [r.xml], connected: {first: 1}, landmarks: {}, pois: x}\n")


def test_a_geojson_map_file_is_the_world_map_and_bounds_crop_it(tmp_path, geojson):
    whole = world_map(load_scenario("paper-urban"))
    mf = MapFile(format="geojson", path=geojson)
    assert mf.file == geojson
    half = crop_map(whole, (0.0, -100.0, 100.0, 100.0))  # the east half of the ring
    assert 0 < len(half.poles) < len(whole.poles) and all(p.base[0] >= 0 for p in half.poles)
    assert len(half.lane_lines) == len(whole.lane_lines)  # the ring's lines are closed loops: kept whole


# ---------------------------------------------------------------------------------- the shipped presets


@needs_roads
@pytest.mark.parametrize(
    ("preset", "network", "traffic_lights"),
    [
        ("sumo-intersection", "tools/sumolib/scenario/scenarios/RiLSA1/rilsa1.net.xml", 4),
        ("sumo-district", "tools/game/DRT/osm.net.xml", 34),
    ],
)
def test_the_shipped_presets_read_their_network_from_the_installed_sumo_package(preset, network, traffic_lights):
    import sumo

    sc = load_scenario(preset)
    assert sc.map_file.package == "sumo" and sc.map_file.file == Path(sumo.__file__).parent / network
    assert sc.sumo.net == sc.map_file.file and sc.n_connected == 4
    hd = world_map(sc)
    assert hd.feature_counts()["traffic_light"] == traffic_lights
    if sc.map_file.bounds is not None:  # every landmark of the district's part lies in its bounds
        x0, y0, x1, y1 = sc.map_file.bounds
        assert all(x0 <= p.base[0] <= x1 and y0 <= p.base[1] <= y1 for p in hd.poles)


@needs_roads
@pytest.mark.parametrize("preset", ["sumo-intersection", "sumo-district"])
def test_the_presets_build_their_world_with_sumo_traffic(preset):
    from mapcontainer.sim import World

    with World(load_scenario(preset), seed=1) as world:
        assert world.vehicle_ids == ["cv0", "cv1", "cv2", "cv3"]
        states = world.states(0.0)
        classes = [s.cls.name for s in states.values()]
        assert classes.count("VEHICLE") > 20 and classes.count("PEDESTRIAN") > 3  # the streets carry traffic
        tick = next(iter(world.run(0.2)))
        assert set(tick.frames) == set(world.vehicle_ids)


def test_a_yaml_error_names_the_field_as_the_file_spells_it(tmp_path) -> None:
    """pydantic puts the union member's tag in the location (map.procedural.lenght_m); the file says map.lenght_m."""
    from mapcontainer.config import ConfigError
    from mapcontainer.sim.config import load_scenario

    bad = tmp_path / "mine.yaml"
    bad.write_text("name: mine\nmap:\n  lenght_m: 300\n")
    with pytest.raises(ConfigError) as exc:
        load_scenario(str(bad))
    assert str(exc.value).splitlines()[1:] == ["  map.lenght_m: Extra inputs are not permitted"]
    bad.write_text("name: mine\nmap: {format: sumo, path: x.net.xml, bogus: 1}\n")
    with pytest.raises(ConfigError) as exc:
        load_scenario(str(bad))
    assert "  map.bogus: Extra inputs are not permitted" in str(exc.value).splitlines()


def test_path_in_file_keeps_list_indices_and_missing_fields() -> None:
    from mapcontainer.config import path_in_file

    data = {"faults": [{"kind": "pose_bias"}], "map": {"format": "sumo"}}
    assert path_in_file(("faults", 0, "pose_bias", "vehicle"), data) == ("faults", 0, "vehicle")
    assert path_in_file(("map", "file", "path"), data) == ("map", "path")
    assert path_in_file(("name",), data) == ("name",)
