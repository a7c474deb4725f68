"""``mapc record``, ``mapc record info`` and ``mapc replay``: the recording commands (thin adapters).

The file format, reading and re-fusion are :mod:`mapcontainer.recording`; this module finds the fleet,
opens Zenoh and prints.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from mapcontainer.cliargs import bounded

positive_float = bounded(float, 0, strict=True)

__all__ = ["add_recording_commands"]


def _fail(msg: str) -> int:
    print(f"mapc: {msg}", file=sys.stderr)
    return 2


def _fleet_endpoints(fleet: str | None, connect: list[str] | None) -> tuple[str, list[str], dict | None] | str:
    """(fleet, endpoints, its registry entry) of a running fleet, or why none is found."""
    from .launcher.control import active_fleets

    running = [f for f in active_fleets() if f["launcher_alive"]]
    names = sorted({f["fleet"] for f in running})
    if fleet is None and len(names) == 1:
        fleet = names[0]
    own = [f for f in running if f["fleet"] == fleet]
    connect = list(connect or [])
    if not connect and own:
        connect = [e for e in own[0]["endpoints"] if "127.0.0.1" in e] or own[0]["endpoints"]
    if not connect:
        if fleet is None:
            return "no fleet is running" if not names else f"several fleets run ({', '.join(names)}): give --fleet"
        return f"no running fleet {fleet!r} (`mapc fleet status` lists them); or give --connect ENDPOINT"
    return fleet or "local", connect, own[0] if own else None


def _login_settings(connect: list[str], entry: dict | None):
    """A client's ZenohSettings for a fleet: with the run's operator login when its mesh asks for one."""
    from .runtime import ZenohSettings

    login = entry.get("zenoh_login") if entry else None
    return ZenohSettings(mode=None if login else "client", connect=connect, connect_timeout_ms=2000, config_file=login)


# ------------------------------------------------------------------------------ record


def _cmd_record(args: argparse.Namespace) -> int:
    if args.sub == "info":
        return _cmd_record_info(args)
    if args.sub == "export":
        return _cmd_record_export(args)
    if not args.out:
        return _fail("record: give --out FILE (or `mapc record info FILE`)")
    found = _fleet_endpoints(args.fleet, args.connect)
    if isinstance(found, str):
        return _fail(found)
    fleet, connect, entry = found
    from .recorder.app import RecorderSettings, main

    run_dir = Path(entry["run_dir"]) if entry and entry.get("run_dir") else None
    scenario, seed = None, 0
    if run_dir is not None and (run_dir / "config.json").exists():
        params = json.loads((run_dir / "config.json").read_text()).get("params", {})
        scenario, seed = params.get("scenario"), int(params.get("seed") or 0)
    keys = None
    if run_dir is not None and (run_dir / "keys").is_dir():
        keys = str(run_dir / "keys")
    s = RecorderSettings(
        fleet=fleet,
        id=f"record-{os.getpid()}",
        zenoh=_login_settings(connect, entry),
        out=args.out,
        max_mb=args.max_mb,
        scenario=scenario,
        seed=seed,
        keys=keys,
        config=str(run_dir / "config.json") if run_dir is not None else None,
        log_level="WARNING",
    )
    print(f"recording fleet {fleet} ({', '.join(connect)}) to {args.out}; Ctrl-C stops", file=sys.stderr)
    rc = main(s)
    if Path(args.out).exists():
        _print_info(_info(Path(args.out)), as_json=False)
    return rc


def _info(path: Path) -> dict:
    from mapcontainer.recording import info, recording_files

    out = info(path)
    out["continued_in"] = [str(p) for p in recording_files(path)[1:]]
    return out


def _cmd_record_info(args: argparse.Namespace) -> int:
    from mapcontainer.recording import RecordingError

    path = Path(args.file)
    if not path.is_file():
        return _fail(f"{path}: no such file")
    try:
        doc = _info(path)
    except RecordingError as exc:
        return _fail(str(exc))
    _print_info(doc, args.json)
    return 0


def _cmd_record_export(args: argparse.Namespace) -> int:
    from mapcontainer.recording import RecordingError
    from mapcontainer.recording.ros2 import export_ros2

    path = Path(args.file)
    if not path.is_file():
        return _fail(f"{path}: no such file")
    try:
        doc = export_ros2(path, Path(args.out))
    except RecordingError as exc:
        return _fail(str(exc))
    if args.json:
        print(json.dumps(doc))
        return 0
    print(f"{doc['bag']}: a ROS 2 bag (MCAP storage), {doc['messages']} messages, fused states of host {doc['host']}")
    for t in doc["topics"]:
        print(f"  {t['topic']:<40} {t['type']:<48} {t['messages']:>6}")
    for what, n in doc["skipped"].items():
        print(f"  not exported: {n} on {what}")
    return 0


def _print_info(doc: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(doc))
        return
    if doc["complete"]:
        state = "complete"
    elif doc.get("trailing_bytes"):
        state = f"FINISHED, THEN APPENDED TO: {doc['stopped']}"
    else:
        state = f"INCOMPLETE (read up to the last whole chunk: {doc['stopped']})"
    rate = f", {doc['mb_per_min']:.2f} MB/min" if doc["mb_per_min"] else ""
    kinds = doc["channels_by_kind"]
    print(
        f"{doc['file']}: {state}; {doc['duration_s']:.1f} s, file {doc['file_bytes'] / 1e6:.2f} MB{rate}\n"
        f"  {doc['keys']} fleet keys: {doc['messages']} messages, {doc['payload_bytes'] / 1e6:.2f} MB of payload\n"
        f"  {len(doc['channels'])} channels: {kinds['key']} keys, {kinds['attachment']} of their Zenoh attachments "
        f"(<key>#attachment), {kinds['viz']} for visualization (/viz/...)"
    )
    print(f"  {'channel':<52} {'kind':<10} {'messages':>8} {'bytes':>11}  schema")
    for c in doc["channels"]:
        print(
            f"  {c['topic']:<52} {c['kind']:<10} {c['messages']:>8} {c['bytes']:>11}  "
            f"{c['schema'] or '-'} ({c['message_encoding']})"
        )
    for a in doc["attachments"]:
        print(f"  attachment {a['name']} ({a['bytes']} bytes)")
    for p in doc.get("continued_in") or []:
        print(f"  continued in {p} (a restarted recorder)")


# ------------------------------------------------------------------------------ replay


def publish_plan(session, items, rec_start_ns: int, speed: float = 1.0, stop=None) -> list[float]:
    """Publish replay items on ``session`` at their times (``at_s`` after the call), each attachment moved
    from the recorded clock (``rec_start_ns``) to this replay's; the lateness of each put in seconds (put
    time minus its scheduled time)."""
    import threading
    import time

    import zenoh

    from mapcontainer.recording.replay import shift_attachment, shift_clock

    stop = stop or threading.Event()
    pubs = {}
    for it in items:
        if it.key not in pubs:
            pubs[it.key] = session.declare_publisher(it.key, congestion_control=zenoh.CongestionControl.BLOCK)
    late: list[float] = []
    t0, start_ns = time.monotonic(), time.time_ns()
    try:
        for it in items:
            delay = t0 + it.at_s - time.monotonic()
            if delay > 0 and stop.wait(delay):
                break
            payload = shift_clock(it.payload, rec_start_ns, start_ns, speed)  # services read the message's clock
            pubs[it.key].put(payload, attachment=shift_attachment(it.attachment, rec_start_ns, start_ns, speed))
            late.append(time.monotonic() - t0 - it.at_s)
    finally:
        for p in pubs.values():
            p.undeclare()
    return late


def _wait_receivers(session, fleet: str, timeout_s: float) -> list[str]:
    """The host and evaluator of ``fleet`` seen alive within ``timeout_s`` (their liveliness tokens)."""
    import time

    seen: list[str] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        replies = session.liveliness().get(f"mc/{fleet}/alive/*/*", timeout=1.0)
        seen = sorted({str(r.ok.key_expr).split("/")[-2] for r in replies if r.ok is not None})
        if "host" in seen and "evaluator" in seen:
            break
        time.sleep(0.2)
    return seen


def _cmd_replay(args: argparse.Namespace) -> int:
    from mapcontainer.recording import RecordingError

    path = Path(args.file)
    if not path.is_file():
        return _fail(f"{path}: no such file")
    try:
        if args.refuse:
            return _refuse(args, path)
        return _live_replay(args, path)
    except RecordingError as exc:
        return _fail(str(exc))


def _live_replay(args: argparse.Namespace, path: Path) -> int:

    from mapcontainer.recording.replay import DEFAULT_TOPICS, replay_plan

    from .runtime import zenoh_config, zenoh_error_text

    if args.fleet is None and not args.connect:
        return _fail("replay: give --fleet NAME (a running fleet, e.g. `mapc fleet up --manifest replay`) or --refuse")
    found = _fleet_endpoints(args.fleet, args.connect)
    if isinstance(found, str):
        return _fail(found)
    fleet, connect, entry = found
    topics = [t.strip() for t in args.topics.split(",") if t.strip()] if args.topics else list(DEFAULT_TOPICS)
    from schemas.topics import TOPICS

    unknown = sorted(set(topics) - {t.name for t in TOPICS if t.model is not None})
    if unknown:
        return _fail(f"replay: unknown topics {', '.join(unknown)}; known: {', '.join(t.name for t in TOPICS)}")
    items, figures = replay_plan(path, fleet, args.speed, topics)
    import zenoh

    try:
        session = zenoh.open(zenoh_config(_login_settings(connect, entry)))
    except Exception as e:  # ZError: nothing listens there
        return _fail(f"cannot reach {', '.join(connect)}: {zenoh_error_text(e)}")
    try:
        seen = _wait_receivers(session, fleet, 5.0)
        print(
            f"replaying {figures['messages']} messages ({figures['duration_s']:.1f} s recorded, speed {args.speed:g}) "
            f"onto fleet {fleet} (alive there: {', '.join(seen) or 'nobody'})",
            file=sys.stderr,
        )
        late = publish_plan(session, items, figures["rec_start_ns"], args.speed)
    except KeyboardInterrupt:
        return 130
    finally:
        session.close()
    import numpy as np

    ms = np.array(late) * 1e3
    doc = {
        "fleet": fleet,
        **figures,
        "published": len(late),
        "lateness_ms_p50": float(np.percentile(ms, 50)) if len(ms) else None,
        "lateness_ms_p99": float(np.percentile(ms, 99)) if len(ms) else None,
        "lateness_ms_max": float(ms.max()) if len(ms) else None,
    }
    if args.json:
        print(json.dumps(doc))
    else:
        sig = "verified offline" if figures["signatures_verified"] else "NOT verified (no CA certificate)"
        print(
            f"replayed {doc['published']} messages onto fleet {fleet}; timing: p50 {doc['lateness_ms_p50']:.2f} ms, "
            f"p99 {doc['lateness_ms_p99']:.2f} ms after the recorded offsets; signatures {sig}, "
            f"{figures['refused_signatures']} refused"
        )
    return 0


def _refuse(args: argparse.Namespace, path: Path) -> int:
    from mapcontainer.config import read_yaml, validate_model
    from mapcontainer.fusion.params import FusionParams
    from mapcontainer.recording.replay import refuse

    if not args.out:
        return _fail("replay --refuse: give --out DIR")
    params = None
    if args.params:
        params = read_yaml(Path(args.params))
        validate_model(FusionParams, params, args.params)  # ConfigError: exit 2, one line
    res = refuse(path, params=params, mode=args.mode, schedule=args.schedule, hdmap=args.map)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    doc = {"recording": str(path), "params": params, **res.summary()}
    (out / "refuse.json").write_text(json.dumps(doc, indent=2, default=str) + "\n")
    if args.json:
        print(json.dumps(doc, default=str))
        return 0
    print(
        f"re-fused {path} ({res.schedule} schedule, {res.setup.mode}, host {res.setup.host_id}): "
        f"{len(res.fused)} fused states from {res.ingested} messages; recorded {len(res.live)}"
    )
    if res.schedule == "host":
        print(f"  reproduction: {res.identical}/{res.compared} byte for byte, max |difference| {res.max_abs_diff:.3g}")
    print(f"  {'':<26} {'recorded (live)':>16} {'re-fused':>12}")
    for part in ("whole", "steady"):
        a, b = res.scores["recorded"][part], res.scores["refused"][part]
        for k, label in (("vehicle_rmse_m", "vehicle RMSE (m)"), ("object_rmse_m", "object RMSE (m)"),
                         ("coverage", "coverage"), ("gospa_m", "GOSPA (m)")):  # fmt: skip
            fa = "-" if a[k] is None else f"{a[k]:.4f}"
            fb = "-" if b[k] is None else f"{b[k]:.4f}"
            print(f"  {part + ' ' + label:<26} {fa:>16} {fb:>12}")
    for n in res.notes:
        print(f"  note: {n}")
    print(f"  wrote {out / 'refuse.json'}")
    return 0


# ------------------------------------------------------------------------------ registration


def add_recording_commands(sub) -> None:
    """``record`` (and ``record info``) and ``replay`` on the ``mapc`` subcommands."""
    rec = sub.add_parser(
        "record",
        help="record every message of a running fleet to an MCAP file (Ctrl-C stops); `record info FILE` describes one",
    )
    rec.add_argument("--fleet", default=None, help="the fleet (default: the one running)")
    rec.add_argument("--out", default=None, help="the MCAP file to write")
    rec.add_argument("--connect", action="append", default=None, help="a Zenoh endpoint of the fleet")
    rec.add_argument("--max-mb", type=positive_float, default=2048.0, help="finish the file at this size (MB)")
    rsub = rec.add_subparsers(dest="sub", required=False)
    ri = rsub.add_parser("info", help="channels, message counts, duration and bytes of a recording (exit 2: not one)")
    ri.add_argument("file")
    ri.add_argument("--json", action="store_true", help="one JSON object")
    rx = rsub.add_parser("export", help="a recording in another format: --ros2 writes a ROS 2 bag (the ros extra)")
    rx.add_argument("file", help="a recording (mapc fleet up --record, mapc record)")
    rx.add_argument("out", help="the directory to write (must not exist)")
    rx.add_argument(
        "--ros2", action="store_true", required=True, help="a ROS 2 bag (MCAP storage) with standard messages"
    )
    rx.add_argument("--json", action="store_true", help="one JSON object")
    rx.set_defaults(func=_cmd_record_export)
    rec.set_defaults(func=_cmd_record)

    rp = sub.add_parser(
        "replay",
        help="publish a recording onto a fleet with its timing (--fleet), or re-fuse it in process (--refuse)",
    )
    rp.add_argument("file", help="a recording (mapc fleet up --record, mapc record)")
    rp.add_argument("--fleet", default=None, help="the fleet to publish onto (e.g. mapc fleet up --manifest replay)")
    rp.add_argument("--connect", action="append", default=None, help="a Zenoh endpoint of that fleet")
    rp.add_argument("--speed", type=positive_float, default=1.0, help="replay this many times faster (default 1)")
    rp.add_argument(
        "--topics", default=None, help="registry names to publish (default truth,prior_tx,raw_tx,prior_rx,raw_rx)"
    )
    rp.add_argument("--refuse", action="store_true", help="run the host's core in process on the recorded messages")
    rp.add_argument(
        "--params", default=None, help="--refuse: a YAML file of FusionParams fields (default: the recorded)"
    )
    rp.add_argument("--mode", choices=["distributed", "centralized"], default=None, help="--refuse: the host's mode")
    rp.add_argument(
        "--map", default=None, help="--refuse: the centralized host's HD map file (default: the recorded --map)"
    )
    rp.add_argument(
        "--schedule",
        choices=["host", "arrival"],
        default="host",
        help="--refuse: the live host's recorded input sets and solve times (exact), or the recorded arrivals "
        "through the frame gate",
    )
    rp.add_argument("--out", default=None, help="--refuse: directory for refuse.json")
    rp.add_argument("--json", action="store_true", help="one JSON object")
    rp.set_defaults(func=_cmd_replay)

    from .viewer import add_view_command

    add_view_command(sub)
