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

from mapcontainer.cli import _bounded

positive_float = _bounded(float, 0, strict=True)

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


# ------------------------------------------------------------------------------ record


def _cmd_record(args: argparse.Namespace) -> int:
    if args.sub == "info":
        return _cmd_record_info(args)
    if not args.out:
        return _fail("record: give --out FILE (or `mapc record info FILE`)")
    found = _fleet_endpoints(args.fleet, args.connect)
    if isinstance(found, str):
        return _fail(found)
    fleet, connect, entry = found
    from .recorder.app import RecorderSettings, main
    from .runtime import ZenohSettings

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
        zenoh=ZenohSettings(mode="client", connect=connect, connect_timeout_ms=2000),
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


def _print_info(doc: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(doc))
        return
    state = "complete" if doc["complete"] else f"INCOMPLETE (read up to the last whole chunk: {doc['stopped']})"
    rate = f", {doc['mb_per_min']:.2f} MB/min" if doc["mb_per_min"] else ""
    print(
        f"{doc['file']}: {state}; {doc['duration_s']:.1f} s, {doc['keys']} keys, {doc['messages']} messages, "
        f"{doc['payload_bytes'] / 1e6:.2f} MB of payload, file {doc['file_bytes'] / 1e6:.2f} MB{rate}"
    )
    print(f"  {'channel':<52} {'messages':>8} {'bytes':>11}  schema")
    for c in doc["channels"]:
        print(f"  {c['topic']:<52} {c['messages']:>8} {c['bytes']:>11}  {c['schema'] or '-'} ({c['message_encoding']})")
    for a in doc["attachments"]:
        print(f"  attachment {a['name']} ({a['bytes']} bytes)")
    for p in doc.get("continued_in") or []:
        print(f"  continued in {p} (a restarted recorder)")


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
    rec.set_defaults(func=_cmd_record)
