"""Network degradation sweep: fused accuracy, bandwidth, delivery and age versus the V2X link.

Every point is one in-process :func:`mapcontainer.pipeline.run_pipeline` run of paper-urban, cold
started (every vehicle initialises its localizer from GNSS at t = 0), with a
:meth:`NetworkProfile.custom` link (latency, Bernoulli loss, per-link capacity) in distributed or
centralized mode; all points share one seed (common random numbers: the same world noise, and the
channel's per-link streams make the messages lost at 10 % a subset of those lost at 30 %). With ``downlink``, every
distributed point also runs with the host's downlink over the same link (:mod:`.network_downlink`).

Row keys (``NETWORK_COLUMNS``; the live-fleet sweep writes rows with the same keys):

* ``object_rmse_m``: horizontal map-frame RMSE of the fused objects (host view with every vehicle)
  matched to the true obstacles within ``radius_m`` of the ego (Hungarian, 3 m gate), over scored
  frames; ``object_coverage``: matched / true obstacles within that radius.
* ``vehicle_rmse_m``: horizontal RMSE of every fused vehicle pose against the truth at the fuse
  time; ``vehicle_coverage``: vehicles in the fused state / vehicles. The fused state holds each
  vehicle's newest pose state predicted to the fuse time at constant velocity (the container's
  ``_output``), so an old message costs what that prediction gets wrong (acceleration and turns
  over its age), not speed x age.
* ``bytes_per_s_per_vehicle``: payload bytes offered to the link per second per sending vehicle
  (the host vehicle's own messages stay on board and are not counted); ``bytes_per_message``. The
  messages are signed as the live fleet sends them (``signed``; ECDSA P-256 with the certificate
  about once a second, :mod:`mapcontainer.security`), so these are bytes on the air;
  ``bytes_per_message_unsigned`` is the message inside.
* ``delivered_fraction``: delivered / (delivered + dropped) over the messages whose fate was decided
  by the end of the run (messages still in flight at the end are left out, so a long latency does
  not count as loss); ``dropped_loss_fraction``, ``dropped_queue_fraction``: the same denominator.
* ``latency_s_p50``, ``latency_s_p99``: arrival minus send time of delivered messages, queueing
  and serialization included.
* ``age_s_mean``, ``age_s_p95``: the age of the remote information at the host — at each scored
  fuse time t and for each remote vehicle v, t minus the newest t_meas among v's messages that had
  arrived by t (before the first arrival: t minus the run's start). Averaged over fuse times and
  vehicles (and its 95th percentile).

Queue: each link's serialization queue holds at most ``queue_s`` (0.5 s) of traffic at its
capacity, i.e. a radio that drops data older than half the fusion window instead of delivering it
late, and never less than ``MIN_QUEUE_BYTES`` (3072 bytes). A message larger than the queue bound
is never sent, and half a second at 20 kbit/s (1250 bytes) is smaller than most centralized
messages (1450 bytes signed on average, up to 2031): with a floor below the largest message, the
lowest-capacity point would refuse them by construction. The floor holds the largest signed
message of either mode (a centralized message with its certificate: 2031 bytes over paper-urban
seeds 90000-90004, 10 s each; 1930 on paper-suburban; ``mapcontainer.experiments.bytes``) with
half of it to spare, so loss there is congestion. It binds only at the 20 kbit/s point, where 3072
bytes are 1.2 s of traffic (a distributed message may wait that long in the queue); at every
other point half a second of traffic is more.
"""

from __future__ import annotations

import csv
import itertools
import math
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .. import jsonout
from ..channel import NetworkProfile
from ..evaluation import age_of_information, horizontal_sq_error, obstacle_errors, rmse_sq, vehicle_pose
from ..jsonout import rounded
from ..pipeline import PipelineResult, View, run_pipeline
from .executors import Executor
from .runner import run_all, write_timing
from .store import TaskStore

__all__ = [
    "BANDWIDTHS_BPS",
    "MIN_QUEUE_BYTES",
    "SMOKE_TEST_NOTE",
    "LATENCIES_MS",
    "LOSSES",
    "NETWORK_COLUMNS",
    "QUICK_GRID",
    "run_network_point",
    "run_network_sweep",
    "sweep_profile",
    "write_network_outputs",
]

LATENCIES_MS = (0.0, 50.0, 100.0, 200.0, 500.0)
LOSSES = (0.0, 0.1, 0.3, 0.5)
BANDWIDTHS_BPS = (6e6, 1e6, 1e5, 2e4)
QUICK_GRID = {"latencies_ms": (0.0, 200.0), "losses": (0.0, 0.3), "bandwidths_bps": (6e6, 2e4)}
MODES = ("distributed", "centralized")
QUEUE_S = 0.5
# The queue's floor: the largest message either mode sends with half of it to spare (module docstring);
# tests/unit/test_network_queue.py checks every sweep point's queue against measured messages.
MIN_QUEUE_BYTES = 3072

NETWORK_COLUMNS = (
    "source",
    "scenario",
    "mode",
    "profile",
    "latency_ms",
    "jitter_ms",
    "loss",
    "bandwidth_bps",
    "queue_bytes",
    "seed",
    "duration_s",
    "warmup_s",
    "object_rmse_m",
    "object_coverage",
    "vehicle_rmse_m",
    "vehicle_coverage",
    "bytes_per_s_per_vehicle",
    "bytes_per_message",
    "bytes_per_message_unsigned",
    "signed",
    "msgs_per_s_per_vehicle",
    "delivered_fraction",
    "dropped_loss_fraction",
    "dropped_queue_fraction",
    "latency_s_p50",
    "latency_s_p99",
    "age_s_mean",
    "age_s_p95",
    "host_rejected",
    "wall_s",
)


def sweep_profile(
    latency_ms: float, loss: float, bandwidth_bps: float | None, queue_s: float = QUEUE_S, jitter_ms: float = 0.0
) -> NetworkProfile:
    """The link of one sweep point: per-link capacity, a queue of ``queue_s`` of traffic but at least
    ``MIN_QUEUE_BYTES`` (the largest message), Bernoulli loss."""
    queue = 65536 if bandwidth_bps is None else max(MIN_QUEUE_BYTES, int(math.ceil(bandwidth_bps * queue_s / 8.0)))
    bw = "inf" if bandwidth_bps is None else f"{bandwidth_bps / 1e3:g}k"
    return NetworkProfile.custom(
        name=f"lat{latency_ms:g}ms-loss{100 * loss:g}pct-bw{bw}",
        latency_ms=latency_ms,
        jitter_ms=jitter_ms,
        loss=loss,
        bandwidth_bps=bandwidth_bps,
        queue_bytes=queue,
    )


SMOKE_TEST_NOTE = (
    "**Smoke test** (`--quick`): points of a few seconds from a cold start, scored before the vehicles have "
    "settled, show that the sweep runs end to end, not what the network does to accuracy (a point may even "
    "look better with more loss). Run without `--quick` for figures."
)


def link_figures(res: PipelineResult, times: Sequence[float]) -> dict[str, float]:
    """A run's link figures (module docstring): delivered_fraction, dropped_loss_fraction,
    dropped_queue_fraction, latency_s_p50/p99 and age_s_mean/p95 at the scored fuse ``times``."""
    senders = sorted(res.tx_msgs)
    ch = res.channel_stats
    dropped_loss, dropped_queue = ch["dropped_msgs"]["loss"], ch["dropped_msgs"]["queue_full"]
    delivered = ch["delivered_msgs"] - ch["duplicated_msgs"]
    decided = delivered + dropped_loss + dropped_queue
    lat = np.array([ta - ts for _, ts, ta in res.deliveries], dtype=float)
    age = age_of_information(res.deliveries, senders, times) if senders else np.zeros((0, 0))
    nan = float("nan")
    return {
        "delivered_fraction": rounded(delivered / decided) if decided else nan,
        "dropped_loss_fraction": rounded(dropped_loss / decided) if decided else nan,
        "dropped_queue_fraction": rounded(dropped_queue / decided) if decided else nan,
        "latency_s_p50": rounded(float(np.percentile(lat, 50))) if lat.size else nan,
        "latency_s_p99": rounded(float(np.percentile(lat, 99))) if lat.size else nan,
        "age_s_mean": rounded(float(age.mean())) if age.size else nan,
        "age_s_p95": rounded(float(np.percentile(age, 95))) if age.size else nan,
    }


def run_network_point(
    profile: NetworkProfile,
    mode: str,
    seed: int = 0,
    duration: float = 4.0,
    *,
    scenario: str = "paper-urban",
    warmup_s: float = 1.0,
    radius_m: float = 50.0,
    signing: bool = True,
    start: str = "cold",
    cpm_rules: bool = False,
    extra: Callable[[PipelineResult], dict[str, Any]] | None = None,
    downlink: bool = False,
) -> dict[str, Any]:
    """One sweep point: run the pipeline and return its row (keys: ``NETWORK_COLUMNS``, then ``extra(res)``'s).

    ``scenario``: a preset name or a ScenarioConfig; ``start``, ``cpm_rules``, ``downlink``: :func:`run_pipeline`'s."""
    if duration <= warmup_s:
        raise ValueError(f"duration ({duration} s) must exceed warmup_s ({warmup_s} s)")
    t0 = time.perf_counter()
    res = run_pipeline(
        scenario,
        seed=seed,
        duration_s=duration,
        mode=mode,
        network=profile,
        views=(View("fused"),),
        signing=signing,
        start=start,
        cpm_rules=cpm_rules,
        downlink=downlink,
    )
    scored = [r for r in res.records if r.t >= warmup_s - 1e-9]
    obj_sq, veh_sq = [], []
    obj_near = veh_total = veh_seen = 0
    for rec in scored:
        truth, fused = rec.truth, rec.fused["fused"]
        ego_true = vehicle_pose(truth, res.ego)
        p_true = np.asarray(truth.obstacle_p_map, dtype=float).reshape(-1, 3)
        near = np.linalg.norm(p_true[:, :2] - ego_true[:2], axis=1) <= radius_m
        obj_near += int(near.sum())
        _, err, _ = obstacle_errors(fused, truth, within=near)
        obj_sq.extend(np.sum(err[:, :2] ** 2, axis=1).tolist())
        for vid in truth.vehicle_ids:
            veh_total += 1
            p = vehicle_pose(fused, vid)
            if p is not None:
                veh_seen += 1
                veh_sq.append(horizontal_sq_error(p, vehicle_pose(truth, vid)))
    senders = sorted(res.tx_msgs)
    link = link_figures(res, [r.t for r in scored])
    n_send = max(1, len(senders))
    tx_bytes, tx_msgs = sum(res.tx_bytes.values()), sum(res.tx_msgs.values())
    rejected = sum(sum(st.get("rejected", {}).values()) for st in res.host_stats.values())
    rejected += sum(res.security_rejected.values())
    return {
        "source": "pipeline",
        "scenario": res.scenario,
        "mode": mode,
        "profile": profile.name,
        "latency_ms": float(profile.latency_ms),
        "jitter_ms": float(profile.jitter_ms),
        "loss": float(profile.loss),
        "bandwidth_bps": float(profile.bandwidth_bps) if profile.bandwidth_bps is not None else float("inf"),
        "queue_bytes": int(profile.queue_bytes),
        "seed": int(seed),
        "duration_s": float(duration),
        "warmup_s": float(warmup_s),
        "object_rmse_m": rounded(rmse_sq(obj_sq)),
        "object_coverage": rounded(len(obj_sq) / obj_near) if obj_near else float("nan"),
        "vehicle_rmse_m": rounded(rmse_sq(veh_sq)),
        "vehicle_coverage": rounded(veh_seen / veh_total) if veh_total else float("nan"),
        "bytes_per_s_per_vehicle": rounded(tx_bytes / duration / n_send, 1),
        "bytes_per_message": rounded(tx_bytes / tx_msgs, 1) if tx_msgs else float("nan"),
        "bytes_per_message_unsigned": rounded(sum(res.tx_message_bytes.values()) / tx_msgs, 1)
        if tx_msgs
        else float("nan"),
        "signed": signing,
        "msgs_per_s_per_vehicle": rounded(tx_msgs / duration / n_send, 2),
        **link,
        "host_rejected": int(rejected),
        "wall_s": rounded(time.perf_counter() - t0, 2),
        **(extra(res) if extra is not None else {}),
    }


def _point_task(task: tuple) -> dict:
    """One point; a ninth element (the downlink off or on) adds the downlink's figures (:mod:`.network_downlink`)."""
    from .network_downlink import point_args

    latency_ms, loss, bw, mode, seed, duration, scenario, warmup_s, *downlink = task
    more = point_args(downlink[0], warmup_s) if downlink else {}
    return run_network_point(
        sweep_profile(latency_ms, loss, bw), mode, seed, duration, scenario=scenario, warmup_s=warmup_s, **more
    )


def _describe_point(task: tuple) -> str:
    latency_ms, loss, bw, mode, seed, *rest = task
    with_downlink = (" downlink " + ("on" if rest[-1] else "off")) if len(rest) == 4 else ""
    return f"{mode}{with_downlink} {sweep_profile(latency_ms, loss, bw).name} seed {seed}"


def run_network_sweep(
    out_dir: str | Path,
    quick: bool = False,
    seed: int = 0,
    executor: Executor | None = None,
    duration: float | None = None,
    scenario: str = "paper-urban",
    warmup_s: float = 1.0,
    progress: bool = True,
    latencies_ms: Sequence[float] | None = None,
    losses: Sequence[float] | None = None,
    bandwidths_bps: Sequence[float] | None = None,
    fresh: bool = False,
    downlink: bool = False,
) -> list[dict]:
    """Run the grid (``quick``: the smoke test, 2 x 2 x 2 points of 2.5 s) in both modes on ``executor`` and write
    the outputs; finished points are kept in ``out_dir/tasks`` (a rerun resumes; ``fresh``: start over).
    ``downlink``: every distributed point without and with the host's downlink (:mod:`.network_downlink`)."""
    grid = QUICK_GRID if quick else {"latencies_ms": LATENCIES_MS, "losses": LOSSES, "bandwidths_bps": BANDWIDTHS_BPS}
    lats = tuple(latencies_ms if latencies_ms is not None else grid["latencies_ms"])
    loss = tuple(losses if losses is not None else grid["losses"])
    bws = tuple(bandwidths_bps if bandwidths_bps is not None else grid["bandwidths_bps"])
    dur = duration if duration is not None else (2.5 if quick else 4.0)
    tasks = [
        (lat, ls, bw, mode, seed, dur, scenario, warmup_s)
        for mode, bw, lat, ls in itertools.product(MODES, bws, lats, loss)
    ]
    if downlink:
        from .network_downlink import twins

        tasks = twins(tasks)  # each distributed point without and with the downlink
    t0 = time.perf_counter()
    executor = executor or Executor()
    store = TaskStore(
        out_dir, "network", {"tasks": tasks, "queue_s": QUEUE_S, "min_queue_bytes": MIN_QUEUE_BYTES}, fresh
    )
    batch = run_all(_point_task, tasks, "experiment network", _describe_point, executor, store, progress)
    rows = batch.results
    rows.sort(key=lambda r: (r["mode"], -r["bandwidth_bps"], r["latency_ms"], r["loss"], r.get("downlink", "")))
    meta = {
        "seed": seed,
        "duration_s": dur,
        "warmup_s": warmup_s,
        "scenario": scenario,
        "quick": quick,
        "smoke_test": quick,
        "start": "cold",
        "queue_s": QUEUE_S,
        "min_queue_bytes": MIN_QUEUE_BYTES,
        **({"downlink": "distributed points without and with it"} if downlink else {}),
    }
    write_network_outputs(rows, out_dir, meta)
    write_timing(out_dir, executor, {"points": batch}, time.perf_counter() - t0)
    return rows


# -------------------------------------------------------------------------------------- outputs


def _num(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _cell(v) -> str:
    if isinstance(v, float):
        if not math.isfinite(v):
            return "inf" if v == float("inf") else ""
        return f"{v:.0f}" if abs(v) >= 1000 else f"{v:.4g}"
    return "" if v is None else str(v)


def _bw_label(bps: float) -> str:
    if not math.isfinite(bps):
        return "unlimited"
    return f"{bps / 1e6:g} Mbit/s" if bps >= 1e6 else f"{bps / 1e3:g} kbit/s"


def _summary(rows: list[dict]) -> list[str]:
    """The key comparison at the lowest bandwidth, on the best link otherwise (lowest latency and loss)."""
    if not rows:
        return ["No rows."]
    bw_min = min(_num(r.get("bandwidth_bps")) for r in rows)
    lat0 = min(_num(r.get("latency_ms")) for r in rows)
    loss0 = min(_num(r.get("loss")) for r in rows)
    bw_max = max(_num(r.get("bandwidth_bps")) for r in rows)

    def pick(mode, bw):
        for r in rows:
            if (
                r.get("mode") == mode
                and _num(r.get("bandwidth_bps")) == bw
                and _num(r.get("latency_ms")) == lat0
                and _num(r.get("loss")) == loss0
            ):
                return r
        return None

    out = [
        f"At {_bw_label(bw_min)} per link ({lat0:g} ms, {100 * loss0:g} % loss), against {_bw_label(bw_max)}:",
        "",
        "| mode | capacity | offered (bytes/s/vehicle) | delivered | object RMSE (m) | object coverage | "
        "vehicle RMSE (m) | vehicle coverage | age (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for mode in MODES:
        for bw in dict.fromkeys((bw_max, bw_min)):  # one row when every point has the same capacity
            r = pick(mode, bw)
            if r is None:
                continue
            out.append(
                f"| {mode} | {_bw_label(bw)} | {_cell(r.get('bytes_per_s_per_vehicle'))} | "
                f"{_cell(r.get('delivered_fraction'))} | {_cell(r.get('object_rmse_m'))} | "
                f"{_cell(r.get('object_coverage'))} | {_cell(r.get('vehicle_rmse_m'))} | "
                f"{_cell(r.get('vehicle_coverage'))} | {_cell(r.get('age_s_mean'))} |"
            )
    d, c = pick("distributed", bw_min), pick("centralized", bw_min)
    if d is not None and c is not None:
        dd, cd = _num(d.get("delivered_fraction")), _num(c.get("delivered_fraction"))
        out += [
            "",
            f"Distributed mode offers {_cell(d.get('bytes_per_s_per_vehicle'))} bytes/s per vehicle and delivers "
            f"{_cell(dd)} of its messages at {_bw_label(bw_min)}; centralized offers "
            f"{_cell(c.get('bytes_per_s_per_vehicle'))} bytes/s and delivers {_cell(cd)}. "
            + (
                "The distributed mode still fuses the remote vehicles while the centralized one loses them."
                if dd > cd
                else "Here the centralized mode is not worse at delivery: check the table."
            ),
        ]
    return out


def _preset_text(name: str) -> str | None:
    """One preset's link as its YAML defines it (None if ``name`` is not a preset)."""
    from ..channel import list_profiles, load_profile

    if name not in list_profiles():
        return None
    p = load_profile(name)
    lat = f"{p.latency_ms:g} ms" + (f" + U[0, {2 * p.jitter_ms:g}] ms jitter" if p.jitter_ms > 0 else ", no jitter")
    if p.burst is not None:
        loss = f"Gilbert-Elliott burst loss (mean {100 * p.mean_loss:.3g} %)"
    else:
        loss = f"Bernoulli loss {100 * p.loss:g} %" if p.loss > 0 else "no loss"
    if p.bandwidth_bps is None:
        cap = "unlimited capacity"
    else:
        medium = "one shared medium" if p.shared_medium else "per link"
        cap = f"{_bw_label(p.bandwidth_bps)} {medium}, queue {p.queue_bytes} bytes"
    dup = f", {100 * p.duplicate:g} % duplicates" if p.duplicate > 0 else ""
    return f"{name}: {lat}, {loss}, {cap}{dup}"


def _links_text(rows: list[dict], m: dict) -> str:
    """What the links of these rows are and what is scored (sweep points or network presets, in process or live)."""
    profiles = list(dict.fromkeys(str(r.get("profile")) for r in rows))
    presets = [t for t in (_preset_text(p) for p in profiles) if t is not None]
    live = m.get("source") == "live" or any(r.get("source") == "live" for r in rows)
    if live:
        scored = (
            f"{m.get('duration_s', '?')} s per point on the live fleet; RMSEs are the evaluator's whole-run "
            "figures (warm-up included)."
        )
    else:
        scored = (
            f"{m.get('duration_s', '?')} s per point, {m.get('start', 'cold')} start (every vehicle initialises "
            f"from GNSS at t = 0), of which the first {m.get('warmup_s', '?')} s are not scored."
        )
    if presets and len(presets) == len(profiles):
        return f"{scored} Links: the presets of `configs/network/` as defined there — " + "; ".join(presets) + "."
    jitter = sorted({_num(r.get("jitter_ms")) for r in rows if math.isfinite(_num(r.get("jitter_ms")))})
    jit = "no jitter" if not jitter or jitter == [0.0] else "jitter per row (column jitter_ms: U[0, 2 jitter_ms])"
    return (
        f"{scored} Per-link capacity with a queue of {m.get('queue_s', QUEUE_S)} s of traffic, at least "
        f"{m.get('min_queue_bytes', MIN_QUEUE_BYTES)} bytes (the largest message of either mode fits, so a "
        f"drop at the lowest capacity is congestion, not a message too large for the queue); Bernoulli loss; {jit}."
    )


def write_network_outputs(rows: Iterable[dict], out_dir: str | Path, meta: dict | None = None) -> dict[str, Path]:
    """Write network.csv, network.md, results.json and PNG plots for sweep rows into ``out_dir``.

    Rows may come from the in-process sweep or the live fleet; missing keys are left empty. Rows with the downlink
    on (``--downlink``): in the table of all points and the section on it, not the summary and the other plots.
    Returns the written paths by name."""
    from . import network_downlink as nd

    rows = list(rows)
    base = [r for r in rows if r.get("downlink") != "on"]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    extra = sorted({k for r in rows for k in r} - set(NETWORK_COLUMNS))
    cols = list(NETWORK_COLUMNS) + extra
    paths = {"csv": out / "network.csv", "md": out / "network.md", "json": out / "results.json"}
    with paths["csv"].open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for r in rows:
            w.writerow([_cell(r.get(c)) for c in cols])
    paths["json"].write_text(jsonout.dumps({"meta": meta or {}, "columns": cols, "rows": rows}, indent=1) + "\n")
    short = [
        ("mode", "mode"),
        ("latency_ms", "latency (ms)"),
        ("loss", "loss"),
        ("bandwidth_bps", "capacity"),
        ("object_rmse_m", "object RMSE (m)"),
        ("object_coverage", "obj. cov."),
        ("vehicle_rmse_m", "vehicle RMSE (m)"),
        ("vehicle_coverage", "veh. cov."),
        ("bytes_per_s_per_vehicle", "bytes/s/veh"),
        ("delivered_fraction", "delivered"),
        ("latency_s_p50", "latency p50 (s)"),
        ("age_s_mean", "age (s)"),
    ]
    if any("downlink" in r for r in rows):
        short.insert(1, ("downlink", "downlink"))
    m = meta or {}
    L = [
        "# Network degradation sweep",
        "",
        f"Scenario {m.get('scenario', rows[0].get('scenario') if rows else '?')}, seed {m.get('seed', '?')}, "
        + _links_text(rows, m)
        + " Column definitions: module docstring of "
        "`mapcontainer/experiments/network.py` (delivered = delivered / messages whose fate was decided; age = "
        "fuse time minus the newest t_meas received from each remote vehicle, averaged). Vehicle RMSE is over the "
        "vehicles present in the fused state (coverage beside it); the fused state carries each vehicle's newest "
        "pose predicted to the fuse time at constant velocity, so an old message costs what that prediction gets "
        "wrong.",
        "",
        *([SMOKE_TEST_NOTE, ""] if m.get("smoke_test") else []),
        "## Key comparison",
        "",
        *_summary(base),
        "",
        "## All points",
        "",
        "| " + " | ".join(h for _, h in short) + " |",
        "|" + "---|" * len(short),
    ]
    for r in rows:
        cells = []
        for k, _ in short:
            v = r.get(k)
            cells.append(_bw_label(_num(v)) if k == "bandwidth_bps" else _cell(v))
        L.append("| " + " | ".join(cells) + " |")
    L += ["", "![RMSE vs latency](network_latency.png)", "", "![bandwidth](network_bandwidth.png)", ""]
    L += nd.section(rows, _cell, _bw_label)
    paths["md"].write_text("\n".join(L))
    smoke = bool(m.get("smoke_test"))
    paths.update(_plots(base, out, smoke_test=smoke))
    paths.update(nd.plot(rows, out, lambda fig: _banner(fig, smoke)))
    return paths


SMOKE_TEST_BANNER = "SMOKE TEST (--quick): a few seconds from a cold start; not figures of the network's effect"


def _plots(rows: list[dict], out: Path, smoke_test: bool = False) -> dict[str, Path]:
    """The sweep's two figures; a smoke test's say so on their face (a picture travels without its report)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not rows:
        return {}
    written = {}
    modes = [m for m in MODES if any(r.get("mode") == m for r in rows)] or sorted({r.get("mode") for r in rows})
    bws = sorted({_num(r.get("bandwidth_bps")) for r in rows}, reverse=True)
    losses = sorted({_num(r.get("loss")) for r in rows})
    lats = sorted({_num(r.get("latency_ms")) for r in rows})
    bw_top, loss0, lat0 = bws[0], losses[0], lats[0]

    def series(mode, key, fixed: dict, along: str, values):
        ys = []
        for v in values:
            match = [
                r
                for r in rows
                if r.get("mode") == mode
                and _num(r.get(along)) == v
                and all(_num(r.get(k)) == fv for k, fv in fixed.items())
            ]
            ys.append(_num(match[0].get(key)) if match else float("nan"))
        return ys

    fig, ax = plt.subplots(2, len(modes), figsize=(5 * len(modes), 7), squeeze=False)
    for j, mode in enumerate(modes):
        for ls in losses:
            fixed = {"bandwidth_bps": bw_top, "loss": ls}
            ax[0, j].plot(
                lats, series(mode, "object_rmse_m", fixed, "latency_ms", lats), "o-", label=f"loss {100 * ls:g} %"
            )
            ax[1, j].plot(
                lats, series(mode, "vehicle_rmse_m", fixed, "latency_ms", lats), "o-", label=f"loss {100 * ls:g} %"
            )
        ax[0, j].set(title=f"{mode}, {_bw_label(bw_top)}", ylabel="fused object RMSE (m)")
        ax[1, j].set(xlabel="latency (ms)", ylabel="fused vehicle RMSE (m)")
        ax[0, j].legend(fontsize=7)
    _banner(fig, smoke_test)
    written["png_latency"] = out / "network_latency.png"
    fig.savefig(written["png_latency"], dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(1, 3, figsize=(14, 4))
    for mode in modes:
        fixed = {"latency_ms": lat0, "loss": loss0}
        ax[0].plot(bws, series(mode, "object_rmse_m", fixed, "bandwidth_bps", bws), "o-", label=mode)
        ax[1].plot(bws, series(mode, "delivered_fraction", fixed, "bandwidth_bps", bws), "o-", label=mode)
        ax[2].plot(bws, series(mode, "age_s_mean", fixed, "bandwidth_bps", bws), "o-", label=mode)
    for a, lab in zip(
        ax, ("fused object RMSE (m)", "delivered fraction", "age of remote information (s)"), strict=True
    ):
        a.set(xscale="log", xlabel="per-link capacity (bit/s)", ylabel=lab)
        a.legend(fontsize=8)
    ax[0].set_title(f"latency {lat0:g} ms, loss {100 * loss0:g} %")
    _banner(fig, smoke_test)
    written["png_bandwidth"] = out / "network_bandwidth.png"
    fig.savefig(written["png_bandwidth"], dpi=110)
    plt.close(fig)
    return written


def _banner(fig, smoke_test: bool) -> None:
    """Lay the figure out, under the smoke-test banner when it is one."""
    if smoke_test:
        fig.suptitle(SMOKE_TEST_BANNER, color="firebrick", fontsize=10, fontweight="bold")
    fig.tight_layout()
