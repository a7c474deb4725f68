"""The ``mapc`` entry point: the core commands of :mod:`mapcontainer.cli` plus the live-fleet ones.

The core package never imports zenoh or ``services``; the commands that need a live Zenoh fleet
(``fleet``, ``health``, live experiments) are registered here:

``mapc fleet up [--scenario S] [--vehicles N] [--network P] [--duration S] [--fleet NAME]
[--mode distributed|centralized] [--detach] [--dry-run]``, ``mapc fleet status [--json]``,
``mapc fleet down [--fleet NAME]``, ``mapc health [--fleet NAME] [--connect EP] [--zenoh-config FILE]
[--json] [--watch]``, and
``mapc experiment network --live --out DIR [--profiles ideal,dsrc,...] [--mode distributed|centralized|both]
[--duration S]`` (the network profiles on the live fleet, beside the in-process figures).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from mapcontainer.cli import build_parser, positive_int, run, seconds

__all__ = ["add_live_commands", "main"]

PROFILES = "ideal,dsrc,lossy,degraded"  # experiment network --live: the default profiles


# ------------------------------------------------------------------------------ fleet


def _cmd_fleet_up(args: argparse.Namespace) -> int:
    from .launcher.app import plan, settings_from_args
    from .launcher.app import run as run_fleet
    from .launcher.control import detach

    s = settings_from_args(args)
    specs = plan(s, "runs/<fleet>-<timestamp>", s.join or "tcp/127.0.0.1:<free port chosen at start>")
    if args.dry_run:
        doc = {
            "params": s.params.model_dump(),
            "rendezvous": s.listen,
            "processes": [p.to_json() for p in specs],
        }
        if args.json:
            print(json.dumps(doc, indent=2))
        else:
            print(f"fleet {s.params.fleet}: {json.dumps(s.params.model_dump())}")
            for p in specs:
                print(f"  [{p.start_order}] {p.name:<14} {' '.join(p.argv[1:])}")
        return 0
    if args.detach:
        rc, info = detach(s)
        if args.json:
            print(json.dumps(info))
        elif rc == 0:
            print(
                f"fleet {s.params.fleet} is up: rendezvous {', '.join(info.get('endpoints', []))}; "
                f"run dir {info['run_dir']}; launcher pid {info['launcher_pid']}"
            )
        if rc != 0:
            print(f"mapc: {info['error']}", file=sys.stderr)
        return rc
    return run_fleet(s)


def _cmd_fleet_status(args: argparse.Namespace) -> int:
    from .launcher.control import active_fleets

    fleets = [f for f in active_fleets() if args.fleet is None or f["fleet"] == args.fleet]
    if args.json:
        print(json.dumps(fleets, indent=2))
        return 0 if any(f["launcher_alive"] for f in fleets) else 1
    if not fleets:
        print("no fleet is running" if args.fleet is None else f"fleet {args.fleet} is not running")
        return 1
    for f in fleets:
        name = f"{f['fleet']}" + (f" ({f['manifest']})" if f.get("manifest") not in (None, "local") else "")
        if f["launcher_alive"]:
            print(f"fleet {name}: {f['status']}; launcher pid {f['launcher_pid']}")
        else:
            print(
                f"fleet {name}: launcher {f['launcher_pid']} is gone (its last status: {f['status']}); "
                f"`mapc fleet down --fleet {f['fleet']}` stops what is left and clears the entry"
            )
        print(f"  connect: {', '.join(f['endpoints'])}   (e.g. mapc health --fleet {f['fleet']})")
        if f["cwd"]:
            print(f"  started in: {f['cwd']}")
        print(f"  run dir: {f['run_dir']}")
        for p in f["processes"]:
            up = "-" if p.get("uptime_s") is None else f"{p['uptime_s']:.0f}s"
            print(
                f"  {p['name']:<14} {p['state']:<9} pid {p.get('pid') or '-':<8} alive {str(p['alive']):<5} "
                f"restarts {p['restarts']:<3} up {up}"
            )
    return 0 if any(f["launcher_alive"] for f in fleets) else 1


def _cmd_fleet_down(args: argparse.Namespace) -> int:
    from .launcher.control import down, to_stop
    from .launcher.report import format_report

    fleets, refused = to_stop(args.fleet, every=args.all)
    if refused:
        print(f"mapc: {refused}", file=sys.stderr)
    rc, results = (2, []) if refused else down(fleets, timeout_s=args.timeout)
    for r in results:  # the run's closing table, as `mapc fleet up` prints it in the foreground
        report = Path(r["run_dir"]) / "report.json"
        r["summary"] = json.loads(report.read_text()).get("summary") if report.is_file() else None
    if args.json:
        print(json.dumps(results))
    elif not results and not refused:
        print("no fleet is running")
    for r in results if not args.json else []:
        if r["summary"]:
            print(format_report(r["summary"]))
        left = f"; STILL RUNNING: {', '.join(r['left'])}" if r["left"] else "; no process left"
        swept = f"; killed leftovers: {', '.join(r['swept'])}" if r["swept"] else ""
        print(f"fleet {r['fleet']} down ({r['run_dir']}){swept}{left}")
    return rc


# ------------------------------------------------------------------------------ health


def _health_zenoh_file(path: str):
    """``mapc health --zenoh-config FILE``: the file as a Zenoh configuration, and its client endpoints.

    A missing or malformed file is a ConfigError in one line (Zenoh's JSON5 parser reports on several)."""
    import re

    from mapcontainer.config import ConfigError

    from .runtime import ZenohSettings, zenoh_config

    try:
        conf = zenoh_config(ZenohSettings(config_file=path))
    except ConfigError as exc:
        text = str(exc)
        where, what = re.search(r"-->\s*(\d+:\d+)", text), re.search(r"^\s*=\s*(.+)$", text, re.M)
        if where and what:  # the parser's "--> line:col ... = expected ..." layout
            text = f"the Zenoh configuration file {path}: line {where.group(1)}: {what.group(1)}"
        raise ConfigError(" ".join(text.split())) from None
    try:
        endpoints = json.loads(conf.get_json("connect/endpoints"))
    except Exception:  # no connect section
        endpoints = []
    if isinstance(endpoints, dict):  # endpoints per mode
        endpoints = endpoints.get("client") or []
    return [str(e) for e in endpoints]


def _health_verifier(keys: str):
    """A verifier of the fleet's CA in ``keys``, for the statuses ``mapc health`` reads."""
    from mapcontainer.security import CA_NAME, VERIFY_WINDOW_S, Verifier, load_certificate

    return Verifier(load_certificate(keys, CA_NAME), window_s=VERIFY_WINDOW_S)


def _cmd_health(args: argparse.Namespace) -> int:
    from .health import exit_code, fleet_health, format_table
    from .launcher.control import active_fleets
    from .runtime import ZenohSettings, zenoh_config, zenoh_error_text

    fleet, connect, expected = args.fleet, list(args.connect or []), []
    if not connect and os.environ.get("MAPC_ZENOH_CONNECT"):
        connect = os.environ["MAPC_ZENOH_CONNECT"].split(",")
    if args.zenoh_config:  # its endpoints come after --connect and $MAPC_ZENOH_CONNECT, before the registry's
        file_connect = _health_zenoh_file(args.zenoh_config)  # ConfigError: exit 2, one line
        connect = connect or file_connect
    running = [f for f in active_fleets() if f["launcher_alive"]]
    names = sorted({f["fleet"] for f in running})
    if fleet is None and len(names) == 1:
        fleet = names[0]
    own = [f for f in running if f["fleet"] == fleet]  # a fleet split over manifests has several launchers
    if own:
        expected = [(p["role"], p["id"]) for f in own for p in f["processes"]]
        if not connect:
            connect = [e for e in own[0]["endpoints"] if "127.0.0.1" in e] or own[0]["endpoints"]
    if not connect:
        if args.json:
            print("[]")  # a JSON consumer gets an empty list, not empty input
        if fleet is None:
            why = "no fleet is running" if not names else f"several fleets run ({', '.join(names)}): give --fleet"
        else:
            why = f"no running fleet {fleet!r} (`mapc fleet status` lists them)"
        print(f"mapc: {why}; or give --connect ENDPOINT", file=sys.stderr)
        return 2
    fleet = fleet or "local"  # --connect without --fleet
    keys = args.keys or (own[0].get("keys_dir") if own else None)
    verifier = _health_verifier(keys) if keys else None  # ConfigError (no CA there): exit 2, one line
    login = args.zenoh_config or (own[0].get("zenoh_login") if own else None)  # the run's operator login
    if own and own[0].get("insecure") and not args.json:
        print(f"fleet {fleet}: open Zenoh mesh (--insecure): anyone on this machine can publish and subscribe")
    # --connect is laid over --zenoh-config (its login, TLS, timeouts) as for the services
    settings = ZenohSettings(mode=None if login else "client", connect=connect, connect_timeout_ms=2000,
                             config_file=login)  # fmt: skip
    conf = zenoh_config(settings)  # a configuration Zenoh refuses: ConfigError, exit 2
    try:
        import zenoh

        session = zenoh.open(conf)
    except Exception as e:  # zenoh raises ZError when nothing listens at the endpoint or the login fails
        if args.json:
            print("[]")
        hint = "" if args.zenoh_config else " (a router that asks for a login or TLS needs --zenoh-config FILE)"
        print(f"mapc: cannot reach {', '.join(connect)}: {zenoh_error_text(e)}{hint}", file=sys.stderr)
        return 2
    try:
        while True:
            views = fleet_health(session, fleet, expected, timeout_s=args.timeout, verifier=verifier)
            rc = exit_code(views)
            if args.json:
                print(json.dumps([v.to_json() for v in views]), flush=True)
            else:
                if args.watch and sys.stdout.isatty():
                    print("\x1b[2J\x1b[H", end="")
                print(format_table(views, fleet) if views else f"fleet {fleet}: nothing answers", flush=True)
            if not args.watch:
                return rc
            time.sleep(1.0)  # --watch: refresh once a second until Ctrl-C
    except KeyboardInterrupt:
        return rc if "rc" in locals() else 130
    finally:
        session.close()


# ------------------------------------------------------------------------------ live experiment


def _cmd_experiment_network_live(args: argparse.Namespace) -> int:
    from .launcher.live_experiment import MODES, run_live_network

    profiles = [p.strip() for p in (args.profiles or PROFILES).split(",") if p.strip()]
    modes = list(MODES) if args.mode in (None, "both") else [args.mode]
    duration = 20.0 if args.duration is None else args.duration
    try:
        res = run_live_network(
            args.out,
            profiles=profiles,
            modes=modes,
            duration=duration,
            seed=args.seed,
            scenario=args.scenario,
            vehicles=args.vehicles,
            inprocess=not args.no_inprocess,
            progress=not args.quiet,
        )
    except ValueError as exc:
        print(f"mapc: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:
        print(f"mapc: {exc}", file=sys.stderr)
        return 1
    n_live, n_inproc = len(res["live"]), len(res["inprocess"])
    print(json.dumps({"out": str(args.out), "live_points": n_live, "inprocess_points": n_inproc}))
    return 0


def _add_live_network_args(parser: argparse.ArgumentParser) -> None:
    """Add ``--live`` and its options to the core ``experiment network`` subcommand."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    exp = next(a for a in sub.choices["experiment"]._actions if isinstance(a, argparse._SubParsersAction))
    en = exp.choices["network"]
    core = en.get_default("func")
    g = en.add_argument_group("live fleet (--live)")
    g.add_argument(
        "--live", action="store_true", help="run network profiles on the live multi-process fleet (mapc fleet up)"
    )
    # defaults None: a live-only option given without --live is refused even when it names the default
    g.add_argument("--profiles", default=None, help=f"comma-separated presets from configs/network/ ({PROFILES})")
    g.add_argument("--mode", choices=["distributed", "centralized", "both"], default=None, help="default both")
    g.add_argument("--vehicles", type=positive_int, default=None, help="connected vehicles (default: the scenario's)")
    g.add_argument("--no-inprocess", action="store_true", default=None, help="skip the in-process side-by-side")

    live_only = {"profiles": "--profiles", "mode": "--mode", "vehicles": "--vehicles", "no_inprocess": "--no-inprocess"}

    def dispatch(args: argparse.Namespace) -> int:
        given = [flag for dest, flag in live_only.items() if getattr(args, dest) is not None]
        if args.live and args.quick:
            en.error("--quick is a grid of the in-process sweep; with --live, choose --profiles and --duration")
        if args.live and (args.executor != "local" or args.scheduler):
            en.error("--executor/--scheduler: the in-process sweep's; the live fleet runs its own processes")
        if not args.live and given:
            en.error(f"{', '.join(given)}: for the live fleet only (add --live)")
        return _cmd_experiment_network_live(args) if args.live else core(args)

    en.set_defaults(func=dispatch)


# ------------------------------------------------------------------------------ parser


def add_live_commands(parser: argparse.ArgumentParser) -> None:
    """Register ``fleet`` and ``health`` on the core parser's subcommands."""
    from .launcher.app import add_fleet_args

    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))

    fleet = sub.add_parser("fleet", help="run the multi-process fleet on Zenoh").add_subparsers(
        dest="sub", required=True
    )
    up = fleet.add_parser("up", help="start every service as its own process (--manifest, default fleet)")
    add_fleet_args(up)
    up.add_argument("--detach", action="store_true", help="run in the background; stop with `mapc fleet down`")
    up.add_argument("--dry-run", action="store_true", help="print the processes and their command lines only")
    up.add_argument(
        "--json", action="store_true", help="JSON output: the plan (--dry-run), the fleet (--detach), the final summary"
    )
    up.set_defaults(func=_cmd_fleet_up)

    st = fleet.add_parser(
        "status",
        help="running fleets: where each was started, its processes and the Zenoh endpoints to connect to "
        "(exit 0 when one runs, 1 when none)",
    )
    st.add_argument("--json", action="store_true")
    st.add_argument("--fleet", default=None, help="this fleet only")
    st.set_defaults(func=_cmd_fleet_status)

    dn = fleet.add_parser(
        "down",
        help="stop a fleet leaving no process behind: the one running (several: pick with --fleet or --all); "
        "exit 0 stopped or none running, 1 a process is left, 2 several fleets or an unknown name (nothing stopped)",
    )
    which = dn.add_mutually_exclusive_group()
    which.add_argument(
        "--fleet", default=None, help="the fleet to stop, all its manifest parts (default: the one running fleet)"
    )
    which.add_argument("--all", action="store_true", help="every fleet in your registry, other checkouts' too")
    dn.add_argument("--timeout", type=seconds, default=90.0, help="seconds to wait for the launcher")
    dn.add_argument("--json", action="store_true")
    dn.set_defaults(func=_cmd_fleet_down)

    h = sub.add_parser(
        "health",
        help="every service's health (exit 0: ok, starting or finished; 1 degraded/missing; 2 nothing answers)",
    )
    h.add_argument("--fleet", default=None, help="fleet name (default: the one running fleet)")
    h.add_argument("--connect", action="append", default=None, help="a Zenoh endpoint of the fleet")
    h.add_argument(
        "--zenoh-config",
        default=None,
        metavar="FILE",
        help="a Zenoh JSON5 client configuration (user/password or TLS, e.g. from deploy/zenoh/secure/) "
        "for a secured router; --connect is laid over its endpoints",
    )
    h.add_argument(
        "--keys",
        default=None,
        metavar="DIR",
        help="the fleet's keys directory: believe only statuses signed by their service (default: the running "
        "fleet's own keys, when it signs)",
    )
    h.add_argument("--json", action="store_true", help="a JSON list of services")
    h.add_argument("--watch", action="store_true", help="refresh every second until Ctrl-C")
    h.add_argument("--timeout", type=seconds, default=1.0, help="seconds to wait for answers")
    h.set_defaults(func=_cmd_health)

    _add_live_network_args(parser)
    from .recording_cli import add_recording_commands

    add_recording_commands(sub)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    add_live_commands(parser)
    return run(parser, argv)


if __name__ == "__main__":
    sys.exit(main())
