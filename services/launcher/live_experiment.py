"""Network profiles on the live fleet: ``mapc experiment network --live`` (issue 5, item 5).

For every chosen network profile (``configs/network/*.yaml``) and mode, one fleet is brought up with
``mapc fleet up --duration S --network P --mode M --fleet <unique>`` (a subprocess: the launcher
installs signal handlers and opens its own Zenoh session), and its row is read from the run's
``report.json`` (the evaluator's whole-run summary) with the keys of
:data:`mapcontainer.experiments.network.NETWORK_COLUMNS`, so the in-process sweep's table and plots
are reused (:func:`write_network_outputs`). The same profiles are then run in process
(:func:`run_network_point`) and both are written side by side to ``live_vs_inprocess.{md,csv,png}``.

Live figures and what they mean (the in-process definitions are in ``mapcontainer/experiments/network.py``):

* ``object_rmse_m``, ``vehicle_rmse_m``: the evaluator's whole-run horizontal RMSE (every fused state
  matched with the truth at its ``t_meas``, objects by the Hungarian algorithm with a 3 m gate). The
  warm-up is not cut out and objects are not limited to a radius around the ego, so they are close to,
  not identical with, the in-process figures.
* ``bytes_per_s_per_vehicle``: V2X payload bytes per second per sending vehicle over the scenario
  duration, the ego (on board the host) left out, as in process.
* ``delivered_fraction``: the evaluator's distinct (src, seq) received over sent, per directed link,
  a message counted once it is 1 s old.
* ``latency_s_p50/p99`` (link latency) and ``age_s_*`` are not measured live (left empty); the live
  rows carry ``e2e_latency_ms_p50/p99`` instead: sensor ``t_meas`` to fused output published, which
  includes processing, the link model and the host's solve.
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mapcontainer.channel import NetworkProfile, list_profiles, load_profile

__all__ = ["COMPARE_METRICS", "DEFAULT_PROFILES", "live_row", "run_live_network", "run_live_point"]

DEFAULT_PROFILES = ("ideal", "dsrc", "lossy", "degraded")
MODES = ("distributed", "centralized")
EGO = "cv0"  # the fleet manifest's `defaults.ego`: its messages stay on board the host

# (row key, label) compared in live_vs_inprocess.*
COMPARE_METRICS = (
    ("object_rmse_m", "object RMSE (m)"),
    ("vehicle_rmse_m", "vehicle RMSE (m)"),
    ("bytes_per_s_per_vehicle", "bytes/s per vehicle"),
    ("delivered_fraction", "delivered fraction"),
)

def _f(x: Any) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def _profile_fields(p: NetworkProfile) -> dict[str, Any]:
    return {
        "profile": p.name,
        "latency_ms": float(p.latency_ms),
        "jitter_ms": float(p.jitter_ms),
        "loss": float(p.mean_loss),  # the burst model's mean loss for lossy
        "bandwidth_bps": float(p.bandwidth_bps) if p.bandwidth_bps is not None else float("inf"),
        "queue_bytes": int(p.queue_bytes),
    }


def live_row(report: dict, profile: NetworkProfile, duration_s: float, warmup_s: float = 1.0, ego: str = EGO) -> dict:
    """A sweep row (``NETWORK_COLUMNS`` keys, ``source`` = ``live``) from a fleet run's report.json (pure)."""
    if duration_s <= 0:
        raise ValueError(f"duration_s must be > 0, got {duration_s}")
    params = report.get("params") or {}
    ev = report.get("evaluation") or {}
    tx_bytes = {k: v for k, v in (ev.get("tx_bytes_total") or {}).items() if k != ego}
    tx_msgs = {k: v for k, v in (ev.get("tx_msgs_total") or {}).items() if k != ego}
    n_send = max(1, len(tx_bytes))
    b, m = sum(tx_bytes.values()), sum(tx_msgs.values())
    nan = float("nan")
    return {
        "source": "live",
        "scenario": params.get("scenario"),
        "mode": params.get("mode"),
        **_profile_fields(profile),
        "seed": params.get("seed"),
        "duration_s": float(duration_s),
        "warmup_s": float(warmup_s),
        "object_rmse_m": _f(ev.get("object_rmse_m")),
        "object_coverage": nan,
        "vehicle_rmse_m": _f(ev.get("vehicle_rmse_m")),
        "vehicle_coverage": nan,
        "bytes_per_s_per_vehicle": round(b / duration_s / n_send, 1) if tx_bytes else nan,
        "bytes_per_message": round(b / m, 1) if m else nan,
        "bytes_per_message_unsigned": nan,  # the evaluator sees the signed bytes only
        "signed": bool(params.get("signing", True)),
        "msgs_per_s_per_vehicle": round(m / duration_s / n_send, 2) if tx_msgs else nan,
        "delivered_fraction": _f(ev.get("delivered_fraction")),
        "dropped_loss_fraction": nan,
        "dropped_queue_fraction": nan,
        "latency_s_p50": nan,
        "latency_s_p99": nan,
        "age_s_mean": nan,
        "age_s_p95": nan,
        "host_rejected": None,
        "wall_s": (report.get("summary") or {}).get("wall_s"),
        "e2e_latency_ms_p50": _f(ev.get("e2e_latency_ms_p50")),
        "e2e_latency_ms_p99": _f(ev.get("e2e_latency_ms_p99")),
        "restarts": (report.get("summary") or {}).get("restarts"),
        "run_dir": (report.get("summary") or {}).get("run_dir"),
    }


def run_live_point(
    profile: str,
    mode: str,
    duration: float,
    runs_dir: str | Path,
    *,
    seed: int = 0,
    scenario: str = "paper-urban",
    vehicles: int | None = None,
    warmup_s: float = 1.0,
    timeout_s: float | None = None,
) -> dict:
    """Run one live fleet (subprocess ``mapc fleet up``) and return its row; RuntimeError if it failed."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    prof = load_profile(profile)  # ConfigError before anything starts
    fleet = f"live-{prof.name}-{mode[:4]}-{os.getpid()}"[:64]
    run_dir = Path(runs_dir) / f"{prof.name}-{mode}"
    if run_dir.exists():
        run_dir = Path(runs_dir) / f"{prof.name}-{mode}-{time.strftime('%H%M%S')}"
    cmd = [
        sys.executable, "-m", "services.cli", "fleet", "up",
        "--duration", f"{duration:g}", "--network", profile, "--mode", mode, "--fleet", fleet,
        "--seed", str(seed), "--scenario", scenario,
        "--runs-dir", str(runs_dir), "--run-dir", str(run_dir), "--no-summary",
    ]  # fmt: skip
    if vehicles is not None:
        cmd += ["--vehicles", str(vehicles)]
    timeout = timeout_s if timeout_s is not None else duration + 180.0
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    report_path = run_dir / "report.json"
    if not report_path.exists():
        raise RuntimeError(
            f"live fleet {fleet} ({profile}, {mode}) wrote no report (exit {proc.returncode}): "
            f"{(proc.stdout + proc.stderr)[-2000:]}"
        )
    report = json.loads(report_path.read_text())
    row = live_row(report, prof, duration, warmup_s)
    row["exit_code"] = proc.returncode
    return row


def _inprocess_row(profile: str, mode: str, seed: int, duration: float, scenario: str, warmup_s: float) -> dict:
    from mapcontainer.experiments.network import run_network_point

    prof = load_profile(profile)
    row = run_network_point(prof, mode, seed, duration, scenario=scenario, warmup_s=warmup_s)
    row.update(_profile_fields(prof))  # preset name and mean loss, as in the live rows
    return row


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        if not math.isfinite(v):
            return "inf" if v == float("inf") else ""
        return f"{v:.0f}" if abs(v) >= 1000 else f"{v:.4g}"
    return str(v)


def compare_rows(live: Sequence[dict], inproc: Sequence[dict]) -> list[dict]:
    """One row per (profile, mode): each COMPARE_METRICS figure live and in process, and the live e2e latency."""
    by_key = {(r["profile"], r["mode"]): r for r in inproc}
    out = []
    for lr in live:
        ir = by_key.get((lr["profile"], lr["mode"]), {})
        row: dict[str, Any] = {"profile": lr["profile"], "mode": lr["mode"]}
        for k, _ in COMPARE_METRICS:
            row[f"{k}_live"] = _f(lr.get(k))
            row[f"{k}_inprocess"] = _f(ir.get(k))
        row["e2e_latency_ms_p50_live"] = _f(lr.get("e2e_latency_ms_p50"))
        row["e2e_latency_ms_p99_live"] = _f(lr.get("e2e_latency_ms_p99"))
        row["age_s_mean_inprocess"] = _f(ir.get("age_s_mean"))
        row["latency_s_p50_inprocess"] = _f(ir.get("latency_s_p50"))
        out.append(row)
    return out


def write_comparison(rows: list[dict], out_dir: str | Path, meta: dict) -> dict[str, Path]:
    """live_vs_inprocess.csv, .md and .png in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {k: out / f"live_vs_inprocess.{k}" for k in ("csv", "md", "png")}
    cols = list(rows[0]) if rows else ["profile", "mode"]
    with paths["csv"].open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for r in rows:
            w.writerow([_cell(r.get(c)) for c in cols])
    heads = ["profile", "mode"]
    for _, lab in COMPARE_METRICS:
        heads += [f"{lab} live", f"{lab} in-process"]
    heads += ["e2e latency p50 / p99 (ms) live", "age (s) in-process"]
    L = [
        "# Live fleet vs in-process pipeline",
        "",
        f"Scenario {meta.get('scenario')}, seed {meta.get('seed')}, {meta.get('duration_s')} s per point "
        f"(live: `mapc fleet up`, {meta.get('vehicles') or 'as many as the scenario defines'} vehicles; in process: "
        "`run_network_point` with the same preset). Live RMSEs are the evaluator's whole-run figures "
        "(warm-up included, every matched object); in-process RMSEs skip the warm-up and keep objects within "
        "50 m of the ego. Bytes/s per vehicle leave the ego's on-board messages out in both.",
        "",
        "| " + " | ".join(heads) + " |",
        "|" + "---|" * len(heads),
    ]
    for r in rows:
        cells = [r["profile"], r["mode"]]
        for k, _ in COMPARE_METRICS:
            cells += [_cell(r[f"{k}_live"]), _cell(r[f"{k}_inprocess"])]
        cells += [
            f"{_cell(r['e2e_latency_ms_p50_live'])} / {_cell(r['e2e_latency_ms_p99_live'])}",
            _cell(r["age_s_mean_inprocess"]),
        ]
        L.append("| " + " | ".join(cells) + " |")
    L += ["", "![live vs in-process](live_vs_inprocess.png)", ""]
    paths["md"].write_text("\n".join(L))
    _comparison_plot(rows, paths["png"])
    return paths


def _comparison_plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(1, len(COMPARE_METRICS), figsize=(4.2 * len(COMPARE_METRICS), 4), squeeze=False)
    labels = [f"{r['profile']}\n{r['mode'][:4]}" for r in rows]
    x = np.arange(len(rows))
    for ax, (k, lab) in zip(axes[0], COMPARE_METRICS, strict=True):
        live = [_f(r[f"{k}_live"]) for r in rows]
        inp = [_f(r[f"{k}_inprocess"]) for r in rows]
        ax.bar(x - 0.2, np.nan_to_num(live), 0.4, label="live")
        ax.bar(x + 0.2, np.nan_to_num(inp), 0.4, label="in-process")
        ax.set_xticks(x, labels, fontsize=7)
        ax.set_title(lab, fontsize=9)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_live_network(
    out_dir: str | Path,
    profiles: Sequence[str] = DEFAULT_PROFILES,
    modes: Sequence[str] = MODES,
    duration: float = 20.0,
    seed: int = 0,
    scenario: str = "paper-urban",
    vehicles: int | None = None,
    warmup_s: float = 1.0,
    inprocess: bool = True,
    progress: bool = True,
) -> dict[str, list[dict]]:
    """Every (profile, mode) on the live fleet, then in process; write the sweep outputs and the comparison."""
    from mapcontainer.experiments.network import write_network_outputs

    known = list_profiles()
    bad = [p for p in profiles if p not in known and not Path(p).suffix]
    if bad:
        raise ValueError(f"unknown network profile(s) {bad}; presets: {', '.join(known)}")
    if duration <= warmup_s:
        raise ValueError(f"duration ({duration} s) must exceed warmup_s ({warmup_s} s)")
    out = Path(out_dir)
    runs = out / "runs"
    t0 = time.perf_counter()
    live: list[dict] = []
    points = [(p, m) for p in profiles for m in modes]
    for i, (p, m) in enumerate(points, 1):
        if progress:
            print(f"[{i}/{len(points)}] live fleet: {p} {m} ({duration:g} s)", file=sys.stderr, flush=True)
        live.append(run_live_point(p, m, duration, runs, seed=seed, scenario=scenario, vehicles=vehicles,
                                   warmup_s=warmup_s))  # fmt: skip
    meta = {
        "source": "live",
        "seed": seed,
        "duration_s": duration,
        "warmup_s": warmup_s,
        "scenario": scenario,
        "vehicles": vehicles,
        "profiles": list(profiles),
        "modes": list(modes),
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    write_network_outputs(live, out, meta)
    inproc: list[dict] = []
    if inprocess:
        for i, (p, m) in enumerate(points, 1):
            if progress:
                print(f"[{i}/{len(points)}] in process: {p} {m}", file=sys.stderr, flush=True)
            inproc.append(_inprocess_row(p, m, seed, duration, scenario, warmup_s))
        write_comparison(compare_rows(live, inproc), out, meta)
        clean = [
            {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()} for r in inproc
        ]
        (out / "inprocess.json").write_text(json.dumps(clean, indent=1, default=str) + "\n")
    return {"live": live, "inprocess": inproc}
