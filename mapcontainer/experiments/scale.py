"""Scaling experiment (``mapc experiment scale``): the paper's thesis, at the size of a city district.

The paper argues for the distributed architecture by cost: a centralized solve grows with the number of
vehicles and their observations (its Jacobian is M x N) and its traffic with the raw data, while each
vehicle's compact prior keeps both small. This experiment measures both as the fleet grows.

Each point is one in-process :func:`mapcontainer.pipeline.run_pipeline` run, cold started, of a SUMO
scenario whose connected vehicles are its first N to depart (``traffic.connected.first``): the same
traffic at every N (the same seed), more of it connected. Every vehicle sends to the host over the
channel model's ``dsrc`` profile, one shared 6 Mbit/s medium (802.11p-like: 18-22 ms, 1.5 % loss, a
32 kB queue), signed as the live fleet sends (:mod:`mapcontainer.security`). Both modes run the same
host code and are scored by the same evaluator (:mod:`mapcontainer.evaluation`) after ``warmup_s``.

Row keys (``SCALE_COLUMNS``):

* ``vehicles``: N; ``obstacles_in_scope``: true obstacles per frame within ``radius_m`` of any connected
  vehicle (the scope of the object figures; the fused objects in the same scope are scored);
* ``bytes_per_s_per_vehicle``, ``bytes_per_s_total``: signed payload bytes offered to the medium (the
  ego's own messages stay on board); ``load_fraction``: those bits per second over the medium's capacity;
* ``delivered_fraction``, ``dropped_queue_fraction``, ``dropped_loss_fraction``: over the messages whose
  fate was decided (as ``mapc experiment network``); queue drops are the medium saturating (the channel
  model's tail drop: the 10 Hz senders all send at the same instants, so a tick's burst can overflow the
  queue before the mean load reaches the capacity);
* ``latency_s_p50/p99``, ``age_s_mean/p95``: as ``mapc experiment network``;
* ``host_cpu_ms_per_cycle``: the host's CPU (verify, ingest and fuse; centralized: it localizes every
  vehicle from its raw observations) per fused frame; ``fuse_cpu_ms_p50``: the fuse call alone;
* ``vehicle_rmse_m``, ``object_rmse_m``, ``coverage``, ``gospa_m``, ``false_tracks_per_frame``: from
  :class:`mapcontainer.evaluation.Totals` over the scored frames; ``anees_objects``: 3-D object ANEES.

``saturation`` (in the report and ``results.json``): per mode, the smallest N whose queue drops exceed
``SATURATION_DROPS`` of its messages, or None within the sizes run. ``realtime_vehicles``: per mode, the
largest N up to which every size's host CPU per cycle fits the fleet's 10 Hz cycle (``CYCLE_BUDGET_MS``),
None if the smallest does not; with ``host_compiled`` in the meta (the host's inner loops compiled by
numba, the ``fast`` extra, or interpreted) and the BLAS threads (one per worker).
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .. import jsonout
from ..channel import load_profile
from ..evaluation import Totals, score_near_vehicles
from ..fusion.compiled import COMPILED
from ..jsonout import rounded
from ..pipeline import View, run_pipeline
from ..sim import ScenarioConfig, load_scenario
from ..sim.config import scale_scenario
from .executors import Executor
from .network import link_figures
from .runner import run_all, write_timing
from .store import TaskStore

__all__ = [
    "SCALE_COLUMNS",
    "SIZES",
    "run_scale_experiment",
    "run_scale_point",
    "scenario_with_connected",
    "write_scale_outputs",
]

SIZES = (2, 4, 8, 16, 32, 50, 100)
MODES = ("distributed", "centralized")
DEFAULT_SCENARIO = "sumo-town"
NETWORK = "dsrc"
SATURATION_DROPS = 0.01
CYCLE_BUDGET_MS = 100.0  # the fleets' 10 Hz cycle

SCALE_COLUMNS = (
    "scenario",
    "mode",
    "vehicles",
    "seed",
    "duration_s",
    "warmup_s",
    "obstacles_in_scope",
    "bytes_per_s_per_vehicle",
    "bytes_per_s_total",
    "load_fraction",
    "delivered_fraction",
    "dropped_queue_fraction",
    "dropped_loss_fraction",
    "latency_s_p50",
    "latency_s_p99",
    "age_s_mean",
    "age_s_p95",
    "host_cpu_ms_per_cycle",
    "fuse_cpu_ms_p50",
    "vehicle_rmse_m",
    "object_rmse_m",
    "coverage",
    "gospa_m",
    "false_tracks_per_frame",
    "anees_objects",
    "wall_s",
)


def scenario_with_connected(scenario: str | ScenarioConfig, n: int) -> ScenarioConfig:
    """A SUMO scenario with its first ``n`` departing vehicles connected (:func:`scale_scenario`); ValueError
    for a scenario whose actors are its own lists: one that grows by adding vehicles around its ring is not
    one scene seen by more connected vehicles."""
    sc = load_scenario(scenario) if isinstance(scenario, str) else scenario
    if sc.sumo is None:
        raise ValueError(
            f"scenario {sc.name!r} lists its own actors: the scaling experiment needs a SUMO scenario "
            "(traffic: {source: sumo}) whose connected vehicles are the first N to depart"
        )
    return scale_scenario(sc, n)


def run_scale_point(
    n: int,
    mode: str,
    seed: int = 0,
    duration: float = 10.0,
    *,
    scenario: str | ScenarioConfig = DEFAULT_SCENARIO,
    warmup_s: float = 3.0,
    radius_m: float = 50.0,
    signing: bool = True,
) -> dict[str, Any]:
    """One point: ``n`` connected vehicles in ``mode``; its row (keys ``SCALE_COLUMNS``)."""
    if duration <= warmup_s:
        raise ValueError(f"duration ({duration} s) must exceed warmup_s ({warmup_s} s)")
    t0 = time.perf_counter()
    sc = scenario_with_connected(scenario, n)
    profile = load_profile(NETWORK)
    res = run_pipeline(
        sc, seed=seed, duration_s=duration, mode=mode, network=profile, views=(View("fused"),), signing=signing
    )
    totals = Totals()
    in_scope = []
    scored = [r for r in res.records if r.t >= warmup_s - 1e-9 and "fused" in r.fused]
    for rec in scored:
        score, n_in_scope = score_near_vehicles(rec.fused["fused"], rec.truth, radius_m)
        in_scope.append(n_in_scope)
        totals.add(score)
    s = totals.summary()
    senders = sorted(res.tx_msgs)
    total_bps = sum(res.tx_bytes.values()) / duration
    cycles = len(res.fuse_cpu_ms["fused"])
    return {
        "scenario": sc.name,
        "mode": mode,
        "vehicles": int(n),
        "seed": int(seed),
        "duration_s": float(duration),
        "warmup_s": float(warmup_s),
        "obstacles_in_scope": rounded(float(np.mean(in_scope)) if in_scope else None, 1),
        "bytes_per_s_per_vehicle": rounded(total_bps / max(1, len(senders)), 1),
        "bytes_per_s_total": rounded(total_bps, 1),
        "load_fraction": rounded(8.0 * total_bps / profile.bandwidth_bps),
        **link_figures(res, [r.t for r in scored]),
        "host_cpu_ms_per_cycle": rounded(1e3 * res.host_cpu_s["fused"] / cycles if cycles else None, 2),
        "fuse_cpu_ms_p50": rounded(float(np.percentile(res.fuse_cpu_ms["fused"], 50)) if cycles else None, 2),
        "vehicle_rmse_m": rounded(s["vehicle_rmse_m"]),
        "object_rmse_m": rounded(s["object_rmse_m"]),
        "coverage": rounded(s["coverage"]),
        "gospa_m": rounded(s["gospa_m"]),
        "false_tracks_per_frame": rounded(s["false_tracks_per_frame"], 2),
        "anees_objects": rounded(s["object_nees"]["anees"], 3),
        "wall_s": rounded(time.perf_counter() - t0, 1),
    }


def _point_task(task: tuple) -> dict:
    n, mode, seed, duration, scenario, warmup_s = task
    return run_scale_point(n, mode, seed, duration, scenario=scenario, warmup_s=warmup_s)


def _describe_point(task: tuple) -> str:
    n, mode, seed, *_ = task
    return f"{mode} {n} vehicles seed {seed}"


def run_scale_experiment(
    out_dir: str | Path,
    sizes: Sequence[int] = SIZES,
    seed: int = 0,
    duration: float = 10.0,
    warmup_s: float = 3.0,
    scenario: str = DEFAULT_SCENARIO,
    executor: Executor | None = None,
    progress: bool = True,
    fresh: bool = False,
) -> list[dict]:
    """Every size in both modes (the largest first, so that the pool ends with short runs) on ``executor``;
    writes the outputs (:func:`write_scale_outputs`) and returns the rows. Finished points are kept in
    ``out_dir/tasks`` (a rerun resumes; ``fresh``: start over)."""
    scenario_with_connected(scenario, max(sizes))  # a scenario that cannot scale fails before the runs
    tasks = [(n, mode, seed, duration, scenario, warmup_s) for n in sorted(sizes, reverse=True) for mode in MODES]
    t0 = time.perf_counter()
    executor = executor or Executor()
    store = TaskStore(out_dir, "scale", {"tasks": tasks, "network": NETWORK}, fresh)
    batch = run_all(_point_task, tasks, "experiment scale", _describe_point, executor, store, progress)
    rows = batch.results
    rows.sort(key=lambda r: (MODES.index(r["mode"]), r["vehicles"]))
    meta = {
        "scenario": scenario,
        "seed": seed,
        "duration_s": duration,
        "warmup_s": warmup_s,
        "network": NETWORK,
        "start": "cold",
        "host_compiled": COMPILED,
    }
    write_scale_outputs(rows, out_dir, meta)
    write_timing(out_dir, executor, {"points": batch}, time.perf_counter() - t0)
    return rows


# -------------------------------------------------------------------------------------- outputs


def fit_exponent(xs: Sequence[float], ys: Sequence[float]) -> float | None:
    """Slope of log y against log x (least squares) over the finite, positive pairs; None below two."""
    pts = [(x, y) for x, y in zip(xs, ys, strict=True) if x > 0 and y > 0 and math.isfinite(x) and math.isfinite(y)]
    if len(pts) < 2:
        return None
    x, y = np.log(np.array(pts)).T
    return float(np.polyfit(x, y, 1)[0])


def analyse(rows: Sequence[dict]) -> dict:
    """Per mode: the host cost's growth exponent against N, and the saturation point (module docstring)."""
    out = {}
    for mode in MODES:
        rs = sorted((r for r in rows if r["mode"] == mode), key=lambda r: r["vehicles"])
        if not rs:
            continue
        sat = next((r["vehicles"] for r in rs if r["dropped_queue_fraction"] > SATURATION_DROPS), None)
        realtime = None
        for r in rs:
            if r["host_cpu_ms_per_cycle"] is None or not r["host_cpu_ms_per_cycle"] <= CYCLE_BUDGET_MS:
                break
            realtime = r["vehicles"]
        out[mode] = {
            "host_cpu_exponent": fit_exponent([r["vehicles"] for r in rs], [r["host_cpu_ms_per_cycle"] for r in rs]),
            "bytes_exponent": fit_exponent([r["vehicles"] for r in rs], [r["bytes_per_s_total"] for r in rs]),
            "saturation_vehicles": sat,
            "realtime_vehicles": realtime,
        }
    return out


def _cell(v) -> str:
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:g}"
    return "" if v is None else str(v)


def write_scale_outputs(rows: Sequence[dict], out_dir: str | Path, meta: dict | None = None) -> dict[str, Path]:
    """scale.csv, scale.md (the claim, what was measured, every point), results.json and two PNG plots."""
    rows = list(rows)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    m = dict(meta or {})
    fits = analyse(rows)
    paths = {"csv": out / "scale.csv", "md": out / "scale.md", "json": out / "results.json"}
    with paths["csv"].open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(SCALE_COLUMNS)
        for r in rows:
            w.writerow([_cell(r.get(c)) for c in SCALE_COLUMNS])
    paths["json"].write_text(jsonout.dumps({"meta": m, "analysis": fits, "rows": rows}, indent=1) + "\n")

    def sat_text(mode: str) -> str:
        f = fits.get(mode)
        if f is None:
            return "not run"
        n = f["saturation_vehicles"]
        top = max(r["vehicles"] for r in rows if r["mode"] == mode)
        return f"from N = {n}" if n is not None else f"not within N <= {top}"

    def realtime_text(mode: str) -> str:
        f = fits.get(mode)
        if f is None:
            return "not run"
        n = f["realtime_vehicles"]
        return "at none of the sizes run" if n is None else f"up to N = {n}"

    def exp_text(mode: str, key: str) -> str:
        e = fits.get(mode, {}).get(key)
        return "n/a" if e is None else f"{e:.2f}"

    short = [
        ("mode", "mode"),
        ("vehicles", "N"),
        ("obstacles_in_scope", "obstacles"),
        ("bytes_per_s_per_vehicle", "B/s/veh"),
        ("load_fraction", "load"),
        ("delivered_fraction", "delivered"),
        ("dropped_queue_fraction", "queue drops"),
        ("age_s_mean", "age (s)"),
        ("host_cpu_ms_per_cycle", "host CPU ms/cycle"),
        ("fuse_cpu_ms_p50", "fuse ms p50"),
        ("vehicle_rmse_m", "vehicle RMSE (m)"),
        ("object_rmse_m", "object RMSE (m)"),
        ("coverage", "coverage"),
        ("gospa_m", "GOSPA (m)"),
    ]
    L = [
        "# Scaling: distributed priors against centralized raw data",
        "",
        f"Scenario {m.get('scenario', '?')} (its first N departing SUMO vehicles connected, the same traffic at "
        f"every N), seed {m.get('seed', '?')}, {m.get('duration_s', '?')} s per run from a cold start, scored "
        f"after {m.get('warmup_s', '?')} s; channel `{NETWORK}`: one shared 6 Mbit/s medium, 32 kB queue, "
        "1.5 % loss; messages signed. Columns: module docstring of `mapcontainer/experiments/scale.py`.",
        "",
        "## The claim and what we measured",
        "",
        "The paper: a centralized estimator's cost grows with the number of vehicles and their observations "
        "and its traffic with the raw data; compact priors keep both small.",
        "",
        f"- Host CPU per cycle grows as N^{exp_text('distributed', 'host_cpu_exponent')} distributed and "
        f"N^{exp_text('centralized', 'host_cpu_exponent')} centralized (log-log fit over the sizes run; "
        "centralized includes localizing every vehicle at the host).",
        f"- Traffic grows as N^{exp_text('distributed', 'bytes_exponent')} distributed and "
        f"N^{exp_text('centralized', 'bytes_exponent')} centralized.",
        f"- The medium saturates (queue drops above {100 * SATURATION_DROPS:g} % of messages): distributed "
        f"{sat_text('distributed')}, centralized {sat_text('centralized')}.",
        f"- The host keeps the 10 Hz cycle (host CPU per cycle <= {CYCLE_BUDGET_MS:g} ms, in process): distributed "
        f"{realtime_text('distributed')}, centralized {realtime_text('centralized')}; the host's inner loops "
        + {True: "compiled (numba).", False: "interpreted (numba not installed).", None: "(not recorded)."}[
            m.get("host_compiled")
        ],
        "",
        "## All points",
        "",
        "| " + " | ".join(h for _, h in short) + " |",
        "|" + "---|" * len(short),
    ]
    for r in rows:
        L.append("| " + " | ".join(_cell(r.get(k)) for k, _ in short) + " |")
    L += ["", "![cost](scale_cost.png)", "", "![channel](scale_channel.png)", ""]
    paths["md"].write_text("\n".join(L))
    paths.update(_plots(rows, fits, out))
    return paths


def _plots(rows: list[dict], fits: dict, out: Path) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written: dict[str, Path] = {}
    modes = [mode for mode in MODES if any(r["mode"] == mode for r in rows)]
    if not modes:
        return written

    def col(mode: str, key: str) -> tuple[list[float], list[float]]:
        rs = sorted((r for r in rows if r["mode"] == mode), key=lambda r: r["vehicles"])
        return [r["vehicles"] for r in rs], [r[key] for r in rs]

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for mode in modes:
        e = fits[mode]["host_cpu_exponent"]
        ax[0].plot(*col(mode, "host_cpu_ms_per_cycle"), "o-", label=f"{mode} (N^{e:.2f})" if e else mode)
        ax[1].plot(*col(mode, "fuse_cpu_ms_p50"), "o-", label=mode)
    ax[0].set(xscale="log", yscale="log", xlabel="connected vehicles N", ylabel="host CPU per cycle (ms)")
    ax[1].set(xscale="log", yscale="log", xlabel="connected vehicles N", ylabel="fuse call CPU, p50 (ms)")
    for a in ax:
        a.legend(fontsize=8)
        a.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    written["png_cost"] = out / "scale_cost.png"
    fig.savefig(written["png_cost"], dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    for mode in modes:
        ns, bps = col(mode, "bytes_per_s_total")
        ax[0].plot(ns, [8 * b for b in bps], "o-", label=mode)
        ax[1].plot(*col(mode, "delivered_fraction"), "o-", label=mode)
        ax[2].plot(*col(mode, "object_rmse_m"), "o-", label=f"{mode} objects")
        ax[2].plot(*col(mode, "vehicle_rmse_m"), "s--", label=f"{mode} vehicles")
    capacity = load_profile(NETWORK).bandwidth_bps
    ax[0].axhline(capacity, color="k", linestyle=":", label="medium capacity")
    ax[0].set(xscale="log", yscale="log", xlabel="connected vehicles N", ylabel="offered load (bit/s)")
    ax[1].set(xscale="log", xlabel="connected vehicles N", ylabel="delivered fraction", ylim=(0, 1.02))
    ax[2].set(xscale="log", xlabel="connected vehicles N", ylabel="RMSE (m)")
    for a in ax:
        a.legend(fontsize=8)
        a.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    written["png_channel"] = out / "scale_channel.png"
    fig.savefig(written["png_channel"], dpi=110)
    plt.close(fig)
    return written
