"""Bytes on the V2X link per mode, measured from the messages a run really encodes.

For each seed the world of ``scenario`` runs once and every vehicle except the host vehicle (whose
messages stay on board, as in :func:`mapcontainer.pipeline.run_pipeline`) turns each sensor frame
into the message of each *variant*, encodes it (msgpack, :func:`schemas.encode`) and, with
``signing``, signs it as the live fleet does (:class:`mapcontainer.security.Signer`: ECDSA P-256,
the certificate about once a second, an 8-byte digest otherwise). The variants:

* ``distributed``: the :class:`~schemas.VehiclePrior` the vehicle sends (it localizes itself);
* ``centralized``: the :class:`~schemas.RawObservations` it sends, the lane mask pooled to the
  width the host's matcher uses (:func:`mapcontainer.lanemask.pool`, ``lane_mask_pooled_png``);
* ``centralized_no_lane_mask``: that message without its lane mask (``lane_mask_png`` empty,
  ``lane_mask_pooled_png`` absent): what the rest of the raw observations cost;
* ``centralized_camera_resolution``: the raw message with the mask at the camera's resolution
  (1280 x 720), as sent before the vehicle pooled it: the host pools it on arrival, so the pixels it
  uses and its poses are the same, and the extra bytes buy nothing.

Per variant: ``bytes_per_message`` (mean encoded message), ``bytes_per_s_per_vehicle`` (bytes / run
duration / sending vehicles), ``max_message_bytes``, and the same with ``_signed`` (bytes on the
air) when signing is on. ``ratio``: each centralized variant over distributed, per message and per
second (equal while both modes send one message per frame). Only the vehicles' side runs (no host,
no channel), so a 10 s urban run takes a few seconds; a test checks the unsigned bytes equal
``run_pipeline``'s ``tx_message_bytes``.

``python -m mapcontainer.experiments.bytes --seeds 90000-90004 --duration 10`` prints the result as JSON.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from schemas import RawObservations, Rejection, encode

from .. import jsonout, lanemask
from ..faults import FaultInjector
from ..pipeline import SIGNING_EPOCH_S
from ..sim import World, load_scenario
from ..vehicle import VehicleAgent
from .executors import Executor, Session
from .runner import Batch, run_all
from .store import TaskStore

__all__ = ["VARIANTS", "bytes_runs", "measure_bytes", "seed_bytes", "summarize_bytes"]

VARIANTS = ("distributed", "centralized", "centralized_no_lane_mask", "centralized_camera_resolution")
_CAMERA_RESOLUTION = 1 << 30  # raw_mask_max_width_px that never pools
_FLEET = "sim"
_NO_MASK = {"lane_mask_png": b"", "lane_mask_pooled_png": None}


def _signers(vehicles: list[str]) -> dict:
    """A CA made for the measurement and a Signer per (variant, vehicle): each variant's stream
    carries its certificate on the same frames."""
    from ..security import Signer, issue, make_ca

    now = SIGNING_EPOCH_S - 3600.0
    ca = make_ca("bytes-ca", now=now, validity_s=30 * 86400.0)
    creds = {v: issue(ca, v, 30 * 86400.0, now) for v in vehicles}
    return {(var, v): Signer(creds[v]) for var in VARIANTS for v in vehicles}


def seed_bytes(scenario: str = "paper-urban", seed: int = 0, duration_s: float = 10.0, signing: bool = True) -> dict:
    """Byte totals of one run per variant (module docstring): ``{variant: {"messages", "bytes",
    "bytes_signed", "max_message_bytes", "max_message_bytes_signed", "lane_mask_bytes"}}`` plus
    ``"senders"`` and ``"lane_mask_px"`` (variant -> [width, height] of the masks sent)."""
    sc = load_scenario(scenario)
    world = World(sc, seed=seed, fleet=_FLEET)
    senders = world.vehicle_ids[1:]  # the host vehicle's own messages stay on board
    agents = {
        "distributed": {v: VehicleAgent(world.hdmap, v, _FLEET, "distributed") for v in senders},
        "centralized": {v: VehicleAgent(world.hdmap, v, _FLEET, "centralized") for v in senders},
        "centralized_camera_resolution": {
            v: VehicleAgent(world.hdmap, v, _FLEET, "centralized", raw_mask_max_width_px=_CAMERA_RESOLUTION)
            for v in senders
        },
    }
    faults = {v: FaultInjector(v, sc.faults) for v in senders}
    signers = _signers(senders) if signing else {}
    zero = {"messages": 0, "bytes": 0, "bytes_signed": 0, "max_message_bytes": 0, "max_message_bytes_signed": 0}
    out: dict[str, Any] = {var: dict(zero, lane_mask_bytes=0) for var in VARIANTS}
    mask_px: dict[str, set] = {var: set() for var in VARIANTS}

    def count(var: str, vid: str, msg, t: float) -> None:
        message = encode(msg)
        acc = out[var]
        acc["messages"] += 1
        acc["bytes"] += len(message)
        acc["max_message_bytes"] = max(acc["max_message_bytes"], len(message))
        if isinstance(msg, RawObservations):
            png = msg.lane_mask_pooled_png or msg.lane_mask_png
            acc["lane_mask_bytes"] += len(png)
            if png:
                mask_px[var].add(lanemask.png_size(png))
        if signing:
            n = len(signers[var, vid].sign(message, SIGNING_EPOCH_S + t))
            acc["bytes_signed"] += n
            acc["max_message_bytes_signed"] = max(acc["max_message_bytes_signed"], n)

    for tick in world.run(duration_s):
        for vid in senders:
            frame = tick.frames.get(vid)
            if frame is None:
                continue
            for var, by_vid in agents.items():
                msg = by_vid[vid].handle(tick.t, frame)
                if isinstance(msg, Rejection):  # the simulator's own frames: a bug, not bad input
                    raise RuntimeError(f"{vid} refused its frame at {tick.t:.2f} s: {msg.reason}: {msg.detail}")
                if var == "distributed":
                    for m in faults[vid].apply(msg) if faults[vid] else [msg]:
                        count(var, vid, m, tick.t)
                    continue
                count(var, vid, msg, tick.t)
                if var == "centralized":
                    count("centralized_no_lane_mask", vid, msg.model_copy(update=_NO_MASK), tick.t)
    if not signing:
        for acc in out.values():
            del acc["bytes_signed"], acc["max_message_bytes_signed"]
    out["senders"] = len(senders)
    out["lane_mask_px"] = {var: sorted(list(s)) for var, s in mask_px.items() if s}
    return out


def _seed_task(task: tuple) -> dict:
    scenario, seed, duration_s, signing = task
    return dict(seed_bytes(scenario, seed, duration_s, signing), seed=seed)


def _r(x: float, nd: int = 1) -> float:
    return float(round(x, nd))


def measure_bytes(
    scenario: str = "paper-urban",
    seeds: tuple[int, ...] | list[int] = (90000, 90001, 90002, 90003, 90004),
    duration_s: float = 10.0,
    signing: bool = True,
    executor: Executor | None = None,
    progress: bool = False,
) -> dict:
    """Bytes per message and per second of each variant over ``seeds`` (module docstring), and the
    centralized / distributed ratios with and without the lane mask. JSON-able (plain floats, ints,
    strings and lists); ``per_seed`` holds every run's ratios so the spread is visible. The runs go to
    ``executor`` (default: this process)."""
    runs = bytes_runs(scenario, seeds, duration_s, signing, executor, progress=progress)
    return summarize_bytes(runs.results, scenario, duration_s, signing)


def bytes_runs(
    scenario: str,
    seeds: tuple[int, ...] | list[int],
    duration_s: float,
    signing: bool = True,
    executor: Executor | Session | None = None,
    store: TaskStore | None = None,
    progress: bool = False,
) -> Batch:
    """:func:`seed_bytes` of every seed on ``executor`` (default: this process), kept in ``store``."""
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("seeds must not be empty")
    if not duration_s > 0:
        raise ValueError(f"duration_s must be positive, got {duration_s}")
    tasks = [(scenario, s, float(duration_s), bool(signing)) for s in seeds]
    return run_all(
        _seed_task, tasks, "bytes", lambda t: f"bytes seed {t[1]}", executor or Executor(workers=1), store, progress
    )


def summarize_bytes(runs: list[dict], scenario: str, duration_s: float, signing: bool = True) -> dict:
    """The figures of :func:`measure_bytes` from its runs (:func:`seed_bytes` of each seed, in seed order)."""
    seeds = [r["seed"] for r in runs]
    sums = ["bytes", "bytes_signed"] if signing else ["bytes"]
    per_vehicle_s = float(duration_s) * sum(r["senders"] for r in runs)  # sender-seconds
    variants: dict[str, dict] = {}
    for var in VARIANTS:
        msgs = sum(r[var]["messages"] for r in runs)
        v: dict[str, Any] = {"messages": msgs, "msgs_per_s_per_vehicle": _r(msgs / per_vehicle_s, 3)}
        for key in sums:
            suffix = key[len("bytes") :]
            total = sum(r[var][key] for r in runs)
            v["bytes_per_message" + suffix] = _r(total / msgs) if msgs else None
            v["bytes_per_s_per_vehicle" + suffix] = _r(total / per_vehicle_s)
            v["max_message_bytes" + suffix] = max(r[var]["max_message_bytes" + suffix] for r in runs)
        if var.startswith("centralized") and msgs:
            v["lane_mask_bytes_per_message"] = _r(sum(r[var]["lane_mask_bytes"] for r in runs) / msgs)
        v["lane_mask_px"] = sorted({tuple(px) for r in runs for px in r["lane_mask_px"].get(var, [])})
        v["lane_mask_px"] = [list(px) for px in v["lane_mask_px"]]
        variants[var] = v

    def ratios(get) -> dict:
        d = variants["distributed"]
        out = {}
        for var in VARIANTS[1:]:
            c = variants[var]
            name = {"centralized": "with_lane_mask", "centralized_no_lane_mask": "without_lane_mask"}.get(
                var, "camera_resolution_lane_mask"
            )
            for key in sums:
                suffix = key[len("bytes") :]
                for per in ("message", "s_per_vehicle"):
                    k = f"bytes_per_{per}{suffix}"
                    out[f"{name}_per_{'message' if per == 'message' else 's'}{suffix}"] = get(c[k], d[k])
        return out

    ratio = ratios(lambda c, d: _r(c / d, 2) if d else None)
    per_seed = []
    for r in runs:
        d, row = r["distributed"], {"seed": r["seed"]}
        for var in VARIANTS[1:]:
            for key in sums:
                row[f"{var}{key[len('bytes') :]}"] = _r(r[var][key] / d[key], 2) if d[key] else None
        per_seed.append(row)
    return {
        "scenario": scenario,
        "seeds": seeds,
        "duration_s": float(duration_s),
        "signed": bool(signing),
        "senders_per_run": [r["senders"] for r in runs],
        "note": "vehicles other than the host vehicle (its messages stay on board); ratio = centralized / "
        "distributed; *_signed = bytes on the air (ECDSA P-256, certificate about once a second)",
        "variants": variants,
        "ratio": ratio,
        "ratio_per_seed": per_seed,
    }


def _seed_range(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b) + 1) if b else [int(a)])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="paper-urban")
    ap.add_argument("--seeds", default="90000-90004", help="e.g. 90000-90004 or 1,2,5")
    ap.add_argument("--duration", type=float, default=10.0, help="scenario seconds per run")
    ap.add_argument("--unsigned", action="store_true", help="do not sign (no *_signed figures)")
    ap.add_argument("--workers", type=int, default=1, help="local worker processes (1: this process)")
    a = ap.parse_args(argv)
    ex = Executor(workers=a.workers)
    res = measure_bytes(a.scenario, _seed_range(a.seeds), a.duration, not a.unsigned, ex, progress=True)
    print(jsonout.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
