"""One run of the paper experiment: a pipeline run scored frame by frame (the runner's task).

Every run keeps its raw per-frame figures with their times, so that the aggregation can score the
steady state (after the burn-in), draw the error against time, and compare runs:

* ``series[name]``: [t, squared horizontal error] pairs, one per estimate (vehicle or target) and frame;
* ``objects[view]``: per frame [t, true obstacles in scope, matched, fused objects in scope, GOSPA^2,
  its localization, missed and false parts] (:func:`mapcontainer.evaluation.gospa`);
* ``nees[name]``: [t, cell, NEES] with a cell id that names the same estimate in every run
  (frame index and obstacle or vehicle), for the per-cell consistency check;
* ``locks``: [t, vehicle index, says map_matching (1/0: the mode its message announces, with a pose),
  horizontal error of its filtered pose (NaN: no pose yet)] (the cold start).
"""

from __future__ import annotations

import math
from dataclasses import asdict, replace
from typing import Any

import numpy as np

from ... import evaluation as ev
from ...metrics import nees
from ...pipeline import PipelineResult, View, run_pipeline
from ...sim import load_scenario
from ...sim.errors import ERROR_SOURCES, with_error_sources
from .settings import CONNECTED, EGO, PaperSettings

__all__ = ["VARIANTS", "describe", "run_task", "scenario_variant"]

# Error-source settings of the sensitivity study: "all" (the scenarios' defaults: every source on),
# "none" (ideal sensors and map), and "no_<source>" (every source but one).
VARIANTS = ("all", "none", *(f"no_{s}" for s in ERROR_SOURCES))


def scenario_variant(name: str, variant: str):
    """The scenario preset ``name`` with the error sources of ``variant`` (see VARIANTS)."""
    sc = load_scenario(name)
    if variant == "all":
        return sc
    if variant == "none":
        return with_error_sources(sc, ())
    if variant.startswith("no_") and variant[3:] in ERROR_SOURCES:
        return with_error_sources(sc, [s for s in ERROR_SOURCES if s != variant[3:]])
    raise ValueError(f"unknown error-source variant {variant!r}; known: {', '.join(VARIANTS)}")


class _Scorer:
    """Accumulates one run's per-frame figures."""

    def __init__(self, res: PipelineResult, radius_m: float):
        self.res = res
        self.radius_m = radius_m
        self.series: dict[str, list[list[float]]] = {}
        self.objects: dict[str, list[list[float]]] = {}
        self.nees: dict[str, list[list[float]]] = {}
        self.locks: list[list[float]] = []

    def add(self, name: str, t: float, sq) -> None:
        rows = self.series.setdefault(name, [])
        rows.extend([t, float(v)] for v in np.atleast_1d(sq))

    def add_nees(self, name: str, t: float, cells, values) -> None:
        rows = self.nees.setdefault(name, [])
        rows.extend([t, int(c), float(v)] for c, v in zip(cells, values, strict=True))

    def score(self, rec, view: str, scoped: bool) -> ev.FrameScore:
        """A view's fused state against the truth; ``scoped``: objects within radius_m of the true ego
        (the obstacles there, and the fused objects there as possible false tracks)."""
        fused, truth = rec.fused[view], rec.truth
        if not scoped:
            return ev.score_frame(fused, truth)
        centre = ev.vehicle_pose(truth, EGO)[:2]
        return ev.score_frame(
            fused,
            truth,
            truth_in_scope=ev.within_radius(truth.obstacle_p_map, centre, self.radius_m),
            est_in_scope=ev.within_radius(fused.object_p_map, centre, self.radius_m),
        )

    def vehicles(self, k: int, rec, vids, fused: dict[str, ev.FrameScore]) -> None:
        """Every estimate of each vehicle in ``vids``: GNSS, its filtered on-board pose (what it sends), its
        per-frame map-matching pose, and each fused view's (name -> its frame score); series and NEES
        "<vid>:<estimate>", NEES cells by frame index."""
        for i, vid in enumerate(rec.truth.vehicle_ids):
            if vid not in vids:
                continue
            p_true = ev.vehicle_pose(rec.truth, vid)
            own = (
                ("gnss", rec.gnss.get(vid), None),
                ("onboard", rec.onboard.get(vid), rec.onboard_covs.get(vid)),
                ("map_matching", rec.per_frame.get(vid), rec.per_frame_covs.get(vid)),
            )
            for name, p, cov in own:
                if p is None:
                    continue
                self.add(f"{vid}:{name}", rec.t, ev.horizontal_sq_error(p, p_true))
                if cov is not None:
                    e = ev.pose_error(p, p_true)
                    self.add_nees(f"{vid}:{name}", rec.t, [k], nees(e, cov))
                    if name == "onboard":  # the horizontal position alone (what the downlink informs)
                        cov_xy = np.asarray(cov, dtype=float)[:2, :2]
                        self.add_nees(f"{vid}:onboard_xy", rec.t, [k], nees(e[:2], cov_xy))
            self.fused_vehicle(k, rec.t, vid, fused)
            if vid in rec.loc_mode:  # NaN error: not initialised yet, no pose
                p = rec.onboard.get(vid)
                err = math.sqrt(ev.horizontal_sq_error(p, p_true)) if p is not None else float("nan")
                self.locks.append([rec.t, i, float(rec.loc_mode[vid] == "map_matching" and p is not None), err])

    def fused_vehicle(self, k: int, t: float, vid: str, fused: dict[str, ev.FrameScore]) -> None:
        """A vehicle's pose in each fused view (name -> its frame score): series and NEES "<vid>:<name>"."""
        for name, fs in fused.items():
            if vid in fs.vehicle_ids:
                j = fs.vehicle_ids.index(vid)
                self.add(f"{vid}:{name}", t, fs.vehicle_sq[j])
                self.add_nees(f"{vid}:{name}", t, [k], fs.vehicle_nees[j : j + 1])

    def objects_of(self, k: int, t: float, fs: ev.FrameScore, name: str) -> None:
        """Map-frame errors, coverage, false tracks and GOSPA of one view's objects in a frame."""
        self.add(name, t, fs.object_sq)
        g = fs.gospa
        self.objects.setdefault(name, []).append(
            [t, fs.n_truth, fs.n_matched, fs.n_fused, g.total, g.localization, g.missed, g.false]
        )
        if fs.n_matched:
            self.add_nees(name, t, k * 100_000 + fs.object_truth_ids, fs.object_nees)

    def targets(self, rec, view: str) -> dict[int, float]:
        """The paper's rms2 terms of one view (targets in the ego frame, within radius_m of the ego);
        returns {obstacle id: squared error}."""
        ids, err, _ = ev.relative_target_errors(rec.fused[view], rec.truth, EGO, self.radius_m)
        sq = np.sum(err**2, axis=1)
        self.add(f"targets:{view}", rec.t, sq)
        return dict(zip(ids.tolist(), sq.tolist(), strict=True))

    def result(self, **extra) -> dict:
        res = self.res
        return {
            "series": self.series,
            "objects": self.objects,
            "nees": self.nees,
            "locks": self.locks,
            "tx_bytes": int(sum(res.tx_bytes.values())),
            "tx_msgs": int(sum(res.tx_msgs.values())),
            # the downlink (host -> vehicles on the air) and what the vehicles did with it, frames by status
            "rx_bytes": int(sum(res.rx_bytes.values())),
            "rx_msgs": int(sum(res.rx_msgs.values())),
            "downlink_frames": _downlink_frames(res),
            **extra,
        }


def _downlink_frames(res: PipelineResult) -> dict[str, int]:
    """Vehicle-frames by what the vehicle did with the downlink (fused, refused, seeded; none: nothing to fuse)."""
    out: dict[str, int] = {}
    for rec in res.records:
        for status in rec.downlink.values():
            out[status] = out.get(status, 0) + 1
    return dict(sorted(out.items()))


def _sim_run(scenario, seed: int, s: PaperSettings, centralized: bool = False) -> dict:
    """paper-urban / paper-suburban (or the presets given in their place): every vehicle's estimates, and the
    targets of the cooperative and the ego-only views (the same host estimator fed every vehicle's messages or the
    ego's);
    ``centralized``: the same run in centralized mode too (:func:`_centralized`)."""
    views = (View("cooperative"), View("ego_only", (EGO,)))
    res = run_pipeline(scenario, seed=seed, duration_s=s.duration_s, views=views, start=s.start, downlink=s.downlink)
    if res.ego != EGO:
        raise ValueError(f"scenario {res.scenario}: the pipeline's ego is {res.ego}, expected {EGO}")
    sc = _Scorer(res, s.radius_m)
    for k, rec in enumerate(res.records):
        scores = {view: sc.score(rec, view, scoped=True) for view in ("ego_only", "cooperative")}
        sc.vehicles(k, rec, rec.truth.vehicle_ids, {"cooperative": scores["cooperative"]})
        for view, fs in scores.items():
            sc.objects_of(k, rec.t, fs, f"objects:{view}")
        per_view = {view: sc.targets(rec, view) for view in ("ego_only", "cooperative")}
        both = sorted(per_view["ego_only"].keys() & per_view["cooperative"].keys())
        for view, d in per_view.items():  # the targets both views estimate
            sc.add(f"targets_common:{view}", rec.t, [d[i] for i in both])
    extra = _centralized(scenario, seed, s, sc) if centralized and s.start == "cold" else {}
    return sc.result(vehicles=list(res.records[0].truth.vehicle_ids) if res.records else [], **extra)


def _centralized(scenario, seed: int, s: PaperSettings, sc: _Scorer) -> dict:
    """The same run (seed: the same world, sensors and link) in centralized mode, the joint estimator
    over every vehicle's raw observations (:class:`mapcontainer.fusion.joint.JointHost`), scored into
    ``sc`` as the estimate "centralized" of every vehicle and of the objects and targets; returns its
    bytes on the air. Only from a cold start (the host localizes the vehicles itself)."""
    res = run_pipeline(scenario, seed=seed, duration_s=s.duration_s, mode="centralized", views=(View("centralized"),))
    for k, rec in enumerate(res.records):
        fs = sc.score(rec, "centralized", scoped=True)
        for vid in rec.truth.vehicle_ids:
            sc.fused_vehicle(k, rec.t, vid, {"centralized": fs})
        sc.objects_of(k, rec.t, fs, "objects:centralized")
        sc.targets(rec, "centralized")
    return {
        "tx_bytes_centralized": int(sum(res.tx_bytes.values())),
        "tx_msgs_centralized": int(sum(res.tx_msgs.values())),
    }


def _overlap_run(scenario, seed: int, s: PaperSettings) -> dict:
    """Table res1: the obstacle in the map frame from the ego car's messages, the connected car's, both."""
    views = (View("ego_car", (EGO,)), View("connected_car", (CONNECTED,)), View("fused"))
    res = run_pipeline(scenario, seed=seed, duration_s=s.duration_s, views=views, start=s.start, downlink=s.downlink)
    sc = _Scorer(res, s.radius_m)
    for k, rec in enumerate(res.records):
        sc.vehicles(k, rec, (EGO, CONNECTED), {})
        for view in ("ego_car", "connected_car", "fused"):
            sc.objects_of(k, rec.t, sc.score(rec, view, scoped=False), f"obstacle:{view}")
    return sc.result()


def _blindspot_run(scenario, seed: int, s: PaperSettings) -> dict:
    """Table res2: the connected car's fused pose (and its own estimates) and the obstacle, cooperative
    and ego-only views."""
    views = (View("cooperative"), View("ego_only", (EGO,)))
    res = run_pipeline(scenario, seed=seed, duration_s=s.duration_s, views=views, start=s.start, downlink=s.downlink)
    sc = _Scorer(res, s.radius_m)
    for k, rec in enumerate(res.records):
        scores = {view: sc.score(rec, view, scoped=False) for view in ("ego_only", "cooperative")}
        sc.vehicles(k, rec, (EGO, CONNECTED), {"cooperative": scores["cooperative"]})
        for view, fs in scores.items():
            sc.objects_of(k, rec.t, fs, f"obstacle:{view}")
    return sc.result()


_RUNNERS = {"sim": _sim_run, "overlap": _overlap_run, "blindspot": _blindspot_run}


def run_task(task: tuple[str, str, str, str, int, dict[str, Any]]) -> dict:
    """One independent run: (kind, key, scenario preset, error-source variant, seed, settings)."""
    kind, key, scenario, variant, seed, settings = task
    s = PaperSettings(**settings)
    extra = {"centralized": True} if kind == "sim" and variant == "all" and _reference_here(s) else {}
    out = _RUNNERS[kind](scenario_variant(scenario, variant), seed, s, **extra)
    out.update(kind=kind, key=key, scenario=scenario, variant=variant, seed=seed, downlink=s.downlink)
    return out


def _reference_here(s: PaperSettings) -> bool:
    """Whether a main simulation run with settings ``s`` runs the centralized reference too (not for the sensitivity
    study): always, but when the downlink is compared, once per seed, with the run without it (the reference does
    not depend on the downlink; the runs with it borrow it: :func:`.figures.borrow_reference`)."""
    return not (s.downlink_compare and s.downlink)


def describe(task: tuple) -> str:
    """A task for people: "sim urban all seed 90001"."""
    kind, key, _, variant, seed, _ = task
    return f"{kind} {key} {variant} seed {seed}"


def tasks(s: PaperSettings) -> list[tuple]:
    """Every run of the experiment, longest first so that the workers finish together: the main
    Monte Carlo runs (all error sources on), the test-site scenarios at both landmark densities,
    and the sensitivity runs (each error setting); with ``downlink_compare``, each twice in a row: with the
    downlink as ``downlink`` says and the other way (the same seed)."""
    from .settings import BLINDSPOT_SCENARIOS, DENSITIES, rv_scenario

    cfg = asdict(s)
    out: list[tuple] = []

    def rv(variant: str, n: int, densities=DENSITIES) -> None:
        for i in range(n):
            for density in densities:
                out.append(("overlap", f"overlap/{density}", rv_scenario("overlap", density), variant, s.seed + i, cfg))
                for key in BLINDSPOT_SCENARIOS:
                    out.append(("blindspot", f"{key}/{density}", rv_scenario(key, density), variant, s.seed + i, cfg))

    if s.downlink_compare:  # every run once more with the downlink the other way, each beside its twin
        once = tasks(replace(s, downlink_compare=False))
        cfg_other = asdict(replace(s, downlink=not s.downlink))
        return [t for task in once for t in (task[:5] + (cfg,), task[:5] + (cfg_other,))]
    sims = list(s.sim_scenarios.items())[::-1]  # the paper's suburban first in each pair: the longer run
    for i in range(s.runs):
        for key, preset in sims:
            out.append(("sim", key, preset, "all", s.seed + i, cfg))
    rv("all", s.real_vehicle_runs)
    for variant in VARIANTS[1:]:
        for i in range(s.sensitivity_run_count):
            for key, preset in sims:
                out.append(("sim", key, preset, variant, s.seed + i, cfg))
        if s.paper:
            rv(variant, s.sensitivity_run_count, ("dense",))
    return out
