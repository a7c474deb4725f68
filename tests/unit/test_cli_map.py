"""``mapc map import|show|export``: files written, JSON printed, and one-line errors with exit 2."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from mapcontainer.cli import main
from mapcontainer.hdmap.io import load_map

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _run(capsys, *argv: str) -> tuple[int, dict | None, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    lines = out.strip().splitlines()
    return code, json.loads(lines[-1]) if lines else None, err


def _rilsa() -> Path:
    sumolib = pytest.importorskip("sumolib")  # the roads extra; CI installs it
    return Path(sumolib.__file__).parent / "scenario/scenarios/RiLSA1/rilsa1.net.xml"


def test_import_a_sumo_network(capsys, tmp_path) -> None:
    code, doc, err = _run(capsys, "map", "import", str(_rilsa()), "--out", str(tmp_path), "--seed", "2")
    assert code == 0, err
    assert doc["centerlines"] == 16 and doc["junctions"] == 5
    assert doc["landmarks"]["traffic_light"] == 4 and doc["walkable"]["crossing"] == 4
    assert Path(doc["png"]).read_bytes()[:8] == PNG_MAGIC
    hd = load_map(doc["geojson"])
    assert len(hd.lane_lines) == doc["lane_lines"]["solid"] + doc["lane_lines"]["dashed"]
    assert hd.feature_counts() == doc["landmarks"]


def test_export_a_scenario_then_show_and_import_it(capsys, tmp_path) -> None:
    pytest.importorskip("lanelet2")
    osm = tmp_path / "urban.osm"
    code, doc, err = _run(
        capsys, "map", "export", "--scenario", "paper-urban", "--format", "lanelet2", "--out", str(osm)
    )
    assert code == 0, err
    assert doc["origin"] == {"lat_deg": 49.0, "lon_deg": 8.4, "alt_m": 0.0} and osm.stat().st_size > 0
    png = tmp_path / "pic" / "urban.png"
    code, doc, err = _run(capsys, "map", "show", str(osm), "--origin", "49.0,8.4", "--out", str(png))
    assert code == 0, err
    assert png.read_bytes()[:8] == PNG_MAGIC
    assert doc["landmarks"] == {"lamp": 14, "traffic_light": 4, "sign": 4}
    code, doc, err = _run(capsys, "map", "import", str(osm), "--origin", "49.0,8.4", "--out", str(tmp_path / "imp"))
    assert code == 0, err
    assert load_map(doc["geojson"]).feature_counts() == {"lamp": 14, "traffic_light": 4, "sign": 4}


def test_export_geojson_and_convert_sumo_to_lanelet2(capsys, tmp_path, monkeypatch) -> None:
    out = tmp_path / "urban.geojson"
    code, doc, err = _run(
        capsys, "map", "export", "--scenario", "paper-urban", "--format", "geojson", "--out", str(out)
    )
    assert code == 0, err
    assert load_map(out).feature_counts() == doc["features"] == {"lamp": 14, "traffic_light": 4, "sign": 4}
    code, doc, err = _run(capsys, "map", "show", str(out), "--out", str(tmp_path / "u.png"))
    assert code == 0 and (tmp_path / "u.png").read_bytes()[:8] == PNG_MAGIC
    monkeypatch.chdir(tmp_path)
    code, doc, err = _run(capsys, "map", "show", str(out))  # default: NAME.png in the working directory
    png = tmp_path / f"{doc['name']}.png"
    assert code == 0 and Path(doc["png"]) == png and png.read_bytes()[:8] == PNG_MAGIC
    pytest.importorskip("lanelet2")
    osm = tmp_path / "rilsa.osm"
    code, doc, err = _run(capsys, "map", "export", "--map", str(_rilsa()), "--format", "lanelet2", "--out", str(osm))
    assert code == 0, err
    assert doc["lanelets"] == 16 and doc["lanelet_bounds_painted"] == 32


def test_unreadable_map_exits_2_with_one_line(capsys, tmp_path) -> None:
    bad = tmp_path / "broken.net.xml"
    bad.write_text("<net><edge")
    code, doc, err = _run(capsys, "map", "import", str(bad), "--out", str(tmp_path / "o"))
    assert code == 2 and doc is None and err.count("\n") == 1
    if importlib.util.find_spec("sumolib") is None:  # without the roads extra: one line naming it
        assert err.startswith("mapc: missing optional dependency: ") and "roads" in err
    else:
        assert err.startswith("mapc: cannot read the map: ") and str(bad) in err
    code, _, err = _run(capsys, "map", "show", str(tmp_path / "nothing.osm"))
    assert code == 2 and "no such file" in err
    what = tmp_path / "what.txt"
    what.write_text("hello")
    code, _, err = _run(capsys, "map", "show", str(what))
    assert code == 2 and "not a map this tool reads" in err


def test_the_parser_knows_every_format() -> None:
    from mapcontainer.hdmap.formats import FORMATS
    from mapcontainer.map_cli import MAP_FORMATS

    assert MAP_FORMATS == FORMATS


def test_options_that_do_not_fit_the_format_exit_2(capsys, tmp_path) -> None:
    osm = tmp_path / "m.osm"
    osm.write_text('<osm version="0.6"/>')
    code, _, err = _run(capsys, "map", "import", str(osm), "--additional", "pois.xml", "--out", str(tmp_path))
    assert code == 2 and "--additional" in err
    code, _, err = _run(capsys, "map", "show", str(_rilsa()), "--origin", "49,8")
    assert code == 2 and "--origin is for Lanelet2 maps" in err


def test_missing_extra_exits_2_naming_it(capsys, monkeypatch, tmp_path) -> None:
    net = _rilsa()
    monkeypatch.setitem(sys.modules, "sumolib", None)
    code, _, err = _run(capsys, "map", "import", str(net), "--out", str(tmp_path))
    assert code == 2 and "mapc: missing optional dependency" in err and "map-container[roads]" in err


# ------------------------------------------------------------------------------ names, views, scale


def _urban_geojson(capsys, tmp_path) -> Path:
    out = tmp_path / "src" / "urban.geojson"
    code, _, err = _run(capsys, "map", "export", "--scenario", "paper-urban", "--format", "geojson", "--out", str(out))
    assert code == 0, err
    return out


def test_import_refuses_to_overwrite_without_force_and_takes_a_name(capsys, tmp_path) -> None:
    src, maps = _urban_geojson(capsys, tmp_path), tmp_path / "maps"
    code, doc, err = _run(capsys, "map", "import", str(src), "--out", str(maps))
    assert code == 0, err
    first = Path(doc["geojson"]).read_bytes()
    code, doc, err = _run(capsys, "map", "import", str(src), "--out", str(maps), "--seed", "3")
    assert code == 2 and doc is None
    assert err.strip().splitlines() == [
        f"mapc: configuration error: {maps} already holds urban.geojson and urban.png: "
        "give the map another --name, or --force to overwrite"
    ]
    assert (maps / "urban.geojson").read_bytes() == first  # untouched
    code, doc, err = _run(capsys, "map", "import", str(src), "--out", str(maps), "--name", "ring-b")
    assert code == 0, err
    assert doc["name"] == "ring-b" and Path(doc["geojson"]).name == "ring-b.geojson"
    assert Path(doc["png"]).read_bytes()[:8] == PNG_MAGIC and load_map(doc["geojson"]).name == "ring-b"
    code, doc, err = _run(capsys, "map", "import", str(src), "--out", str(maps), "--force")
    assert code == 0, err
    with pytest.raises(SystemExit):
        main(["map", "import", str(src), "--out", str(maps), "--name", "../up"])
    assert "not a map name" in capsys.readouterr().err


def test_show_a_rectangle_or_around_a_point_or_a_vehicle(capsys, tmp_path) -> None:
    src = _urban_geojson(capsys, tmp_path)
    png = tmp_path / "b.png"
    code, doc, err = _run(capsys, "map", "show", str(src), "--bounds=-20,-40,30,10", "--out", str(png))
    assert code == 0, err
    assert doc["bounds"] == [-20.0, -40.0, 30.0, 10.0] and png.read_bytes()[:8] == PNG_MAGIC
    code, doc, err = _run(capsys, "map", "show", str(src), "--around", "10,5", "--radius", "25", "--out", str(png))
    assert code == 0, err
    assert doc["around"] == [10.0, 5.0] and doc["radius_m"] == 25.0
    code, doc, err = _run(capsys, "map", "show", "--scenario", "paper-urban", "--around", "cv1", "--out", str(png))
    assert code == 0, err
    assert doc["vehicle"] == "cv1" and doc["radius_m"] == 50.0 and len(doc["around"]) == 2
    for argv, says in (
        (["map", "show", str(src), "--around", "cv1"], "a vehicle needs --scenario"),
        (["map", "show", "--scenario", "paper-urban", "--around", "cv9"], "no such vehicle"),
        (["map", "show", str(src), "--radius", "5"], "--radius goes with --around"),
        (["map", "show"], "give a map FILE or --scenario S"),
    ):
        code, _, err = _run(capsys, *argv, "--out", str(png))
        assert code == 2 and says in err, (argv, err)
    for bad in ("1,2,3", "5,0,1,10", "a,b,c,d"):
        with pytest.raises(SystemExit):
            main(["map", "show", str(src), "--bounds", bad])
        assert "--bounds" in capsys.readouterr().err


def test_landmarks_are_no_bigger_than_lane_lines_at_city_scale() -> None:
    from mapcontainer.sim.render import map_mark_sizes

    for m_per_pt in (1.0, 1.5, 3.0, 10.0):  # a district or a city on one page
        landmark, lane = map_mark_sizes(m_per_pt)
        assert landmark <= lane, m_per_pt
    landmark, lane = map_mark_sizes(0.1)  # a crossing: landmarks big enough to tell apart
    assert landmark == 5.0 and lane == 1.5
    with pytest.raises(ValueError, match="m_per_pt"):
        map_mark_sizes(0.0)
