"""Geometric-link sweeps of ``mapc experiment network --radio``: distance (and the corner) and density.

**Distance** (``distance.csv``): blindspot-occluded — the ego (cv0) behind a connected vehicle (cv1) that
hides an obstacle 12 m ahead of it — with cv1 and the obstacle moved ``gap`` metres ahead of the ego
along the ring. From about 70 m on, cv1 is round the ring's corner: the block of buildings inside the
ring stands between them (NLOS). Distributed mode, warm start, each radio profile. Rows: PRR
(``delivered_fraction``), age of information, the obstacle's fused RMSE and coverage (scored within
``gap + 40`` m of the ego), the link's states (fractions of LOS / NLOSv / NLOS pair observations).

**Density** (``density.csv``): paper-urban with ``extra`` more (non-connected) vehicles spread over the
ring's lanes, each sending 10 Hz CAMs (the profile's background traffic); both modes (distributed warm
started, centralized cold: the host localizes every vehicle from its raw data, so its scoring starts
after ``warmup_s``); each radio profile with and without ETSI reactive DCC, and in distributed mode
with and without the CPM inclusion rules (``cpm=False``: without only); and the ideal link at the same
density as the reference; every point for each of ``seeds``. Rows add the mean CBR of the connected
vehicles, the radio drops by cause, ``rmse_vs_ideal``: the fused vehicle-pose RMSE over the ideal
link's at the same density, mode and seed (what the link costs), and ``rmse_vs_sparsest``: over the same
link's at the sweep's lowest density (what density costs). ``degradation.json`` gives, per mode, profile,
DCC and CPM setting and for each of the two ratios, its mean over the seeds at each density (with its
smallest and largest seed), and the lowest density (vehicles per km of ring) at which that mean is 10 %
worse (linear interpolation between points; None: not reached in the sweep; already at the sweep's
lowest density: that density, flagged ``..._at_or_below_lowest_density``, since the sweep cannot say
where below it the loss began).
"""

from __future__ import annotations

import csv
import itertools
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..channel import load_profile
from ..jsonout import rounded
from ..pipeline import PipelineResult
from ..radio.dcc import DccParams
from ..radio.link import RadioProfile
from ..sim.config import ScenarioConfig, VehicleSpec, load_scenario
from .executors import Executor
from .network import run_network_point
from .runner import run_all
from .store import TaskStore

__all__ = ["DEGRADATION", "GAPS_M", "EXTRA_VEHICLES", "run_radio_sweeps", "density_scenario", "gap_scenario"]

GAPS_M = (12.0, 40.0, 70.0, 100.0, 150.0, 200.0, 300.0)
EXTRA_VEHICLES = (0, 20, 40, 80, 120)
DEGRADATION = 0.10


def gap_scenario(gap_m: float, base: str = "blindspot-occluded") -> ScenarioConfig:
    """``base`` with cv1 ``gap_m`` ahead of the ego and its obstacle 12 m ahead of cv1."""
    sc = load_scenario(base)
    data = sc.model_dump()
    s0 = data["connected"][0]["s0_m"]
    data["connected"][1]["s0_m"] = s0 + gap_m
    data["obstacle_vehicles"] = data["obstacle_vehicles"][:1]
    data["obstacle_vehicles"][0]["s0_m"] = s0 + gap_m + 12.0
    data["name"] = f"{base}-gap{gap_m:g}"
    return ScenarioConfig.model_validate(data)


def density_scenario(extra: int, base: str = "paper-urban") -> ScenarioConfig:
    """``base`` with ``extra`` more obstacle vehicles spread evenly over its ring's lanes."""
    sc = load_scenario(base)
    data = sc.model_dump()
    lanes = 2 * sc.map.lanes_per_direction
    ring_m = 2 * (sc.map.length_m + sc.map.width_m)
    speed = float(np.mean([v.speed_mps for v in sc.connected]))
    for i in range(extra):
        data["obstacle_vehicles"].append(
            VehicleSpec(lane=i % lanes, s0_m=(i + 0.37) * ring_m / max(extra, 1), speed_mps=speed).model_dump()
        )
    data["name"] = f"{base}+{extra}"
    return ScenarioConfig.model_validate(data)


def vehicles_per_km(sc: ScenarioConfig) -> float:
    ring_km = 2 * (sc.map.length_m + sc.map.width_m) / 1000.0
    return (len(sc.connected) + len(sc.obstacle_vehicles)) / ring_km


def _with_dcc(profile: RadioProfile, on: bool) -> RadioProfile:
    radio = profile.radio.model_copy(update={"dcc": DccParams(enabled=on)})
    return profile.model_copy(update={"radio": radio, "name": profile.name + ("+dcc" if on else "")})


def radio_figures(res: PipelineResult) -> dict[str, Any]:
    """The radio columns of a row: CBR, drops by cause, link-state fractions (NaN on a classic link)."""
    st = res.channel_stats
    out: dict[str, Any] = {}
    cbr = [v["mean"] for k, v in st.get("cbr", {}).items() if k in res.tx_msgs or k == res.ego]
    out["cbr_mean"] = rounded(float(np.mean(cbr))) if cbr else float("nan")
    drops = st.get("radio_drops", {})
    offered = max(1, st["offered_msgs"])
    for cause in ("dcc", "sensing", "propagation", "collision", "half_duplex"):
        out[f"drop_{cause}_fraction"] = rounded(drops.get(cause, 0) / offered) if drops else float("nan")
    states = st.get("link_states", {})
    total = sum(states.values())
    for k in ("los", "nlosv", "nlos"):
        out[f"state_{k}_fraction"] = rounded(states[k] / total) if total else float("nan")
    dcc_bytes = st.get("radio_drop_bytes", {}).get("dcc", 0)
    sent = sum(res.tx_bytes.values()) - dcc_bytes
    out["bytes_on_air_per_s_per_vehicle"] = rounded(sent / res.duration_s / max(1, len(res.tx_msgs)), 1)
    return out


def _task(task: tuple) -> dict:
    kind, x, profile_name, dcc, cpm, mode, seed, duration, warmup = task
    if kind == "distance":
        sc, radius = gap_scenario(x), x + 40.0
    else:
        sc, radius = density_scenario(int(x)), 50.0
    prof = load_profile(profile_name)
    if isinstance(prof, RadioProfile):
        prof = _with_dcc(prof, dcc)
    row = run_network_point(
        prof,
        mode,
        seed,
        duration,
        scenario=sc,
        warmup_s=warmup,
        radius_m=radius,
        start="warm" if mode == "distributed" else "cold",  # centralized: the host localizes from raw data
        cpm_rules=cpm,
        extra=radio_figures,
    )
    row.update(
        {
            "sweep": kind,
            "x": x,
            "vehicles_per_km": rounded(vehicles_per_km(sc), 1),
            "dcc": dcc,
            "cpm": cpm,
            "radio_profile": profile_name,
        }
    )
    return row


def run_radio_sweeps(
    out_dir: str | Path,
    profiles: tuple[str, ...] = ("its-g5",),
    sweeps: tuple[str, ...] = ("distance", "density"),
    quick: bool = False,
    seeds: tuple[int, ...] = (0,),
    executor: Executor | None = None,
    duration: float | None = None,
    warmup_s: float = 1.0,
    progress: bool = True,
    gaps_m: tuple[float, ...] | None = None,
    extra_vehicles: tuple[int, ...] | None = None,
    density_profiles: tuple[str, ...] | None = None,
    cpm: bool = True,
    fresh: bool = False,
) -> list[dict]:
    """Run the sweeps and write ``distance.csv``, ``density.csv``, ``degradation.json`` and the PNGs.

    ``seeds``: every point runs once per seed; ``gaps_m``, ``extra_vehicles``: the grids (default
    :data:`GAPS_M`, :data:`EXTRA_VEHICLES`; quick: 3 and 2 points); ``density_profiles``: the profiles of the
    density sweep (default ``profiles``); ``cpm``: also run the density points with the CPM rules. Finished
    points are kept in ``out_dir/tasks`` (the same call resumes; ``fresh``: start over)."""
    if not seeds:
        raise ValueError("seeds must name at least one seed")
    dur = duration if duration is not None else (3.0 if quick else 8.0)
    if dur <= warmup_s:
        raise ValueError(f"duration ({dur} s) must exceed warmup_s ({warmup_s} s)")
    gaps = gaps_m or ((12.0, 100.0, 200.0) if quick else GAPS_M)
    extras = extra_vehicles or ((0, 60) if quick else EXTRA_VEHICLES)
    tasks: list[tuple] = []
    for seed in seeds:
        if "distance" in sweeps:
            tasks += [
                ("distance", g, p, False, False, "distributed", seed, dur, warmup_s) for p in profiles for g in gaps
            ]
        if "density" in sweeps:
            for n, mode in itertools.product(extras, ("distributed", "centralized")):
                tasks.append(("density", n, "ideal", False, False, mode, seed, dur, warmup_s))
                for p, dcc in itertools.product(density_profiles or profiles, (False, True)):
                    tasks.append(("density", n, p, dcc, False, mode, seed, dur, warmup_s))
                    if mode == "distributed" and cpm:
                        tasks.append(("density", n, p, dcc, True, mode, seed, dur, warmup_s))
    t0 = time.perf_counter()
    out = Path(out_dir)
    store = TaskStore(out, "network-radio", {"format": 1}, fresh=fresh)  # each task carries its settings
    batch = run_all(
        _task,
        tasks,
        "experiment network --radio",
        lambda t: f"{t[0]} {t[1]} {t[2]}{' +dcc' if t[3] else ''}{' +cpm' if t[4] else ''} {t[5]} seed {t[6]}",
        executor,
        store,
        progress,
    )
    rows = list(batch.results)
    rows.sort(key=lambda r: (r["sweep"], r["mode"], r["radio_profile"], r["dcc"], r["cpm"], r["x"], r["seed"]))
    _reference(rows)
    out.mkdir(parents=True, exist_ok=True)
    for kind in ("distance", "density"):
        part = [r for r in rows if r["sweep"] == kind]
        if part:
            with open(out / f"{kind}.csv", "w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=list(part[0]))
                w.writeheader()
                w.writerows(part)
    deg = degradation(rows)
    meta = {
        "seeds": list(seeds),
        "duration_s": dur,
        "warmup_s": warmup_s,
        "quick": quick,
        "profiles": list(profiles),
        "wall_s": round(time.perf_counter() - t0, 1),
        "tasks": len(tasks),
        "resumed": batch.resumed,
        "task_cpu_s": round(sum(t.get("cpu_s", 0.0) for t in batch.timing if t), 1),
        "degradation_threshold": DEGRADATION,
    }
    (out / "degradation.json").write_text(json.dumps({"meta": meta, "degradation": deg}, indent=1, default=str) + "\n")
    _plots(rows, out)
    return rows


def _reference(rows: list[dict]) -> None:
    """``rmse_vs_ideal``: vehicle RMSE over the ideal link's at the same density, mode and seed (the link's
    cost); ``rmse_vs_sparsest``: over the same link's (profile, DCC, CPM) at the sweep's lowest density,
    same mode and seed (what density costs, the estimator's own share in dense traffic included)."""
    dens = [r for r in rows if r["sweep"] == "density"]
    ideal = {(r["mode"], r["x"], r["seed"]): r for r in dens if r["radio_profile"] == "ideal"}
    x0 = min((r["x"] for r in dens), default=None)
    link = lambda r: (r["mode"], r["radio_profile"], r["dcc"], r["cpm"], r["seed"])  # noqa: E731
    sparse = {link(r): r for r in dens if r["x"] == x0}
    for r in rows:
        r["rmse_vs_ideal"] = _ratio(r, ideal.get((r["mode"], r["x"], r["seed"])) if r["sweep"] == "density" else None)
        r["rmse_vs_sparsest"] = _ratio(r, sparse.get(link(r)) if r["sweep"] == "density" else None)


def _ratio(r: dict, ref: dict | None) -> float:
    ok = ref is not None and ref["vehicle_rmse_m"] and np.isfinite(ref["vehicle_rmse_m"])
    return rounded(r["vehicle_rmse_m"] / ref["vehicle_rmse_m"]) if ok else float("nan")


READOUTS = {"rmse_vs_ideal": "degrades_10pct_at_per_km", "rmse_vs_sparsest": "density_degrades_10pct_at_per_km"}
"""The two 10 % read-outs of :func:`degradation`: column -> its key in ``degradation.json``."""


def degradation(rows: list[dict]) -> list[dict]:
    """Per mode, radio profile, DCC and CPM, for each column of :data:`READOUTS`: its mean over the seeds at
    each density (and its smallest and largest seed), and the density where that mean first reaches
    1 + DEGRADATION (``at_or_below_lowest_density`` when the sweep's first point already does)."""
    out = []
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        if r["sweep"] == "density" and r["radio_profile"] != "ideal":
            groups.setdefault((r["mode"], r["radio_profile"], r["dcc"], r["cpm"]), []).append(r)
    for (mode, prof, dcc, cpm), rs in sorted(groups.items()):
        x = sorted({r["vehicles_per_km"] for r in rs})
        entry: dict[str, Any] = {"mode": mode, "profile": prof, "dcc": dcc, "cpm": cpm, "densities_per_km": x}
        for col, key in READOUTS.items():
            per_seed = [np.asarray([r.get(col, np.nan) for r in rs if r["vehicles_per_km"] == xi], float) for xi in x]
            y = [float(np.nanmean(v)) if np.isfinite(v).any() else float("nan") for v in per_seed]
            at, below = _crossing(x, y)
            entry.update(
                {
                    f"{col}_seeds": [int(np.isfinite(v).sum()) for v in per_seed],
                    col: [rounded(v) for v in y],
                    f"{col}_min": [rounded(float(np.nanmin(v))) if np.isfinite(v).any() else None for v in per_seed],
                    f"{col}_max": [rounded(float(np.nanmax(v))) if np.isfinite(v).any() else None for v in per_seed],
                    key: None if at is None else round(float(at), 1),
                    f"{key}_at_or_below_lowest_density": below,
                }
            )
        out.append(entry)
    return out


def _crossing(x: list[float], y: list[float]) -> tuple[float | None, bool]:
    """The first x where y reaches 1 + DEGRADATION (linear interpolation), and whether it is x[0]."""
    for i, yi in enumerate(y):
        if np.isfinite(yi) and yi >= 1 + DEGRADATION:
            if i == 0:
                return x[0], True
            x0, y0 = x[i - 1], y[i - 1]
            return (x0 + (x[i] - x0) * (1 + DEGRADATION - y0) / (yi - y0) if yi != y0 else x[i]), False
    return None, False


def _plots(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dist = [r for r in rows if r["sweep"] == "distance"]
    if dist:
        fig, ax = plt.subplots(1, 3, figsize=(14, 4))
        for prof in sorted({r["radio_profile"] for r in dist}):
            rs = [r for r in dist if r["radio_profile"] == prof]
            x = _xs(rs, "x")
            ax[0].plot(x, _mean_by_x(rs, "x", "delivered_fraction"), "o-", label=prof)
            ax[1].plot(x, _mean_by_x(rs, "x", "age_s_mean"), "o-", label=prof)
            ax[2].plot(x, _mean_by_x(rs, "x", "object_coverage"), "o-", label=f"{prof}: coverage")
            ax[2].plot(x, _mean_by_x(rs, "x", "state_nlos_fraction"), "x--", label=f"{prof}: NLOS fraction")
        for a, lab in zip(ax, ("PRR cv1 -> host", "age of information (s)", "obstacle coverage / NLOS"), strict=True):
            a.set(xlabel="gap ego -> cv1 along the ring (m)", ylabel=lab)
            a.legend(fontsize=7)
        fig.suptitle("blindspot-occluded: cv1 and its hidden obstacle moved ahead (the corner at about 70 m)")
        fig.tight_layout()
        fig.savefig(out / "radio_distance.png", dpi=110)
        plt.close(fig)
    dens = [r for r in rows if r["sweep"] == "density" and not r["cpm"]]
    if dens:
        fig, ax = plt.subplots(1, 4, figsize=(18, 4))
        for (mode, prof, dcc), rs in sorted(_group(dens).items()):
            k = "vehicles_per_km"
            x = _xs(rs, k)
            lab = f"{mode[:4]} {prof}{' +DCC' if dcc else ''}"
            if prof != "ideal":
                ax[0].plot(x, _mean_by_x(rs, k, "cbr_mean"), "o-", label=lab)
                ax[1].plot(x, _mean_by_x(rs, k, "delivered_fraction"), "o-", label=lab)
                ax[2].plot(x, _mean_by_x(rs, k, "rmse_vs_ideal"), "o-", label=lab)
            ax[3].plot(x, _mean_by_x(rs, k, "bytes_on_air_per_s_per_vehicle"), "o-", label=lab)
        ax[2].axhline(1 + DEGRADATION, color="grey", ls=":")
        for a, lab in zip(
            ax,
            (
                "CBR (connected vehicles)",
                "PRR to the host",
                "vehicle RMSE / ideal link's",
                "bytes on air / s / vehicle",
            ),
            strict=True,
        ):
            a.set(xlabel="vehicles per km of ring", ylabel=f"{lab} (mean over seeds)")
            a.legend(fontsize=6)
        fig.tight_layout()
        fig.savefig(out / "radio_density.png", dpi=110)
        plt.close(fig)


def _xs(rows: list[dict], xkey: str) -> list[float]:
    return sorted({r[xkey] for r in rows})


def _mean_by_x(rows: list[dict], xkey: str, ykey: str) -> list[float]:
    """``ykey``'s mean over the seeds at each ``xkey`` (in :func:`_xs` order; the plots show seed means)."""
    return [float(np.nanmean([float(r[ykey]) for r in rows if r[xkey] == x])) for x in _xs(rows, xkey)]


def _group(rows: list[dict]) -> dict[tuple, list[dict]]:
    g: dict[tuple, list[dict]] = {}
    for r in rows:
        g.setdefault((r["mode"], r["radio_profile"], r["dcc"]), []).append(r)
    return g
