"""The paper experiment's outputs: report.md, runs.csv and the PNG plots."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .figures import run_rmse
from .onoff import section as downlink_section
from .settings import (
    BLINDSPOT_SCENARIOS,
    CONNECTED,
    DENSITIES,
    EGO,
    GROSS_ERROR_M,
    LOCALIZED_HOLD_S,
    LOCKED_M,
    PAPER,
)

__all__ = ["plots", "report", "runs_csv"]

ESTIMATE_LABELS = {
    "gnss": "GNSS alone",
    "onboard": "vehicle alone (filtered on-board)",
    "map_matching": "per-frame map matching",
    "cooperative": "cooperative (host, fused)",
    "centralized": "centralized joint estimator (raw observations)",
}
VIEW_LABELS = {"ego_only": "ego only", "cooperative": "cooperative", "centralized": "centralized joint"}


def _fmt(x, nd: int = 3) -> str:
    if x is None:  # a figure with nothing to compute it from (objects_summary of no frames): like NaN
        return "n/a"
    if isinstance(x, (list, tuple)):
        return "[" + ", ".join(_fmt(v, nd) for v in x) + "]"
    if isinstance(x, float):
        return "inf" if x == math.inf else "n/a" if not math.isfinite(x) else f"{x:.{nd}f}"
    return str(x)


def _method(res: dict) -> list[str]:
    s = res["settings"]
    start = (
        "cold: every vehicle initialises from GNSS, the map's driving directions and the camera"
        if s["start"] == "cold"
        else "WARM (a labelled variant): every vehicle starts from its true pose plus seeded noise"
    )
    return [
        "## Method",
        "",
        f"* **Seeds**: run *i* uses seed {res['seed']} + *i*: {res['seeds']} seeds"
        + (
            f" (the evaluation range starts at {s['evaluation_seeds_from']}; development never uses it)."
            if res["seeds"] == "evaluation"
            else f" — NOT the evaluation range (from {s['evaluation_seeds_from']}): not figures to report."
        ),
        "* **Runs differ in traffic and in noise**: start positions, speeds, speed profiles and pedestrians are "
        "drawn per run from the seed, as are every sensor's noise, the HD-map error, the calibration errors and the "
        "clock offsets.",
        "* **Realistic error sources, all on** (`mapcontainer/sim/errors.py`, values and sources in the scenario "
        "configs): HD-map error (the vehicles and the host use an erroneous map, the world renders from the true one), "
        "camera calibration error, time-correlated detector errors with approximately right covariances, class "
        "confusion and clutter, per-vehicle clock offsets. The sensitivity table turns each off in turn.",
        f"* **Start**: {start}.",
        "* **Downlink**: "
        + (
            "on: after each solve the host sends every vehicle what the others know about it (its own share "
            "removed); *vehicle alone* is then the vehicle's on-board estimate with it fused (docs/downlink.md)."
            if s.get("downlink")
            else "off: the vehicles localize alone (`--downlink`: the host's downlink fused on board)."
        )
        + (
            " Every run ran a second time with the downlink the other way (the same seed): *The downlink on and "
            "off* compares the two."
            if s.get("downlink_compare")
            else ""
        ),
        f"* **Duration and burn-in**: {s['duration_s']:g} s per run; every frame from t = {s['burnin_s']:g} s on is "
        "scored (steady state); the error against time covers the whole run, start-up included.",
        f"* **Runs**: {res['runs']} per simulated scenario; {s['real_vehicle_runs']} per test-site scenario and "
        f"landmark density; {s['sensitivity_runs']} per scenario and error setting for the sensitivity table.",
        "* **Channel**: ideal, distributed mode (this experiment is about estimation; `mapc experiment network` "
        "sweeps the channel).",
        "* **Vehicle estimates**: *GNSS alone* = the raw fix; *vehicle alone* = the vehicle's own filtered on-board "
        "estimate (what it knows without cooperation, and what it sends); *per-frame map matching* = this frame's "
        "camera evidence alone (with a weak prior; in fallback the filtered pose), the baseline of map matching "
        "without a tracker; *cooperative* = the host's fused pose. Horizontal map-frame RMSE (rms1).",
        f"* **Targets** (rms2): true obstacles within {s['radius_m']:g} m of the ego, matched to fused objects "
        "(Hungarian, 3 m gate), horizontal error in the ego's body frame. *Ego only* = the same host estimator fed "
        "only the ego's messages. Beside every RMSE: coverage (matched / true in scope), false tracks (fused objects "
        "in scope matching no obstacle) and GOSPA (`mapcontainer.evaluation`: order 2, alpha 2, cutoff stated there) "
        "split into localization, missed and false parts.",
        "",
    ]


def _sim_table(sim: dict) -> list[str]:
    keys = list(sim)
    L = ["| RMSE (m), steady state | " + " | ".join(keys) + " |", "|---" * (len(keys) + 1) + "|"]
    for m, label in ESTIMATE_LABELS.items():
        L.append(f"| ego: {label} | " + " | ".join(_fmt(sim[k]["ego_rmse_m"][m]) for k in keys) + " |")
    for m, label in ESTIMATE_LABELS.items():
        L.append(f"| all vehicles: {label} | " + " | ".join(_fmt(sim[k]["vehicles_rmse_m"][m]) for k in keys) + " |")
    for m, label in VIEW_LABELS.items():
        L.append(f"| targets: {label} | " + " | ".join(_fmt(sim[k]["target_rmse_m"][m]) for k in keys) + " |")
    for m, label in list(VIEW_LABELS.items())[:2]:
        L.append(
            f"| targets both views estimate: {label} | "
            + " | ".join(_fmt(sim[k]["target_rmse_common_m"][m]) for k in keys)
            + " |"
        )
    for m, label in VIEW_LABELS.items():
        o = [sim[k]["objects"][m] for k in keys]
        L.append(f"| target coverage: {label} | " + " | ".join(_fmt(x.get("coverage"), 2) for x in o) + " |")
        L.append(
            f"| false tracks per frame: {label} | " + " | ".join(_fmt(x.get("false_per_frame"), 2) for x in o) + " |"
        )
        L.append(
            f"| GOSPA (m) [loc / missed / false, m²]: {label} | "
            + " | ".join(
                f"{_fmt(x.get('gospa_m'), 2)} [{_fmt(x.get('gospa_localization_m2'), 2)} / "
                f"{_fmt(x.get('gospa_missed_m2'), 2)} / {_fmt(x.get('gospa_false_m2'), 2)}]"
                for x in o
            )
            + " |"
        )
    L.append(
        f"| runs where a vehicle lost lock (filtered pose > {GROSS_ERROR_M:g} m after the burn-in; ego / any) | "
        + " | ".join(
            f"{sim[k]['lost_lock_runs']['ego']} / {sim[k]['lost_lock_runs']['any_vehicle']} of {sim[k]['runs']}"
            for k in keys
        )
        + " |"
    )
    return L


def _seconds(x: float) -> str:
    return "never" if x == math.inf else _fmt(x, 1)


def _startup(sim: dict) -> list[str]:
    keys = [k for k in sim if sim[k].get("startup")]
    if not keys:
        return []
    L = [
        "## Cold start (every vehicle of every run, from GNSS, no prior)",
        "",
        f"*Time to localize*: from a vehicle's first frame to the start of the first stretch in which its filtered "
        f"pose stays within {LOCKED_M:g} m of the truth for {LOCALIZED_HOLD_S:g} s (or to the run's end when less "
        "remains). A vehicle that never does is *never* and counts as infinitely late: the q-th percentile is the "
        "time by which q % of the vehicle starts had localized. From that frame on, a frame is *gross* when the "
        f"filtered pose is off by more than {GROSS_ERROR_M:g} m (or the vehicle has no pose), and *silent* when it is "
        "gross while the vehicle says map_matching: it lost lock without saying so. Pass/fail in *Targets*.",
        "",
        "| scenario | vehicle starts | time to localize (s): median | p90 | p95 | max | never |",
        "|---|---|---|---|---|---|---|",
    ]
    for key in keys:
        f = sim[key]["startup"]["time_to_localize_s"]
        L.append(
            f"| {key} | {f['vehicles']} | {_seconds(f['median'])} | {_seconds(f['p90'])} | {_seconds(f['p95'])} | "
            f"{_seconds(f['max'])} | {f['never']} ({_fmt(100 * f['never_fraction'], 1)} %) |"
        )
    L += [
        "",
        "| scenario | vehicle-frames after localizing | gross | silent | runs with a silent loss "
        "| before localizing: silent frames (runs) |",
        "|---|---|---|---|---|---|",
    ]
    for key in keys:
        st = sim[key]["startup"]
        a, b = st["after_localized"], st["before_localized"]
        L.append(
            f"| {key} | {a['frames']} | {a['gross_frames']} ({_fmt(100 * a['gross_fraction'], 2)} %) | "
            f"{a['silent_frames']} | {a['silent_runs']} of {st['runs']} | {b['silent_frames']} ({b['silent_runs']}) |"
        )
    L += [
        "",
        f"At each whole second, the fraction of vehicles that say map_matching, are within {LOCKED_M:g} m in that "
        f"frame, have localized by then, and are off by more than {GROSS_ERROR_M:g} m (a vehicle without a pose "
        "yet is none of the last three):",
        "",
        "| scenario | t (s) | map matching | within | localized | gross |",
        "|---|---|---|---|---|---|",
    ]
    for key in keys:
        for t, a in sim[key]["startup"]["at"].items():
            L.append(
                f"| {key} | {t} | {_fmt(a['map_matching'], 2)} | {_fmt(a['accurate'], 2)} | "
                f"{_fmt(a['localized'], 2)} | {_fmt(a['gross'], 2)} |"
            )
    L.append("")
    return L


def _test_site(res: dict) -> list[str]:
    p1 = PAPER["res1"]
    L = [
        "## Test-site scenarios (Tables res1 and res2)",
        "",
        "Each at two landmark densities: *dense* (40 lamps + 16 signs: the presets were densified after the res2 "
        "targets were first written) and *sparse* (14 lamps + 4 signs, the original density).",
        "",
        "Table res1, perception overlap (obstacle RMSE, m; coverage in brackets):",
        "",
        "| | ego car | connected car | fused (proposed) | (1/a²+1/b²)^-1/2 |",
        "|---|---|---|---|---|",
        *(
            f"| paper, experiment {i + 1} | {p1['ego_car_m'][i]} | {p1['connected_car_m'][i]} | {p1['fused_m'][i]} | |"
            for i in range(2)
        ),
    ]
    for density in DENSITIES:
        ov = res["overlap"].get(density)
        if ov:
            cells = [
                f"{_fmt(ov[f'{n}_m'])} ({_fmt(ov['objects'][n].get('coverage'), 2)})"
                for n in ("ego_car", "connected_car", "fused")
            ]
            L.append(
                f"| ours, {density} ({ov['runs']} runs) | "
                + " | ".join(cells)
                + f" | {_fmt(ov['independent_fusion_m'])} |"
            )
    L += [
        "",
        "Table res2, blind spot (RMSE, m). The connected car's fused pose beside its own estimates; the obstacle "
        "with its coverage, the coverage the ego alone reaches, and the runs in which the ego or the connected car "
        f"lost lock (filtered pose > {GROSS_ERROR_M:g} m after the burn-in):",
        "",
        "| | connected car: paper | fused | on-board | per-frame MM | obstacle: paper | ours | coverage "
        "| ego-only coverage | lost lock |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key in BLINDSPOT_SCENARIOS:
        p = PAPER["res2"][key]
        for density in DENSITIES:
            b = res["blindspot"].get(key, {}).get(density)
            if not b:
                continue
            L.append(
                f"| ({key}) {density} | {p['connected_car_m']} | {_fmt(b['connected_car_m'])} | "
                f"{_fmt(b['connected_car_onboard_m'])} | {_fmt(b['connected_car_map_matching_m'])} | "
                f"{p['obstacle_m']} | "
                f"{_fmt(b['obstacle_m'])} | {_fmt(b['objects']['cooperative'].get('coverage'), 2)} | "
                f"{_fmt(b['objects']['ego_only'].get('coverage'), 2)} | {b['lost_lock_runs']} of {b['runs']} |"
            )
    L.append("")
    return L


def _consistency(sim: dict) -> list[str]:
    L = [
        "## Consistency (NEES)",
        "",
        "Two forms. *Per run*: each run's mean NEES is one sample (samples within a run are correlated in time); "
        "ANEES = their mean, against the 95 % band for n = runs — lenient: outside it is a real inconsistency. "
        "*Per cell*: for each (frame, object or vehicle) estimated in at least 5 runs, the mean NEES over those "
        "independent runs against the band of that many samples; the fraction of cells inside (0.95 expected).",
        "",
        "| scenario | estimate | dof | ANEES | band | inside | per-run 5/50/95 % | cells | cells inside |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    labels = {
        "objects_cooperative_3d": "objects, cooperative",
        "vehicles_cooperative_6dof": "vehicle poses, fused",
        "vehicles_onboard_6dof": "vehicle poses, on-board filtered",
        "vehicles_map_matching_6dof": "vehicle poses, per-frame map matching",
    }
    for key in sim:
        for name, label in labels.items():
            c = sim.get(key, {}).get("consistency", {}).get(name)
            if not c or "anees" not in c:
                continue
            L.append(
                f"| {key} | {label} | {c['dof']} | {_fmt(c['anees'], 2)} | {_fmt(c['band'], 2)} | "
                f"{'yes' if c['inside'] else 'NO'} | {_fmt(c['per_run_p5_p50_p95'], 2)} | {c['cells']} | "
                f"{_fmt(c['cells_inside_fraction'], 2)} |"
            )
    L.append("")
    return L


def _sensitivity(res: dict) -> list[str]:
    sens = res.get("sensitivity") or {}
    if not sens:
        return []
    variants = list(sens)
    rows = list(sens[variants[0]])
    L = [
        "## Sensitivity to the error sources",
        "",
        f"The headline figures (steady-state RMSE in m, coverage as a fraction, the fused estimates' ANEES: 6 and 3 "
        f"expected) on the first "
        f"{res['settings']['sensitivity_runs']} seeds, the same seeds in every column: all error sources on, all off "
        "(ideal map and sensors), and each source off in turn. Test-site columns: dense landmarks.",
        "",
        "| figure | " + " | ".join(v.replace("_", " ") for v in variants) + " |",
        "|---" * (len(variants) + 1) + "|",
    ]
    for row in rows:
        L.append(f"| {row} | " + " | ".join(_fmt(sens[v].get(row, float("nan"))) for v in variants) + " |")
    L.append("")
    return L


def _efficiency(sim: dict) -> list[str]:
    """Distributed against the centralized joint estimator on the same runs."""
    keys = [k for k in sim if sim[k].get("efficiency")]
    if not keys:
        return []
    effs = [sim[k]["efficiency"] for k in keys]
    vids = sorted({v for e in effs for v in e["vehicles"]})
    L = [
        "## Distributed against the centralized joint estimator",
        "",
        "Each simulation run again in centralized mode (the same seed: the same world, sensors and link): the "
        "vehicles send their raw observations and the host estimates every vehicle and object in one joint filter "
        "(`mapcontainer/fusion/joint.py`). Efficiency = centralized MSE / distributed MSE (1: the distributed "
        "architecture is as accurate as the joint optimum), steady state. An efficiency is a figure of merit only "
        "where the reference is consistent: the reference's ANEES with its 95 % band says where it is valid.",
        "",
        "| efficiency | " + " | ".join(keys) + " |",
        "|---" * (len(keys) + 1) + "|",
    ]
    for v in vids:
        L.append(f"| vehicle {v} | " + " | ".join(_fmt(e["vehicles"].get(v), 2) for e in effs) + " |")
    L.append("| all vehicles | " + " | ".join(_fmt(e["all_vehicles"], 2) for e in effs) + " |")
    L.append("| targets (ego frame) | " + " | ".join(_fmt(e["targets"], 2) for e in effs) + " |")
    L.append("| objects (map frame) | " + " | ".join(_fmt(e["objects"], 2) for e in effs) + " |")
    for what in ("vehicles", "objects"):
        cells = []
        for e in effs:
            r = e.get("reference_nees", {}).get(what, {})
            band = r.get("band") or [float("nan"), float("nan")]
            ok = "valid" if e.get("valid", {}).get(what) else "NOT VALID"
            cells.append(f"{_fmt(r.get('anees') or float('nan'), 2)} [{_fmt(band[0], 2)}, {_fmt(band[1], 2)}]: {ok}")
        L.append(f"| reference ANEES, {what} [95 % band] | " + " | ".join(cells) + " |")
    L.append(
        "| bytes per message, distributed / centralized | "
        + " | ".join(
            f"{_fmt(e['bytes_per_message']['distributed'], 0)} / {_fmt(e['bytes_per_message']['centralized'], 0)} "
            f"({_fmt(e['bytes_ratio'], 1)}×)"
            for e in effs
        )
        + " |"
    )
    return [*L, ""]


def _bytes(res: dict) -> list[str]:
    m = (res.get("bytes") or {}).get("measured")
    if not m:
        return []
    v, r = m["variants"], m["ratio"]
    L = [
        "## Bandwidth",
        "",
        f"Measured from the messages of {len(m['seeds'])} {m.get('scenario', 'paper-urban')} runs of "
        f"{m['duration_s']:g} s (seeds "
        f"{m['seeds'][0]}–{m['seeds'][-1]}), every vehicle but the host vehicle, encoded as on the wire; *signed* = "
        "bytes on the air (ECDSA P-256, the certificate about once a second). Centralized mode sends the lane mask at "
        "the resolution the host's matcher uses.",
        "",
        "| message | bytes/message | signed | bytes/s per vehicle | signed |",
        "|---|---|---|---|---|",
    ]
    labels = {
        "distributed": "distributed: VehiclePrior",
        "centralized": "centralized: RawObservations",
        "centralized_no_lane_mask": "centralized without the lane mask",
        "centralized_camera_resolution": "centralized, lane mask at camera resolution (before)",
    }
    for name, label in labels.items():
        x = v.get(name)
        if x:
            L.append(
                f"| {label} | {_fmt(x['bytes_per_message'], 0)} | {_fmt(x.get('bytes_per_message_signed'), 0)} | "
                f"{_fmt(x['bytes_per_s_per_vehicle'], 0)} | {_fmt(x.get('bytes_per_s_per_vehicle_signed'), 0)} |"
            )
    L += [
        "",
        f"Ratio centralized / distributed per message: {_fmt(r['with_lane_mask_per_message'], 1)}× with the lane mask, "
        f"{_fmt(r['without_lane_mask_per_message'], 1)}× without it; signed "
        f"{_fmt(r.get('with_lane_mask_per_message_signed'), 1)}× and "
        f"{_fmt(r.get('without_lane_mask_per_message_signed'), 1)}×; "
        f"per second the same (both modes send one message per frame: "
        f"{_fmt(r['with_lane_mask_per_s'], 1)}× and {_fmt(r['without_lane_mask_per_s'], 1)}×).",
        "",
    ]
    return L


def _scenario_flags(res: dict) -> str:
    """`` --scenario NAME`` for each preset run in place of the paper's (none for the paper's own), and
    `` --downlink on|both`` when the downlink was on or compared."""
    given = res["settings"].get("scenarios") or {}
    flags = "".join(f" --scenario {name}" for key, name in given.items() if key == name)
    if res["settings"].get("downlink"):
        return flags + " --downlink on"  # compared too: only from Python (the method says so)
    return flags + (" --downlink both" if res["settings"].get("downlink_compare") else "")


def report(res: dict) -> str:
    sim = res["simulation"]
    L = [
        "# Map Container: reproduction of the paper's results",
        "",
        f"`mapc experiment paper --runs {res['runs']} --seed {res['seed']}{_scenario_flags(res)}`. Raw numbers: "
        "`results.json`; per-run figures: `runs.csv`; what the runs cost and where they ran: `timing.json` (the "
        "one output that differs between two runs of the command; everything here follows from the seeds).",
        "",
        *_method(res),
        "## Simulation (paper figure exp_sim)",
        "",
        "The paper's figure exp_sim is a bar chart without printed values; its claims are qualitative.",
        "",
        *_sim_table(sim),
        "",
        "Paper's claims on our steady-state numbers:" if "claims" in res else "",
        "",
    ]
    if "claims" not in res:
        L.append("The paper's claims are about its own scenarios: not evaluated on these.")
    for c in res.get("claims", []):
        L.append(f"* {'HOLDS' if c['holds'] else 'DOES NOT HOLD'}: {c['claim']} — {_fmt(c['values'])}")
    L += [
        "",
        "![exp_sim](exp_sim.png)",
        "",
        "RMSE against time (per-second buckets; line = mean of the runs' RMSE in the bucket, band = 5–95 % over runs):",
        "",
        "![over time](over_time.png)",
        "",
        *_startup(sim),
        *(
            _test_site(res) + ["![test site](real_vehicle.png)", ""]
            if res["overlap"] or any(res["blindspot"].values())
            else []
        ),
        *_consistency(sim),
        *_sensitivity(res),
        *_efficiency(sim),
        *_bytes(res),
        *downlink_section(res),
        "## Targets",
        "",
        "| target | ours | threshold | result |",
        "|---|---|---|---|",
    ]
    for t in res["targets"]:
        L.append(f"| {t['target']} | {_fmt(t['value'])} | {_fmt(t['threshold'])} | {'PASS' if t['pass'] else 'FAIL'} |")
    L.append("")
    return "\n".join(L)


_CSV_FIGURES = {
    "sim": [f"{EGO}:{m}" for m in ESTIMATE_LABELS] + [f"targets:{m}" for m in VIEW_LABELS],
    "overlap": ["obstacle:ego_car", "obstacle:connected_car", "obstacle:fused"],
    "blindspot": [f"{CONNECTED}:cooperative", f"{CONNECTED}:onboard", "obstacle:ego_only", "obstacle:cooperative"],
}


def runs_csv(results: list[dict], burnin_s: float, downlink_column: bool = False) -> str:
    """One line per run: its steady-state RMSE of each figure of its kind (empty where none applies);
    ``downlink_column``: with a column ``downlink`` (on/off) after the seed, for runs of both settings."""
    cols = sorted({c for v in _CSV_FIGURES.values() for c in v})
    head = ("kind", "key", "variant", "seed", *(("downlink",) if downlink_column else ()))
    lines = [",".join((*head, *cols))]
    for r in sorted(results, key=lambda r: (r["kind"], r["key"], r["variant"], r["seed"], bool(r.get("downlink")))):
        want = set(_CSV_FIGURES[r["kind"]])
        cells = []
        for c in cols:
            v = run_rmse(r, c, burnin_s) if c in want else float("nan")
            cells.append(f"{v:.4f}" if math.isfinite(v) else "")
        setting = ["on" if r.get("downlink") else "off"] if downlink_column else []
        lines.append(",".join([r["kind"], r["key"], r["variant"], str(r["seed"]), *setting, *cells]))
    return "\n".join(lines) + "\n"


def plots(res: dict, results: list[dict], out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written: list[Path] = []
    sim = res["simulation"]
    keys = list(sim)

    def save(fig, name: str) -> None:
        fig.tight_layout()
        written.append(out / name)
        fig.savefig(written[-1], dpi=110)
        plt.close(fig)

    if keys:
        x = np.arange(len(keys))
        fig, ax = plt.subplots(1, 2, figsize=(11, 4))
        w = 0.2
        for i, m in enumerate(ESTIMATE_LABELS):
            ax[0].bar(x + (i - 2) * w, [sim[k]["ego_rmse_m"][m] for k in keys], w, label=ESTIMATE_LABELS[m])
        ax[0].set(xticks=x, xticklabels=keys, ylabel="RMSE (m)", title="(a) ego self-positioning (rms1)", yscale="log")
        ax[0].legend(fontsize=7)
        for i, m in enumerate(VIEW_LABELS):
            ax[1].bar(x + (i - 1) * 0.25, [sim[k]["target_rmse_m"][m] for k in keys], 0.25, label=VIEW_LABELS[m])
        ax[1].set(xticks=x, xticklabels=keys, ylabel="RMSE (m)", title="(b) target relative positioning (rms2)")
        ax[1].legend(fontsize=7)
        fig.suptitle(f"Simulation, {res['runs']} runs, steady state (t >= {res['settings']['burnin_s']:g} s)")
        save(fig, "exp_sim.png")

        fig, axes = plt.subplots(2, len(keys), figsize=(5.5 * len(keys), 7), squeeze=False)
        for j, k in enumerate(keys):
            ot = sim[k]["over_time"]
            for name, label, ax in [(f"{EGO}:{m}", ESTIMATE_LABELS[m], axes[0, j]) for m in ESTIMATE_LABELS] + [
                (f"targets:{m}", f"targets, {VIEW_LABELS[m]}", axes[1, j]) for m in VIEW_LABELS
            ]:
                a = np.asarray(ot.get(name, []), dtype=float).reshape(-1, 5)
                if not len(a):
                    continue
                t = a[:, 0] + 0.5
                ax.plot(t, a[:, 1], "o-", ms=3, label=label)
                ax.fill_between(t, a[:, 2], a[:, 3], alpha=0.15)
            for ax, title in ((axes[0, j], f"{k}: ego pose"), (axes[1, j], f"{k}: targets (rms2)")):
                ax.axvline(res["settings"]["burnin_s"], color="k", ls=":", lw=1)
                ax.set(xlabel="time (s)", ylabel="RMSE (m)", title=title, yscale="log")
                ax.legend(fontsize=7)
        save(fig, "over_time.png")

    cols = []
    for density in DENSITIES:
        if density in res["overlap"]:
            cols.append((f"overlap {density}: fused", res["overlap"][density]["fused_m"], PAPER["res1"]["fused_m"][0]))
        for key in BLINDSPOT_SCENARIOS:
            b = res["blindspot"].get(key, {}).get(density)
            if b:
                cols.append((f"({key}) {density}: car", b["connected_car_m"], PAPER["res2"][key]["connected_car_m"]))
                cols.append((f"({key}) {density}: obstacle", b["obstacle_m"], PAPER["res2"][key]["obstacle_m"]))
    if cols:
        fig, ax = plt.subplots(figsize=(max(6.0, 0.9 * len(cols)), 4))
        xb = np.arange(len(cols))
        ax.bar(xb - 0.2, [c[2] for c in cols], 0.4, label="paper")
        ax.bar(xb + 0.2, [c[1] for c in cols], 0.4, label="ours")
        ax.set_xticks(xb, [c[0] for c in cols], rotation=30, ha="right", fontsize=7)
        ax.set(ylabel="RMSE (m)", title="test site (res1, res2)", yscale="log")
        ax.legend(fontsize=7)
        save(fig, "real_vehicle.png")
    return written
