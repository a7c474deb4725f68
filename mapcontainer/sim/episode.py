"""Recording a simulated episode to files, and reading it back.

An episode directory holds:

* ``episode.msgpack`` — a stream of msgpack arrays ``[t_meas, key, payload]``: ``key`` is the
  topic key the payload would be published on (``mc/{fleet}/sim/truth`` or
  ``mc/{fleet}/sim/{vid}/sensors``) and ``payload`` the message bytes from :func:`schemas.encode`;
* ``map.geojson`` — the HD map the vehicles carry (:mod:`mapcontainer.hdmap.io`; with the map error of
  the seed), ``map_true.geojson`` — the world's map the cameras saw;
* ``scenario.json`` — the resolved scenario configuration and seed;
* ``birdseye.png``, ``camera_<vid>.png`` — pictures; ``summary.json`` — the figures printed by the CLI.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import msgpack
import numpy as np

from schemas import GroundTruth, Rejection, SensorFrame, decode, encode
from schemas.topics import topic

from .. import geometry as geo
from ..config import ConfigError
from ..hdmap.io import save_map
from .render import render_birdseye, render_camera_view
from .world import Tick, World

__all__ = ["read_episode", "record_episode"]

EPISODE_FILE = "episode.msgpack"


def record_episode(world: World, duration_s: float, out_dir: Path) -> dict:
    """Run ``world`` for ``duration_s`` and write the episode to ``out_dir``; returns the summary."""
    sc = world.scenario
    if not round(duration_s / world.dt) >= 1:  # refused before anything is written
        raise ConfigError(f"a duration of {duration_s:g} s gives no frame at {sc.sensors.rate_hz:g} Hz")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    truth_key = topic("truth").key(fleet=world.fleet)
    sensor_keys = {v: topic("sensors").key(fleet=world.fleet, vid=v) for v in world.vehicle_ids}
    tracks: dict[str, list[np.ndarray]] = {}
    classes: dict[str, int] = {}
    frame_bytes: list[int] = []
    det_err2: list[float] = []
    gnss_err2: list[float] = []
    n_frames = 0
    middle: Tick | None = None
    last: Tick | None = None
    n_total = int(round(duration_s / world.dt))
    with open(out_dir / EPISODE_FILE, "wb") as fh:
        packer = msgpack.Packer(use_bin_type=True)
        for tick in world.run(duration_s):
            n_frames += 1
            fh.write(packer.pack([tick.t, truth_key, encode(tick.truth)]))
            for vid, frame in tick.frames.items():
                payload = encode(frame)
                frame_bytes.append(len(payload))
                fh.write(packer.pack([tick.t, sensor_keys[vid], payload]))
                det_err2 += _detection_errors2(tick, vid)
                gnss_err2.append(float(np.sum((frame.gnss.p_map[:2] - tick.states[vid].p_map[:2]) ** 2)))
            for aid, st in tick.states.items():
                tracks.setdefault(aid, []).append(st.p_map[:2])
                classes[aid] = st.cls
            if tick.k == n_total // 2:
                middle = tick
            last = tick
    assert last is not None and middle is not None  # at least one frame, checked above

    save_map(world.hdmap, out_dir / "map.geojson")
    save_map(world.true_map, out_dir / "map_true.geojson")
    (out_dir / "scenario.json").write_text(
        json.dumps(
            {
                "seed": world.seed,
                "fleet": world.fleet,
                "duration_s": duration_s,
                "scenario": sc.model_dump(mode="json"),
            },
            indent=2,
        )
        + "\n"
    )
    render_birdseye(
        out_dir / "birdseye.png",
        world.true_map,
        {k: np.array(v) for k, v in tracks.items()},
        last.states,
        world.vehicle_ids,
        sc.sensors.detector.fov_deg,
        sc.sensors.detector.range_m,
        f"{sc.name}  seed {world.seed}  {duration_s:g} s",
        classes,
    )
    for vid in world.vehicle_ids:
        render_camera_view(out_dir / f"camera_{vid}.png", middle.debug[vid].camera, f"{vid}  t = {middle.t:.1f} s")

    obstacles: dict[str, int] = {}  # every obstacle that was in the world during the episode
    for aid, cls in classes.items():
        if aid not in world.vehicle_ids:
            name = cls.name.lower()
            obstacles[name] = obstacles.get(name, 0) + 1
    summary = {
        "scenario": sc.name,
        "seed": world.seed,
        "duration_s": duration_s,
        "frames": n_frames,
        "vehicles": len(world.vehicle_ids),
        "obstacles": obstacles,
        "map_features": world.true_map.feature_counts(),
        "published_map_features": world.hdmap.feature_counts(),
        "sensor_frame_bytes_mean": round(float(np.mean(frame_bytes)), 1),
        "detection_rmse_m": round(float(np.sqrt(np.mean(det_err2))), 3) if det_err2 else None,
        "gnss_rmse_m": round(float(np.sqrt(np.mean(gnss_err2))), 3),
        "episode_bytes": (out_dir / EPISODE_FILE).stat().st_size,
        "out": str(out_dir),
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def _detection_errors2(tick: Tick, vid: str) -> list[float]:
    """Squared body-frame errors of vehicle ``vid``'s true-positive object detections."""
    T_body_map = geo.inverse(geo.pose_to_matrix(tick.states[vid].pose))
    frame = tick.frames[vid]
    out = []
    for p, tid in zip(frame.objects.p_body, tick.debug[vid].object_truth_ids, strict=True):
        if tid is not None:
            out.append(float(np.sum((p - geo.transform_points(T_body_map, tick.states[tid].p_map)) ** 2)))
    return out


def read_episode(out_dir: Path) -> Iterator[tuple[float, str, GroundTruth | SensorFrame]]:
    """Yield ``(t_meas, key, message)`` from an episode directory, decoding each payload."""
    with open(Path(out_dir) / EPISODE_FILE, "rb") as fh:
        for t, key, payload in msgpack.Unpacker(fh, raw=False):
            model = GroundTruth if key.endswith("/truth") else SensorFrame
            msg = decode(payload, model)
            if isinstance(msg, Rejection):
                raise ValueError(f"corrupt episode record at t={t} on {key}: {msg}")
            yield t, key, msg
