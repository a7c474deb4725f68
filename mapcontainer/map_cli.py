"""``mapc map import|show|export``: HD maps on the command line (thin adapters around :mod:`.hdmap`)."""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import time
from pathlib import Path

from . import jsonout
from .cliargs import bounded, non_negative_int, origin_arg, output_dir, output_file
from .config import ConfigError

__all__ = ["add_map_commands", "around_arg", "bounds_arg"]

metres = bounded(float, 0, strict=True, unit=" m")


def map_name(text: str) -> str:
    """A file name stem: letters, digits, '.', '_' or '-' (no directory)."""
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}", text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a map name (letters, digits, '.', '_' or '-')")
    return text


def _import_args(args: argparse.Namespace):
    """The reader's options from the command line; ConfigError for options that do not fit the format."""
    from .hdmap.formats import detect_format
    from .hdmap.sumo import PlacementRule

    fmt = detect_format(Path(args.file)) if args.format == "auto" else args.format
    if args.additional is not None and fmt != "sumo":
        raise ConfigError(f"--additional (SUMO POIs) needs a SUMO network, {args.file} is read as {fmt}")
    for flag, value in (("--origin", args.origin), ("--projector", args.projector)):
        if value is not None and fmt != "lanelet2":
            raise ConfigError(f"{flag} is for Lanelet2 maps, {args.file} is read as {fmt}")
    return fmt, PlacementRule(seed=args.seed)


def _read_map(args: argparse.Namespace):
    from .hdmap.formats import read_any_map

    fmt, rule = _import_args(args)
    return read_any_map(args.file, fmt, rule, args.additional, args.origin, args.projector or "local")


def _cmd_map_import(args: argparse.Namespace) -> int:
    from .hdmap.io import save_map
    from .sim.render import render_map

    t0 = time.perf_counter()
    imported = _read_map(args)
    import_s = time.perf_counter() - t0
    if args.name is not None:  # the map is called what its files are
        imported.hdmap = dataclasses.replace(imported.hdmap, name=args.name)
    name = imported.hdmap.name
    geojson, png = args.out / f"{name}.geojson", args.out / f"{name}.png"
    taken = [p.name for p in (geojson, png) if p.exists()]
    if taken and not args.force:  # SUMO's networks are all osm.net.xml: one import must not overwrite another
        raise ConfigError(
            f"{args.out} already holds {' and '.join(taken)}: give the map another --name, or --force to overwrite"
        )
    args.out.mkdir(parents=True, exist_ok=True)
    save_map(imported.hdmap, geojson, imported.origin)
    render_map(png, imported.hdmap, f"{name} ({imported.source.split(':', 1)[0]})")
    doc = {**imported.summary(), "import_s": round(import_s, 3), "geojson": str(geojson), "png": str(png)}
    print(jsonout.dumps(doc))
    return 0


def bounds_arg(text: str) -> tuple[float, float, float, float]:
    """``X0,Y0,X1,Y1``: a rectangle of the map frame (m), X0 < X1 and Y0 < Y1."""
    try:
        v = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"not X0,Y0,X1,Y1: {text!r}") from None
    if len(v) != 4 or not all(math.isfinite(x) for x in v):
        raise argparse.ArgumentTypeError(f"not X0,Y0,X1,Y1: {text!r}")
    if not (v[0] < v[2] and v[1] < v[3]):
        raise argparse.ArgumentTypeError(f"need X0 < X1 and Y0 < Y1, got {text!r}")
    return v  # type: ignore[return-value]


def around_arg(text: str) -> str | tuple[float, float]:
    """``X,Y`` (a point of the map frame, m) or a vehicle id (resolved against --scenario)."""
    if "," in text:
        try:
            x, y = (float(v) for v in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"not X,Y or a vehicle id: {text!r}") from None
        if not (math.isfinite(x) and math.isfinite(y)):
            raise argparse.ArgumentTypeError(f"not X,Y: {text!r}")
        return (x, y)
    return text


def _view_bounds(args: argparse.Namespace, scenario) -> tuple[tuple[float, float, float, float] | None, dict]:
    """The rectangle to draw (None: the whole map) and where it came from, for the JSON line."""
    if args.bounds is not None:
        return args.bounds, {"bounds": list(args.bounds)}
    if args.around is None:
        if args.radius is not None:
            raise ConfigError("--radius goes with --around VEHICLE|X,Y")
        return None, {}
    radius = 50.0 if args.radius is None else args.radius
    center, about = args.around, {}
    if isinstance(center, str):
        if scenario is None:
            raise ConfigError(
                f"--around {center}: a vehicle needs --scenario (a map file has no vehicles); or give X,Y"
            )
        from .sim.world import World

        with World(scenario, seed=args.seed, fleet="map") as world:
            if center not in world.vehicle_ids:
                raise ConfigError(
                    f"--around {center}: no such vehicle; {scenario.name} has {', '.join(world.vehicle_ids)}"
                )
            p = world.states(0.0)[center].p_map
        about = {"vehicle": center}
        center = (float(p[0]), float(p[1]))
    x, y = center
    return (x - radius, y - radius, x + radius, y + radius), {**about, "around": [x, y], "radius_m": radius}


def _cmd_map_show(args: argparse.Namespace) -> int:
    from .hdmap.imported import ImportedMap
    from .sim.render import render_map

    scenario = None
    if args.scenario is not None:
        if args.file is not None:
            raise ConfigError("give a map FILE or --scenario, not both")
        from .sim.config import load_scenario
        from .sim.maps import world_map

        scenario = load_scenario(args.scenario)
        imported = ImportedMap(world_map(scenario), source=f"scenario:{scenario.name}")
    elif args.file is None:
        raise ConfigError("give a map FILE or --scenario S")
    else:
        imported = _read_map(args)
    bounds, view = _view_bounds(args, scenario)
    png = args.out if args.out is not None else Path.cwd() / f"{imported.hdmap.name}.png"
    png.parent.mkdir(parents=True, exist_ok=True)
    marks = {view["vehicle"]: view["around"]} if "vehicle" in view else {}
    render_map(png, imported.hdmap, f"{imported.hdmap.name} ({imported.source.split(':', 1)[0]})", bounds, marks)
    print(jsonout.dumps({**imported.summary(), **view, "png": str(png)}))
    return 0


def _cmd_map_export(args: argparse.Namespace) -> int:
    from .hdmap.io import MapOrigin, save_map

    if args.scenario is not None:
        from .sim.config import load_scenario
        from .sim.maps import world_map

        hdmap, origin = world_map(load_scenario(args.scenario)), None
    else:
        from .hdmap.formats import read_any_map

        imported = read_any_map(args.map)
        hdmap, origin = imported.hdmap, imported.origin
    origin = args.origin or origin
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.format == "geojson":
        print(jsonout.dumps({"out": str(save_map(hdmap, args.out, origin)), "features": hdmap.feature_counts()}))
        return 0
    from .hdmap.lanelet import export_lanelet2

    doc = export_lanelet2(hdmap, args.out, origin if isinstance(origin, MapOrigin) else None, args.projector)
    print(jsonout.dumps(doc))
    return 0


MAP_FORMATS = ("geojson", "sumo", "lanelet2")  # mapcontainer.hdmap.formats.FORMATS, not imported to build the parser


def _add_map_reader_args(p: argparse.ArgumentParser, file_nargs: str | None = None) -> None:
    p.add_argument(
        "file",
        nargs=file_nargs,
        default=None,
        help="a map: our GeoJSON, a SUMO network (.net.xml, .net.xml.gz) or a Lanelet2 .osm file",
    )
    p.add_argument("--format", choices=("auto", *MAP_FORMATS), default="auto", help="default: from the name or content")
    p.add_argument(
        "--seed", type=non_negative_int, default=0, help="SUMO: seed of the lamp and sign placement rule (default 0)"
    )
    p.add_argument(
        "--additional",
        default=None,
        help="SUMO: an additional file whose POIs give lamps, traffic lights and signs (replacing the rule's)",
    )
    p.add_argument(
        "--origin",
        type=origin_arg,
        default=None,
        help="Lanelet2: LAT,LON[,ALT] of the map origin (default: the file's first node)",
    )
    p.add_argument(
        "--projector",
        choices=("local", "utm"),
        default=None,
        help="Lanelet2: local east-north-up at the origin (default) or UTM minus the origin's UTM position",
    )


def add_map_commands(sub) -> None:
    """``map import``, ``map show`` and ``map export`` on the ``mapc`` subcommands."""
    mp = sub.add_parser(
        "map", help="HD maps: import SUMO and Lanelet2 maps, draw any map, export a scenario's map"
    ).add_subparsers(dest="sub", required=True)
    mi = mp.add_parser(
        "import",
        help="read a SUMO network or Lanelet2 map (the roads extra) or our GeoJSON; write NAME.geojson and NAME.png",
    )
    _add_map_reader_args(mi)
    mi.add_argument("--out", required=True, type=output_dir, help="output directory")
    mi.add_argument("--name", type=map_name, default=None, help="NAME of the files written (default: the map's own)")
    mi.add_argument("--force", action="store_true", help="overwrite NAME.geojson and NAME.png if they exist")
    mi.set_defaults(func=_cmd_map_import)
    ms = mp.add_parser("show", help="draw any supported map (or a scenario's) as a PNG, whole or a part of it")
    _add_map_reader_args(ms, file_nargs="?")
    ms.add_argument("--scenario", default=None, help="draw this scenario's map instead of a FILE")
    ms.add_argument("--out", type=output_file, default=None, help="the PNG (default: ./NAME.png)")
    view = ms.add_mutually_exclusive_group()
    view.add_argument("--bounds", type=bounds_arg, default=None, help="X0,Y0,X1,Y1: draw this rectangle (map frame, m)")
    view.add_argument(
        "--around", type=around_arg, default=None, help="VEHICLE (at its start, with --scenario) or X,Y: the centre"
    )
    ms.add_argument("--radius", type=metres, default=None, help="half the side drawn --around (m, default 50)")
    ms.set_defaults(func=_cmd_map_show)
    me = mp.add_parser("export", help="write a scenario's map (or any supported map) as Lanelet2 OSM or our GeoJSON")
    src = me.add_mutually_exclusive_group(required=True)
    src.add_argument("--scenario", default=None, help="a scenario preset (mapc scenario list) or YAML file")
    src.add_argument("--map", default=None, help="a map file of any supported format")
    me.add_argument("--format", choices=("lanelet2", "geojson"), required=True)
    me.add_argument("--out", required=True, type=output_file, help="the file to write")
    me.add_argument(
        "--origin",
        type=origin_arg,
        default=None,
        help="LAT,LON[,ALT] of the map origin (default: the map's own, else 49.0,8.4 for Lanelet2)",
    )
    me.add_argument("--projector", choices=("local", "utm"), default="local", help="Lanelet2 projector")
    me.set_defaults(func=_cmd_map_export)
