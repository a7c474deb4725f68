"""``mapc view``: a live view in the browser, with Rerun's web viewer (thin adapter).

Why Rerun: its Python wheel (``rerun-sdk``, the ``view`` extra) serves its own web viewer (WebAssembly)
from this machine, so the page works offline, and it draws what we need (line strips, boxes,
ellipsoids with labels, text, scalars over time) with a timeline to scrub; Foxglove's SDK serves a
WebSocket, but its app is a hosted page. We write only the conversion
(:mod:`mapcontainer.recording.view`) and this adapter: it serves the viewer (gRPC on ``--grpc-port``,
the page on ``--web-port``) and feeds it from a running fleet (``--fleet``: every message on
``mc/{fleet}/**``, drawn as it arrives, i.e. at the fused rate) or a recording (``--file``: all at once
for scrubbing, or ``--paced`` at its recorded pace).
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import threading
import time
from pathlib import Path
from urllib.parse import quote

__all__ = ["add_view_command"]


def _fail(msg: str) -> int:
    print(f"mapc: {msg}", file=sys.stderr)
    return 2


def _scenario_map(scenario: str | None):
    if not scenario:
        return None
    from mapcontainer.hdmap.generator import generate_map
    from mapcontainer.sim.config import load_scenario

    return generate_map(load_scenario(scenario).map)


def _cmd_view(args: argparse.Namespace) -> int:
    from mapcontainer.config import ConfigError
    from mapcontainer.recording import RecordingError

    if (args.file is None) == (args.fleet is None and not args.connect):
        return _fail("view: give --fleet NAME (a running fleet) or --file RECORDING")
    try:
        import rerun as rr
    except ImportError:
        return _fail("view needs Rerun: pip install 'map-container[view]' (the rerun-sdk wheel)")
    if args.file is not None and not Path(args.file).is_file():
        return _fail(f"{args.file}: no such file")
    try:
        records, scenario, source, verifier, entry = None, args.scenario, None, None, None
        if args.file is not None:
            from mapcontainer.recording import read_records, recording_files
            from mapcontainer.recording.mcapio import read_scan
            from mapcontainer.recording.replay import _verifier

            path = Path(args.file)
            meta = read_scan(path).metadata.get("recording", {})
            scenario = scenario or meta.get("scenario") or None
            records = [r for p in recording_files(path) for r in read_records(p)]
            source = str(path)
            verifier = _verifier(path)  # the recording's CA: None for an unsigned fleet's
        else:
            from .recording_cli import _fleet_endpoints

            found = _fleet_endpoints(args.fleet, args.connect)
            if isinstance(found, str):
                return _fail(found)
            fleet, connect, entry = found
            if entry and entry.get("run_dir"):
                conf = Path(entry["run_dir"]) / "config.json"
                params = json.loads(conf.read_text()).get("params", {}) if conf.exists() else {}
                scenario = scenario or params.get("scenario")
                verifier = _fleet_verifier(Path(entry["run_dir"]), params)
            source = f"fleet {fleet}"
    except (RecordingError, ConfigError) as exc:
        return _fail(str(exc))

    from mapcontainer.recording.view import RerunView

    rec = rr.RecordingStream("mapcontainer", recording_id=f"mapc-view-{time.time_ns()}")
    uri = rr.serve_grpc(grpc_port=args.grpc_port, recording=rec)
    rr.serve_web_viewer(web_port=args.web_port, open_browser=False, connect_to=uri)
    view = RerunView(rec, verifier)
    view.layout()
    hdmap = _scenario_map(scenario)
    if hdmap is not None:
        view.log_map(hdmap)
    page = f"http://127.0.0.1:{args.web_port}/?url={quote(uri, safe='')}"
    print(f"view of {source}: open {page}  (Ctrl-C stops)", flush=True)
    try:
        if records is not None:
            _play(view, records, args.paced, args.speed)
            print(f"drawn: {json.dumps(view.drawn)} refused: {json.dumps(view.refused)}", flush=True)
            _wait(args.exit_after)
        else:
            t0 = time.monotonic()
            try:
                _live(view, fleet, connect, args.exit_after, entry)
            finally:
                dt = time.monotonic() - t0
                rate = view.drawn["fused"] / dt if dt > 0 else 0.0
                print(
                    f"drawn: {json.dumps(view.drawn)} in {dt:.1f} s ({rate:.1f} fused states/s) "
                    f"refused: {json.dumps(view.refused)}",
                    flush=True,
                )
    except KeyboardInterrupt:
        pass
    return 0


def _fleet_verifier(run_dir: Path, params: dict):
    """A Verifier of a running fleet's CA (its run's keys, or the ``--keys`` it was given); None when the
    fleet does not sign."""
    from mapcontainer.security import CA_NAME, VERIFY_WINDOW_S, Verifier, load_certificate

    from .launcher.manifest import FleetParams, keys_dir

    where = keys_dir(FleetParams(**params), run_dir)
    return None if where is None else Verifier(load_certificate(where, CA_NAME), window_s=VERIFY_WINDOW_S)


def _play(view, records, paced: bool, speed: float) -> None:
    t0, w0 = time.monotonic(), records[0].log_time_ns if records else 0
    for r in records:
        if paced:
            delay = t0 + (r.log_time_ns - w0) * 1e-9 / speed - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        view.handle(r.key, r.payload, r.log_time_ns)


def _wait(seconds: float | None) -> None:
    deadline = None if seconds is None else time.monotonic() + seconds
    while deadline is None or time.monotonic() < deadline:
        time.sleep(0.2)


def _live(view, fleet: str, connect: list[str], seconds: float | None, entry: dict | None = None) -> None:
    import zenoh

    from .recording_cli import _login_settings
    from .runtime import zenoh_config

    inbox: queue.Queue = queue.Queue(maxsize=10_000)

    def on_sample(sample) -> None:
        try:
            inbox.put_nowait((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))
        except queue.Full:  # the viewer falls behind: newest wins at the next message
            pass

    stop = threading.Event()
    with zenoh.open(zenoh_config(_login_settings(connect, entry))) as session:
        sub = session.declare_subscriber(f"mc/{fleet}/**", on_sample)
        deadline = None if seconds is None else time.monotonic() + seconds
        try:
            while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
                try:
                    key, payload, t_ns = inbox.get(timeout=0.2)
                except queue.Empty:
                    continue
                view.handle(key, payload, t_ns)
        finally:
            sub.undeclare()


def add_view_command(sub) -> None:
    from mapcontainer.cli import positive_float

    v = sub.add_parser(
        "view",
        help="a live view in the browser (Rerun's web viewer, served offline) of a running fleet or a recording",
    )
    v.add_argument("--fleet", default=None, help="a running fleet (default: the one running, with --connect)")
    v.add_argument("--connect", action="append", default=None, help="a Zenoh endpoint of the fleet")
    v.add_argument("--file", default=None, help="a recording (mapc fleet up --record) instead of a fleet")
    v.add_argument("--paced", action="store_true", help="--file: play it at its recorded pace, not all at once")
    v.add_argument("--speed", type=positive_float, default=1.0, help="--paced: this many times faster")
    v.add_argument("--scenario", default=None, help="whose map to draw (default: the run's)")
    v.add_argument("--web-port", type=int, default=9090, help="the page's port (default 9090)")
    v.add_argument("--grpc-port", type=int, default=9876, help="the viewer's data port (default 9876)")
    v.add_argument("--exit-after", type=positive_float, default=None, help=argparse.SUPPRESS)
    v.set_defaults(func=_cmd_view)
