"""Replaying a recording: onto another fleet namespace and clock (:func:`replay_plan`), or through the
host's core in process (:func:`refuse`), scored with the evaluator's scoring against the recorded truth.

**Live replay.** Each recorded message is published again ``(log_time - first log_time) / speed``
after the replay starts, on its key with the recorded fleet's chunk replaced by the target's. So that
the services take it as live traffic:

* the payload's ``fleet`` field (tag 1) is set to the target fleet (the host refuses another fleet's
  messages); only that field changes, the other bytes stay as recorded;
* signed messages (SecuredMessage) are verified offline against the recording's CA certificate at
  their recorded receive time and published as the verified inner message: the live verifier refuses
  a generation time more than 5 s from its own clock, and re-signing would need the vehicles' private
  keys, which a recording never holds. The target fleet runs without signing (``--no-signing``);
* the attachments' clock is moved to the replay: ``epoch_wall_ns`` and every ``*_wall_ns`` field are
  shifted by the replay's start minus the recording's (and scaled by ``1 / speed``, ``time_scale``
  multiplied by ``speed``), so scenario times, receive times and latencies come out as recorded.

**Re-fusion.** The recorded host's set-up (:func:`host_setup`: its command line, read with the host's own
flags) builds the same host loop (:func:`mapcontainer.host.build_host`), which is fed the recorded vehicle
messages and solved, two ways:

* ``schedule="host"`` (exact): the live host publishes with every fused state the solve time, the
  frame tolerance and the ``[sender, seq, t_recv]`` of each payload it ingested since its previous
  solve, in order (services.host). Re-fusion ingests exactly those payloads with those receive times
  and solves at those times: the container is deterministic for a given input sequence, so the same
  parameters reproduce the recorded fused states byte for byte (the gate's wall-clock moments do not
  matter any more: they are recorded as the input sets);
* ``schedule="arrival"``: the recorder's arrival order and times drive the host's frame gate
  (``FrameGate``, the pipeline's and the host's one solve policy), receive times in scenario seconds
  from the world's clock in the attachments. Deterministic, for a recording without input sets or to
  see another solve policy; it does not reproduce the live solve moments (the live gate ran on the
  host's own clock and order of arrival).

Signatures are verified offline with the recording's CA certificate (``ca.cert.json``) at each
message's recorded receive time, with the live host's window, so what the live verifier refused is
refused again; without a certificate the payloads are unwrapped unverified and the result says so.
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict, deque
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from schemas.codec import Rejection, decode, encode, peek
from schemas.models import FusedState, GroundTruth
from schemas.tags import TAGS
from schemas.topics import topic

from ..clock import SimClock
from ..evaluation import Totals, score_frame
from ..host import HostSetup, add_host_args, build_host, host_setup_from_args
from .mcapio import Record, RecordingError, read_records, read_scan, recording_files

__all__ = [
    "HostSetup",
    "RefuseResult",
    "ReplayItem",
    "host_setup",
    "refuse",
    "replay_plan",
    "retarget",
    "shift_attachment",
    "shift_clock",
]

_NO_CLOCK = {"epoch_wall_ns": None, "time_scale": None, "t_next": None}  # encode leaves None out
TRUTH_TOL_S = 0.02  # the evaluator's t_tol_s: a fused state is scored against the truth this close in time
BURNIN_S = 5.0  # the evaluator's steady state
_FLEET_TAG = TAGS["fleet"]
_EPOCH_TAG, _SCALE_TAG = TAGS["epoch_wall_ns"], TAGS["time_scale"]


# ---------------------------------------------------------------------------- bytes


def retarget(payload: bytes, fleet: str) -> bytes:
    """``payload`` with its envelope's ``fleet`` (tag 1) set to ``fleet``; anything that is not one of our
    messages (not a msgpack map with tag 1) is returned unchanged."""
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception:  # not msgpack: not ours to change
        return payload
    if not isinstance(obj, dict) or not isinstance(obj.get(_FLEET_TAG), str) or obj[_FLEET_TAG] == fleet:
        return payload
    obj[_FLEET_TAG] = fleet
    return msgpack.packb(obj, use_bin_type=True)


def shift_clock(payload: bytes, rec_start_ns: int, replay_start_ns: int, speed: float) -> bytes:
    """``payload`` with the world's clock in its envelope (``epoch_wall_ns``, ``time_scale``) moved from the
    recording's wall clock to the replay's, as :func:`shift_attachment` moves an attachment's: services take
    the clock from the message itself. Replay publishes the verified inner messages, unsigned, so they can
    change; anything without a clock is returned unchanged."""
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception:  # not msgpack: not ours to change
        return payload
    if not isinstance(obj, dict) or type(obj.get(_EPOCH_TAG)) is not int:
        return payload
    obj[_EPOCH_TAG] = replay_start_ns + int(round((obj[_EPOCH_TAG] - rec_start_ns) / speed))
    if isinstance(obj.get(_SCALE_TAG), int | float):
        obj[_SCALE_TAG] = float(obj[_SCALE_TAG]) * speed
    return msgpack.packb(obj, use_bin_type=True)


def shift_attachment(attachment: bytes | None, rec_start_ns: int, replay_start_ns: int, speed: float) -> bytes | None:
    """An attachment moved from the recording's wall clock to the replay's (module docstring)."""
    if not attachment:
        return attachment
    try:
        obj = msgpack.unpackb(attachment, raw=False)
    except Exception:  # instrumentation: an unreadable one is passed on as recorded
        return attachment
    if not isinstance(obj, dict):
        return attachment

    def move(ns: int) -> int:
        return replay_start_ns + int(round((ns - rec_start_ns) / speed))

    for k, v in list(obj.items()):
        if isinstance(k, str) and k.endswith("wall_ns") and type(v) is int:
            obj[k] = move(v)
    if isinstance(obj.get("time_scale"), int | float):
        obj["time_scale"] = float(obj["time_scale"]) * speed
    return msgpack.packb(obj, use_bin_type=True)


def _verifier(path: Path, ca=None):
    """A Verifier of the recording's CA certificate (attachment ``ca.cert.json``, or ``ca`` when given),
    or None without one."""
    from pydantic import ValidationError

    from schemas.models import Certificate

    from ..security import VERIFY_WINDOW_S, Verifier

    if ca is not None:
        return Verifier(ca, window_s=VERIFY_WINDOW_S)
    data = _attachment(path, "ca.cert.json")
    if data is None:
        return None
    try:
        return Verifier(Certificate.model_validate_json(data), window_s=VERIFY_WINDOW_S)
    except ValidationError as exc:
        raise RecordingError(f"{path}: its ca.cert.json is not a certificate ({exc.errors()[0]['msg']})") from None


def _attachment(path: Path, name: str) -> bytes | None:
    for a in read_scan(path).attachments:
        if a.name == name:
            return bytes(a.data)
    return None


def _unwrap(payload: bytes, verifier, now_s: float, sender: str | None) -> bytes | Rejection:
    """The message inside a signed payload (verified when a verifier is given); unsigned ones as they are."""
    if not isinstance(peek(payload).get("payload"), bytes):
        return payload
    if verifier is None:
        return peek(payload)["payload"]
    out = verifier.verify(payload, now_s, expected_sender=sender)
    return out if isinstance(out, Rejection) else out.payload


def _records(path: Path) -> list[Record]:
    out: list[Record] = []
    for p in recording_files(path):
        out.extend(read_records(p))
    return out


# ---------------------------------------------------------------------------- live replay


@dataclass(frozen=True)
class ReplayItem:
    """One message to publish ``at_s`` seconds after the replay starts."""

    at_s: float
    key: str
    payload: bytes
    attachment: bytes | None
    log_time_ns: int


DEFAULT_TOPICS = ("truth", "prior_tx", "raw_tx", "prior_rx", "raw_rx")


def replay_plan(
    path: str | Path,
    fleet: str,
    speed: float = 1.0,
    topics: Iterable[str] = DEFAULT_TOPICS,
) -> tuple[list[ReplayItem], dict[str, Any]]:
    """What to publish, when: the recording's messages on ``topics`` (registry names; by default what the
    world, vehicles and channel emitted: the host's and the evaluator's input), moved to ``fleet``. The
    attachments and the messages' clocks stay on the recorded clock: the publisher moves each with
    :func:`shift_attachment` and :func:`shift_clock` from ``figures["rec_start_ns"]`` to its own start as it
    puts it. Returns the items and figures (messages,
    refused signatures)."""
    if not (math.isfinite(speed) and speed > 0):
        raise ValueError(f"speed must be finite and > 0, got {speed}")
    path = Path(path)
    tps = [topic(n) for n in topics]
    records = _records(path)
    if not records:
        raise RecordingError(f"{path}: no messages")
    start = records[0].log_time_ns
    verifiers: dict[str, Any] = {}  # one per key: a signed message travels on tx and again on rx, both recorded
    ca = _verifier(path)
    items, refused, signed = [], 0, 0
    for r in records:
        tp = next((t for t in tps if t.parse(r.key) is not None), None)
        if tp is None:
            continue
        where = tp.parse(r.key)
        payload = r.payload
        if isinstance(peek(payload).get("payload"), bytes):
            signed += 1
            if ca is not None and r.key not in verifiers:
                verifiers[r.key] = _verifier(path, ca.ca)
            inner = _unwrap(payload, verifiers.get(r.key), r.log_time_ns * 1e-9, where.get("src"))
            if isinstance(inner, Rejection):
                refused += 1
                continue
            payload = inner
        key = tp.key(**{**where, "fleet": fleet})
        items.append(ReplayItem(0.0, key, retarget(payload, fleet), r.attachment, r.log_time_ns))
    start = items[0].log_time_ns if items else start  # the first replayed message goes out at once
    items = [
        ReplayItem((it.log_time_ns - start) * 1e-9 / speed, it.key, it.payload, it.attachment, it.log_time_ns)
        for it in items
    ]
    figures = {
        "messages": len(items),
        "signed": signed,
        "signatures_verified": ca is not None,
        "refused_signatures": refused,
        "duration_s": (items[-1].log_time_ns - start) * 1e-9 if items else 0.0,
        "rec_start_ns": start,
        "speed": speed,
    }
    return items, figures


# ---------------------------------------------------------------------------- re-fusion


def host_setup(path: str | Path) -> HostSetup:
    """The recorded host's set-up: its command line in the run's config.json kept in the recording, read with
    the host's own flags (:func:`mapcontainer.host.add_host_args`), else the fleet from the recording's
    metadata and the defaults. A ``--map`` or ``--params`` file is named as recorded (relative to where the
    host ran)."""
    path = Path(path)
    scan = read_scan(path)
    meta = scan.metadata.get("recording", {})
    conf = next((a for a in scan.attachments if a.name == "config.json"), None)
    fleet = meta.get("fleet")
    if conf is not None:
        doc = json.loads(bytes(conf.data))
        host = next(
            (
                p
                for p in doc.get("processes", [])
                if p.get("role") == "host" and "--standby-for" not in p.get("argv", [])
            ),
            None,
        )
        if host is not None:
            p = argparse.ArgumentParser(add_help=False)
            add_host_args(p)
            p.add_argument("--fleet", default=fleet or "local")
            p.add_argument("--id", default="host")
            a, _ = p.parse_known_args(host["argv"])  # the service's transport flags are not the container's
            return host_setup_from_args(a, a.fleet, a.id)
    if not fleet:
        raise RecordingError(f"{path}: no config.json or metadata says which fleet and host were recorded")
    return HostSetup(fleet=fleet)


@dataclass
class RefuseResult:
    """Re-fused states beside the recorded ones, and both scored against the recorded truth."""

    setup: HostSetup
    schedule: str
    fused: list[FusedState]  # re-fused, in order
    live: list[FusedState]  # the recorded host's, in order
    identical: int  # re-fused states byte for byte equal to the recorded payload (host schedule)
    compared: int
    max_abs_diff: float  # over poses, pose covariances, object positions/covariances of matching states
    ingested: int
    not_found: int  # inputs the host listed that the recording does not hold
    signature_refused: int
    signatures_verified: bool
    scores: dict[str, Any]
    notes: list[str]

    def summary(self) -> dict[str, Any]:
        return {
            "setup": self.setup.model_dump(mode="json"),
            "schedule": self.schedule,
            "fused_states": len(self.fused),
            "recorded_fused_states": len(self.live),
            "compared": self.compared,
            "identical": self.identical,
            "max_abs_diff": self.max_abs_diff,
            "ingested": self.ingested,
            "inputs_not_found": self.not_found,
            "signature_refused": self.signature_refused,
            "signatures_verified": self.signatures_verified,
            "scores": self.scores,
            "notes": self.notes,
        }


def _state_diff(a: FusedState, b: FusedState) -> float | None:
    """Largest absolute difference of two states' numbers, None if their vehicles or objects differ."""
    if list(a.vehicle_ids) != list(b.vehicle_ids) or not np.array_equal(a.object_id, b.object_id):
        return None
    d = 0.0
    for f in ("vehicle_pose", "vehicle_pose_cov", "object_p_map", "object_v_map", "object_cov"):
        x, y = np.asarray(getattr(a, f), float), np.asarray(getattr(b, f), float)
        if x.size:
            d = max(d, float(np.max(np.abs(x - y))))
    return d


def _score(states: list[FusedState], truth: dict[int, GroundTruth], burnin_s: float) -> dict[str, Any]:
    whole, steady = Totals(), Totals()
    keys = np.array(sorted(truth))
    for s in states:
        k = int(round(float(s.t_meas) * 1000))
        if not len(keys):
            break
        j = int(np.argmin(np.abs(keys - k)))
        if abs(keys[j] - k) > TRUTH_TOL_S * 1000:
            continue
        sc = score_frame(s, truth[int(keys[j])])
        whole.add(sc)
        if float(s.t_meas) >= burnin_s:
            steady.add(sc)
    return {"whole": whole.summary(), "steady": steady.summary()}


def refuse(
    path: str | Path,
    *,
    params: dict[str, Any] | None = None,
    mode: str | None = None,
    schedule: str = "host",
    burnin_s: float = BURNIN_S,
    setup: HostSetup | None = None,
    hdmap=None,
) -> RefuseResult:
    """Re-fuse a recording's vehicle messages with the host's loop (module docstring); ``params``
    (FusionParams fields) replace the recorded host's, ``mode`` must be the recorded one. ``hdmap`` (an
    HDMap or a map file): the centralized host's map, else the recorded ``--map``."""
    from ..fusion.blas import limit_blas_threads
    from ..fusion.params import FusionParams
    from ..security import fused_signers, unwrap

    if schedule not in ("host", "arrival"):
        raise ValueError(f"schedule must be 'host' or 'arrival', got {schedule!r}")
    path = Path(path)
    setup = setup or host_setup(path)
    if mode is not None and mode != setup.mode:
        raise RecordingError(
            f"{path}: recorded in {setup.mode} mode; its vehicles sent "
            f"{'priors' if setup.mode == 'distributed' else 'raw observations'}, which the {mode} host cannot fuse"
        )
    limit_blas_threads(1)  # as the live host's worker: the same BLAS path for the same numbers
    if params is not None:
        setup = setup.model_copy(update={"params": FusionParams(**params)})
    if isinstance(hdmap, str | Path):
        setup, hdmap = setup.model_copy(update={"map_file": str(hdmap)}), None
    if setup.mode == "centralized" and hdmap is None and (setup.map_file is None or not Path(setup.map_file).is_file()):
        raise RecordingError(
            f"{path}: the centralized host needs its HD map: the recorded --map {setup.map_file} is not here; "
            "give the map file (--map)"
        )
    host = build_host(setup, hdmap)
    kind = "prior" if setup.mode == "distributed" else "raw"
    rx, tx = topic(f"{kind}_rx"), topic(f"{kind}_tx")
    fused_t, truth_t = topic("fused"), topic("truth")
    verifier = _verifier(path)
    records = _records(path)
    notes: list[str] = []
    if verifier is None:
        notes.append("no CA certificate in the recording: signed payloads unwrapped without verification")

    inputs: list[tuple[Record, str]] = []  # (record, source) the host subscribed to, in recorded order
    live: list[tuple[Record, FusedState]] = []
    truth: dict[int, GroundTruth] = {}
    refused = 0
    # its own replay table: these are read to the end first, and the inputs' verifier must not see them
    state_verifier = _verifier(path)

    def believed(r: Record, model, senders):
        """A recorded fused state or truth: signed by its host (or standby) or the world when the recording
        has the CA, else refused and counted (a fake fused state on the host's key scores nothing)."""
        nonlocal refused
        inner = unwrap(r.payload, state_verifier, r.log_time_ns * 1e-9, senders)
        if isinstance(inner, Rejection):
            refused += 1
            return None
        m = decode(inner, model)
        return m if m else None

    for r in records:
        w = rx.parse(r.key)
        if w is not None and w["fleet"] == setup.fleet and w["dst"] == setup.host_id:
            inputs.append((r, w["src"]))
            continue
        w = tx.parse(r.key)
        if w is not None and w["fleet"] == setup.fleet and w["src"] in setup.local:
            inputs.append((r, w["src"]))
            continue
        w = fused_t.parse(r.key)
        if w is not None and w["hid"] == setup.host_id:
            m = believed(r, FusedState, fused_signers(setup.host_id))
            if m:
                live.append((r, m))
            continue
        if truth_t.parse(r.key) is not None:
            m = believed(r, GroundTruth, "world")
            if m:
                truth[int(round(float(m.t_meas) * 1000))] = m

    def inner(r: Record, src: str) -> bytes | None:
        nonlocal refused
        out = _unwrap(r.payload, verifier, r.log_time_ns * 1e-9, src)
        if isinstance(out, Rejection):
            refused += 1
            return None
        return out

    fused: list[FusedState] = []
    payloads: list[bytes] = []
    ingested = not_found = 0
    if schedule == "host":
        by_id: dict[tuple[str, int], deque] = defaultdict(deque)
        for r, src in inputs:
            seq = peek(_unwrap(r.payload, None, 0.0, None)).get("seq")
            by_id[(src, seq)].append((r, src))
        if live and live[0][1].seq != 1:
            notes.append(
                f"the recording starts at the host's fused state {live[0][1].seq}, not its first: re-fusion starts "
                "from an empty container and differs until the recorded window has turned over"
            )
        cache: dict[int, bytes | None] = {}
        for r, _ in live:
            att = msgpack.unpackb(r.attachment, raw=False) if r.attachment else {}
            if not isinstance(att, dict) or "inputs" not in att or "t_fused" not in att:
                raise RecordingError(
                    f"{path}: the host's fused states carry no input sets (recorded from an older host): "
                    "use --schedule arrival"
                )
            for sender, seq, t_recv in att["inputs"]:
                q = by_id.get((sender, seq))
                if not q:
                    not_found += 1
                    continue
                rec, src = q.popleft()
                if id(rec) not in cache:
                    cache[id(rec)] = inner(rec, src)
                data = cache[id(rec)]
                if data is not None:
                    host.receive(data, float(t_recv))
                    ingested += 1
            out = host.fuse(float(att["t_fused"]), float(att.get("tol", 0.0)))
            fused.append(out.state)
            payloads.append(out.payload())
        if not_found:
            notes.append(f"{not_found} messages the host ingested are not in the recording (the recorder missed them)")
    else:
        clock = SimClock()  # the host service's clock rules: from the (verified) message, capped at t_next
        t0_ns = inputs[0][0].log_time_ns if inputs else 0
        solved = []
        for r, src in inputs:
            now = (r.log_time_ns - t0_ns) * 1e-9  # seconds since the first input: Unix seconds lose the ns
            solved += host.timeouts(now)
            data = inner(r, src)
            if data is None:
                continue
            clock.update(peek(data), r.log_time_ns)
            t_recv = clock.now(r.log_time_ns)
            if t_recv is None:
                continue
            host.receive(data, t_recv, now)
            ingested += 1
            if (f := host.step(now)) is not None:
                solved.append(f)
        solved += host.timeouts(math.inf)
        fused = [f.state for f in solved]
        payloads = [f.payload() for f in solved]

    identical = compared = 0
    max_diff = 0.0
    if schedule == "host":
        for (_, m), p, f in zip(live, payloads, fused, strict=True):
            compared += 1
            identical += p == encode(m.model_copy(update=_NO_CLOCK))  # the container's: the service adds the clock
            d = _state_diff(f, m)
            max_diff = max(max_diff, math.inf if d is None else d)
    scores = {
        "recorded": _score([m for _, m in live], truth, burnin_s),
        "refused": _score(fused, truth, burnin_s),
        "truth_frames": len(truth),
    }
    return RefuseResult(
        setup=setup,
        schedule=schedule,
        fused=fused,
        live=[m for _, m in live],
        identical=identical,
        compared=compared,
        max_abs_diff=max_diff,
        ingested=ingested,
        not_found=not_found,
        signature_refused=refused,
        signatures_verified=verifier is not None,
        scores=scores,
        notes=notes,
    )


