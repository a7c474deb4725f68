"""Write rilsa1.rou.xml: the demand of the sumo-intersection scenario on sumolib's RiLSA1 crossroads.

Run from this directory: ``python make_routes.py`` (no dependencies; README.md says what and why).
"""

from __future__ import annotations

from pathlib import Path

# The RiLSA example 1 demand, as sumolib ships it (sumolib/scenario/scenarios/rilsa1.py, flowsRiLSA1): per
# approach, (leaving edge, vehicles per hour, heavy vehicles in %).
FLOWS = {
    "nmp": [("ms", 359, 9), ("me", 59, 9), ("mw", 64, 12)],
    "wmp": [("me", 508, 10), ("mn", 80, 14), ("ms", 130, 2)],
    "emp": [("mw", 571, 10), ("mn", 57, 9), ("ms", 47, 3)],
    "smp": [("mn", 354, 2), ("me", 49, 2), ("mw", 92, 2)],
}
# Connected vehicles: one straight and one turning from each approach, departing 80-87 s (SUMO runs 90 s before
# t = 0): the arms end at the network's fringe, so they must be near the junction, not past it, at t = 0.
CAV = [("wmp", "me"), ("emp", "mw"), ("nmp", "ms"), ("smp", "mn"), ("wmp", "ms"), ("emp", "mn"), ("nmp", "me"),
       ("smp", "mw")]  # fmt: skip
ARMS = ["wm", "sm", "em", "nm"]  # the approach edges next to the junction (87 m, with sidewalks)
PED_PH = 100  # persons per hour per pedestrian flow


def main() -> None:
    out = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        "<!-- Demand on sumolib's RiLSA1 crossroads (made by make_routes.py beside this file, see README.md). -->",
        "<routes>",
        '    <vType id="passenger" vClass="passenger"/>',
        '    <vType id="hdv" vClass="truck" length="12.0" width="2.5" height="3.5"/>',
        '    <vType id="cav" vClass="passenger" color="0,0.6,1"/>',
        '    <vType id="ped" vClass="pedestrian"/>',
    ]
    for src, rels in FLOWS.items():
        for dst, vph, hdv in rels:
            for vtype, share in (("passenger", 1 - hdv / 100), ("hdv", hdv / 100)):
                out.append(
                    f'    <flow id="{src}_{dst}_{vtype}" type="{vtype}" begin="0" end="3600"'
                    f' probability="{vph * share / 3600:.5f}" from="{src}" to="{dst}" departLane="best"'
                    ' departSpeed="max"/>'
                )
    for i, a in enumerate(ARMS):  # around the corner and along the road, each way
        for b in (ARMS[(i + 1) % 4], ARMS[(i + 2) % 4]):
            out.append(
                f'    <personFlow id="ped_{a}_{b}" type="ped" begin="0" end="3600" probability="{PED_PH / 3600:.5f}"'
                f' departPos="random"><walk from="{a}" to="{b}" arrivalPos="random"/></personFlow>'
            )
    for k, (src, dst) in enumerate(CAV):
        out.append(
            f'    <trip id="cav_{src}_{dst}" type="cav" depart="{80 + k}" from="{src}" to="{dst}" departLane="best"'
            ' departSpeed="max"/>'
        )
    out.append("</routes>")
    Path("rilsa1.rou.xml").write_text("\n".join(out) + "\n")


if __name__ == "__main__":
    main()
