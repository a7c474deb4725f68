"""Write district.rou.xml: the demand of the sumo-district scenario on eclipse-sumo's Berlin network (tools/game/DRT).

Run from this directory with the roads extra installed: ``python make_routes.py`` (README.md says what and why).
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import numpy as np
import sumo
import sumolib

NET = Path(sumo.SUMO_HOME) / "tools/game/DRT/osm.net.xml"
BOUNDS = (1350.0, 600.0, 2200.0, 1300.0)  # xmin, ymin, xmax, ymax: the scenario's map.bounds
SEED = 1
ARTERIAL_VPH = 600  # each direction of the signalled arterial, through the whole box
OD_FLOWS, OD_VPH = 40, 30  # origin-destination flows between the box's streets, each this many veh/h
CAV = 8  # connected vehicles (type cav), departing at random from 60 s on
PED_FLOWS, PED_PH = 40, 30  # pedestrian flows between sidewalks in the box, each this many persons/h


def inside(shape) -> bool:
    xy = np.asarray(shape)
    x0, y0, x1, y1 = BOUNDS
    return bool(np.all((xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)))


def routable(net, src, dst, vclass: str = "passenger") -> bool:
    """A path from edge src to edge dst for this vehicle class in sumolib's view (pedestrians: either direction)."""
    walk = vclass == "pedestrian"
    return net.getShortestPath(src, dst, vClass=vclass, ignoreDirection=walk)[0] is not None


def unroutable(routes: Path) -> set[str]:
    """Flows SUMO itself finds no route for (sumolib's graph misses some of this network's connection rules): a
    400 s run that ignores route errors, its warnings read."""
    proc = subprocess.run(
        [str(Path(sumo.SUMO_HOME) / "bin/sumo"), "-n", str(NET), "-r", str(routes), "--end", "400",
         "--ignore-route-errors", "--no-step-log", "--seed", "1"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    return set(re.findall(r"No route for (?:vehicle|person) '([^']+)\.\d+'", proc.stderr))


def main() -> None:
    net = sumolib.net.readNet(str(NET), withPedestrianConnections=True)
    rng = np.random.default_rng(SEED)
    roads = [e for e in net.getEdges() if e.allows("passenger") and inside(e.getShape()) and e.getLength() > 20]
    walks = [e for e in net.getEdges() if e.allows("pedestrian") and inside(e.getShape()) and e.getLength() > 20]
    # the arterial: the fastest multi-lane edges; its two ends in the box are the most distant pair of them
    art = [e for e in roads if e.getLaneNumber() >= 2 and e.getSpeed() >= 13.0]
    pts = np.array([e.getShape()[0] for e in art])
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    i, j = np.unravel_index(np.argmax(d), d.shape)
    ends = {}
    for k in (i, j):  # an edge leaving each end into the box and one arriving there
        here = pts[k]
        near = sorted(art, key=lambda e, h=here: np.linalg.norm(np.asarray(e.getShape()[0]) - h))
        ends[k] = near[:4]
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        "<!-- Demand of the sumo-district scenario (made by make_routes.py beside this file, see README.md). -->",
        "<routes>",
        '    <vType id="passenger" vClass="passenger"/>',
        '    <vType id="cav" vClass="passenger" color="0,0.6,1"/>',
        '    <vType id="ped" vClass="pedestrian"/>',
    ]
    n = 0
    for a, b in ((i, j), (j, i)):
        for src in ends[a]:
            for dst in ends[b]:
                if not routable(net, src, dst):
                    continue
                lines.append(
                    f'    <flow id="art{n}" type="passenger" begin="0" end="3600"'
                    f' probability="{ARTERIAL_VPH / 4 / 3600:.5f}"'
                    f' from="{src.getID()}" to="{dst.getID()}" departLane="best" departSpeed="max"/>'
                )
                n += 1
                break
    made = 0
    while made < OD_FLOWS:
        src, dst = roads[rng.integers(len(roads))], roads[rng.integers(len(roads))]
        if src is dst or not routable(net, src, dst):
            continue
        lines.append(
            f'    <flow id="od{made}" type="passenger" begin="0" end="3600" probability="{OD_VPH / 3600:.5f}"'
            f' from="{src.getID()}" to="{dst.getID()}" departLane="best" departSpeed="max"/>'
        )
        made += 1
    made = 0
    while made < PED_FLOWS:
        src, dst = walks[rng.integers(len(walks))], walks[rng.integers(len(walks))]
        if src is dst or not routable(net, src, dst, "pedestrian"):
            continue
        lines.append(
            f'    <personFlow id="ped{made}" type="ped" begin="0" end="3600" probability="{PED_PH / 3600:.5f}"'
            f' departPos="random"><walk from="{src.getID()}" to="{dst.getID()}" arrivalPos="random"/></personFlow>'
        )
        made += 1
    made = 0
    while made < 2 * CAV:  # twice as many: the first CAV that SUMO can route are kept
        src, dst = roads[rng.integers(len(roads))], roads[rng.integers(len(roads))]
        path = net.getShortestPath(src, dst, vClass="passenger")[0]
        if src is dst or path is None or sum(e.getLength() for e in path) < 800:
            continue
        lines.append(
            f'    <flow id="cav{made}" type="cav" begin="60" probability="0.1" number="1"'
            f' from="{src.getID()}" to="{dst.getID()}" departLane="best" departSpeed="max"/>'
        )
        made += 1
    lines.append("</routes>")
    out = Path("district.rou.xml")
    out.write_text("\n".join(lines) + "\n")
    bad = unroutable(out)
    lines = [ln for ln in lines if not any(f'id="{b}"' in ln for b in bad)]
    cav = [ln for ln in lines if 'type="cav"' in ln]
    lines = [ln for ln in lines if ln not in cav[CAV:]]
    out.write_text("\n".join(lines) + "\n")
    print(f"left out flows SUMO finds no route for: {sorted(bad)}")
    print(f"{len(roads)} road and {len(walks)} sidewalk edges in the box; wrote district.rou.xml")


if __name__ == "__main__":
    main()
