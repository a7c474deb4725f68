"""Reproduce the paper's results (sections "Simulation Validation" and "Test Vehicle Evaluation"), honestly.

Every run is one :func:`mapcontainer.pipeline.run_pipeline` call on the simulated clock, ideal V2X
channel, distributed mode, with every realistic error source of the simulator on
(:mod:`mapcontainer.sim.errors`) and traffic drawn per run from its seed. Runs start cold and last
``duration_s`` (10 s); everything from ``burnin_s`` (3 s) on is scored, and the error against time
of the whole run is drawn so that no window hides anything. Seeds come from the evaluation range.

* **simulation** (figure exp_sim): ``runs`` runs of paper-urban and paper-suburban, two host views
  each: "cooperative" (every vehicle's messages) and "ego_only" (the ego's own, the same estimator).
  Vehicle poses against four estimates: GNSS alone, the vehicle's filtered on-board estimate (the
  vehicle alone), the per-frame map-matching pose it sends, and the host's fused pose. Targets: the
  paper's rms2 (ego frame, within ``radius_m``) with coverage, false tracks and GOSPA.
* **test site** (Tables res1, res2): overlap and blind spots (ii), (iii), each at both landmark
  densities, ``rv_runs`` runs.
* **cold start** (:func:`.figures.startup_summary`): each vehicle's time to localize from GNSS, and
  its gross errors after it, those it did not announce (in map matching) apart.
* **consistency**: per scenario, object NEES (3-D) and vehicle pose NEES (6-DoF) in both forms.
* **sensitivity**: the headline figures with each error source off in turn, with all off, and all on,
  on the first ``sensitivity_runs`` seeds (the same seeds for every setting).
* **bytes**: distributed vs centralized payloads from real encoded messages.
* **downlink on and off** (``downlink_compare``, ``mapc experiment paper --downlink both``): every run twice, the
  same seed without and with the host's downlink; every figure for both, the headline ones side by side
  (:mod:`.onoff`).
"""

from __future__ import annotations

import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

from ... import jsonout
from ...seeds import EVAL_SEED0, seed_kind
from ..executors import Executor, Session
from ..runner import Batch, run_all, write_timing
from ..store import TaskStore
from .figures import (
    ESTIMATES,
    TARGET_VIEWS,
    consistency,
    evaluate_claims,
    evaluate_targets,
    group,
    rv_figures,
    sim_figures,
    startup_summary,
    time_series,
)
from .onoff import on_off, split_by_downlink
from .runs import VARIANTS, describe, run_task, tasks
from .settings import BLINDSPOT_SCENARIOS, DENSITIES, EGO, PAPER, SIM_SCENARIOS, PaperSettings

__all__ = [
    "PAPER",
    "PaperSettings",
    "consistency",
    "evaluate_claims",
    "evaluate_targets",
    "run_paper_experiment",
    "run_task",
]


def _rv(by: dict, variant: str, burnin_s: float, seeds: set[int] | None = None) -> tuple[dict, dict]:
    overlap, blindspot = {}, {k: {} for k in BLINDSPOT_SCENARIOS}
    for density in DENSITIES:
        rs = [r for r in by.get(("overlap", f"overlap/{density}", variant), []) if seeds is None or r["seed"] in seeds]
        if rs:
            overlap[density] = rv_figures("overlap", rs, burnin_s)
        for key in BLINDSPOT_SCENARIOS:
            rs = [
                r for r in by.get(("blindspot", f"{key}/{density}", variant), []) if seeds is None or r["seed"] in seeds
            ]
            if rs:
                blindspot[key][density] = rv_figures("blindspot", rs, burnin_s)
    return overlap, blindspot


def _headline(sim: dict, overlap: dict, blindspot: dict) -> dict[str, float]:
    """The figures the sensitivity table follows."""
    out = {}
    for key, f in sim.items():
        if not f:
            continue
        for m in ("onboard", "map_matching", "cooperative"):
            out[f"{key}: ego {m.replace('_', ' ')}"] = f["ego_rmse_m"][m]
        for m in ("ego_only", "cooperative"):
            out[f"{key}: targets {m.replace('_', ' ')}"] = f["target_rmse_m"][m]
            out[f"{key}: target coverage {m.replace('_', ' ')}"] = f["objects"][m].get("coverage", float("nan"))
        cons = f.get("consistency", {})  # does the estimator know its error with this source on or off?
        out[f"{key}: fused vehicles ANEES (6-DoF)"] = cons.get("vehicles_cooperative_6dof", {}).get("anees", float("nan"))
        out[f"{key}: fused objects ANEES (3-D)"] = cons.get("objects_cooperative_3d", {}).get("anees", float("nan"))
    if "dense" in overlap:
        out["overlap: fused obstacle"] = overlap["dense"]["fused_m"]
    for key in BLINDSPOT_SCENARIOS:
        b = blindspot[key].get("dense")
        if b:
            out[f"blind spot ({key}): connected car"] = b["connected_car_m"]
            out[f"blind spot ({key}): obstacle"] = b["obstacle_m"]
    return out


def aggregate(results: list[dict], s: PaperSettings, bytes_figures: dict | None = None) -> dict:
    """Every figure of the experiment from its runs (see the module docstring), in the runs' task order: a
    function of the settings alone (what the runs cost is in timing.json, :func:`..runner.timing_doc`).

    With ``downlink_compare`` the figures are those of the runs with the downlink as ``s.downlink`` says, and
    ``downlink_other`` holds every figure of the runs the other way, ``downlink_on_off`` the comparison
    (:mod:`.onoff`); both sets score against the one centralized reference per seed."""
    if not s.downlink_compare:
        return _aggregate(results, s, bytes_figures)
    main, other = split_by_downlink(results, s.downlink)
    res = _aggregate(main, s, bytes_figures)
    res["downlink_other"] = _aggregate(other, replace(s, downlink=not s.downlink), bytes_figures)
    res["downlink_on_off"] = on_off(res, res["downlink_other"], main + other, s)
    return res


def _aggregate(results: list[dict], s: PaperSettings, bytes_figures: dict | None = None) -> dict:
    by = group(results)
    b = s.burnin_s
    simulation = {}
    for key in s.sim_scenarios:
        rs = by.get(("sim", key, "all"), [])
        if rs:
            simulation[key] = sim_figures(rs, b)
            names = [f"{EGO}:{m}" for m in ESTIMATES] + [f"targets:{m}" for m in TARGET_VIEWS]
            simulation[key]["over_time"] = {n: time_series(rs, n) for n in names}
            simulation[key]["startup"] = startup_summary(rs, s.duration_s)
    overlap, blindspot = _rv(by, "all", b)
    sens_seeds = {s.seed + i for i in range(s.sensitivity_run_count)}
    sensitivity = {}
    if s.sensitivity_run_count:
        for variant in VARIANTS:
            sim_v = {
                key: sim_figures([r for r in by.get(("sim", key, variant), []) if r["seed"] in sens_seeds], b)
                for key in s.sim_scenarios
                if by.get(("sim", key, variant))
            }
            sensitivity[variant] = _headline(sim_v, *_rv(by, variant, b, sens_seeds))
    out: dict[str, Any] = {
        "simulation": simulation,
        "overlap": overlap,
        "blindspot": blindspot,
        "sensitivity": sensitivity,
        "bytes": bytes_figures or {},
        "runs": s.runs,
        "seed": s.seed,
        "seeds": seed_kind(s.seed),
        "settings": {
            **asdict(s),
            "real_vehicle_runs": s.real_vehicle_runs,
            "sensitivity_runs": s.sensitivity_run_count,
            "scenarios": s.sim_scenarios,
            "evaluation_seeds_from": EVAL_SEED0,
        },
    }
    if s.paper and len(simulation) == len(SIM_SCENARIOS):
        out["claims"] = evaluate_claims(simulation)
    out["targets"] = evaluate_targets(out)
    return out


def byte_figures(
    s: PaperSettings, executor: Executor | Session | None = None, store: TaskStore | None = None
) -> tuple[dict, Batch]:
    """Bytes per message and per second of both modes from real encoded messages of paper-urban runs (of the first
    given preset instead) (:func:`mapcontainer.experiments.bytes.measure_bytes`, the first min(runs, 5) seeds);
    ``ratio`` is the headline: centralized (lane mask at the matcher's resolution) over distributed, per message.
    Also the runs' batch (their timing)."""
    from ..bytes import bytes_runs, summarize_bytes

    seeds = [s.seed + i for i in range(min(s.runs, 5))]
    preset = SIM_SCENARIOS["urban"] if s.paper else s.scenarios[0]
    batch = bytes_runs(preset, seeds, s.duration_s, True, executor or Executor(), store)
    m = summarize_bytes(batch.results, preset, s.duration_s, signing=True)
    return {"ratio": m["ratio"]["with_lane_mask_per_message"], "measured": m}, batch


def run_paper_experiment(
    out_dir: str | Path,
    settings: PaperSettings | None = None,
    executor: Executor | None = None,
    progress: bool = True,
    fresh: bool = False,
) -> dict:
    """Run everything on ``executor`` (default: a local pool of 2); write results.json, report.md, runs.csv,
    the PNG plots and timing.json into ``out_dir``. Every finished run is kept in ``out_dir/tasks`` as it
    finishes: the same call on the same directory runs only what is missing (``fresh``: start over).
    Everything but timing.json is a function of ``settings`` alone, whatever ran the tasks."""
    from .report import plots, report, runs_csv

    s = settings or PaperSettings()
    executor = executor or Executor()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    store = TaskStore(out, "paper", asdict(s), fresh=fresh)
    with Session(executor) as session:  # one pool (or cluster) for both phases
        runs = run_all(run_task, tasks(s), "experiment paper", describe, session, store, progress)
        bytes_figures, bytes_batch = byte_figures(s, session, store)
    res = aggregate(runs.results, s, bytes_figures)
    (out / "results.json").write_text(jsonout.dumps(res, indent=2) + "\n")
    main, other = split_by_downlink(runs.results, s.downlink) if s.downlink_compare else (runs.results, [])
    (out / "runs.csv").write_text(runs_csv(main + other, s.burnin_s, downlink_column=s.downlink_compare))
    files = plots(res, main, out)
    (out / "report.md").write_text(report(res))
    timing = write_timing(out, executor, {"runs": runs, "bytes": bytes_batch}, time.perf_counter() - t0)
    res["wall_s"] = round(time.perf_counter() - t0, 1)
    res["resumed"] = runs.resumed + bytes_batch.resumed
    res["files"] = [str(p) for p in [out / "results.json", out / "report.md", out / "runs.csv", *files, timing]]
    return res
