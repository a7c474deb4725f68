"""``mapc``: the command line. Each command that measures something prints JSON as its last line."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from . import jsonout
from .cliargs import (
    Parser,
    config_dir_arg,
    fleet_name,
    fleet_sizes,
    non_negative_int,
    non_negative_seconds,
    output_dir,
    positive_days,
    positive_float,
    positive_int,
    seconds,
    service_ids,
    vehicle_ids,
)
from .config import ConfigError
from .map_cli import add_map_commands
from .security import SERVICE_SIGNERS
from .seeds import EVAL_SEED0

__all__ = [
    "build_parser",
    "fleet_name",
    "main",
    "non_negative_int",
    "non_negative_seconds",
    "output_dir",
    "positive_float",
    "positive_int",
    "run",
    "seconds",
    "vehicle_ids",
]


def _cmd_scenario_list(args: argparse.Namespace) -> int:
    from .config import BUILTIN_DIR, list_presets
    from .sim.config import load_scenario

    rows = []
    for name, path in list_presets("scenarios").items():
        row = {"name": name, "file": str(path), "builtin": path.is_relative_to(BUILTIN_DIR)}
        try:
            sc = load_scenario(path)
        except ConfigError as exc:  # e.g. a SUMO preset without the roads extra: listed, with the reason
            rows.append({**row, "vehicles": None, "obstacles": None, "description": "", "unavailable": str(exc)})
            continue
        rows.append(
            {
                **row,
                "vehicles": sc.n_connected,
                "obstacles": len(sc.obstacle_vehicles) + len(sc.pedestrians) if sc.sumo is None else None,
                "description": sc.description,
            }
        )
    if args.json:
        print(jsonout.dumps(rows))
    else:
        width = max(len(r["name"]) for r in rows)
        for r in rows:
            own = "" if r["builtin"] else f"  ({r['file']})"
            if "unavailable" in r:
                print(f"{r['name']:<{width}}  unavailable: {r['unavailable'].splitlines()[-1].strip()}{own}")
                continue
            others = "SUMO traffic" if r["obstacles"] is None else f"{r['obstacles']:>2} obstacles"
            counts = f"{r['vehicles']} vehicles  {others}"
            print(f"{r['name']:<{width}}  {counts}  {r['description']}{own}")
    return 0


def _cmd_sim(args: argparse.Namespace) -> int:
    from .sim.config import load_scenario
    from .sim.episode import record_episode
    from .sim.world import World

    sc = load_scenario(args.scenario)
    with World(sc, seed=args.seed, fleet=args.fleet) as world:
        summary = record_episode(world, args.duration if args.duration is not None else sc.duration_s, Path(args.out))
    print(jsonout.dumps(summary))
    return 0


def _cmd_schemas_export(args: argparse.Namespace) -> int:
    from schemas import export

    out = Path(args.out) if args.out else export.DEFAULT_DIR
    if args.check:
        stale = export.stale(out)
        print(jsonout.dumps({"dir": str(out), "stale": stale}))
        return 1 if stale else 0
    written = export.export(out)
    print(jsonout.dumps({"dir": str(out), "written": [p.name for p in written]}))
    return 0


def _cmd_bench_localization(args: argparse.Namespace) -> int:
    from .bench import bench_localization

    if not args.duration > args.warmup:
        raise ConfigError(f"--duration must be longer than the {args.warmup:g} s warm-up, got {args.duration:g}")
    print(
        jsonout.dumps(
            bench_localization(
                args.scenario,
                args.seeds,
                args.duration,
                args.warmup,
                ideal=args.ideal,
                seed0=args.seed0,
                stanford_png=args.stanford,
                startup_accept=args.startup_accept,
                map_errors=args.map_errors,
                **({} if args.search_budget is None else {"search_budget": args.search_budget or None}),
            )
        )
    )
    return 0


def _cmd_bench_fusion(args: argparse.Namespace) -> int:
    from .fusion.bench import bench_fusion_sizes, parse_sizes

    if args.host == "joint":
        return _bench_joint(args)
    if args.ticks <= args.window:
        raise ConfigError(f"--ticks must exceed --window ({args.window}): timings skip the first window")
    try:
        sizes = parse_sizes(args.sizes) if args.sizes else [(args.vehicles, args.objects)]
    except ValueError as e:
        raise ConfigError(f"--sizes: {e}") from None
    result = bench_fusion_sizes(
        sizes,
        compare_exact=args.compare_exact,
        window=args.window,
        seed=args.seed,
        ticks=args.ticks,
        batch_samples=args.batch_samples,
        density=args.density,
        cpu_phases=args.cpu_phases,
    )
    print(jsonout.dumps(result["runs"][0] if not args.sizes else result))
    return 0


def _bench_joint(args: argparse.Namespace) -> int:
    """``mapc bench fusion --host joint``: the centralized host on recorded raw observations (jointbench)."""
    from .fusion.bench import parse_sizes
    from .fusion.jointbench import JOINT_WARMUP_S, bench_joint

    duration = args.ticks / 10.0
    if duration <= JOINT_WARMUP_S:
        raise ConfigError(f"--host joint: --ticks must exceed {JOINT_WARMUP_S * 10:g} (the localizers' start-up)")
    if args.compare_exact:
        raise ConfigError("--compare-exact is the distributed smoother's oracle: not with --host joint")
    try:
        sizes = parse_sizes(args.sizes) if args.sizes else [(args.vehicles, args.objects)]
    except ValueError as e:
        raise ConfigError(f"--sizes: {e}") from None
    runs = [bench_joint(v, seed=args.seed, duration_s=duration) for v, _ in sizes]
    print(jsonout.dumps(runs[0] if not args.sizes else {"sizes": [r["vehicles"] for r in runs], "runs": runs}))
    return 0


def _cmd_bench_world(args: argparse.Namespace) -> int:
    from .sim.bench import bench_world

    result = bench_world(
        args.vehicles, args.scenario, seed=args.seed, ticks=args.ticks, cull=not args.no_cull, density=args.density
    )
    print(jsonout.dumps(result))
    return 0


def _cmd_bench_security(args: argparse.Namespace) -> int:
    from .security_bench import bench_security

    print(jsonout.dumps(bench_security(iterations=args.iterations, objects=args.objects)))
    return 0


def _cmd_keys_init(args: argparse.Namespace) -> int:
    from .security import write_fleet_keys

    vehicles = args.vehicles if args.vehicles is not None else [f"cv{i}" for i in range(args.count)]
    doc = write_fleet_keys(
        Path(args.out), vehicles, args.validity_days * 86400.0, args.ca_name, force=args.force, services=args.services
    )
    print(jsonout.dumps(doc))
    return 0


def _add_executor_args(p: argparse.ArgumentParser, workers: int = 2) -> None:
    """``--executor``, ``--scheduler``, ``--workers`` and ``--fresh``: where an experiment's tasks run, and
    whether to start over in an output directory that holds finished tasks."""
    p.add_argument(
        "--executor",
        choices=("local", "dask"),
        default="local",
        help="local worker processes (default) or Dask's distributed scheduler (the cluster extra)",
    )
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="with --executor dask: a running Dask scheduler (tcp://host:8786); without it, a LocalCluster of "
        "--workers processes on this machine",
    )
    p.add_argument(
        "--workers",
        type=positive_int,
        default=workers,
        help=f"local worker processes, or the LocalCluster's (default {workers}; 1: in this process)",
    )
    p.add_argument(
        "--fresh",
        action="store_true",
        help="delete the finished tasks kept in OUT/tasks and start over (default: resume, running only what is "
        "missing)",
    )


def _run_experiment(args: argparse.Namespace, experiment) -> int:
    """``experiment(executor)`` on the executor of :func:`_add_executor_args`' options; the runner's refusals and
    failures as people read them (the finished tasks stay in OUT/tasks for the next run)."""
    from .experiments.executors import Executor
    from .experiments.runner import TasksFailed
    from .experiments.store import SettingsChanged

    try:
        executor = Executor(args.executor, args.workers, args.scheduler)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    try:
        return experiment(executor)
    except SettingsChanged as exc:
        raise ConfigError(str(exc)) from None
    except TasksFailed as exc:
        print(f"mapc: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(
            f"mapc: interrupted; the finished tasks are kept in {args.out / 'tasks'}: the same command resumes",
            file=sys.stderr,
        )
        return 130


def _cmd_experiment_paper(args: argparse.Namespace) -> int:
    from .experiments.paper import PaperSettings, run_paper_experiment
    from .sim.config import load_scenario

    for name in args.scenario or ():
        load_scenario(name)  # a preset that does not load: one line before any run
    try:
        settings = PaperSettings(
            scenarios=tuple(args.scenario or ()),
            runs=args.runs,
            seed=args.seed,
            duration_s=args.duration,
            burnin_s=args.burnin,
            rv_runs=args.rv_runs,
            sensitivity_runs=args.sensitivity_runs,
            start=args.start,
            downlink=args.downlink == "on",
            downlink_compare=args.downlink == "both",
        )
    except ValueError as exc:
        print(f"mapc: {exc}", file=sys.stderr)
        return 2
    res = _run_experiment(
        args, lambda ex: run_paper_experiment(args.out, settings, ex, progress=not args.quiet, fresh=args.fresh)
    )
    if isinstance(res, int):
        return res
    targets = {t["target"]: "PASS" if t["pass"] else "FAIL" for t in res["targets"]}
    summary = {"out": str(args.out), "wall_s": res["wall_s"], "resumed": res["resumed"], "runs": res["runs"]}
    print(jsonout.dumps({**summary, "targets": targets}))
    return 1 if args.check and "FAIL" in targets.values() else 0


def _cmd_experiment_network(args: argparse.Namespace) -> int:
    from .experiments.network import run_network_sweep

    if args.radio:
        from .experiments.network_radio import run_radio_sweeps

        if args.downlink:
            raise ConfigError("--downlink: the latency x loss x bandwidth grid only, not with --radio")

        try:
            seeds = tuple(int(s) for s in args.seeds.split(",")) if args.seeds else (args.seed,)
            extras = tuple(int(n) for n in args.extra_vehicles.split(",")) if args.extra_vehicles else None
        except ValueError:
            raise ConfigError(
                f"--seeds, --extra-vehicles: integers, got {args.seeds!r}, {args.extra_vehicles!r}"
            ) from None
        if args.duration is not None and args.duration <= args.warmup:
            raise ConfigError(f"--duration ({args.duration:g} s) must exceed --warmup ({args.warmup:g} s)")
        rows = _run_experiment(
            args,
            lambda ex: run_radio_sweeps(
                args.out,
                profiles=tuple(args.radio.split(",")),
                sweeps=tuple(args.sweep.split(",")),
                quick=args.quick,
                seeds=seeds,
                executor=ex,
                duration=args.duration,
                warmup_s=args.warmup,
                progress=not args.quiet,
                extra_vehicles=extras,
                cpm=not args.no_cpm,
                fresh=args.fresh,
            ),
        )
        if isinstance(rows, int):
            return rows
        print(jsonout.dumps({"out": str(args.out), "points": len(rows), "radio": args.radio, "seeds": list(seeds)}))
        return 0

    if args.duration is not None and args.duration <= 1.0:
        print(f"mapc: --duration must exceed the 1 s warm-up, got {args.duration}", file=sys.stderr)
        return 2
    rows = _run_experiment(
        args,
        lambda ex: run_network_sweep(
            args.out,
            quick=args.quick,
            seed=args.seed,
            executor=ex,
            duration=args.duration,
            scenario=args.scenario,
            progress=not args.quiet,
            fresh=args.fresh,
            downlink=args.downlink,
        ),
    )
    if isinstance(rows, int):
        return rows
    doc = {"out": str(args.out), "points": len(rows)}
    if args.quick:
        doc["smoke_test"] = "short cold-started points: they show the sweep runs, not what the network does"
    print(jsonout.dumps(doc))
    return 0


def _cmd_experiment_radio(args: argparse.Namespace) -> int:
    from .experiments.radio import link_cost, run_radio_validation

    if args.cost_vehicles:
        doc = link_cost(args.cost_vehicles, args.cost_duration, seed=args.seed)
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "link_cost.json").write_text(jsonout.dumps(doc) + "\n")
        print(jsonout.dumps(doc))
        return 0
    doc = run_radio_validation(args.out, messages=args.messages, seed=args.seed)
    worst = {f"{p['profile']} {p['state']}": p["max_abs_diff"] for p in doc["prr"]}
    pl = max(abs(r["diff_db"]) for r in doc["path_loss_vs_ns3"])
    ok = doc["all_within_tolerance"]
    print(
        jsonout.dumps(
            {"out": str(args.out), "all_within_tolerance": ok, "max_abs_diff": worst, "path_loss_max_diff_db": pl}
        )
    )
    return 0 if ok else 1


def _cmd_experiment_scale(args: argparse.Namespace) -> int:
    from .experiments.scale import analyse, run_scale_experiment, scenario_with_connected

    if args.duration <= args.warmup:
        raise ConfigError(f"--duration ({args.duration:g} s) must exceed --warmup ({args.warmup:g} s)")
    try:
        sizes = sorted({int(x) for x in args.sizes.split(",")})
    except ValueError:
        raise ConfigError(f"--sizes: comma-separated vehicle counts, got {args.sizes!r}") from None
    if not sizes or sizes[0] < 1:
        raise ConfigError(f"--sizes: vehicle counts of at least 1, got {args.sizes!r}")
    try:
        scenario_with_connected(args.scenario, max(sizes))  # a scenario that cannot scale fails before any run
    except ValueError as e:
        raise ConfigError(str(e)) from None
    rows = _run_experiment(
        args,
        lambda ex: run_scale_experiment(
            args.out,
            sizes=sizes,
            seed=args.seed,
            duration=args.duration,
            warmup_s=args.warmup,
            scenario=args.scenario,
            executor=ex,
            progress=not args.quiet,
            fresh=args.fresh,
        ),
    )
    if isinstance(rows, int):
        return rows
    print(jsonout.dumps({"out": str(args.out), "points": len(rows), "analysis": analyse(rows)}))
    return 0


def _cmd_experiment_faults(args: argparse.Namespace) -> int:
    from .experiments.faults import run_fault_experiment

    def run(ex):
        try:
            return run_fault_experiment(
                args.out,
                seeds=args.seeds,
                seed0=args.seed0,
                duration_s=args.duration,
                scenario=args.scenario,
                executor=ex,
                faults=args.faults,
                progress=not args.quiet,
                fresh=args.fresh,
            )
        except ValueError as exc:  # the store's SettingsChanged is one, and exits 2 as well
            raise ConfigError(str(exc)) from None

    res = _run_experiment(args, run)
    if isinstance(res, int):
        return res
    print(jsonout.dumps({"out": str(args.out), **res["meta"], "summary": res["summary"]}))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="mapc",
        description="Map Container: map-based cooperative perception over V2X",
        epilog="Presets (scenarios/, network/, sensors/, manifests/ of YAML files) are looked up in --config-dir "
        "(or $MAPC_CONFIG_DIR), then ~/.config/mapcontainer, then the ones shipped with the package.",
    )
    p.add_argument(
        "--config-dir",
        type=config_dir_arg,
        default=None,
        help="a directory of your own presets, searched before the built-in ones (sets MAPC_CONFIG_DIR)",
    )
    sub = p.add_subparsers(dest="command", required=True)

    sc = sub.add_parser("scenario", help="scenario presets").add_subparsers(dest="sub", required=True)
    ls = sc.add_parser("list", help="list the scenario presets (built-in and your own)")
    ls.add_argument("--json", action="store_true", help="print JSON")
    ls.set_defaults(func=_cmd_scenario_list)

    sim = sub.add_parser("sim", help="simulate an episode and write it to a directory")
    sim.add_argument("scenario", help="preset name (mapc scenario list) or a scenario YAML file")
    sim.add_argument("--seed", type=non_negative_int, default=0)
    sim.add_argument("--duration", type=seconds, default=None, help="seconds (default: the scenario's)")
    sim.add_argument("--out", required=True, type=output_dir, help="output directory")
    sim.add_argument("--fleet", type=fleet_name, default="sim", help="fleet name written into the messages")
    sim.set_defaults(func=_cmd_sim)

    bench = sub.add_parser("bench", help="benchmarks that print one JSON line").add_subparsers(
        dest="sub", required=True
    )
    bl = bench.add_parser("localization", help="map-matching accuracy, consistency and speed")
    bl.add_argument("--scenario", default="paper-urban")
    bl.add_argument("--seeds", type=positive_int, default=3, help="independent episodes")
    bl.add_argument(
        "--warmup",
        type=non_negative_seconds,
        default=2.0,
        help="seconds at the start not scored (default 2: the cold start)",
    )
    bl.add_argument(
        "--seed0",
        type=non_negative_int,
        default=0,
        help=f"first seed (default 0: development; the evaluation seeds start at {EVAL_SEED0})",
    )
    bl.add_argument("--duration", type=seconds, default=20.0, help="seconds per episode (the first 2 are not scored)")
    bl.add_argument(
        "--ideal", action="store_true", help="every simulator error source off (exact map, calibration, clocks)"
    )
    bl.add_argument("--stanford", default=None, help="draw the Stanford diagram (error against protection level) here")
    bl.add_argument(
        "--startup-accept",
        choices=("landmarks", "posterior"),
        default="landmarks",
        help="the start-up acceptance rule (LocalizerParams.search.accept): 'landmarks' (default: enough distinct "
        "landmarks and a margin) or 'posterior' (opt-in: posterior mass over basins; see docs/localization.md)",
    )
    bl.add_argument(
        "--search-budget",
        type=non_negative_int,
        default=None,
        help="the start-up search's matcher solves per frame (LocalizerParams.search.solves_per_frame; the starts "
        "left carry to the next frames); 0: no budget (default: the localizer's)",
    )
    bl.add_argument(
        "--map-errors",
        choices=("independent", "consider"),
        default="independent",
        help="how the tracker folds a match in (LocalizerParams.map_errors): 'independent' (default) or "
        "'consider' (opt-in: each landmark's map error shared by its views; see docs/localization.md)",
    )
    bl.set_defaults(func=_cmd_bench_localization)
    bf = bench.add_parser("fusion", help="host container speed and accuracy on a synthetic scene")
    bf.add_argument("--vehicles", type=positive_int, default=4)
    bf.add_argument("--objects", type=non_negative_int, default=14)
    bf.add_argument("--window", type=positive_int, default=10, help="frames in the sliding window")
    bf.add_argument("--ticks", type=positive_int, default=100, help="frames to run (timings skip the first window)")
    bf.add_argument("--seed", type=non_negative_int, default=0)
    bf.add_argument(
        "--density",
        choices=("dense", "city"),
        default="dense",
        help="dense: every vehicle sees about half of the obstacles; city: about 25 within range, the square "
        "growing with the fleet (constant density)",
    )
    bf.add_argument(
        "--sizes",
        metavar="V/O,...",
        help="several sizes in one process (e.g. 4/14,16/100,50/500; replaces --vehicles/--objects): one JSON "
        "line with every run and the cost's growth between them",
    )
    bf.add_argument(
        "--compare-exact",
        action="store_true",
        help="run each size again with the exact smoother (FusionParams(solver='exact'), the oracle) and print "
        "its RMSE and ANEES beside",
    )
    bf.add_argument(
        "--batch-samples",
        type=non_negative_int,
        default=5,
        help="windows also solved by plain GTSAM LM + Marginals after the run, as a yardstick of the "
        "machine's speed (batch_ms_p50, cycle_over_batch); 0 skips it",
    )
    bf.add_argument(
        "--cpu-phases",
        action="store_true",
        help="phases_ms_p50 in this process's CPU time instead of wall time (a loaded machine's waits left out)",
    )
    bf.add_argument(
        "--host",
        choices=("container", "joint"),
        default="container",
        help="joint: the centralized host instead, on raw observations of the sumo-town scene with --vehicles "
        "(or each size's vehicles) connected; the scene's city density sets the objects, --ticks / 10 s are run, "
        "timed after 3 s",
    )
    bf.set_defaults(func=_cmd_bench_fusion)
    bw = bench.add_parser(
        "world",
        help="the world's cost per tick (every vehicle's sensor frames, encoded) against the fleet size, "
        "with the growth exponent and a paired yardstick of the machine's speed",
    )
    bw.add_argument("--vehicles", type=fleet_sizes, default=[2, 4, 8, 16, 32], help="fleet sizes (default 2,4,8,16,32)")
    bw.add_argument("--scenario", default="paper-urban", help="scaled to each size as mapc fleet up --vehicles does")
    bw.add_argument("--ticks", type=positive_int, default=40, help="ticks timed per size (after 5 untimed)")
    bw.add_argument("--seed", type=non_negative_int, default=0)
    bw.add_argument("--no-cull", action="store_true", help="every sensor looks at every actor (what culling saves)")
    bw.add_argument(
        "--density",
        choices=("fixed", "constant"),
        default="fixed",
        help="fixed: the scenario's scene with the vehicles added (denser as the fleet grows, as mapc fleet up "
        "--vehicles); constant: the ring grows with the fleet, obstacles and landmarks copied along it",
    )
    bw.set_defaults(func=_cmd_bench_world)
    bs = bench.add_parser(
        "security",
        help="signed V2X messages: microseconds per sign and verify, bytes added to a typical VehiclePrior "
        "(ecdsa_*: the cryptography package alone, a yardstick of the machine's speed)",
    )
    bs.add_argument("--iterations", type=positive_int, default=1000, help="calls timed per figure (the median)")
    bs.add_argument("--objects", type=non_negative_int, default=8, help="object detections in the prior")
    bs.set_defaults(func=_cmd_bench_security)

    exp = sub.add_parser("experiment", help="experiments that write tables and plots").add_subparsers(
        dest="sub", required=True
    )
    ep = exp.add_parser(
        "paper",
        help="reproduce the paper's results (figure exp_sim, Tables res1/res2), steady state, realistic errors",
        description=(
            "Monte Carlo runs of the paper's scenarios with every realistic error source on and traffic drawn per "
            f"run, cold start, scored after a burn-in. The default seeds are the evaluation range (from {EVAL_SEED0}), "
            "which development never uses; a report on other seeds says it is a development run."
        ),
    )
    ep.add_argument("--runs", type=positive_int, default=200, help="Monte Carlo runs per simulated scenario")
    ep.add_argument("--out", required=True, type=output_dir, help="output directory")
    ep.add_argument(
        "--seed",
        type=non_negative_int,
        default=EVAL_SEED0,
        help=f"run i uses seed S + i (default {EVAL_SEED0}: the evaluation seeds; development uses seeds below)",
    )
    _add_executor_args(ep)
    ep.add_argument("--duration", type=seconds, default=10.0, help="simulated seconds per run, burn-in included")
    ep.add_argument(
        "--burnin", type=non_negative_seconds, default=3.0, help="seconds at the start of every run not scored"
    )
    ep.add_argument(
        "--rv-runs",
        type=positive_int,
        default=None,
        help="runs per test-site scenario and density (default min(runs, 20))",
    )
    ep.add_argument(
        "--sensitivity-runs",
        type=non_negative_int,
        default=None,
        help="runs per scenario and error setting in the sensitivity table (default min(runs, 5); 0: no table)",
    )
    ep.add_argument(
        "--start",
        choices=("cold", "warm"),
        default="cold",
        help="vehicles start from GNSS alone (cold, default) or localized (warm: truth + stated noise, a variant)",
    )
    ep.add_argument(
        "--downlink",
        nargs="?",
        choices=("off", "on", "both"),
        const="on",
        default="off",
        help="the host sends every vehicle what the others know about its pose (vehicle estimates are then the "
        "vehicles' own with it fused): off (default), on (--downlink alone), or both: every run with it off and on "
        "(the same seeds), the report's sections without it and a section comparing the two",
    )
    ep.add_argument(
        "--scenario",
        action="append",
        default=None,
        help="a preset for the simulation part in place of paper-urban and paper-suburban (repeatable); the test-site "
        "scenarios and the paper's claims are then left out, and targets are the ones that do not name the paper's",
    )
    ep.add_argument("--quiet", action="store_true", help="no progress bar")
    ep.add_argument("--check", action="store_true", help="exit 1 if a target fails (default: exit 0, see targets)")
    ep.set_defaults(func=_cmd_experiment_paper)

    en = exp.add_parser(
        "network", help="latency x loss x bandwidth sweep in both modes (in process; --live: on the fleet)"
    )
    en.add_argument("--out", required=True, type=output_dir, help="output directory")
    en.add_argument(
        "--quick",
        action="store_true",
        help="a smoke test: a 2 x 2 x 2 grid of 2.5 s cold-started points (1.5 s scored), too short for figures",
    )
    en.add_argument("--seed", type=non_negative_int, default=0)
    _add_executor_args(en)
    en.add_argument("--duration", type=seconds, default=None, help="seconds per point (default 4, quick 2.5)")
    en.add_argument("--scenario", default="paper-urban")
    en.add_argument(
        "--radio",
        default=None,
        help="geometric radio profiles (comma-separated, e.g. its-g5,cv2x-mode4): run the distance and density "
        "sweeps (docs/radio.md) instead of the latency x loss x bandwidth grid",
    )
    en.add_argument("--sweep", default="distance,density", help="with --radio: distance, density or both")
    en.add_argument("--seeds", default=None, help="with --radio: comma-separated seeds, every point once per seed")
    en.add_argument(
        "--extra-vehicles", default=None, help="with --radio: the density sweep's added vehicles (e.g. 0,40,120)"
    )
    en.add_argument(
        "--warmup", type=seconds, default=1.0, help="with --radio: seconds of each run left unscored (default 1)"
    )
    en.add_argument("--no-cpm", action="store_true", help="with --radio: skip the density points with the CPM rules")
    en.add_argument(
        "--downlink",
        action="store_true",
        help="every distributed point twice, without and with the host's downlink over the same link: the report's "
        "section on the downlink's gain (on-board RMSE without minus with) per latency, loss and capacity",
    )
    en.add_argument("--quiet", action="store_true", help="no progress bar")
    en.set_defaults(func=_cmd_experiment_network)

    er = exp.add_parser(
        "radio",
        help="validate the geometric radio model: PRR vs distance (LOS, NLOS) per PHY profile against the published "
        "models, path loss against ns-3's TR 37.885 vectors, CBR vs density (docs/radio.md)",
    )
    er.add_argument("--out", required=True, type=output_dir, help="output directory")
    er.add_argument("--messages", type=positive_int, default=1000, help="messages per distance point")
    er.add_argument("--seed", type=non_negative_int, default=0)
    er.add_argument(
        "--cost-vehicles",
        type=positive_int,
        default=None,
        help="instead: the link model's CPU cost, one in-process run with this many connected vehicles per profile "
        "(dsrc, its-g5, cv2x-mode4), the ratio to dsrc (OUT/link_cost.json)",
    )
    er.add_argument("--cost-duration", type=seconds, default=3.0, help="with --cost-vehicles: scenario seconds")
    er.set_defaults(func=_cmd_experiment_radio)

    es = exp.add_parser(
        "scale",
        help="N connected vehicles on one SUMO scene, distributed vs centralized over a shared 6 Mbit/s medium: "
        "bytes, delivery, age, host CPU, accuracy",
    )
    es.add_argument("--out", required=True, type=output_dir, help="output directory")
    es.add_argument("--sizes", default="2,4,8,16,32,50,100", help="connected-vehicle counts (comma-separated)")
    es.add_argument("--scenario", default="sumo-town", help="a SUMO scenario (its first N vehicles connected)")
    es.add_argument("--seed", type=non_negative_int, default=0)
    es.add_argument("--duration", type=seconds, default=10.0, help="seconds per run (cold start)")
    es.add_argument("--warmup", type=seconds, default=3.0, help="seconds before scoring")
    _add_executor_args(es)
    es.add_argument("--quiet", action="store_true", help="no progress bar")
    es.set_defaults(func=_cmd_experiment_scale)

    ef = exp.add_parser(
        "faults", help="each misbehaving-vehicle fault against a clean run: time to flag, false flags, others' RMSE"
    )
    ef.add_argument("--out", required=True, type=output_dir, help="output directory")
    ef.add_argument("--seeds", type=positive_int, default=3, help="seeds per fault")
    ef.add_argument(
        "--seed0",
        type=non_negative_int,
        default=EVAL_SEED0,
        help=f"first seed (evaluation seeds from {EVAL_SEED0}; development uses seeds below)",
    )
    ef.add_argument("--duration", type=seconds, default=15.0, help="seconds per run (the fault starts at 5 s)")
    ef.add_argument("--scenario", default="paper-urban")
    ef.add_argument("--faults", type=lambda t: [x for x in t.split(",") if x], default=None, help="a,b,...")
    _add_executor_args(ef)
    ef.add_argument("--quiet", action="store_true", help="no progress bar")
    ef.set_defaults(func=_cmd_experiment_faults)

    add_map_commands(sub)

    sch = sub.add_parser("schemas", help="the wire contract").add_subparsers(dest="sub", required=True)
    ex = sch.add_parser("export", help="write JSON Schema files (default: schemas/json/)")
    ex.add_argument("--out", default=None)
    ex.add_argument("--check", action="store_true", help="only report stale files; exit 1 if any")
    ex.set_defaults(func=_cmd_schemas_export)

    keys = sub.add_parser("keys", help="credentials for signed V2X messages").add_subparsers(dest="sub", required=True)
    ki = keys.add_parser(
        "init",
        help="write a test CA (ca.key.pem, ca.cert.json) and each vehicle's key and certificate "
        "(ID.key.pem, ID.cert.json) into a directory; certificates start an hour before now (clock skew)",
    )
    ki.add_argument("--out", required=True, type=output_dir, help="output directory")
    who = ki.add_mutually_exclusive_group()
    who.add_argument("--vehicles", type=vehicle_ids, default=None, help="comma-separated vehicle ids (cv0,cv1,...)")
    who.add_argument("--count", type=positive_int, default=4, help="vehicles cv0..cv{N-1} (default 4)")
    ki.add_argument(
        "--services",
        type=service_ids,
        default=list(SERVICE_SIGNERS),
        help="comma-separated service ids that sign (their health status; the world its truth, a host its fused "
        f"state, the evaluator its metrics); default {','.join(SERVICE_SIGNERS)}",
    )
    ki.add_argument("--validity-days", type=positive_days, default=30.0, help="days the certificates are valid")
    ki.add_argument("--ca-name", type=fleet_name, default="mapc-ca", help="the CA certificate's subject")
    ki.add_argument("--force", action="store_true", help="replace credentials already in --out")
    ki.set_defaults(func=_cmd_keys_init)
    return p


def run(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> int:
    """Parse ``argv`` with ``parser`` and run the chosen command; configuration errors exit 2."""
    args = parser.parse_args(argv)
    if getattr(args, "config_dir", None) is not None:
        os.environ["MAPC_CONFIG_DIR"] = str(args.config_dir)  # for this process and every one it starts
    try:
        return int(args.func(args) or 0)
    except ConfigError as exc:
        print(f"mapc: {getattr(exc, 'label', 'configuration error')}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `mapc ... | head`: the reader left; no traceback (recipe of the signal docs)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


def main(argv: list[str] | None = None) -> int:
    """The core commands only (``python -m mapcontainer.cli``); ``mapc`` adds the fleet ones."""
    return run(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
