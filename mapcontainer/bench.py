"""Benchmarks behind ``mapc bench ...``: accuracy and speed figures as one JSON-able dict each."""

from __future__ import annotations

import time
from typing import Literal

import numpy as np

from schemas import body_pose_cov, encode

from . import geometry as geo
from .fusion.jointbench import yardstick_ms
from .localization import LocalizerParams
from .localization.search import PoseSearchParams
from .metrics import percentile, rmse
from .seeds import seed_kind
from .sim import World, load_scenario
from .sim.errors import enabled_error_sources, with_error_sources
from .vehicle import VehicleAgent

__all__ = ["ALERT_LIMIT_M", "WARMUP_S", "bench_localization", "integrity_summary"]


WARMUP_S = 2.0  # seconds of an episode not scored (initialisation from GNSS)


def bench_localization(
    scenario: str,
    seeds: int = 3,
    duration_s: float = 20.0,
    warmup_s: float = WARMUP_S,
    ideal: bool = False,
    seed0: int = 0,
    stanford_png: str | None = None,
    startup_accept: Literal["landmarks", "posterior"] = "landmarks",
    search_budget: int | None = PoseSearchParams().solves_per_frame,
    yardstick_every: int = 200,
    map_errors: Literal["independent", "consider"] = "independent",
) -> dict:
    """Map-matching self-localization of every connected vehicle over ``seeds`` seeded episodes (seeds
    ``seed0`` ... ``seed0 + seeds - 1``; development seeds are below :data:`~mapcontainer.seeds.EVAL_SEED0`).

    ``ideal``: every error source of the simulator off (exact map, calibration and clocks:
    :func:`mapcontainer.sim.errors.with_error_sources`); otherwise the scenario's own (realistic) ones.

    The vehicle's estimate is the localizer's filtered pose (what the vehicle knows of itself);
    position errors are horizontal, lateral / longitudinal along the true heading (the vehicle frame:
    ``lateral_*``, ``longitudinal_*`` beside each horizontal figure, with the 95th percentiles of their
    magnitudes). The map-matching
    figures (``mapmatch_*``, ``lateral_*``, ``longitudinal_*``, ``yaw_*``) are over the frames the
    vehicle reports map matching (``converged_fraction`` of them); ``all_frames_*`` include the
    GNSS + odometry fallback frames (start-up, blind stretches). NEES is over the six pose parameters
    and all frames: the covariance must be honest in fallback too (``fallback_*``: the frames the vehicle does
    not report map matching, their horizontal RMSE and horizontal NEES, 2 when honest, with its 95th
    percentile: 5.99 when Gaussian and honest); ``nees_axes_mean`` is the mean of
    each parameter's squared error over its variance (1 when honest; it shows which axes a NEES above
    6 comes from). ``prior_*`` score what the
    VehiclePrior carries instead: this frame's
    camera evidence with a weak prior (independent from frame to frame, for the host's graph) --
    noisier, with its own covariance. Frames in the first ``warmup_s`` seconds (initialisation
    from GNSS) are not scored, nor frames without a pose (``no_pose_frames``: the localizer re-initialising).
    Time is the whole vehicle step (PNG decode, distance transform,
    matching, message build): ``ms_per_frame_*`` in wall time, ``cpu_ms_per_frame_*`` in this process's CPU time
    (``time.process_time``: what a loaded machine's waits do not inflate), and ``yardstick_ms_p50`` a fixed workload
    (:func:`~mapcontainer.fusion.jointbench.yardstick_ms`) timed every ``yardstick_every`` frames, with the frame's
    wall p50 / p99 over it (``*_over_yardstick``: the machine's speed at the time divided out);
    ``solves_per_frame_*``: the matcher's solves per step (association rounds + LM
    from one start pose), the machine-independent part of that time (the start-up search's anytime budget,
    ``PoseSearchParams.solves_per_frame``, bounds it; ``search_budget``, None: no budget).
    ``after_localized_rmse_m``: every vehicle's horizontal RMSE from the frame it localizes on (steady state,
    whatever its start). ``startup``: the cold start from GNSS of every vehicle, from t = 0, as the paper
    experiment scores it (:func:`mapcontainer.experiments.paper.figures.startup_summary`:
    time to localize, gross errors after it, those the vehicle did not announce). ``integrity``: see
    :func:`integrity_summary`; ``stanford_png``: draw its Stanford diagram there. ``startup_accept``: the
    localizer's start-up acceptance rule (``PoseSearchParams.accept``: 'landmarks', the default, or 'posterior').
    ``map_errors``: how its tracker folds a match in (``LocalizerParams.map_errors``).
    """
    from .experiments.paper.figures import startup_summary

    if seeds < 1 or not duration_s > warmup_s:
        raise ValueError(f"need seeds >= 1 and duration_s > warmup_s, got {seeds}, {duration_s}, {warmup_s}")
    acc: dict[str, list] = {k: [] for k in _ACC}
    params = LocalizerParams(
        search=PoseSearchParams(accept=startup_accept, solves_per_frame=search_budget), map_errors=map_errors
    )
    sc = load_scenario(scenario)
    if ideal:
        sc = with_error_sources(sc, ())
    runs = []
    for seed in range(seed0, seed0 + seeds):
        with World(sc, seed=seed) as world:
            runs.append({"locks": _episode(world, duration_s, warmup_s, acc, params, yardstick_every)})
    yard = float(np.median(acc["yardstick"]))
    (e_pos, e_lat, e_lon, e_yaw, e_gnss, nees, ms, sizes, matched, e_prior, nees_prior, e_all, e_all_yaw, nees_axes) = (
        acc[k] for k in _ACC[:14]
    )
    return {
        "scenario": scenario,
        "error_sources": enabled_error_sources(sc),
        "seeds": seeds,
        "seed0": seed0,
        "seed_kind": seed_kind(seed0),
        "startup_accept": startup_accept,
        "search_budget": search_budget,
        "map_errors": map_errors,
        "duration_s": duration_s,
        "warmup_s": warmup_s,
        "frames": len(matched),
        "no_pose_frames": len(acc["no_pose"]),
        "gnss_rmse_m": round(rmse(e_gnss), 3),
        "mapmatch_rmse_m": round(rmse(e_pos), 3),
        "lateral_rmse_m": round(rmse(e_lat), 3),
        "longitudinal_rmse_m": round(rmse(e_lon), 3),
        "yaw_rmse_deg": round(rmse(e_yaw), 3),
        "converged_fraction": round(float(np.mean(matched)), 4),
        "all_frames_rmse_m": round(rmse(e_all), 3),
        "all_frames_lateral_rmse_m": round(rmse(acc["e_all_lat"]), 3),
        "all_frames_longitudinal_rmse_m": round(rmse(acc["e_all_lon"]), 3),
        "all_frames_lateral_p95_m": round(percentile(np.abs(np.ravel(acc["e_all_lat"])), 95), 3),
        "all_frames_longitudinal_p95_m": round(percentile(np.abs(np.ravel(acc["e_all_lon"])), 95), 3),
        "lateral_p95_m": round(percentile(np.abs(np.ravel(e_lat)), 95), 3),
        "all_frames_yaw_rmse_deg": round(rmse(e_all_yaw), 3),
        "nees_mean": round(float(np.mean(nees)), 2),
        "fallback_frames": len(acc["e_fallback"]),
        "fallback_rmse_m": round(rmse(acc["e_fallback"]), 3) if acc["e_fallback"] else None,
        "fallback_nees_h_mean": round(float(np.mean(acc["nees_h_fallback"])), 2) if acc["e_fallback"] else None,
        "fallback_nees_h_p95": round(percentile(acc["nees_h_fallback"], 95), 2) if acc["e_fallback"] else None,
        "nees_axes_mean": dict(zip(_AXES, np.round(np.mean(nees_axes, axis=0), 2).tolist(), strict=True)),
        "ms_per_frame_p50": round(percentile(ms, 50), 2),
        "ms_per_frame_p99": round(percentile(ms, 99), 2),
        "cpu_ms_per_frame_p50": round(percentile(acc["cpu_ms"], 50), 2),
        "cpu_ms_per_frame_p99": round(percentile(acc["cpu_ms"], 99), 2),
        "yardstick_ms_p50": round(yard, 2),
        "ms_p50_over_yardstick": round(percentile(ms, 50) / yard, 3),
        "ms_p99_over_yardstick": round(percentile(ms, 99) / yard, 3),
        "solves_per_frame_p99": percentile(acc["solves"], 99),
        "solves_per_frame_max": int(np.max(acc["solves"], initial=0)),
        "prior_bytes_mean": round(float(np.mean(sizes)), 1),
        "prior_rmse_m": round(rmse(e_prior), 3),
        "prior_nees_mean": round(float(np.mean(nees_prior)), 2),
        "after_localized_rmse_m": round(_after_localized_rmse(runs), 3),
        "integrity": integrity_summary(acc["integrity"], stanford_png),
        "startup": startup_summary(runs, duration_s),
    }


_AXES = ("x", "y", "z", "roll", "pitch", "yaw")
_ACC = (
    "e_pos", "e_lat", "e_lon", "e_yaw", "e_gnss", "nees", "ms", "sizes", "matched", "e_prior", "nees_prior", "e_all",
    "e_all_yaw", "nees_axes", "no_pose", "e_all_lat", "e_all_lon", "integrity", "solves", "cpu_ms", "yardstick",
    "e_fallback", "nees_h_fallback",
)  # fmt: skip
ALERT_LIMIT_M = 0.5  # lateral protection level at most this: the frame is available (local streets)


def _episode(
    world: World,
    duration_s: float,
    warmup_s: float,
    acc: dict[str, list],
    params: LocalizerParams,
    yardstick_every: int = 100,
) -> list[list[float]]:
    """Every vehicle of one episode localized frame by frame (with ``params``); the scored frames' figures appended
    to ``acc`` (lists named in :data:`_ACC`; the yardstick timed once per ``yardstick_every`` frames, between
    frames); returns the cold-start rows [t, vehicle index, says map_matching,
    horizontal error]."""
    e_pos, e_lat, e_lon, e_yaw, e_gnss, nees, ms, sizes, matched, e_prior, nees_prior, e_all, e_all_yaw, nees_axes = (
        acc[k] for k in _ACC[:14]
    )
    agents = {v: VehicleAgent(world.hdmap, v, world.fleet, params=params) for v in world.vehicle_ids}
    index = {v: i for i, v in enumerate(world.vehicle_ids)}
    locks: list[list[float]] = []
    for tick in world.run(duration_s):
        for vid, frame in tick.frames.items():
            if len(ms) % yardstick_every == 0:
                acc["yardstick"].append(yardstick_ms())
            t0, c0, solves0 = time.perf_counter(), time.process_time(), agents[vid].localizer.matcher.solves
            prior = agents[vid].handle(tick.t, frame)
            ms.append((time.perf_counter() - t0) * 1e3)
            acc["cpu_ms"].append((time.process_time() - c0) * 1e3)
            acc["solves"].append(agents[vid].localizer.matcher.solves - solves0)
            sizes.append(len(encode(prior)))
            res = agents[vid].last_result
            truth = tick.states[vid].pose
            has_pose = res is not None and res.cov_filtered is not None  # none: (re-)initialising from GNSS
            err_h = float(np.hypot(*_pose_error(res.pose_filtered, truth)[:2])) if has_pose else float("nan")
            locks.append([tick.t, index[vid], float(prior.quality.mode == "map_matching"), err_h])
            if tick.t < warmup_s:
                continue
            if not has_pose:
                acc["no_pose"].append(1)
                continue
            err = _pose_error(res.pose_filtered, truth)
            e_all.append(err[:2])
            e_body = geo.rot_z(truth[5]).T[:2, :2] @ err[:2]  # along, across the true heading
            acc["e_all_lon"].append(e_body[:1])
            acc["e_all_lat"].append(e_body[1:])
            pl = res.protection_level
            claimed = pl is not None
            acc["integrity"].append(
                [float(claimed), *(pl if claimed else (np.inf, np.inf)), abs(e_body[1]), abs(e_body[0])]
            )
            e_all_yaw.append(np.degrees(err[5:]))
            e_gnss.append(np.asarray(frame.gnss.p_map[:2], float) - truth[:2])
            nees.append(float(err @ np.linalg.solve(res.cov_filtered, err)))
            nees_axes.append(err**2 / np.diag(res.cov_filtered))
            matched.append(prior.quality.mode == "map_matching")
            if matched[-1]:
                e_pos.append(err[:2])
                e_lon.append(e_body[:1])
                e_lat.append(e_body[1:])
                e_yaw.append(np.degrees(err[5:]))
            else:
                acc["e_fallback"].append(err[:2])
                acc["nees_h_fallback"].append(float(err[:2] @ np.linalg.solve(res.cov_filtered[:2, :2], err[:2])))
            err_p = _pose_error(prior.pose, truth)
            e_prior.append(err_p[:2])
            nees_prior.append(float(err_p @ np.linalg.solve(body_pose_cov(prior), err_p)))
    return locks


def integrity_summary(rows, stanford_png: str | None = None) -> dict:
    """Integrity of the scored frames' protection levels; rows [claimed, PL lateral, PL longitudinal, |error|
    lateral, |error| longitudinal] (the vehicle frame; PL inf where the vehicle claimed none).

    ``availability``: the fraction of frames the vehicle claims integrity with a lateral protection level of at
    most :data:`ALERT_LIMIT_M`. HMI (hazardously misleading information): a frame the vehicle claims integrity
    whose true error exceeds its protection level on an axis; ``hmi_rate`` is per claimed frame (the integrity
    risk stated is per axis). ``stanford_png``: error against protection level, lateral and longitudinal."""
    a = np.asarray(rows, dtype=float).reshape(-1, 5)
    claimed = a[:, 0] > 0
    hmi = claimed & ((a[:, 3] > a[:, 1]) | (a[:, 4] > a[:, 2]))
    out = {
        "alert_limit_m": ALERT_LIMIT_M,
        "frames": len(a),
        "claimed_fraction": round(float(claimed.mean()), 4) if len(a) else float("nan"),
        "availability": round(float((claimed & (a[:, 1] <= ALERT_LIMIT_M)).mean()), 4) if len(a) else float("nan"),
        "hmi_frames": int(hmi.sum()),
        "hmi_rate": float(hmi.sum() / claimed.sum()) if claimed.any() else float("nan"),
        "pl_lateral_p50_m": round(percentile(a[claimed, 1], 50), 3),
        "pl_longitudinal_p50_m": round(percentile(a[claimed, 2], 50), 3),
    }
    if stanford_png:
        _stanford(a[claimed], stanford_png)
    return out


def _stanford(a: np.ndarray, path: str) -> None:
    """Stanford diagram: |error| (x) against protection level (y), lateral and longitudinal, with the diagonal
    (below it: misleading) and the alert limit."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    panels = (("lateral", a[:, 1], a[:, 3]), ("longitudinal", a[:, 2], a[:, 4]))
    for ax, (name, pl, err) in zip(axes, panels, strict=True):
        top = max(1.0, float(np.max(np.r_[pl, err], initial=1.0)) * 1.05)
        ax.plot([0, top], [0, top], "k-", lw=0.8)
        if name == "lateral":
            ax.axhline(ALERT_LIMIT_M, color="r", lw=0.8, ls="--")
        bad = err > pl
        ax.scatter(err[~bad], pl[~bad], s=3, alpha=0.4, label=f"PL >= error ({int((~bad).sum())})")
        ax.scatter(err[bad], pl[bad], s=6, color="r", label=f"misleading ({int(bad.sum())})")
        ax.set(xlim=(0, top), ylim=(0, top), xlabel=f"|{name} error| (m)", ylabel=f"{name} protection level (m)")
        ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _after_localized_rmse(runs: list[dict]) -> float:
    """Horizontal RMSE of every vehicle's filtered pose from the frame it localizes on (the cold start's
    :func:`~mapcontainer.experiments.paper.figures.localized_index`) to the episode's end: the steady state,
    whatever the start took (NaN if no vehicle localized)."""
    from .experiments.paper.figures import localized_index

    errs = []
    for r in runs:
        a = np.asarray(r["locks"], dtype=float).reshape(-1, 4)
        for i in np.unique(a[:, 1]):
            v = a[a[:, 1] == i]
            k = localized_index(v[:, 0], v[:, 3])
            if k is not None:
                errs.append(v[k:, 3])
    return float(np.sqrt(np.mean(np.concatenate(errs) ** 2))) if errs else float("nan")


def _pose_error(pose, truth) -> np.ndarray:
    err = np.asarray(pose, float) - truth
    err[3:] = geo.wrap_angle(err[3:])
    return err
