"""Traffic from SUMO (mapcontainer.sim.sumo): SUMO's angle and front-bumper position to our pose, the choice of
connected vehicles, determinism per seed (also when two Worlds share libsumo), the scenario section's errors,
and the sumo-grid preset through the World. Networks: a straight road netconvert builds here, and the grid
the preset ships."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

libsumo = pytest.importorskip("libsumo")  # the roads extra; CI installs it (.ci/run), so these run there
sumo = pytest.importorskip("sumo")

from mapcontainer.config import ConfigError  # noqa: E402
from mapcontainer.hdmap.errors import MissingExtraError  # noqa: E402
from mapcontainer.sim import World, load_scenario, with_error_sources, with_traffic  # noqa: E402
from mapcontainer.sim.config import scale_scenario  # noqa: E402
from mapcontainer.sim.sumo import KEEP_STEPS, FrontTrail, SumoTrafficError, sumo_pose, sumo_yaw  # noqa: E402
from schemas import ObjectClass  # noqa: E402

NODES = """<nodes>
  <node id="W" x="0" y="0" type="priority"/>
  <node id="E" x="300" y="0" type="priority"/>
</nodes>"""
EDGES = """<edges>
  <edge id="WE" from="W" to="E" numLanes="1" speed="13.0"/>
  <edge id="EW" from="E" to="W" numLanes="1" speed="13.0"/>
</edges>"""
# Sorted by departure, as SUMO wants; "cav" vehicles are 10 m long so that front and centre are far apart.
ROUTES = """<routes>
  <vType id="car" length="5" width="1.8" height="1.5" vClass="passenger"/>
  <vType id="cav" length="10" width="2.0" height="1.6" vClass="passenger"/>
  <vehicle id="a" type="car" depart="0" departPos="20" departSpeed="0"><route edges="WE"/></vehicle>
  <vehicle id="b" type="cav" depart="1" departPos="60" departSpeed="0"><route edges="WE"/></vehicle>
  <vehicle id="c" type="car" depart="2" departPos="50" departSpeed="0"><route edges="EW"/></vehicle>
  <vehicle id="d" type="cav" depart="3" departPos="80" departSpeed="0"><route edges="EW"/></vehicle>
</routes>"""


@pytest.fixture(scope="module")
def road(tmp_path_factory) -> Path:
    """A directory with a straight two-way road (300 m, one lane each way) and the route file above."""
    d = tmp_path_factory.mktemp("road")
    (d / "n.nod.xml").write_text(NODES)
    (d / "e.edg.xml").write_text(EDGES)
    (d / "r.rou.xml").write_text(ROUTES)
    netconvert = Path(sumo.SUMO_HOME) / "bin" / "netconvert"
    subprocess.run(
        [str(netconvert), "-n", "n.nod.xml", "-e", "e.edg.xml", "--no-turnarounds", "-o", "road.net.xml"],
        cwd=d, check=True, capture_output=True, timeout=60,
    )  # fmt: skip
    return d


def _scenario(d: Path, traffic: str, name: str = "road", extra: str = "", net: str = "road.net.xml"):
    """A scenario file in ``d`` on the SUMO network ``net`` with this traffic section (YAML flow mapping), loaded."""
    path = d / f"{name}.yaml"
    path.write_text(f"name: {name}\nduration_s: 5\nmap: {{format: sumo, path: {net}}}\n{extra}traffic: {traffic}\n")
    return load_scenario(path)


def _road(road: Path, connected: str = "{ids: [b]}", more: str = ""):
    return _scenario(road, f"{{source: sumo, routes: [r.rou.xml], connected: {connected}, warmup_s: 0{more}}}")


# ------------------------------------------------------------------------------------------ conversion


def test_sumo_angle_is_clockwise_from_north_and_our_yaw_counter_clockwise_from_east():
    angles_deg = [90.0, 0.0, 180.0, 45.0, 315.0, 360.0]
    yaws = [0.0, np.pi / 2, -np.pi / 2, np.pi / 4, 3 * np.pi / 4, np.pi / 2]
    np.testing.assert_allclose(sumo_yaw(angles_deg), yaws, atol=1e-12)
    assert sumo_yaw(270.0) == pytest.approx(np.pi)  # west: the wrap is (-pi, pi]
    # the front is half a length ahead of the footprint centre, along the heading
    x, y, yaw = sumo_pose(10.0, 5.0, 90.0, 4.0)  # driving east
    assert (x, y, yaw) == pytest.approx((8.0, 5.0, 0.0))
    x, y, yaw = sumo_pose(10.0, 5.0, 0.0, 4.0)  # driving north
    assert (x, y, yaw) == pytest.approx((10.0, 3.0, np.pi / 2))


def test_the_body_follows_the_path_its_front_drove():
    length = 4.0
    trail = FrontTrail((0.0, 0.0), 0.0, length)  # new: straight behind the front
    assert trail.pose() == pytest.approx((-2.0, 0.0, 0.0))
    for x in np.arange(0.5, 10.01, 0.5):  # east along y = 0
        trail.add((x, 0.0))
    assert trail.pose() == pytest.approx((8.0, 0.0, 0.0))
    # a left quarter circle of radius 10 m about (10, 10): the front turns, the rear still on the straight
    for a in np.linspace(0.0, np.pi / 2, 60)[1:]:
        trail.add((10.0 + 10.0 * np.sin(a), 10.0 - 10.0 * np.cos(a)))
    x, y, yaw = trail.pose()
    # front at (20, 10) heading north; the rear 4 m back along the arc (0.4 rad): the chord's direction
    rear = np.array([10.0 + 10.0 * np.sin(np.pi / 2 - 0.4), 10.0 - 10.0 * np.cos(np.pi / 2 - 0.4)])
    chord = np.array([20.0, 10.0]) - rear
    assert yaw == pytest.approx(np.arctan2(chord[1], chord[0]), abs=2e-3)
    assert (x, y) == pytest.approx(tuple((rear + [20.0, 10.0]) / 2), abs=2e-3)
    trail.add((20.0, 10.0))  # standing: nothing changes
    assert trail.pose() == pytest.approx((x, y, yaw))


def test_a_vehicle_driving_east_has_yaw_zero_and_its_centre_behind_its_front(road):
    sc = _road(road, "{ids: [b, d]}", ", max_warmup_s: 10")
    with World(sc, seed=0) as world:
        lanes = {
            round(float(c.polyline.points[-1, 0] - c.polyline.points[0, 0])): c for c in world.true_map.centerlines
        }
        east, west = lanes[300], lanes[-300]  # the two lanes' centre lines, in driving direction
        assert world.vehicle_ids == ["cv0", "cv1"] and world.sumo.sumo_ids == ["b", "d"]
        st = world.states(0.0)
        b, d = st["cv0"], st["cv1"]
        libsumo_front = np.array(libsumo.vehicle.getPosition("d"))  # SUMO is one step ahead of t = 0 now
        # b drives east along WE: yaw 0, on its lane's centre line, its centre 5 m behind its front; d west.
        assert b.yaw == pytest.approx(0.0, abs=1e-9) and abs(d.yaw) == pytest.approx(np.pi, abs=1e-9)
        assert b.p_map[1] == pytest.approx(east.polyline.points[0, 1], abs=1e-6)
        assert d.p_map[1] == pytest.approx(west.polyline.points[0, 1], abs=1e-6)
        # d departed at 3 s at 80 m along EW (its front), standing: b has driven since 1 s
        assert d.p_map[0] == pytest.approx(west.polyline.points[0, 0] - 80.0 + 5.0, abs=0.05)
        assert d.speed == pytest.approx(0.0, abs=0.5)
        assert libsumo_front[0] < d.p_map[0] - 4.9  # its front is ahead of its centre (west of it)
        assert b.p_map[0] > east.polyline.points[0, 0] + 60.0 - 5.0  # moving on from its start
        np.testing.assert_array_equal(b.size, [10.0, 2.0, 1.6])
        np.testing.assert_allclose(b.v_map, [b.speed, 0.0, 0.0], atol=1e-9)
        assert b.cls == ObjectClass.VEHICLE and b.p_map[2] == pytest.approx(0.0)
        # a and c are obstacles, numbered in the order they appeared
        assert [k for k in st if not k.startswith("cv")] == ["1", "2"]
        assert world.sumo.sumo_id("1") == "a" and world.sumo.sumo_id("2") == "c"


# ------------------------------------------------------------------------------- connected vehicles


@pytest.mark.parametrize(
    ("connected", "chosen", "last_depart_s"),
    [("{ids: [d, a]}", ["d", "a"], 3), ("{first: 3}", ["a", "b", "c"], 2), ("{first: 2, type: cav}", ["b", "d"], 3)],
)
def test_connected_vehicles_by_id_by_departure_and_by_type(road, connected, chosen, last_depart_s):
    with World(_road(road, connected), seed=0) as world:
        assert world.sumo.sumo_ids == chosen
        assert world.vehicle_ids == [f"cv{i}" for i in range(len(chosen))]
        # t = 0 is the end of the SUMO step in which the last of them departed (warmup_s is 0)
        assert world.sumo.t0_sumo_s == pytest.approx(last_depart_s + 0.1, abs=1e-9)
        st = world.states(0.0)
        assert list(st)[: len(chosen)] == world.vehicle_ids


def test_scale_scenario_takes_the_first_n_to_depart_or_the_first_listed(road):
    sc = _road(road, "{first: 2}")
    assert scale_scenario(sc, 3).sumo.connected.first == 3 and scale_scenario(sc, 3).n_connected == 3
    ids = _road(road, "{ids: [d, a, b]}")
    assert scale_scenario(ids, 2).sumo.connected.ids == ["d", "a"]
    with pytest.raises(ConfigError, match="names 3 connected SUMO vehicles, 4 asked for"):
        scale_scenario(ids, 4)


def test_a_connected_vehicle_that_leaves_the_network_stops_the_episode(road):
    # The straight road leads nowhere: b cannot get a new destination, reaches the end of WE and leaves.
    with World(_road(road), seed=0) as world, pytest.raises(SumoTrafficError, match=r"cv0 \(SUMO vehicle 'b'\) left"):
        for _ in world.run(60.0):
            pass


# ------------------------------------------------------------------------------------------- errors


def test_a_connected_id_that_never_departs_is_an_error(road):
    with pytest.raises(SumoTrafficError, match=r"\['ghost'\] did not depart within max_warmup_s = 5 s"):
        World(_road(road, "{ids: [a, ghost]}", ", max_warmup_s: 5"), seed=0)
    with pytest.raises(SumoTrafficError, match="only 2 vehicles of type 'cav' departed.*3 connected ones"):
        World(_road(road, "{first: 3, type: cav}", ", max_warmup_s: 5"), seed=0)


@pytest.mark.parametrize(
    ("traffic", "message"),
    [
        ("{source: sumo, net: nowhere.net.xml, routes: [r.rou.xml], connected: {first: 1}}", "net file .*nowhere"),
        ("{source: sumo, net: r.rou.xml, routes: [r.rou.xml], connected: {first: 1}}", "not the map's network"),
        ("{source: sumo, net: road.net.xml, routes: [none.rou.xml], connected: {first: 1}}", "routes file"),
        ("{source: sumo, net: road.net.xml, connected: {first: 1}}", "needs routes"),
        (
            "{source: sumo, net: road.net.xml, routes: [r.rou.xml], connected: {ids: [a], first: 1}}",
            "ids: .* or as first",
        ),
        ("{source: sumo, net: road.net.xml, routes: [r.rou.xml], connected: {first: 0}}", "greater than or equal to 1"),
        ("{source: sumo, net: road.net.xml, routes: [r.rou.xml], connected: {ids: [a, a]}}", "repeat"),
        ("{source: sumo, net: road.net.xml, random: {vehicles: 0}, connected: {first: 1}}", "vehicles"),
        ("{source: sumo, net: road.net.xml, random: {vehicles: 3}, connected: {first: 4}}", "make only 3 vehicles"),
        (
            "{source: sumo, net: road.net.xml, random: {vehicles: 3, pedestrians: -1}, connected: {first: 1}}",
            "pedestrians",
        ),
        ("{source: sumo, net: road.net.xml, routes: [r.rou.xml], connected: {first: 1}, lanes: 2}", "lanes"),
    ],
)
def test_bad_traffic_sections_are_refused_naming_the_problem(road, traffic, message):
    with pytest.raises(ConfigError, match=message):
        _scenario(road, traffic, name="bad")


def test_a_sumo_scenario_takes_its_actors_and_map_from_sumo_only(road):
    traffic = "{source: sumo, routes: [r.rou.xml], connected: {first: 1}}"
    with pytest.raises(ConfigError, match="leave out connected"):
        _scenario(road, traffic, name="both", extra="connected: [{lane: 0}]\n")
    path = road / "ring.yaml"
    path.write_text(f"name: ring\nmap: {{name: ring, length_m: 100}}\ntraffic: {traffic}\n")
    with pytest.raises(ConfigError, match=r"the map is the SUMO network: map: \{format: sumo"):
        load_scenario(path)


def test_without_libsumo_the_error_names_the_extra(road, monkeypatch):
    sc = _road(road)
    monkeypatch.setitem(sys.modules, "libsumo", None)  # import libsumo now fails
    with pytest.raises(MissingExtraError, match=r"SUMO traffic needs the Python package 'libsumo'.*\[roads\]"):
        World(sc, seed=0)


def test_libsumo_is_imported_without_its_pyarrow_warning():
    """With the view extra's newer pyarrow, `import libsumo` printed a version warning on every SUMO run."""
    code = (
        "import os; from mapcontainer.sim.sumo import import_libsumo; ls = import_libsumo(); "
        "assert ls.simulation is not None and 'LIBSUMO_AS_TRACI' not in os.environ"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout == "" and "pyarrow" not in r.stderr, (r.stdout, r.stderr)


# ------------------------------------------------------------------------------- determinism, preset


def _trajectories(world: World, n: int) -> dict[str, np.ndarray]:
    out: dict[str, list] = {}
    for k in range(n):
        for aid, s in world.states(k * world.dt).items():
            out.setdefault(aid, []).append([k, *s.p_map, s.yaw, s.speed, s.yaw_rate, *s.body, s.cls])
    return {a: np.array(v) for a, v in out.items()}


def _same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


@pytest.fixture(scope="module")
def grid():
    return load_scenario("sumo-grid")


def test_the_same_seed_gives_the_same_trajectories_another_seed_other_ones(grid):
    with World(grid, seed=11) as w:
        first = _trajectories(w, 30)
    with World(grid, seed=11) as w:
        again = _trajectories(w, 30)
    with World(grid, seed=12) as w:
        other = _trajectories(w, 30)
    assert _same(first, again)
    assert not _same(first, other)
    assert sum(a.startswith("cv") for a in first) == 4 and len(first) > 10  # the fleet, other vehicles, people
    classes = {int(v[0, -1]) for v in first.values()}
    assert classes == {ObjectClass.VEHICLE, ObjectClass.PEDESTRIAN}


def test_two_worlds_in_one_process_take_turns_with_libsumo_without_changing_their_traffic(grid):
    with World(grid, seed=11) as w:
        alone = _trajectories(w, 12)
    a, b = World(grid, seed=11), World(grid, seed=12)  # b's start closes a's simulation in libsumo
    try:
        turns: dict[str, list] = {}
        for k in range(12):  # each call finds the other's simulation loaded: replays its own to step k
            for aid, s in a.states(k * a.dt).items():
                turns.setdefault(aid, []).append([k, *s.p_map, s.yaw, s.speed, s.yaw_rate, *s.body, s.cls])
            b.states(k * b.dt)
        assert _same(alone, {x: np.array(v) for x, v in turns.items()})
    finally:
        a.close()
        b.close()


def test_traffic_variation_off_fixes_the_seeds_and_old_steps_are_refused(grid):
    fixed = with_traffic(grid, False)
    with World(fixed, seed=1) as w1:
        one = _trajectories(w1, 5)
        with pytest.raises(ValueError, match="no longer kept"):
            w1.states((KEEP_STEPS + 10) * w1.dt)  # far ahead: simulated
            w1.states(0.0)  # then step 0 is more than KEEP_STEPS behind
    with World(fixed, seed=2) as w2:  # the same traffic; the bodies' motion is the sensors' (drawn per run)
        other = _trajectories(w2, 5)
    assert _same({a: v[:, :7] for a, v in one.items()}, {a: v[:, :7] for a, v in other.items()})
    assert not _same(one, other)
    # the error sources switch as on any scenario (the section survives a dump and validation)
    assert with_error_sources(grid, []).sumo == grid.sumo


def test_sumo_actors_move_smoothly_through_junctions_and_lane_changes(grid):
    # Each vehicle's centre advances by its speed x dt (within 0.1 m: no sideways jumps where a junction's lane
    # meets the next, nor at lane changes), and turns at most 12 degrees a step.
    with World(grid, seed=2) as world:
        tracks = _trajectories(world, 200)
    worst_m, worst_deg = 0.0, 0.0
    for tr in tracks.values():
        tr = tr[tr[:, -1] == ObjectClass.VEHICLE]
        if len(tr) < 2 or np.any(np.diff(tr[:, 0]) != 1):
            continue
        step = np.hypot(*np.diff(tr[:, 1:3], axis=0).T)
        worst_m = max(worst_m, float(np.max(step - 0.05 * (tr[1:, 5] + tr[:-1, 5]))))
        worst_deg = max(worst_deg, float(np.degrees(np.max(np.abs(np.angle(np.exp(1j * np.diff(tr[:, 4]))))))))
    assert worst_m < 0.1 and worst_deg < 12.0, (worst_m, worst_deg)


def test_the_grid_preset_senses_sumo_actors_as_the_world_does_its_own(grid):
    with World(grid, seed=2) as world:
        assert world.true_map.name == "grid" and len(world.true_map.junctions) == 9
        ticks = list(world.run(1.0))
    last = ticks[-1]
    assert list(last.frames) == ["cv0", "cv1", "cv2", "cv3"]
    assert list(last.truth.vehicle_ids) == ["cv0", "cv1", "cv2", "cv3"]
    assert len(last.truth.obstacle_id) == len(last.states) - 4
    for vid in last.frames:  # the truth is SUMO's state, the body pose on the map's road
        pose = last.truth.vehicle_pose[list(last.truth.vehicle_ids).index(vid)]
        np.testing.assert_allclose(pose, last.states[vid].pose)
    seen = sum(len(t.frames[v].objects.p_body) for t in ticks for v in t.frames)
    landmarks = sum(len(t.frames[v].points_cls) for t in ticks for v in t.frames)
    assert seen > 0 and landmarks > 0


def test_the_birdseye_draws_actors_that_left_by_their_tracks(grid, tmp_path):
    from mapcontainer.sim.render import render_birdseye

    with World(grid, seed=2) as world:
        st = world.states(0.0)
        hdmap = world.true_map
    gone = next(a for a in st if not a.startswith("cv"))
    tracks = {a: np.array([s.p_map[:2], s.p_map[:2] + 1.0]) for a, s in st.items()}
    final = {a: s for a, s in st.items() if a != gone}  # `gone` left before the end: no final state
    render_birdseye(tmp_path / "b.png", hdmap, tracks, final, ["cv0"], 60.0, 40.0, "t", {gone: st[gone].cls})
    assert (tmp_path / "b.png").stat().st_size > 10_000
