"""Recorder service: every message on ``mc/{fleet}/**`` into an MCAP file (mapcontainer.recording).

The Zenoh callback only queues ``(key, payload, attachment, receive wall ns)``; a writer thread hands
them to :class:`mapcontainer.recording.RecordingWriter` (the exact bytes, the attachment on its
parallel channel, Foxglove visualization channels beside) and finishes a chunk every ``--flush``
seconds, so a killed recorder loses at most that much. A file that reaches ``--max-mb`` is finished
and closed with an error in the log and the health note; the recorder then only counts what it drops.
A recorder restarted after a crash continues in ``NAME-1.mcap``, ``NAME-2.mcap``, ... beside the first
file (``mapc record info`` and ``mapc replay`` take the first and read the others after it).
"""

from __future__ import annotations

import argparse
import json
import queue
import threading
import time
from pathlib import Path
from typing import Any

from pydantic import Field

from mapcontainer.recording import RecordingWriter
from mapcontainer.recording.foxglove import SCENE_UPDATE, map_points, map_scene, point_cloud_schema, visualizer
from mapcontainer.security import CA_NAME, VERIFY_WINDOW_S, Verifier, load_certificate

from ..runtime import Service, ServiceSettings, add_service_args, service_settings_from_args, setup_logging

__all__ = ["RecorderSettings", "free_path", "main", "parse_args", "recorder_files"]


class RecorderSettings(ServiceSettings):
    out: str = Field(description="the MCAP file to write (a restarted recorder continues in NAME-1.mcap, ...)")
    max_mb: float = Field(2048.0, ge=2.0, description="the file is finished at this size (MB)")
    flush_s: float = Field(1.0, gt=0, le=60, description="a chunk is finished at least this often (seconds)")
    scenario: str | None = Field(None, description="draw this scenario's HD map on /viz/map")
    seed: int = Field(0, ge=0)
    keys: str | None = Field(None, description="the fleet's keys directory: its CA certificate goes into the file")
    config: str | None = Field(None, description="the run's config.json, kept in the file")
    viz: bool = True
    queue: int = Field(100_000, ge=100)


def parse_args(argv: list[str] | None = None) -> RecorderSettings:
    p = argparse.ArgumentParser(prog="python -m services.recorder", description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="MCAP file to write")
    p.add_argument("--max-mb", type=float, default=2048.0, help="finish the file at this size (MB)")
    p.add_argument("--flush", type=float, default=1.0, help="finish a chunk at least every this many seconds")
    p.add_argument("--scenario", default=None, help="the run's scenario: its HD map is drawn on /viz/map")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--keys", default=None, help="the fleet's keys directory (its CA certificate is kept)")
    p.add_argument("--config", default=None, help="the run's config.json (kept in the file)")
    p.add_argument("--no-viz", dest="viz", action="store_false", help="no Foxglove visualization channels")
    add_service_args(p, "recorder", default_id="recorder")
    a = p.parse_args(argv)
    return RecorderSettings(
        **service_settings_from_args(a).model_dump(),
        out=a.out,
        max_mb=a.max_mb,
        flush_s=a.flush,
        scenario=a.scenario,
        seed=a.seed,
        keys=a.keys,
        config=a.config,
        viz=a.viz,
    )


def free_path(path: Path) -> Path:
    """``path``, or the first ``NAME-k.mcap`` beside it that does not exist yet."""
    k, p = 0, path
    while p.exists():
        k += 1
        p = path.with_name(f"{path.stem}-{k}{path.suffix}")
    return p


def recorder_files(s: RecorderSettings) -> dict[str, bytes]:
    """The MCAP attachments of a recording: the CA certificate and the run's configuration, when known."""

    files: dict[str, bytes] = {}
    if s.keys:
        ca = Path(s.keys) / f"{CA_NAME}.cert.json"
        if ca.exists():
            files["ca.cert.json"] = ca.read_bytes()
    if s.config and Path(s.config).exists():
        files["config.json"] = Path(s.config).read_bytes()
    return files


def main(s: RecorderSettings) -> int:
    log = setup_logging("recorder", s.id, s.log_level)
    log.info("settings: %s", s.model_dump_json())
    path = free_path(Path(s.out))
    path.parent.mkdir(parents=True, exist_ok=True)
    # signed fleets: only truth and fused states that verify are drawn; the recording keeps every message
    verifier = Verifier(load_certificate(s.keys, CA_NAME), window_s=VERIFY_WINDOW_S) if s.keys else None
    viz_refused: dict[str, int] = {}
    meta = {"fleet": s.fleet, "scenario": s.scenario or "", "seed": str(s.seed), "started_wall_ns": time.time_ns()}
    writer = RecordingWriter(
        path,
        max_bytes=int(s.max_mb * 1e6),
        metadata=meta,
        files=recorder_files(s),
        viz=visualizer(verifier, viz_refused) if s.viz else None,
    )
    if s.viz and s.scenario:
        from mapcontainer.hdmap.generator import generate_map
        from mapcontainer.sim.config import load_scenario

        hdmap, now = generate_map(load_scenario(s.scenario).map), time.time_ns()
        writer.add_viz("/viz/map", *SCENE_UPDATE, map_scene(hdmap, now), now)
        writer.add_viz("/viz/points/map", *point_cloud_schema(), map_points(hdmap, now), now)
    log.info("recording mc/%s/** to %s", s.fleet, path)
    inbox: queue.Queue[tuple[str, bytes, bytes | None, int]] = queue.Queue(maxsize=s.queue)
    fig: dict[str, Any] = {"recorded": 0, "dropped": 0, "file_bytes": 0, "full": 0}

    with Service("recorder", s, figures=lambda: {**fig, "viz_refused": dict(viz_refused)}, keys=s.keys) as svc:

        def on_sample(key: str, payload: bytes, att: bytes | None, t_ns: int) -> None:
            try:
                inbox.put_nowait((key, payload, att, t_ns))
            except queue.Full:
                fig["dropped"] += 1
                svc.metrics.reject("queue_full", f"the writer falls behind ({s.queue} waiting)", log)

        def write() -> None:
            next_flush = time.monotonic() + s.flush_s
            while True:
                stopping = svc.stop_requested.is_set()
                try:
                    item = inbox.get(timeout=0.1)
                except queue.Empty:
                    item = None
                    if stopping:
                        break
                if item is not None:
                    if writer.add(*item):
                        fig["recorded"] += 1
                    else:
                        fig["dropped"] += 1
                        if not fig["full"]:
                            fig["full"] = 1
                            why = f"recording stopped: {path} reached --max-mb {s.max_mb:g} MB; the file is finished"
                            log.error(why)
                            svc.set_state("degraded", why)
                if time.monotonic() >= next_flush:
                    writer.flush()
                    next_flush = time.monotonic() + s.flush_s
                    fig["file_bytes"] = writer.bytes_written

        th = threading.Thread(target=write, name="writer", daemon=True)
        th.start()
        svc.subscribe_raw(f"mc/{s.fleet}/**", on_sample)
        svc.ready()
        svc.wait()
        th.join(timeout=30.0)
    writer.close()
    summary = {"file": str(path), "messages": writer.messages, "bytes": path.stat().st_size, "dropped": fig["dropped"]}
    log.info("recording finished: %s", json.dumps(summary))
    return 0
