"""The downlink on and off: the same runs (scenario, seed, network) with and without it.

Per scenario and setting, over every vehicle and run, scored after ``burnin_s`` (cold start by default):
the on-board horizontal RMSE (each vehicle's own estimate, with the downlink fused when on), its average
NEES over the horizontal position (2 dof; a consistent estimator averages 2) with the fraction of frames
inside the 95 % chi^2 interval, the time to localize (:func:`.paper.figures.localized_index` on the
on-board error: median and 95th percentile over vehicle starts), the bytes per second on the air up
(vehicles -> host) and down (host -> vehicles, on the air: the ego's own stay on board), and what the
vehicles did with the downlink (fused, refused by their gate, seeded a search).

    python -m mapcontainer.experiments.downlink --runs 5 --seed 90000 --duration 10

prints JSON (``--markdown`` a table). Seeds below 90000 are for development; the evaluation seeds only measure.
"""

from __future__ import annotations

import argparse
import json
import math
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from ..metrics import chi2_quantile
from ..onboard import DownlinkParams
from ..pipeline import run_pipeline
from .paper.figures import localized_index

__all__ = ["compare", "from_runs", "main", "run_one", "summarize"]


def run_one(
    scenario: str,
    seed: int,
    duration_s: float,
    downlink: bool,
    network: str = "ideal",
    ci: bool = False,
    seed_search: bool = False,
) -> dict[str, Any]:
    """One run's on-board errors per vehicle: rows [t, horizontal error, NEES (2 dof)], and its bytes; ``ci``: the
    vehicles fuse the downlink by covariance intersection always (DownlinkParams.always_ci)."""
    params = DownlinkParams(always_ci=ci, seed_search=seed_search)
    res = run_pipeline(
        scenario, seed=seed, duration_s=duration_s, network=network, downlink=downlink, downlink_params=params
    )
    rows: dict[str, list[list[float]]] = {}
    for rec in res.records:
        ids = list(rec.truth.vehicle_ids)
        for vid in ids:
            est = rec.onboard.get(vid)
            if est is None:
                rows.setdefault(vid, []).append([rec.t, math.nan, math.nan])
                continue
            e = np.asarray(est[:2], float) - np.asarray(rec.truth.vehicle_pose[ids.index(vid)][:2], float)
            C = np.asarray(rec.onboard_covs[vid], float)[:2, :2]
            rows.setdefault(vid, []).append([rec.t, float(np.hypot(*e)), float(e @ np.linalg.solve(C, e))])
    counts: Counter = Counter()
    for c in res.downlink_counts.values():
        counts.update(c)
    return {
        "scenario": scenario,
        "seed": seed,
        "downlink": downlink,
        "duration_s": duration_s,
        "network": network,
        "ci": ci,
        "seed_search": seed_search,
        "rows": rows,
        "tx_bytes": int(sum(res.tx_bytes.values())),
        "rx_bytes": int(sum(res.rx_bytes.values())),
        "rx_msgs_by_vehicle": dict(res.rx_msgs),
        "downlink_counts": dict(counts),
    }


def summarize(runs: list[dict], burnin_s: float) -> dict[str, Any]:
    """The figures of the module docstring over ``runs`` (one scenario and setting)."""
    err, nis, ttl = [], [], []
    per_vehicle: dict[str, list[float]] = {}
    for r in runs:
        for vid, rows in r["rows"].items():
            a = np.asarray(rows, float)
            k = localized_index(a[:, 0], a[:, 1])
            ttl.append(math.inf if k is None else float(a[k, 0] - a[0, 0]))
            after = a[a[:, 0] >= burnin_s]
            e = np.where(np.isnan(after[:, 1]), np.inf, after[:, 1])  # no pose yet: counted, as lost
            err.append(e)
            per_vehicle.setdefault(vid, []).append(e)
            nis.append(after[~np.isnan(after[:, 2]), 2])
    e = np.concatenate(err) if err else np.zeros(0)
    n = np.concatenate(nis) if nis else np.zeros(0)
    lo, hi = chi2_quantile([0.025, 0.975], 2)
    seconds = sum(r["duration_s"] for r in runs)
    counts: Counter = Counter()
    for r in runs:
        counts.update(r["downlink_counts"])
    finite = e[np.isfinite(e)]
    return {
        "runs": len(runs),
        "onboard_rmse_m": float(np.sqrt(np.mean(finite**2))) if len(finite) else math.nan,
        "frames_without_pose": int((~np.isfinite(e)).sum()),
        "onboard_rmse_by_vehicle_m": {
            v: float(np.sqrt(np.mean(np.concatenate(x)[np.isfinite(np.concatenate(x))] ** 2)))
            for v, x in sorted(per_vehicle.items())
        },
        "onboard_anees_2dof": float(n.mean()) if len(n) else math.nan,
        "onboard_nees_in_95": float(np.mean((n >= lo) & (n <= hi))) if len(n) else math.nan,
        "time_to_localize_s": {
            "p50": float(np.percentile(ttl, 50, method="inverted_cdf")),  # never = +inf: a percentile may be inf
            "p95": float(np.percentile(ttl, 95, method="inverted_cdf")),
            "never": int(np.sum(np.isinf(ttl))),
        },
        "uplink_bytes_per_s": sum(r["tx_bytes"] for r in runs) / seconds,
        "downlink_bytes_per_s": sum(r["rx_bytes"] for r in runs) / seconds,
        "downlink": dict(sorted(counts.items())),
    }


def compare(
    scenarios: list[str],
    seeds: list[int],
    duration_s: float,
    burnin_s: float,
    network: str,
    runs_file: str | None = None,
    ci: bool = False,
    seed_search: bool = False,
) -> dict:
    """Every scenario with the downlink off and on, the same seeds; the runs in pairs (seed by seed, off then on,
    scenario by scenario), each appended to ``runs_file`` (JSON lines) as it ends if given, and taken from it
    when it is there already (a cut-off comparison resumes; :func:`from_runs` summarises what a file holds; a file
    holds the runs of one ``ci`` setting)."""
    done = {}
    if runs_file is not None and Path(runs_file).exists():
        for line in Path(runs_file).read_text().splitlines():
            r = json.loads(line)
            done[(r["scenario"], r["seed"], r["downlink"], r["duration_s"], r.get("network", "ideal"))] = r
    runs = []
    for seed in seeds:
        for sc in scenarios:
            for on in (False, True):
                r = done.get((sc, seed, on, duration_s, network))
                if r is None:
                    r = run_one(sc, seed, duration_s, on, network, ci, seed_search)
                    if runs_file is not None:
                        with open(runs_file, "a") as f:
                            f.write(json.dumps(r, default=float) + "\n")
                runs.append(r)
    return from_runs(runs, burnin_s, network)


def from_runs(runs: list[dict], burnin_s: float, network: str = "ideal") -> dict:
    """:func:`compare`'s result from its runs."""
    out: dict[str, Any] = {
        "seeds": sorted({r["seed"] for r in runs}),
        "duration_s": sorted({r["duration_s"] for r in runs}),
        "burnin_s": burnin_s,
        "network": network,
    }
    for sc in dict.fromkeys(r["scenario"] for r in runs):
        by = {
            key: [r for r in runs if r["scenario"] == sc and r["downlink"] == on] for key, on in (("off", 0), ("on", 1))
        }
        out[sc] = {key: summarize(rs, burnin_s) for key, rs in by.items() if rs}
    return out


_COLUMNS = (
    "scenario | downlink | on-board RMSE (m) | ANEES (2 dof) | in 95 % | TTL p50 / p95 (s) | never | up B/s | down B/s"
)


def markdown(res: dict) -> str:
    """The on/off table of :func:`compare`'s result."""
    lines = [f"| {_COLUMNS} |", "|" + "---|" * 9]
    for sc, by in res.items():
        if not isinstance(by, dict):
            continue
        for key in (k for k in ("off", "on") if k in by):
            f, t = by[key], by[key]["time_to_localize_s"]
            cells = [
                sc,
                key,
                f"{f['onboard_rmse_m']:.3f}",
                f"{f['onboard_anees_2dof']:.2f}",
                f"{f['onboard_nees_in_95']:.2f}",
                f"{t['p50']:.2f} / {t['p95']:.2f}",
                str(t["never"]),
                f"{f['uplink_bytes_per_s']:.0f}",
                f"{f['downlink_bytes_per_s']:.0f}",
            ]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m mapcontainer.experiments.downlink", description=__doc__.split("\n")[0])
    p.add_argument("--scenarios", default="paper-urban,paper-suburban")
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--seed", type=int, default=90000, help="run i uses seed + i (>= 90000: evaluation seeds)")
    p.add_argument("--duration", type=float, default=10.0)
    p.add_argument("--burnin", type=float, default=3.0)
    p.add_argument("--network", default="ideal")
    p.add_argument("--markdown", action="store_true")
    p.add_argument("--ci", action="store_true", help="the vehicles fuse the downlink by covariance intersection always")
    p.add_argument("--seed-search", action="store_true", help="a searching vehicle is seeded by the downlink")
    p.add_argument("--runs-file", default=None, help="JSON lines of the runs: appended as they end, reused when there")
    a = p.parse_args(argv)
    seeds = [a.seed + i for i in range(a.runs)]
    res = compare(a.scenarios.split(","), seeds, a.duration, a.burnin, a.network, a.runs_file, a.ci, a.seed_search)
    print(markdown(res) if a.markdown else json.dumps(res, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
