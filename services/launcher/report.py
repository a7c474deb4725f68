"""What a fleet run tells its user: the live line each second, ``report.json``, and the table at the end.

Pure functions of their arguments (the launcher passes what it knows), so each is tested without a fleet.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

__all__ = ["console_event", "down_reasons", "format_report", "make_summary", "scenario_time", "summary_line"]


def scenario_time(run_dir: Path, now_wall_ns: int) -> float | None:
    """Scenario seconds on the world's clock (``world-clock.json``: epoch and time scale); None before it starts."""
    try:
        clock = json.loads((Path(run_dir) / "world-clock.json").read_text())
        t = (now_wall_ns - int(clock["epoch_wall_ns"])) * 1e-9 * float(clock["time_scale"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return max(t, 0.0)


def down_reasons(procs: list[dict[str, Any]]) -> str:
    """Why the processes that are not up are not: ``world done``, ``host restarting``, ``cv2 failed`` ..."""
    # a process that has ended but is not yet reaped still shows the state it ran in
    words = {
        "exited": "done",
        "backoff": "restarting",
        "failed": "failed",
        "pending": "not started",
        "starting": "exiting",
        "ready": "exiting",
    }
    out = []
    for p in procs:
        if p.get("alive"):
            continue
        state = p.get("state")
        word = words.get(state, state or "down")
        if state == "exited" and p.get("returncode") not in (0, None):
            word = f"exited {p['returncode']}"
        out.append(f"{p['name']} {word}")
    return ", ".join(out)


def console_event(event: str, name: str, details: dict[str, Any], stopping: bool) -> str | None:
    """The supervisor events a person watching the console is told of: crashes, restarts, kills."""
    if event == "stop_timeout":
        return f"{name} did not stop in time: killed"
    if stopping:
        return None
    if event == "exited" and details.get("returncode") != 0:
        rc = details.get("returncode")
        how = f"killed by signal {-rc}" if isinstance(rc, int) and rc < 0 else f"exit {rc}"
        return f"{name} crashed ({how} after {details.get('ran_s', 0):g} s)"
    if event == "restart_scheduled":
        return f"{name} restarts in {details.get('in_s', 0):g} s (restart {details.get('restarts')})"
    if event == "started" and details.get("restarts"):
        return f"{name} restarted (pid {details.get('pid')})"
    if event == "frozen_kill":
        return f"{name} stopped answering (its liveliness token is gone) and was killed"
    return None


def summary_line(
    t_scenario: float | None,
    duration_s: float | None,
    up: int,
    expected: int,
    metrics: dict | None,
    why_down: str = "",
) -> str:
    """The live line: scenario time, processes up (and why the others are not), the last seconds' figures."""

    def f(x, spec=".2f", unit=""):
        return "-" if x is None else f"{x:{spec}}{unit}"

    t = "t -" if t_scenario is None else f"t {t_scenario:5.1f}"
    if duration_s is not None:
        t += f"/{duration_s:g}"
    parts = [t + " s", f"up {up}/{expected}" + (f" ({why_down})" if why_down else "")]
    m = metrics or {}
    window = f" last {m['window_s']:g}s" if m.get("window_s") else ""  # the final report's are whole-run
    parts.append(
        f"RMSE{window} veh {f(m.get('vehicle_rmse_m'), '.2f', ' m')} obj {f(m.get('object_rmse_m'), '.2f', ' m')}"
    )
    bps = m.get("tx_bytes_per_s") or {}
    if bps:
        parts.append("kB/s " + " ".join(f"{k} {v / 1e3:.1f}" for k, v in bps.items()))
    parts.append(f"delivered {f(m.get('delivered_fraction'), '.3f')}")
    parts.append(f"e2e p50 {f(m.get('e2e_latency_ms_p50'), '.0f', ' ms')}")
    return " | ".join(parts)


def _round(x: Any) -> Any:
    """Floats to 4 significant decimals for people (report.json's ``evaluation`` keeps every digit)."""
    if isinstance(x, float):
        return None if not math.isfinite(x) else round(x, 4)
    if isinstance(x, dict):
        return {k: _round(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_round(v) for v in x]
    return x


def make_summary(
    fleet: str, run_dir: Path, params: dict, procs: list[dict], ev: dict | None, wall_s: float
) -> dict[str, Any]:
    """The run's headline figures (report.json ``summary``; ``mapc fleet up --json`` prints it)."""
    ev = ev or {}
    pictures = {name: str(Path(run_dir) / f"{name}.png") for name in ("birdseye", "errors")}
    try:  # how the world's clock went (the world's state file)
        clock = json.loads((Path(run_dir) / "world-clock.json").read_text())
    except (OSError, ValueError):
        clock = {}
    return _round(
        {
            "fleet": fleet,
            "run_dir": str(run_dir),
            "scenario": params.get("scenario"),
            "mode": params.get("mode"),
            "network": params.get("network"),
            "ego": params.get("ego"),
            "t_scenario_s": ev.get("t_meas_last"),
            "wall_s": round(wall_s, 1),
            "time_scale": params.get("time_scale"),
            "achieved_time_scale": clock.get("achieved_time_scale"),
            "paused_s": clock.get("paused_s"),
            "skipped_frames": clock.get("skipped_frames"),
            "waits_timed_out": clock.get("waits_timed_out"),
            "restarts": sum(p["restarts"] for p in procs),
            "restarts_by_process": {p["name"]: p["restarts"] for p in procs if p["restarts"]},
            "burnin_s": ev.get("burnin_s"),
            "vehicle_rmse_m": ev.get("vehicle_rmse_m"),
            "vehicle_rmse_steady_m": ev.get("vehicle_rmse_steady_m"),
            "vehicle_rmse_by_id_m": ev.get("vehicle_rmse_by_id_m") or {},
            "vehicle_rmse_steady_by_id_m": ev.get("vehicle_rmse_steady_by_id_m") or {},
            "object_rmse_m": ev.get("object_rmse_m"),
            "object_rmse_steady_m": ev.get("object_rmse_steady_m"),
            "object_coverage_steady": ev.get("object_coverage_steady"),
            "false_track_fraction_steady": ev.get("false_track_fraction_steady"),
            "e2e_latency_ms_p50": ev.get("e2e_latency_ms_p50"),
            "e2e_latency_ms_p99": ev.get("e2e_latency_ms_p99"),
            "delivered_fraction": ev.get("delivered_fraction"),
            "tx_bytes_per_msg": ev.get("tx_bytes_per_msg") or {},
            "flagged_first_t": ev.get("flagged_first_t") or {},
            **{name: path if Path(path).exists() else None for name, path in pictures.items()},
        }
    )


def format_report(s: dict[str, Any]) -> str:
    """The summary as a short table a person reads at the end of a run."""

    def num(x, spec=".3f", unit=""):
        return "-" if x is None else f"{x:{spec}}{unit}"

    def pct(x):
        return "-" if x is None else f"{100 * x:.1f} %"

    t = num(s.get("t_scenario_s"), ".1f", " s")
    head = f"fleet {s['fleet']}: {s.get('scenario')}, {s.get('mode')}, network {s.get('network')}"
    lines = [f"{head}; {t} of scenario time in {s['wall_s']:.1f} s"]
    steady = f"steady (t >= {s['burnin_s']:g} s)" if s.get("burnin_s") is not None else "steady"
    lines.append(f"  {'':<14}{'RMSE ' + steady:>24}  {'RMSE whole run':>15}  {'bytes/msg':>9}")
    ids = sorted(set(s["vehicle_rmse_by_id_m"]) | set(s["tx_bytes_per_msg"]))
    for vid in ids:
        name = f"{vid} (ego)" if vid == s.get("ego") else vid
        lines.append(
            f"  {name:<14}{num(s['vehicle_rmse_steady_by_id_m'].get(vid), '.3f', ' m'):>24}"
            f"  {num(s['vehicle_rmse_by_id_m'].get(vid), '.3f', ' m'):>15}"
            f"  {num(s['tx_bytes_per_msg'].get(vid), '.0f'):>9}"
        )
    lines.append(
        f"  {'all vehicles':<14}{num(s.get('vehicle_rmse_steady_m'), '.3f', ' m'):>24}"
        f"  {num(s.get('vehicle_rmse_m'), '.3f', ' m'):>15}"
    )
    lines.append(
        f"  {'objects':<14}{num(s.get('object_rmse_steady_m'), '.3f', ' m'):>24}"
        f"  {num(s.get('object_rmse_m'), '.3f', ' m'):>15}"
        f"  coverage {pct(s.get('object_coverage_steady'))}, false tracks {pct(s.get('false_track_fraction_steady'))}"
    )
    lines.append(
        f"  e2e latency   p50 {num(s.get('e2e_latency_ms_p50'), '.0f', ' ms')}, "
        f"p99 {num(s.get('e2e_latency_ms_p99'), '.0f', ' ms')} (sensor time to fused output)"
    )
    lines.append(f"  delivered     {pct(s.get('delivered_fraction'))} of the messages sent over the radio")
    scale, dropped = s.get("time_scale"), s.get("skipped_frames")
    if scale == "auto" and s.get("achieved_time_scale") is not None:
        gone_on = s.get("waits_timed_out") or 0
        every = f"{gone_on:.0f} frames went on without a silent service" if gone_on else "every frame processed"
        lines.append(
            f"  time scale    auto: {s['achieved_time_scale']:.2f} achieved, {every} "
            f"(the clock paused {s.get('paused_s') or 0:.1f} s for the services)"
        )
    elif scale is not None and scale != "auto":
        lost = f"; the world dropped {dropped:.0f} frames to keep up" if dropped else ""
        lines.append(f"  time scale    {scale:g}{lost}")
    flagged = s.get("flagged_first_t") or {}
    if flagged:
        first = ", ".join(f"{v} from t = {t:.1f} s" for v, t in flagged.items())
        lines.append(f"  flagged       {first} (misbehaviour: why in the host's log and health)")
    by = s.get("restarts_by_process") or {}
    which = f" ({', '.join(f'{k} {v}' for k, v in by.items())})" if by else ""
    lines.append(f"  restarts      {s['restarts']}{which}")
    files = ["report.json"] + [f"{n}.png" for n in ("birdseye", "errors") if s.get(n)]
    lines.append(f"  run dir       {s['run_dir']} ({', '.join(files)})")
    return "\n".join(lines)
