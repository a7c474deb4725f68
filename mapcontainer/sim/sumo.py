"""Traffic from SUMO, in process (libsumo): the world's actors are SUMO's vehicles and persons.

:class:`SumoTraffic` runs one SUMO simulation at the sensor rate (``--step-length`` = the World's dt) and
turns SUMO's states into :class:`~.actors.ActorState`. The conversion (:func:`sumo_pose`):

* SUMO's angle is in degrees clockwise from north; our yaw is counter-clockwise from east (map frame: x
  east, y north): ``yaw = radians(90 - angle)``, wrapped to (-pi, pi];
* SUMO's position is the middle of the front bumper (of a person: its front, 0.2 m ahead of its centre);
  our reference point is the centre of the footprint: ``p = p_front - (length / 2) (cos yaw, sin yaw)``.
  For vehicles the heading is not SUMO's angle but the body's on the path the front has driven
  (:class:`FrontTrail`): SUMO's angle is the direction of the lane under the front, which turns in steps
  of 10-30 degrees where a junction's internal lane meets the next lane (and a rigid body would swing its
  centre sideways by a metre with it); the rear follows the front's path ``length`` behind, the yaw is the
  direction from rear to front and the centre their midpoint. On a straight lane both are SUMO's. Lane
  changes are continuous (SUMO's sublane model, ``--lateral-resolution``), never at a standstill and no
  faster sideways than forwards, instead of SUMO's default jump of a lane width in one step;
* the height is the HD map's road height under that point (``MapIndex.nearest_lane_height``), so the
  actors stand on the road the cameras see;
* velocity and yaw rate: central differences of the centre and the yaw over one step each side (one-sided
  at an actor's first and last step), so the odometry measures the motion the pose makes (SUMO's speed is
  the longitudinal one, without a lane change's sideways motion).

Connected vehicles are SUMO vehicles (``traffic.connected``: listed ids, or the first N to depart, of one
type when given) renamed ``cv0``, ``cv1``, ... in that order; every other vehicle and person is an obstacle
numbered 1, 2, ... in the order it first appears. SUMO time runs ahead of scenario time: before t = 0 SUMO
runs at least ``warmup_s`` and until the last connected vehicle has departed (:class:`SumoTrafficError`
if one has not by ``max_warmup_s``). A connected vehicle near the end of its route gets a new
destination drawn from the run's seed (on the second last edge of its route: the last may lead only out of the
network), so the fleet stays the same through the episode; one that leaves
the simulation anyway (a teleport after standing ``time_to_teleport_s``, a removal) raises
:class:`SumoTrafficError` on the step it happens: the vehicle's sensors and its track would end, which
the fleet, the host and the evaluation do not expect, so the episode stops there rather than going on
with a vehicle silently gone.

libsumo is one simulation per process. A SumoTraffic that finds another has started since (two Worlds in
one process) loads its own again and steps it to where it was: SUMO is deterministic for a seed, so its
trajectories are unchanged (tested), at the cost of the replay. Same scenario and seed: the same
trajectories.
"""

from __future__ import annotations

import atexit
import functools
import math
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from schemas import ObjectClass

from ..config import ConfigError
from ..hdmap.errors import require
from ..hdmap.model import HDMap
from ..hdmap.query import MapIndex
from .actors import ActorState
from .config import SumoTrafficConfig
from .maps import map_bounds

__all__ = ["KEEP_STEPS", "SumoTraffic", "SumoTrafficError", "sumo_pose", "sumo_yaw"]

KEEP_STEPS = 100  # steps of states kept behind the newest (10 s at 10 Hz): a World reads forward in time
REROUTE_TRIES = 20  # destinations tried for a connected vehicle at the end of its route
REROUTE_STREAM = 0x524F5554  # "ROUT": spawn key of the connected vehicles' new destinations
_CYCLIST_CLASSES = ("bicycle", "moped", "motorcycle")


class SumoTrafficError(ConfigError):
    """The SUMO traffic cannot go on as the scenario asks (a connected vehicle never departs or leaves)."""


def sumo_yaw(angle_deg):
    """Our yaw (rad, counter-clockwise from east, in (-pi, pi]) of SUMO's angle (degrees clockwise from north)."""
    a = np.radians(90.0 - np.asarray(angle_deg, dtype=float))
    return np.pi - np.mod(np.pi - a, 2 * np.pi)


def sumo_pose(x: float, y: float, angle_deg: float, length_m: float) -> tuple[float, float, float]:
    """Footprint centre (x, y) and yaw of an actor whose front is at SUMO's position (x, y) with SUMO's angle:
    ``p = p_front - (length / 2) (cos yaw, sin yaw)``."""
    yaw = float(sumo_yaw(angle_deg))
    half = 0.5 * length_m
    return x - half * math.cos(yaw), y - half * math.sin(yaw), yaw


def _sumo_tools() -> Path:
    return Path(require("sumo", "SUMO random trips (randomTrips.py)").SUMO_HOME) / "tools"


_RANDOM_TRIPS = """
import sys
sys.path.append(sys.argv[1])
import randomTrips
for i, args in enumerate(eval(sys.argv[2])):
    randomTrips.main(randomTrips.get_options(["-n", sys.argv[3], "-o", f"{sys.argv[4]}/{i}.xml", *args]))
"""


@functools.lru_cache(maxsize=32)
def _random_trips_xml(net: str, mtime_ns: int, jobs: tuple[tuple[str, ...], ...]) -> tuple[str, ...]:
    """The trips files SUMO's randomTrips.py writes for ``net``, one per argument list in ``jobs``, run in one
    child process (randomTrips seeds Python's global ``random``: not in ours). Cached per process: the
    output is a function of the arguments."""
    with tempfile.TemporaryDirectory(prefix="mapc-trips-") as tmp:
        proc = subprocess.run(
            [sys.executable, "-c", _RANDOM_TRIPS, str(_sumo_tools()), repr(jobs), net, tmp],
            capture_output=True,
            text=True,
            check=False,
            cwd=tmp,  # randomTrips may write other files (routes.rou.xml) beside its output
        )
        outs = [Path(tmp) / f"{i}.xml" for i in range(len(jobs))]
        if proc.returncode != 0 or not all(o.is_file() for o in outs):
            err = (proc.stderr or proc.stdout).strip().splitlines()
            raise SumoTrafficError(f"randomTrips.py failed on {net}: {err[-1] if err else proc.returncode}")
        return tuple(o.read_text() for o in outs)


@dataclass(frozen=True)
class _Raw:
    """One actor at one step, converted to our frame (z not yet set)."""

    cls: ObjectClass
    x: float
    y: float
    yaw: float
    speed: float


def import_libsumo():
    """libsumo, imported without the pyarrow version warning it prints on every import.

    libsumo 1.28 compares the installed pyarrow with the Arrow it was built against and prints a warning
    to stdout when they differ; the ``view`` extra's rerun-sdk brings a newer pyarrow, so every SUMO run
    printed it. libsumo uses Arrow only to write SUMO's Parquet outputs, which we never ask for (we step
    it in process and read the states through its API), so the mismatch does not concern us. Its own
    switch, ``LIBSUMO_AS_TRACI=quiet``, skips the check; set only around the import, after ``traci`` is
    imported as itself (with the variable set, importing traci would load libsumo in its place).
    """
    if sys.modules.get("libsumo") is not None:
        return sys.modules["libsumo"]
    require("traci", "SUMO traffic")
    old = os.environ.get("LIBSUMO_AS_TRACI")
    os.environ["LIBSUMO_AS_TRACI"] = "quiet"
    try:
        return require("libsumo", "SUMO traffic")
    finally:
        if old is None:
            del os.environ["LIBSUMO_AS_TRACI"]
        else:
            os.environ["LIBSUMO_AS_TRACI"] = old


_ACTIVE: list[SumoTraffic] = []  # the SumoTraffic whose simulation libsumo holds (at most one)


def _close_active() -> None:
    if _ACTIVE:
        _ACTIVE[0].close()


atexit.register(_close_active)


class FrontTrail:
    """The path a vehicle's front has driven, and its body on it (module docstring).

    The rear is on the path ``length`` (arc length) behind the front; yaw = direction of the chord from rear
    to front; centre = the chord's midpoint. A new trail starts straight behind the front along ``yaw``.
    """

    def __init__(self, front_xy, yaw: float, length_m: float):
        f = np.asarray(front_xy, dtype=float)
        self.length = float(length_m)
        self._pts = [f - self.length * np.array([math.cos(yaw), math.sin(yaw)]), f]
        self._s = [0.0, self.length]

    def add(self, front_xy) -> None:
        """The front's position at the next step (no move: nothing changes)."""
        f = np.asarray(front_xy, dtype=float)
        d = float(np.hypot(*(f - self._pts[-1])))
        if d < 1e-9:
            return
        self._pts.append(f)
        self._s.append(self._s[-1] + d)
        while len(self._s) > 2 and self._s[1] <= self._s[-1] - self.length:  # keep one point at or behind the rear
            del self._pts[0], self._s[0]

    def pose(self) -> tuple[float, float, float]:
        """Centre (x, y) of the footprint and yaw."""
        s_rear = self._s[-1] - self.length
        i = max(0, int(np.searchsorted(self._s, s_rear, side="right")) - 1)
        i = min(i, len(self._s) - 2)
        w = (s_rear - self._s[i]) / (self._s[i + 1] - self._s[i])
        rear = self._pts[i] + w * (self._pts[i + 1] - self._pts[i])
        front = self._pts[-1]
        c = 0.5 * (front + rear)
        return float(c[0]), float(c[1]), float(np.arctan2(*(front - rear)[::-1]))


class SumoTraffic:
    """One run of SUMO traffic for a scenario's ``traffic`` section and a seed; states per step (module docstring).

    ``states(k)``: every actor at step k (scenario time k dt), connected vehicles first (``cv0``...); steps
    at most :data:`KEEP_STEPS` behind the newest one asked for (ValueError for older ones).
    """

    def __init__(self, cfg: SumoTrafficConfig, hdmap: HDMap, dt: float, seed: int):
        self._ls = import_libsumo()
        self.cfg = cfg
        self.dt = float(dt)
        self.seed = int(seed)
        self._index = MapIndex(hdmap)
        self._bounds = map_bounds(hdmap)  # new destinations of connected vehicles: edges inside the map
        self._tmp = tempfile.TemporaryDirectory(prefix="mapc-sumo-")
        run_seed = self.seed if cfg.enabled else cfg.seed
        self.sumo_seed = run_seed
        routes = [str(p) for p in cfg.routes]
        if cfg.random is not None:
            routes += self._random_trips(run_seed if cfg.random.seed is None else cfg.random.seed)
        self._args = [
            "sumo",
            "--net-file", str(cfg.net),
            "--route-files", ",".join(routes),
            "--step-length", repr(self.dt),
            "--begin", "0",
            "--seed", str(self.sumo_seed),
            "--time-to-teleport", repr(float(cfg.time_to_teleport_s)),
            "--collision.action", "warn",
            "--lateral-resolution", repr(float(cfg.lateral_resolution_m)),
            "--ignore-route-errors", "true",
            "--no-step-log", "true",
            "--no-warnings", "true",
            "--duration-log.disable", "true",
        ]  # fmt: skip
        if cfg.additional:
            self._args += ["--additional-files", ",".join(str(p) for p in cfg.additional)]
        self._reroute_rng = np.random.default_rng(np.random.SeedSequence([run_seed, REROUTE_STREAM]))
        self._sizes: dict[str, tuple[float, float, float]] = {}
        self._ids: dict[str, str] = {}  # SUMO id -> our id
        self._n_obstacles = 0
        self._steps: dict[int, dict[str, _Raw]] = {}  # scenario step -> SUMO id -> state
        self._sumo_steps = 0  # simulation steps since load
        self._k_newest = -1
        self._closed = False
        self._dest_edges: dict[str, list[str]] = {}
        self._trails: dict[str, FrontTrail] = {}
        self._commands: dict[int, list[tuple[str, str]]] = {}  # SUMO step -> (vehicle, new destination)
        self._start()
        self.sumo_ids = self._warm_up()
        self._ids.update({sid: f"cv{i}" for i, sid in enumerate(self.sumo_ids)})
        self.t0_sumo_s = self._sumo_steps * self.dt  # SUMO time at scenario time 0
        self._step_to(0)

    # -------------------------------------------------------------------------------- setup

    def _random_trips(self, seed: int) -> list[str]:
        """Trip files for the scenario's random traffic (vehicles, pedestrians), written to the run's temp dir."""
        r = self.cfg.random
        jobs, names = [], []
        for prefix, n, extra in (
            ("v", r.vehicles, ("--fringe-factor", repr(r.fringe_factor))),
            ("p", r.pedestrians, ("--pedestrians",)),
        ):
            if n == 0:
                continue
            period = r.period_s / n
            jobs.append(
                (
                    "--seed", str(seed),
                    "--begin", "0",
                    "--end", repr(r.period_s - period / 2),  # departures at i period, i = 0 .. n - 1
                    "--period", repr(period),
                    "--min-distance", repr(r.min_distance_m),
                    "--prefix", prefix,
                    *extra,
                )
            )  # fmt: skip
            names.append(f"{prefix}.trips.xml")
        texts = _random_trips_xml(str(self.cfg.net), self.cfg.net.stat().st_mtime_ns, tuple(jobs))
        files = []
        for name, text in zip(names, texts, strict=True):
            path = Path(self._tmp.name) / name
            path.write_text(text)
            files.append(str(path))
        return files

    def _start(self) -> None:
        """Load this run's simulation into libsumo (closing whichever simulation it holds)."""
        if _ACTIVE:
            _ACTIVE[0]._suspend()
        try:
            self._ls.start(self._args)
        except self._ls.TraCIException as exc:  # a bad route or additional file
            raise SumoTrafficError(f"SUMO could not load {self.cfg.net}: {exc}") from None
        _ACTIVE.append(self)
        self._sumo_steps = 0

    def _suspend(self) -> None:
        self._ls.close()
        _ACTIVE.clear()

    def _resume(self) -> None:
        """Load the simulation again and replay it to where it was, with the same new destinations at the same
        steps (SUMO is deterministic: the same states)."""
        n = self._sumo_steps
        self._start()
        for _ in range(n):
            self._sim_step()
            for vid, edge in self._commands.get(self._sumo_steps, []):
                self._ls.vehicle.changeTarget(vid, edge)

    def _warm_up(self) -> list[str]:
        """Step SUMO until the connected vehicles have departed and ``warmup_s`` has passed; their SUMO ids."""
        sel, cfg = self.cfg.connected, self.cfg
        ls = self._ls
        departed: list[str] = []
        n_warm = int(round(cfg.warmup_s / self.dt))
        n_max = int(round(cfg.max_warmup_s / self.dt))
        while True:
            chosen = self._choose(departed)
            if chosen is not None and self._sumo_steps >= n_warm:
                return chosen
            if self._sumo_steps >= n_max:
                break
            self._sim_step()
            self._follow_fronts()
            new = list(ls.simulation.getDepartedIDList())
            if sel.type is not None:
                new = [v for v in new if ls.vehicle.getTypeID(v) == sel.type]
            departed += new
            for v in self._candidates(departed):
                self._keep_driving(v)
        if sel.ids is not None:
            missing = [v for v in sel.ids if v not in departed]
            raise SumoTrafficError(
                f"connected vehicle(s) {missing} did not depart within max_warmup_s = {cfg.max_warmup_s:g} s of SUMO"
                f" time ({len(departed)} vehicles departed: {departed[:10]}{' ...' if len(departed) > 10 else ''})"
            )
        of = f" of type {sel.type!r}" if sel.type is not None else ""
        raise SumoTrafficError(
            f"only {len(departed)} vehicles{of} departed within max_warmup_s = {cfg.max_warmup_s:g} s of SUMO time,"
            f" {sel.first} connected ones asked for"
        )

    def _choose(self, departed: list[str]) -> list[str] | None:
        """The connected vehicles' SUMO ids once all have departed (and are still driving), else None."""
        sel = self.cfg.connected
        chosen = list(sel.ids) if sel.ids is not None else departed[: sel.first]
        if len(chosen) < sel.count or any(v not in departed for v in chosen):
            return None
        alive = set(self._ls.vehicle.getIDList())
        gone = [v for v in chosen if v not in alive]
        if gone:
            raise SumoTrafficError(f"connected vehicle(s) {gone} left the simulation during the warm-up (before t = 0)")
        return chosen

    def _candidates(self, departed: list[str]) -> list[str]:
        """Vehicles that are (or may become) connected ones during the warm-up, kept driving like them."""
        sel = self.cfg.connected
        return [v for v in (sel.ids if sel.ids is not None else departed[: sel.first]) if v in departed]

    # ------------------------------------------------------------------------------ stepping

    def _sim_step(self) -> None:
        """One SUMO step; vehicles that departed in it do not move sideways standing (the sublane model's
        ``lcMaxSpeedLatStanding`` = 0: a standing car cannot change lanes) and at most as fast as they drive
        (``lcMaxSpeedLatFactor`` = 1, SUMO's default, set so a route file's vType cannot unset it)."""
        ls = self._ls
        ls.simulationStep()
        self._sumo_steps += 1
        for vid in ls.simulation.getDepartedIDList():
            ls.vehicle.setParameter(vid, "laneChangeModel.lcMaxSpeedLatStanding", "0")
            ls.vehicle.setParameter(vid, "laneChangeModel.lcMaxSpeedLatFactor", "1")

    def _keep_driving(self, vid: str) -> None:
        """A new destination for vehicle ``vid`` when it is on the second last edge of its route or beyond
        (seeded draws; before the last edge, which may lead nowhere but out of the network)."""
        ls = self._ls
        if vid not in self._alive:
            return
        route = ls.vehicle.getRoute(vid)
        if ls.vehicle.getRouteIndex(vid) < len(route) - 2:
            return
        edges = self._destinations(ls.vehicle.getVehicleClass(vid))
        here = ls.vehicle.getRoadID(vid)
        for _ in range(REROUTE_TRIES if edges else 0):
            edge = edges[int(self._reroute_rng.integers(len(edges)))]
            if edge in (route[-1], here):  # the edge it is on: it would arrive at its end
                continue
            try:
                ls.vehicle.changeTarget(vid, edge)
            except ls.TraCIException:  # no route to it: nothing changed
                continue
            self._commands.setdefault(self._sumo_steps, []).append((vid, edge))
            return

    @property
    def _alive(self) -> set[str]:
        return set(self._ls.vehicle.getIDList())

    def _destinations(self, vclass: str) -> list[str]:
        """Normal edges a vehicle of ``vclass`` may drive on that lead on to another edge (not into a dead
        end: a vehicle there could go nowhere else) and lie wholly inside the extent of the map (of a cropped map:
        about its bounds), sorted by id: the same list every run."""
        if vclass not in self._dest_edges:
            ls = self._ls
            x0, y0, x1, y1 = self._bounds
            out = []
            for e in sorted(ls.edge.getIDList()):
                if e.startswith(":"):
                    continue
                lanes = [f"{e}_{i}" for i in range(ls.edge.getLaneNumber(e))]
                shape = np.array(ls.lane.getShape(lanes[0]))
                if not (np.all((shape[:, 0] >= x0) & (shape[:, 0] <= x1) & (shape[:, 1] >= y0) & (shape[:, 1] <= y1))):
                    continue
                if any(self._allows(ls.lane.getAllowed(ln), vclass) and ls.lane.getLinks(ln) for ln in lanes):
                    out.append(e)
            self._dest_edges[vclass] = out  # empty: nowhere to go on; the vehicle drives to its end
        return self._dest_edges[vclass]

    @staticmethod
    def _allows(allowed, vclass: str) -> bool:
        return not allowed or vclass in allowed

    def _follow_fronts(self) -> set[str]:
        """Every vehicle's front added to its trail (trails of vehicles gone dropped); the vehicles' ids."""
        ls = self._ls
        alive = self._alive
        for sid in sorted(alive):
            front = ls.vehicle.getPosition(sid)
            trail = self._trails.get(sid)
            if trail is None:
                self._sizes[sid] = (ls.vehicle.getLength(sid), ls.vehicle.getWidth(sid), ls.vehicle.getHeight(sid))
                self._trails[sid] = FrontTrail(front, float(sumo_yaw(ls.vehicle.getAngle(sid))), self._sizes[sid][0])
            else:
                trail.add(front)
        for sid in [s for s in self._trails if s not in alive]:
            del self._trails[sid]
        return alive

    def _record(self, k: int) -> None:
        """SUMO's state after its latest step as scenario step ``k``."""
        ls = self._ls
        alive = self._follow_fronts()
        lost = [f"{self._ids[s]} (SUMO vehicle {s!r})" for s in self.sumo_ids if s not in alive]
        if lost:
            raise SumoTrafficError(
                f"{', '.join(lost)} left the SUMO simulation at t = {k * self.dt:.1f} s (arrived, teleported after"
                f" standing {self.cfg.time_to_teleport_s:g} s, or removed): the episode stops here"
            )
        for v in self.sumo_ids:
            self._keep_driving(v)
        raw: dict[str, _Raw] = {}
        for sid in [*self.sumo_ids, *sorted(alive - set(self.sumo_ids))]:
            x, y, yaw = self._trails[sid].pose()
            raw[sid] = _Raw(self._vehicle_class(sid), x, y, yaw, float(ls.vehicle.getSpeed(sid)))
        for sid in sorted(ls.person.getIDList()):
            raw[sid] = self._raw(sid, ObjectClass.PEDESTRIAN, ls.person)
        for sid in raw:
            if sid not in self._ids:
                self._n_obstacles += 1
                self._ids[sid] = str(self._n_obstacles)
        self._steps[k] = raw
        self._steps.pop(k - KEEP_STEPS - 2, None)

    def _vehicle_class(self, sid: str) -> ObjectClass:
        vc = self._ls.vehicle.getVehicleClass(sid)
        return ObjectClass.CYCLIST if vc in _CYCLIST_CLASSES else ObjectClass.VEHICLE

    def _raw(self, sid: str, cls: ObjectClass, domain: Any) -> _Raw:
        if sid not in self._sizes:
            self._sizes[sid] = (domain.getLength(sid), domain.getWidth(sid), domain.getHeight(sid))
        x, y = domain.getPosition(sid)
        cx, cy, yaw = sumo_pose(x, y, domain.getAngle(sid), self._sizes[sid][0])
        return _Raw(cls, cx, cy, yaw, float(domain.getSpeed(sid)))

    def _step_to(self, k: int) -> None:
        """Simulate until scenario step ``k`` is recorded."""
        if self._closed:
            raise RuntimeError("this SumoTraffic is closed")
        if not _ACTIVE or _ACTIVE[0] is not self:
            self._resume()
        while self._k_newest < k:
            if self._k_newest >= 0:  # step 0 is SUMO's state at the end of the warm-up
                self._sim_step()
            self._k_newest += 1
            self._record(self._k_newest)

    # ------------------------------------------------------------------------------ reading

    @property
    def vehicle_ids(self) -> list[str]:
        """Our ids of the connected vehicles (``cv0``, ...), in the order of :attr:`sumo_ids`."""
        return [self._ids[s] for s in self.sumo_ids]

    def sumo_id(self, our_id: str) -> str:
        """The SUMO id of one of our actors."""
        for s, o in self._ids.items():
            if o == our_id:
                return s
        raise KeyError(our_id)

    def states(self, k: int, body: Callable[[str, float], np.ndarray] | None = None) -> dict[str, ActorState]:
        """Every actor at scenario step ``k``: connected vehicles (``cv0``...) first, then obstacles by our id.

        ``body(vid, t)``: the body motion (heave, roll, pitch) of a connected vehicle, or None (rigid)."""
        if k < 0:
            raise ValueError(f"step {k} is before t = 0")
        self._step_to(k + 1)  # the yaw rate's central difference needs the next step
        if k not in self._steps:
            raise ValueError(
                f"step {k} (t = {k * self.dt:.1f} s) is no longer kept: SUMO runs forward, the newest step is"
                f" {self._k_newest} and {KEEP_STEPS} before it are kept"
            )
        t = k * self.dt
        now, before, after = self._steps[k], self._steps.get(k - 1, {}), self._steps.get(k + 1, {})
        out: dict[str, ActorState] = {}
        connected = set(self.sumo_ids)
        for sid, r in now.items():
            a, b = before.get(sid, r), after.get(sid, r)  # central differences, one-sided at either end
            span = self.dt * ((a is not r) + (b is not r))
            if span > 0:
                yaw_rate = float(np.angle(np.exp(1j * (b.yaw - a.yaw)))) / span
                v_map = np.array([(b.x - a.x) / span, (b.y - a.y) / span, 0.0])
            else:  # one step only: SUMO's speed along the heading
                yaw_rate, v_map = 0.0, r.speed * np.array([math.cos(r.yaw), math.sin(r.yaw), 0.0])
            p = np.array([r.x, r.y, self._index.nearest_lane_height((r.x, r.y, 0.0))])
            our = self._ids[sid]
            b_motion = body(our, t) if body is not None and sid in connected else None
            out[our] = ActorState(
                our,
                r.cls,
                p,
                r.yaw,
                v_map,
                yaw_rate,
                np.array(self._sizes[sid], dtype=float),
                np.zeros(3) if b_motion is None else b_motion,
            )
        cv = set(self.vehicle_ids)
        obstacles = sorted((o for o in out if o not in cv), key=int)
        return {o: out[o] for o in [*self.vehicle_ids, *obstacles]}

    def close(self) -> None:
        """End the simulation (libsumo is free for another) and remove the run's files. Idempotent."""
        if self._closed:
            return
        if _ACTIVE and _ACTIVE[0] is self:
            self._suspend()
        self._closed = True
        self._tmp.cleanup()

    def __enter__(self) -> SumoTraffic:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
