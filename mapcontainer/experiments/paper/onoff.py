"""The downlink on and off in the paper experiment (``mapc experiment paper --downlink both``).

Every run of the experiment runs twice, with the same seed (the same world, sensors, noise and link): with the
host's downlink (docs/downlink.md) and without it. The centralized reference does not depend on the downlink: it
runs once per seed, beside the run without the downlink, and the run with it borrows it
(:func:`borrow_reference`), so both settings' efficiencies are against the same reference. Every figure of the
experiment is aggregated for both settings (``results.json``: the report's settings at the top level, the other
under ``downlink_other``); :func:`on_off` puts the headline figures side by side, and :func:`section` writes them
into the report. All of it is a function of the runs grouped by seed, whatever order they finished in.

Per simulated scenario and setting (steady state, every vehicle of every run):

* RMSE (m, horizontal): the vehicles' on-board estimates (the vehicle's own, with the downlink fused when on),
  their fused poses at the host, the objects (map frame) and the targets (the ego frame, rms2);
* consistency: the on-board ANEES of the horizontal position (2 dof, what the downlink informs) with its 95 % band,
  the on-board and fused 6-DoF ANEES, the objects' 3-D ANEES (per run, :func:`.figures.consistency`);
* the cold start's time to localize (median, 95th percentile, never: :func:`.figures.startup_summary`);
* bytes per second on the air over the whole fleet (unsigned): up (vehicles -> host) and down (host -> vehicles;
  the ego's downlink stays on board); the distributed efficiency against the centralized reference (vehicles,
  objects) and the centralized bytes over the distributed bytes counting both directions;
* what the vehicles did with the downlink, in vehicle-frames by status (:class:`mapcontainer.onboard.Onboard`:
  fused, fused_ci (by covariance intersection), refused by their gate, stale (too old), none (nothing arrived)).
"""

from __future__ import annotations

from typing import Any

from ...jsonout import rounded
from .figures import _pooled_consistency, group

__all__ = ["borrow_reference", "on_off", "section", "split_by_downlink"]

REFERENCE = ":centralized"  # the suffix of the centralized reference's series, NEES and object rows


def _setting(downlink: bool) -> str:
    return "on" if downlink else "off"


def borrow_reference(runs: list[dict], donors: list[dict]) -> list[dict]:
    """``runs`` (with the downlink), each simulation run given the centralized reference of its twin in ``donors``
    (the same kind, scenario, variant and seed, without the downlink): its series, NEES and object rows of the
    centralized estimate and the reference's bytes. Runs without a twin that has one stay as they are."""
    by = {(d["kind"], d["key"], d["variant"], d["seed"]): d for d in donors if "tx_msgs_centralized" in d}
    out = []
    for r in runs:
        d = by.get((r["kind"], r["key"], r["variant"], r["seed"]))
        if d is None or "tx_msgs_centralized" in r:
            out.append(r)
            continue
        borrowed = {
            part: {**r[part], **{n: v for n, v in d[part].items() if n.endswith(REFERENCE)}}
            for part in ("series", "nees", "objects")
        }
        out.append(
            {
                **r,
                **borrowed,
                "tx_bytes_centralized": d["tx_bytes_centralized"],
                "tx_msgs_centralized": d["tx_msgs_centralized"],
            }
        )
    return out


def split_by_downlink(results: list[dict], downlink: bool) -> tuple[list[dict], list[dict]]:
    """The runs with the downlink as ``downlink`` says and the others, those with the downlink given the
    reference of their twins without it (:func:`borrow_reference`)."""
    on = [r for r in results if r.get("downlink", False)]
    off = [r for r in results if not r.get("downlink", False)]
    on = borrow_reference(on, off)
    return (on, off) if downlink else (off, on)


def _scenario_row(fig: dict, runs: list[dict], duration_s: float, burnin_s: float) -> dict[str, Any]:
    """One scenario's headline figures in one setting (module docstring) from its figures and its main runs."""
    cons = fig.get("consistency", {})
    xy = _pooled_consistency(runs, [f"{v}:onboard_xy" for v in fig["per_vehicle_rmse_m"]], burnin_s, dof=2)
    ttl = fig.get("startup", {}).get("time_to_localize_s", {})
    eff = fig.get("efficiency") or {}
    seconds = len(runs) * duration_s
    up, down = sum(r["tx_bytes"] for r in runs), sum(r.get("rx_bytes", 0) for r in runs)
    central = sum(r.get("tx_bytes_centralized", 0) for r in runs if "tx_msgs_centralized" in r)
    counts: dict[str, int] = {}
    for r in runs:
        for k, n in r.get("downlink_frames", {}).items():
            counts[k] = counts.get(k, 0) + n
    per = fig["per_vehicle_rmse_m"]
    nan = float("nan")
    return {
        "vehicles_onboard_rmse_m": fig["vehicles_rmse_m"]["onboard"],
        "ego_onboard_rmse_m": fig["ego_rmse_m"]["onboard"],
        "vehicles_fused_rmse_m": fig["vehicles_rmse_m"]["cooperative"],
        "objects_rmse_m": fig["object_rmse_m"]["cooperative"],
        "targets_rmse_m": fig["target_rmse_m"]["cooperative"],
        "fused_worse_than_onboard": sorted(v for v, f in per.items() if not f["cooperative"] <= f["onboard"]),
        "onboard_anees_2dof": xy.get("anees", nan),
        "onboard_anees_2dof_band": xy.get("band", [nan, nan]),
        "onboard_anees_2dof_inside": bool(xy.get("inside", False)),
        "onboard_anees_6dof": cons.get("vehicles_onboard_6dof", {}).get("anees", nan),
        "fused_anees_6dof": cons.get("vehicles_cooperative_6dof", {}).get("anees", nan),
        "objects_anees_3d": cons.get("objects_cooperative_3d", {}).get("anees", nan),
        "time_to_localize_s": {k: ttl.get(k, nan) for k in ("median", "p95", "never", "vehicles")},
        "up_bytes_per_s": rounded(up / seconds, 1) if seconds else nan,
        "down_bytes_per_s": rounded(down / seconds, 1) if seconds else nan,
        "efficiency_vehicles": eff.get("all_vehicles", nan),
        "efficiency_objects": eff.get("objects", nan),
        "reference_valid": eff.get("valid", {}),
        "centralized_over_distributed_bytes": rounded(central / (up + down), 2) if central and up + down else nan,
        "downlink_frames": dict(sorted(counts.items())),
        "runs": len(runs),
    }


def _test_site_rows(res: dict) -> dict[str, dict[str, float]]:
    """The test-site figures of one setting: the overlap's fused obstacle, the blind spots' connected car (fused,
    on board) and obstacle, per scenario and landmark density."""
    out = {}
    for density, ov in res.get("overlap", {}).items():
        out[f"overlap, {density}"] = {"fused_obstacle_m": ov["fused_m"]}
    for key, by_density in res.get("blindspot", {}).items():
        for density, b in by_density.items():
            out[f"({key}), {density}"] = {
                "connected_car_fused_m": b["connected_car_m"],
                "connected_car_onboard_m": b["connected_car_onboard_m"],
                "obstacle_m": b["obstacle_m"],
            }
    return out


def _target_name(t: dict) -> str:
    return t["target"].split(" (not valid")[0]


def on_off(main: dict, other: dict, results: list[dict], s) -> dict[str, Any]:
    """The headline figures of both settings side by side (module docstring): ``main`` and ``other`` are the
    aggregates of the runs with the downlink as ``s.downlink`` says and the other way, ``results`` every run
    (each with its ``downlink``; those with it carry the borrowed reference)."""
    by_setting = {_setting(s.downlink): main, _setting(not s.downlink): other}
    by = group([r for r in results if r["kind"] == "sim" and r["variant"] == "all"])
    simulation: dict[str, dict] = {}
    for key in main["simulation"]:
        simulation[key] = {}
        for name in ("off", "on"):
            fig = by_setting[name]["simulation"].get(key)
            runs = [r for r in by.get(("sim", key, "all"), []) if _setting(r.get("downlink", False)) == name]
            if fig and runs:
                simulation[key][name] = _scenario_row(fig, runs, s.duration_s, s.burnin_s)
    sites = {name: _test_site_rows(r) for name, r in by_setting.items()}
    test_site = {k: {name: sites[name].get(k, {}) for name in ("off", "on")} for k in sites["off"]}
    targets_on = {_target_name(t): t for t in by_setting["on"]["targets"]}
    targets = []
    for t in by_setting["off"]["targets"]:
        o = targets_on.get(_target_name(t))
        if o is not None:
            targets.append(
                {
                    "target": _target_name(t),
                    "threshold": t["threshold"],
                    "off": t["value"],
                    "on": o["value"],
                    "off_pass": t["pass"],
                    "on_pass": o["pass"],
                }
            )
    seeds = sorted({r["seed"] for r in results if r["kind"] == "sim" and r["variant"] == "all"})
    return {"report_setting": _setting(s.downlink), "seeds": seeds, "simulation": simulation,
            "test_site": test_site, "targets": targets}  # fmt: skip


# ------------------------------------------------------------------------------------------------- the report


def section(res: dict) -> list[str]:
    """The report's section "The downlink on and off" (nothing when the experiment did not compare)."""
    from .report import _fmt as _f
    from .report import _seconds

    c = res.get("downlink_on_off")
    if not c:
        return []
    seeds = c["seeds"]
    span = f"{seeds[0]}–{seeds[-1]}" if len(seeds) > 1 else str(seeds[0]) if seeds else "none"
    L = [
        "## The downlink on and off",
        "",
        f"Every run twice with the same seed (seeds {span}: the same world, sensors, noise and link), without and with "
        "the host's downlink (after each solve the host sends every vehicle what the others know about its pose, "
        "its own share removed; docs/downlink.md). The sections above are the runs with the downlink "
        f"**{c['report_setting']}**; `results.json` holds every figure of the other setting under `downlink_other`. "
        "One centralized reference per seed (it does not depend on the downlink) for both efficiencies.",
        "",
        "*On board* = the vehicles' own estimates (with the downlink fused when on), *fused* = the host's; RMSE over "
        "every vehicle of every run, steady state. ANEES per run: the on-board horizontal position (2 dof, its 95 % "
        "band in brackets), the on-board and fused poses (6-DoF), the objects (3-D).",
        "",
        "| scenario | downlink | on-board RMSE (m) | ego on-board | fused RMSE (m) | objects RMSE (m) | targets rms2 "
        "(m) | on-board ANEES 2 dof [band] | on-board ANEES 6-DoF | fused ANEES 6-DoF | objects ANEES 3-D |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    rows = [(key, name, f) for key, by in c["simulation"].items() for name, f in by.items()]
    for key, name, f in rows:
        band = f["onboard_anees_2dof_band"]
        L.append(
            f"| {key} | {name} | {_f(f['vehicles_onboard_rmse_m'])} | {_f(f['ego_onboard_rmse_m'])} | "
            f"{_f(f['vehicles_fused_rmse_m'])} | {_f(f['objects_rmse_m'])} | {_f(f['targets_rmse_m'])} | "
            f"{_f(f['onboard_anees_2dof'], 2)} [{_f(band[0], 2)}, {_f(band[1], 2)}] | "
            f"{_f(f['onboard_anees_6dof'], 2)} | {_f(f['fused_anees_6dof'], 2)} | {_f(f['objects_anees_3d'], 2)} |"
        )
    L += [
        "",
        "Cold start (time to localize, every vehicle start), bytes per second on the air over the whole fleet "
        "(unsigned; up = vehicles -> host, down = host -> vehicles), the efficiency against the centralized reference "
        "(centralized MSE / distributed MSE of the fused vehicles and objects) and the centralized bytes over the "
        "distributed bytes of both directions; the downlink's frames: vehicle-frames by what the vehicle did with it "
        "(fused; fused_ci: by covariance intersection; refused: by its gate; stale: too old; none: nothing arrived).",
        "",
        "| scenario | downlink | TTL median / p95 (s) | never | up B/s | down B/s | efficiency vehicles / objects "
        "| centralized / (up + down) bytes | fused worse than on board | downlink frames |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key, name, f in rows:
        t = f["time_to_localize_s"]
        frames = ", ".join(f"{k} {n}" for k, n in f["downlink_frames"].items()) or "none"
        L.append(
            f"| {key} | {name} | {_seconds(t['median'])} / {_seconds(t['p95'])} | {t['never']} of "
            f"{t['vehicles']} | {_f(f['up_bytes_per_s'], 0)} | {_f(f['down_bytes_per_s'], 0)} | "
            f"{_f(f['efficiency_vehicles'], 2)} / {_f(f['efficiency_objects'], 2)} | "
            f"{_f(f['centralized_over_distributed_bytes'], 1)}× | "
            f"{', '.join(f['fused_worse_than_onboard']) or 'none'} | {frames} |"
        )
    if c["test_site"]:
        L += [
            "",
            "Test site (RMSE, m; the connected car's fused pose and its own on-board estimate):",
            "",
            "| scenario | downlink | connected car fused | connected car on board | obstacle |",
            "|---|---|---|---|---|",
        ]
        for key, by in c["test_site"].items():
            for name, f in by.items():
                if "fused_obstacle_m" in f:
                    L.append(f"| {key} | {name} | | | {_f(f['fused_obstacle_m'])} |")
                elif f:
                    L.append(
                        f"| {key} | {name} | {_f(f['connected_car_fused_m'])} | {_f(f['connected_car_onboard_m'])} "
                        f"| {_f(f['obstacle_m'])} |"
                    )
    if c["targets"]:
        L += ["", "| target | off | on | threshold | off | on |", "|---|---|---|---|---|---|"]
        for t in c["targets"]:
            L.append(
                f"| {t['target']} | {_f(t['off'])} | {_f(t['on'])} | {_f(t['threshold'])} | "
                f"{'PASS' if t['off_pass'] else 'FAIL'} | {'PASS' if t['on_pass'] else 'FAIL'} |"
            )
    return [*L, ""]
