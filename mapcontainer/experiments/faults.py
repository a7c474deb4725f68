"""Fault experiment: what each misbehaving vehicle costs the others, and whether the host catches it.

Every run is one in-process :func:`mapcontainer.pipeline.run_pipeline` of ``scenario`` as a user
meets it (cold start from GNSS, every realistic error source of the simulator on, traffic drawn per
seed, signed messages as the live fleet sends them) for ``duration_s``; vehicle ``cv1`` misbehaves
from ``FAULT_START_S`` on (after the burn-in the paper experiment uses) as each entry of
:data:`FAULTS` says (:mod:`mapcontainer.faults`), and a clean run of the same seed is the reference.
Scoring is :mod:`mapcontainer.evaluation`'s, over the fused states from ``score_from_s`` (the fault's
start plus two seconds) on. Figures per (fault, seed):

* ``time_to_flag_s``: the first fused state that flags cv1, minus the fault's start (None: never);
* flags of the other vehicles, per fused state: ``warranted_flags`` when the flagged vehicle's fused
  position was more than :data:`WARRANTED_M` off the truth (its localization failed: the flag is
  right, though nobody misbehaved), ``false_flags`` otherwise; in a clean run cv1's flags count the
  same way;
* ``others_rmse_m``: horizontal RMSE of the fused poses of every vehicle but cv1, ``objects_rmse_m``
  of the matched fused objects, ``false_tracks`` per fused state; ``*_clean`` the clean run's over
  the same states, ``*_ratio`` fault over clean;
* ``refused``: messages the host's verifier refused, by reason (replays, impostors).

Seeds: the evaluation seeds start at ``EVAL_SEED0``; the detector was developed on seeds 101-106.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from .. import jsonout
from ..evaluation import score_frame
from ..pipeline import run_pipeline
from ..seeds import EVAL_SEED0, seed_kind
from ..sim import load_scenario
from .executors import Executor
from .runner import run_all, write_timing
from .store import TaskStore

__all__ = ["EVAL_SEED0", "FAULTS", "FAULT_START_S", "WARRANTED_M", "run_fault_experiment", "run_fault_seed"]

FAULT_START_S = 5.0
WARRANTED_M = 1.0  # a flagged vehicle this far off the truth was wrong, misbehaving or not (m)
FAULTS: dict[str, dict[str, Any]] = {
    "pose_bias_1m": {"kind": "pose_bias", "bias_m": [0.0, 1.0]},
    "pose_bias_3m": {"kind": "pose_bias", "bias_m": [0.0, 3.0]},
    "ghost_objects": {"kind": "ghost_objects", "count": 2},
    "drop_detections": {"kind": "drop_detections"},
    "clock_offset": {"kind": "clock_offset", "offset_s": -0.3},
    "frozen_clock": {"kind": "frozen_clock"},
    "replay": {"kind": "replay", "delay_s": 1.0},
    "impostor": {"kind": "impostor", "as_vehicle": "cv2", "bias_m": [5.0, 0.0]},
}
FAULTY = "cv1"


def _scores(res, score_from_s: float, faulty: str | None) -> dict[str, Any]:
    """Per run: the first flag of ``faulty`` once its fault started, the other flags (warranted or false; a flag
    of ``faulty`` before its fault counts as one of them), and the squared errors
    of the other vehicles and of the objects, and the false tracks, from ``score_from_s`` on."""
    first, false_flags, warranted, others, objects, false_tracks, states = None, 0, 0, [], [], 0, 0
    for rec in res.records:
        fused, truth = rec.fused["cooperative"], rec.truth
        s = score_frame(fused, truth)
        err = dict(zip(s.vehicle_ids, np.sqrt(s.vehicle_sq), strict=True))
        for v in fused.flagged:
            if v == faulty and rec.t >= FAULT_START_S:
                first = rec.t if first is None else first
            elif err.get(v, 0.0) > WARRANTED_M:
                warranted += 1
            else:
                false_flags += 1
        if rec.t < score_from_s:
            continue
        states += 1
        others += [float(q) for v, q in zip(s.vehicle_ids, s.vehicle_sq, strict=True) if v != FAULTY]
        objects += s.object_sq.tolist()
        false_tracks += s.n_false
    return {
        "first_flag_t": first,
        "false_flags": false_flags,
        "warranted_flags": warranted,
        "others": others,
        "objects": objects,
        "false_tracks_per_state": false_tracks / states if states else float("nan"),
    }


def _rmse(sq: list[float]) -> float:
    return math.sqrt(sum(sq) / len(sq)) if sq else float("nan")


def run_fault_seed(task: tuple) -> dict[str, Any]:
    """One seed: its clean run (row ``fault`` "none") and each of ``faults`` against it: {"rows": [...]}."""
    faults, seed, duration_s, scenario = task
    score_from = FAULT_START_S + 2.0
    clean = _scores(run_pipeline(scenario, seed=seed, duration_s=duration_s, signing=True), score_from, None)
    rows: list[dict[str, Any]] = [
        {
            "fault": "none",
            "seed": seed,
            "false_flags": clean["false_flags"],
            "warranted_flags": clean["warranted_flags"],
            "others_rmse_m": _rmse(clean["others"]),
            "objects_rmse_m": _rmse(clean["objects"]),
            "false_tracks": clean["false_tracks_per_state"],
        }
    ]
    for fault in faults:
        spec = {**FAULTS[fault], "vehicle": FAULTY, "start_s": FAULT_START_S}
        res = run_pipeline(load_scenario(scenario, {"faults": [spec]}), seed=seed, duration_s=duration_s, signing=True)
        s = _scores(res, score_from, FAULTY)
        row = {
            "fault": fault,
            "seed": seed,
            "time_to_flag_s": None if s["first_flag_t"] is None else round(s["first_flag_t"] - FAULT_START_S, 2),
            "false_flags": s["false_flags"],
            "warranted_flags": s["warranted_flags"],
            "others_rmse_m": _rmse(s["others"]),
            "others_rmse_clean_m": _rmse(clean["others"]),
            "objects_rmse_m": _rmse(s["objects"]),
            "objects_rmse_clean_m": _rmse(clean["objects"]),
            "false_tracks": s["false_tracks_per_state"],
            "false_tracks_clean": clean["false_tracks_per_state"],
            "refused": dict(res.security_rejected),
        }
        row["others_ratio"] = row["others_rmse_m"] / row["others_rmse_clean_m"]
        row["objects_ratio"] = row["objects_rmse_m"] / row["objects_rmse_clean_m"]
        rows.append(row)
    return {"seed": seed, "rows": rows}


def run_fault_experiment(
    out_dir: str | Path,
    seeds: int = 3,
    seed0: int = EVAL_SEED0,
    duration_s: float = 15.0,
    scenario: str = "paper-urban",
    executor: Executor | None = None,
    faults: list[str] | None = None,
    progress: bool = True,
    fresh: bool = False,
) -> dict[str, Any]:
    """Every fault (and clean runs) on ``seeds`` seeds from ``seed0`` on ``executor``; writes results.json,
    faults.md, faults.png and timing.json. Finished seeds are kept in ``out_dir/tasks`` (a rerun resumes;
    ``fresh``: start over)."""
    names = list(FAULTS) if faults is None else faults
    unknown = [f for f in names if f not in FAULTS]
    if unknown:
        raise ValueError(f"unknown fault(s) {unknown}; known: {list(FAULTS)}")
    if duration_s <= FAULT_START_S + 2.0:
        raise ValueError(
            f"duration_s must exceed {FAULT_START_S + 2.0} s (the fault's start and 2 s), got {duration_s}"
        )
    tasks = [(names, seed0 + k, duration_s, scenario) for k in range(seeds)]
    t0 = time.perf_counter()
    executor = executor or Executor()
    store = TaskStore(out_dir, "faults", {"tasks": tasks}, fresh)
    batch = run_all(run_fault_seed, tasks, "experiment faults", lambda t: f"seed {t[1]}", executor, store, progress)
    rows = [row for r in batch.results for row in r["rows"]]
    rows.sort(key=lambda r: (["none", *names].index(r["fault"]), r["seed"]))
    summary = _summary(rows, names)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "scenario": scenario,
        "seeds": [seed0 + k for k in range(seeds)],
        "duration_s": duration_s,
        "fault_start_s": FAULT_START_S,
        "score_from_s": FAULT_START_S + 2.0,
        "start": "cold",
        "signed": True,
        "warranted_m": WARRANTED_M,
    }
    (out / "results.json").write_text(jsonout.dumps({"meta": meta, "summary": summary, "runs": rows}, indent=1))
    (out / "faults.md").write_text(_markdown(summary, meta))
    _plot(summary, out / "faults.png")
    write_timing(out, executor, {"seeds": batch}, time.perf_counter() - t0)
    return {"meta": meta, "summary": summary}


def _summary(rows: list[dict], names: list[str]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    clean = [r for r in rows if r["fault"] == "none"]
    out["none"] = {
        "runs": len(clean),
        "runs_with_false_flags": sum(r["false_flags"] > 0 for r in clean),
        "runs_with_warranted_flags": sum(r["warranted_flags"] > 0 for r in clean),
        "others_rmse_m": float(np.mean([r["others_rmse_m"] for r in clean])),
        "objects_rmse_m": float(np.mean([r["objects_rmse_m"] for r in clean])),
        "false_tracks": float(np.mean([r["false_tracks"] for r in clean])),
    }
    for f in names:
        rs = [r for r in rows if r["fault"] == f]
        ttf = [r["time_to_flag_s"] for r in rs if r["time_to_flag_s"] is not None]
        refused: dict[str, int] = {}
        for r in rs:
            for k, n in r["refused"].items():
                refused[k] = refused.get(k, 0) + n
        out[f] = {
            "runs": len(rs),
            "flagged_runs": len(ttf),
            "flagged_within_2s": sum(t <= 2.0 for t in ttf),
            "time_to_flag_s_median": float(np.median(ttf)) if ttf else None,
            "time_to_flag_s_max": max(ttf) if ttf else None,
            "runs_with_false_flags": sum(r["false_flags"] > 0 for r in rs),
            "runs_with_warranted_flags": sum(r["warranted_flags"] > 0 for r in rs),
            "others_ratio_mean": float(np.mean([r["others_ratio"] for r in rs])),
            "others_ratio_max": float(np.max([r["others_ratio"] for r in rs])),
            "objects_ratio_mean": float(np.mean([r["objects_ratio"] for r in rs])),
            "false_tracks": float(np.mean([r["false_tracks"] for r in rs])),
            "false_tracks_clean": float(np.mean([r["false_tracks_clean"] for r in rs])),
            "refused": refused,
        }
    return out


def _markdown(summary: dict, meta: dict) -> str:
    clean = summary["none"]
    lines = [
        "# Fault experiment",
        "",
        f"{meta['scenario']}, cold start, every realistic error source on, signed messages, "
        f"{meta['duration_s']:g} s per run, cv1 misbehaves from {meta['fault_start_s']:g} s; RMSE from "
        f"{meta['score_from_s']:g} s; seeds {meta['seeds']} ({seed_kind(min(meta['seeds']))} seeds). A flag of "
        f"another vehicle is *warranted* when that vehicle's fused position was more than {meta['warranted_m']:g} m "
        "off the truth (its localization had failed), *false* otherwise.",
        "",
        f"Clean runs: {clean['runs']}; {clean['runs_with_false_flags']} with a false flag, "
        f"{clean['runs_with_warranted_flags']} with a warranted one; others' RMSE {clean['others_rmse_m']:.3f} m, "
        f"objects {clean['objects_rmse_m']:.3f} m, false tracks {clean['false_tracks']:.2f} per fused state.",
        "",
        "| fault | cv1 flagged (within 2 s) | time to flag (median, max) | runs with false / warranted flags |"
        " others' RMSE / clean (mean, max) | objects' RMSE / clean | false tracks per state (clean) |"
        " refused by signatures |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for f, s in summary.items():
        if f == "none":
            continue
        ttf = (
            "-"
            if s["time_to_flag_s_max"] is None
            else f"{s['time_to_flag_s_median']:.1f} s, {s['time_to_flag_s_max']:.1f} s"
        )
        refused = ", ".join(f"{k} {n}" for k, n in s["refused"].items()) or "-"
        lines.append(
            f"| {f} | {s['flagged_runs']}/{s['runs']} ({s['flagged_within_2s']}) | {ttf} | "
            f"{s['runs_with_false_flags']} / {s['runs_with_warranted_flags']} | "
            f"{s['others_ratio_mean']:.2f}, {s['others_ratio_max']:.2f} | {s['objects_ratio_mean']:.2f} | "
            f"{s['false_tracks']:.2f} ({s['false_tracks_clean']:.2f}) | {refused} |"
        )
    lines += ["", "![others' RMSE with each fault](faults.png)", ""]
    return "\n".join(lines)


def _plot(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [f for f in summary if f != "none"]
    fig, ax = plt.subplots(figsize=(10, 4.5))
    x = np.arange(len(names))
    ax.bar(x - 0.2, [summary[f]["others_ratio_mean"] for f in names], 0.4, label="other vehicles")
    ax.bar(x + 0.2, [summary[f]["objects_ratio_mean"] for f in names], 0.4, label="objects")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.axhline(1.1, color="tab:red", lw=0.8, ls="--", label="+10 %")
    ax.set_xticks(x, names, rotation=20)
    ax.set_ylabel("RMSE with the fault / clean")
    ax.set_title("What a misbehaving cv1 costs the others (mean over seeds)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
