"""The evaluator's core: live accuracy, latency and bandwidth of a running fleet (pure: time is an argument).

Accuracy. Each FusedState is compared with the GroundTruth of the same ``t_meas`` (the host solves
at camera-frame times; truth is kept for ``truth_keep_s`` and matched within ``t_tol_s``) and
scored by :func:`mapcontainer.evaluation.score_frame`, the code the in-process experiments use, so
the same states and truth give the same numbers: vehicles paired by id, objects with the true
obstacles (all of the scenario's, seen by a vehicle or not) by the GOSPA assignment on horizontal
distance (cutoff 3 m). RMSE = sqrt(mean ||e_xy||^2) over every pair in the window (the paper's rms1
for vehicles; its map-frame counterpart for objects). The whole-run summary
(:class:`mapcontainer.evaluation.Totals`) gives each figure over the whole run and in steady state,
over the fused states with ``t_meas >= burnin_s`` (the vehicles start cold, from GNSS): beside every
RMSE the coverage (matched obstacles / obstacles), false tracks (per frame and as a fraction of the
fused objects), GOSPA in its localization, missed and false parts, and the consistency of the
6-DoF vehicle poses and 3-D object positions (ANEES with its band, fraction of cells inside their
own 95 % band). Every scored state also leaves a row of :func:`mapcontainer.evaluation.frame_row`
in :attr:`Evaluator.frames`, or goes to ``frame_sink`` (the service streams them to ``eval_frames.csv``).
Everything else it keeps is bounded, so a run of any length has a flat memory: sums for the figures,
the pictures' traces thinned (:class:`Trace`).

Latency. End to end = wall time the fused state was published (``t_wall_ns`` in the host's
attachment) minus the wall time its ``t_meas`` happened on the world's clock
(``epoch_wall_ns + t_meas / time_scale``), so it includes the vehicle's processing, the link
model, the host's reorder wait and its solve. One outside [0, MAX_E2E_LATENCY_MS] comes from a
broken or forged clock: it is counted (``latency_refused``) and left out.

Bandwidth. Payload bytes each vehicle puts on ``v2x/tx`` per second (what the radio would carry),
and the delivered fraction: distinct (src, seq) received on ``v2x/rx/{dst}/{src}`` over messages
sent by src to dst (sources on board a receiver excluded) over the last ``delivery_window_s``, each
message counted once it is ``settle_s`` old (later arrivals count as lost).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mapcontainer.evaluation import GATE_M, GOSPA_ALPHA, GOSPA_C_M, GOSPA_P, Totals, frame_row, score_frame
from mapcontainer.metrics import match_objects
from schemas import EvalMetrics, FusedState, GroundTruth

__all__ = ["SCORE_KEYS", "Evaluator", "match_objects", "steady_name"]

MAX_SOURCES = 256  # distinct V2X sources counted; more are a flood of names (counted in sources_refused)
MAX_E2E_LATENCY_MS = 60_000.0  # a longer (or negative) end-to-end latency is a forged or broken clock
LATENCIES_KEPT = 100_000  # newest end-to-end latencies for the whole-run percentiles (10 Hz: 2.8 h)
TRACE_RECENT = 1_200  # newest points of a picture trace kept at full rate (10 Hz: two minutes)
TRACE_OLDER = 4_000  # older points, thinned to stay spread over the whole run (Trace)
MAX_TRACES = 1_024  # traces of one kind kept; the oldest one goes when a new obstacle comes
OBSTACLE_GONE_S = 120.0  # an obstacle not in the truth for this long (scenario s) loses its trace
OBJECTS_RECENT = 20_000  # fused objects kept for the picture (it draws the last seconds only)
FRAMES_KEPT = 10_000  # frame rows kept in memory when nobody streams them (Evaluator.frame_sink)
SCORE_KEYS = (  # of mapcontainer.evaluation.Totals.summary, in the whole-run summary
    "frames",
    "vehicle_rmse_m",
    "vehicle_pairs",
    "vehicle_rmse_by_id_m",
    "object_rmse_m",
    "object_pairs",
    "coverage",
    "false_tracks_per_frame",
    "false_track_fraction",
    "gospa_m",
    "gospa_localization_m2",
    "gospa_missed_m2",
    "gospa_false_m2",
    "vehicle_nees",
    "object_nees",
)


def steady_name(key: str) -> str:
    """The steady-state figure's name: ``_steady`` before the unit (vehicle_rmse_m -> vehicle_rmse_steady_m)."""
    for unit in ("_by_id_m", "_m2", "_m"):
        if key.endswith(unit):
            return key[: -len(unit)] + "_steady" + unit
    return key + "_steady"


class Trace:
    """Rows of ``width`` numbers for a picture, in memory fixed when the trace is made, over a run of any
    length: the newest ``recent`` at full rate, the older ones thinned (when ``older`` of them are kept,
    every other one goes and from then on only every other one is kept, and so on), so that they stay
    spread over the whole run. The arrays are allocated (and touched) at once: the evaluator's memory is
    flat from its first traces, not growing for the better part of an hour until they fill."""

    def __init__(self, width: int = 3, recent: int = TRACE_RECENT, older: int = TRACE_OLDER) -> None:
        self._recent = np.full((recent, width), np.nan)  # a ring: the oldest at _head once full
        self._older = np.full((older, width), np.nan)
        self._n_recent = self._head = self._n_older = 0
        self._stride, self._aged = 1, 0

    def append(self, row) -> None:
        cap = len(self._recent)
        if self._n_recent < cap:
            self._recent[self._n_recent] = row
            self._n_recent += 1
            return
        if self._aged % self._stride == 0:  # the oldest recent row ages into the thinned part
            if self._n_older == len(self._older):
                kept = self._older[::2].copy()
                self._older[: len(kept)] = kept
                self._n_older, self._stride = len(kept), self._stride * 2
            self._older[self._n_older] = self._recent[self._head]
            self._n_older += 1
        self._aged += 1
        self._recent[self._head] = row
        self._head = (self._head + 1) % cap

    def array(self) -> np.ndarray:
        """Every kept row, oldest first: (len(self), width)."""
        recent = np.roll(self._recent[: self._n_recent], -self._head, axis=0)
        return np.vstack([self._older[: self._n_older], recent])

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        return self.array() if dtype is None else self.array().astype(dtype)

    def last(self) -> np.ndarray | None:
        """The newest row, or None."""
        if not self._n_recent:
            return None
        return self._recent[(self._head + self._n_recent - 1) % len(self._recent)]

    def __len__(self) -> int:
        return self._n_older + self._n_recent


class Ring:
    """The newest ``size`` numbers (e.g. end-to-end latencies for the whole-run percentiles), allocated at once."""

    def __init__(self, size: int) -> None:
        self._a = np.full(size, np.nan)
        self._n = 0

    def append(self, x: float) -> None:
        self._a[self._n % len(self._a)] = x
        self._n += 1

    def values(self) -> np.ndarray:
        return self._a[: min(self._n, len(self._a))]


def _trace(traces: dict, key, width: int = 3) -> Trace:
    """The trace of ``key`` (made on first use; past MAX_TRACES keys the oldest trace goes)."""
    if key not in traces:
        if len(traces) >= MAX_TRACES:
            del traces[next(iter(traces))]
        traces[key] = Trace(width)
    return traces[key]


def _append_per_vehicle(traces: dict, rows: dict, t: float) -> None:
    """Each vehicle's row to its trace; a vehicle absent from ``rows`` gets a NaN row (the drawn line
    breaks there) unless its trace already ends in one."""
    for vid, row in rows.items():
        _trace(traces, vid, 1 + len(row)).append((t, *row))
    for vid, tr in traces.items():
        last = tr.last()
        if vid not in rows and last is not None and not np.isnan(last[1]):
            tr.append(np.r_[t, np.full(len(last) - 1, np.nan)])


@dataclass
class _Sample:
    t_wall: float
    vehicle_sq: list[float]
    object_sq: list[float]
    latency_ms: float | None


@dataclass
class Evaluator:
    fleet: str
    evaluator_id: str = "evaluator"
    window_s: float = 5.0
    truth_keep_s: float = 10.0
    t_tol_s: float = 0.02
    settle_s: float = 1.0
    gate_m: float = GATE_M
    onboard: dict[str, set[str]] = field(default_factory=lambda: {"host": set()})  # receiver -> on-board sources
    delivery_window_s: float = 30.0
    plot_every_s: float = 0.5
    burnin_s: float = 5.0  # scenario seconds left out of the steady-state figures
    frame_sink: Callable[[dict], None] | None = None  # gets each frame row (e.g. a CSV writer's writerow)

    def __post_init__(self) -> None:
        self._truth: dict[int, GroundTruth] = {}
        self._pending: deque[tuple[FusedState, int | None, int | None, float]] = deque()
        self._samples: deque[_Sample] = deque()
        self.totals = Totals()  # every scored state
        self.totals_steady = Totals()  # those with t_meas >= burnin_s
        # frame_row of every scored state: to frame_sink (the service streams them to eval_frames.csv), else the
        # last FRAMES_KEPT kept here
        self.frames: deque[dict] = deque(maxlen=FRAMES_KEPT)
        self.evaluated = 0
        self.no_truth = 0
        self.latency_refused = 0
        self.flagged_first: dict[str, float] = {}  # vehicle -> scenario time the host first flagged it
        self.sources_refused = 0
        self.t_meas: float | None = None
        self.last: dict[str, int] = {"objects_fused": 0, "objects_matched": 0, "obstacles_truth": 0}
        self._tx: dict[str, deque[tuple[float, int]]] = {}
        self._tx_sent: deque[tuple[float, str, int]] = deque()  # (t_wall, src, seq) not yet settled
        self._rx_seen: dict[tuple[str, str, int], float] = {}  # (dst, src, seq) -> t_wall received
        self._settled: deque[tuple[float, bool]] = deque()  # (t_wall sent, delivered) per directed message
        self.sent_total = 0
        self.delivered_total = 0
        self.tx_bytes_total: dict[str, int] = {}
        self.tx_msgs_total: dict[str, int] = {}
        self._lat_all = Ring(LATENCIES_KEPT)
        self._seq = 0
        # picture material, in scenario time (bounded): truth every plot_every_s, every fused state
        self.truth_vehicles: dict[str, Trace] = {}  # vid -> (t, x, y)
        self.truth_obstacles: dict[int, Trace] = {}  # obstacle id -> (t, x, y)
        self.tracks_fused: dict[str, Trace] = {}  # vid -> (t, x, y), NaN at gaps
        # t, id, cls, x, y
        self.fused_objects: deque[tuple[float, int, int, float, float]] = deque(maxlen=OBJECTS_RECENT)
        # per fused state: each vehicle's horizontal error (t_meas, m; NaN at gaps) and the objects'
        # (t_meas, RMSE m, coverage; NaN where there is none)
        self.vehicle_errors: dict[str, Trace] = {}
        self.object_errors = Trace(3)
        self.last_fused: FusedState | None = None
        self.last_truth: GroundTruth | None = None
        self._last_plot_t = -np.inf

    # -- inputs -----------------------------------------------------------------------------
    @staticmethod
    def _k(t: float) -> int:
        return int(round(t * 1000))

    def on_truth(self, truth: GroundTruth) -> None:
        self._truth[self._k(truth.t_meas)] = truth
        lo = self._k(truth.t_meas - self.truth_keep_s)
        for k in [k for k in self._truth if k < lo]:
            del self._truth[k]
        if truth.t_meas - self._last_plot_t >= self.plot_every_s - 1e-9:
            self._last_plot_t = t = truth.t_meas
            for vid, pose in zip(truth.vehicle_ids, truth.vehicle_pose, strict=True):
                _trace(self.truth_vehicles, vid).append((t, float(pose[0]), float(pose[1])))
            for oid, p in zip(truth.obstacle_id, truth.obstacle_p_map, strict=True):
                _trace(self.truth_obstacles, int(oid)).append((t, float(p[0]), float(p[1])))
            gone = [oid for oid, tr in self.truth_obstacles.items() if tr.last()[0] < t - OBSTACLE_GONE_S]
            for oid in gone:  # obstacles that left the scene: their trails go, the picture keeps the present
                del self.truth_obstacles[oid]

    def _find_truth(self, t: float) -> GroundTruth | None:
        k = self._k(t)
        if k in self._truth:
            return self._truth[k]
        tol = self._k(self.t_tol_s)
        best = min(self._truth, key=lambda x: abs(x - k), default=None)
        return self._truth[best] if best is not None and abs(best - k) <= tol else None

    def on_fused(self, fused: FusedState, pub_wall_ns: int | None, t_meas_wall_ns: int | None, now_wall: float) -> None:
        """A fused state, when it was published, and when its t_meas happened (wall clock, ns)."""
        self._pending.append((fused, pub_wall_ns, t_meas_wall_ns, now_wall))
        self._resolve(now_wall)

    def _resolve(self, now_wall: float) -> None:
        keep: deque = deque()
        while self._pending:
            fused, pub_ns, meas_ns, t_in = self._pending.popleft()
            truth = self._find_truth(fused.t_meas)
            if truth is None:
                newest = max(self._truth, default=None)
                if now_wall - t_in < 2.0 and (newest is None or newest < self._k(fused.t_meas)):
                    keep.append((fused, pub_ns, meas_ns, t_in))  # truth not here yet
                else:
                    self.no_truth += 1
                continue
            self._evaluate(fused, truth, pub_ns, meas_ns, now_wall)
        self._pending = keep

    def _evaluate(self, fused: FusedState, truth: GroundTruth, pub_ns, meas_ns, now_wall: float) -> None:
        score = score_frame(fused, truth, self.gate_m)
        self.totals.add(score)
        if fused.t_meas >= self.burnin_s:
            self.totals_steady.add(score)
        row = frame_row(score)
        (self.frames.append if self.frame_sink is None else self.frame_sink)(row)
        v_sq = [float(x) for x in score.vehicle_sq]
        v_err = {vid: float(np.sqrt(x)) for vid, x in zip(score.vehicle_ids, v_sq, strict=True)}
        o_sq = [float(x) for x in score.object_sq]
        p_f = np.asarray(fused.object_p_map, float).reshape(-1, 3)
        lat = (pub_ns - meas_ns) * 1e-6 if pub_ns is not None and meas_ns is not None else None
        if lat is not None and not 0.0 <= lat <= MAX_E2E_LATENCY_MS:
            self.latency_refused += 1  # e.g. t_wall_ns = 1 in the host's attachment
            lat = None
        self._samples.append(_Sample(now_wall, v_sq, o_sq, lat))
        if lat is not None:
            self._lat_all.append(lat)
        self.evaluated += 1
        self.t_meas = fused.t_meas
        self.last = {"objects_fused": len(p_f), "objects_matched": score.n_matched, "obstacles_truth": score.n_truth}
        self.last_fused = fused
        self.last_truth = truth  # the truth at the last fused state's t_meas (for the picture)
        t = fused.t_meas
        for vid in fused.flagged:
            self.flagged_first.setdefault(vid, t)
        _append_per_vehicle(self.vehicle_errors, {vid: (e,) for vid, e in v_err.items()}, t)
        o_rmse = float(np.sqrt(np.mean(o_sq))) if o_sq else np.nan
        self.object_errors.append((t, o_rmse, np.nan if score.coverage is None else score.coverage))
        poses = {vid: (float(p[0]), float(p[1])) for vid, p in zip(fused.vehicle_ids, fused.vehicle_pose, strict=True)}
        _append_per_vehicle(self.tracks_fused, poses, t)
        self.fused_objects.extend(
            (t, int(i), int(c), float(p[0]), float(p[1]))
            for i, c, p in zip(fused.object_id, fused.object_cls, p_f, strict=True)
        )

    def on_tx(self, src: str, seq: int | None, nbytes: int, now_wall: float) -> None:
        if src not in self._tx and len(self._tx) >= MAX_SOURCES:
            self.sources_refused += 1
            return
        self._tx.setdefault(src, deque()).append((now_wall, nbytes))
        self.tx_bytes_total[src] = self.tx_bytes_total.get(src, 0) + nbytes
        self.tx_msgs_total[src] = self.tx_msgs_total.get(src, 0) + 1
        if seq is not None:
            self._tx_sent.append((now_wall, src, seq))

    def on_rx(self, dst: str, src: str, seq: int | None, now_wall: float) -> None:
        if seq is not None and src in self._tx:  # a delivery of a source never seen sending counts for nothing
            self._rx_seen[(dst, src, seq)] = now_wall

    # -- outputs ----------------------------------------------------------------------------
    def _settle(self, now_wall: float) -> None:
        """Messages sent more than settle_s ago: count them as delivered or not, once."""
        while self._tx_sent and self._tx_sent[0][0] <= now_wall - self.settle_s:
            t, src, seq = self._tx_sent.popleft()
            for dst, onboard in self.onboard.items():
                if src == dst or src in onboard:
                    continue
                got = self._rx_seen.pop((dst, src, seq), None) is not None
                self._settled.append((t, got))
                self.sent_total += 1
                self.delivered_total += got
        lo = now_wall - self.delivery_window_s
        while self._settled and self._settled[0][0] < lo:
            self._settled.popleft()
        for key in [k for k, t in self._rx_seen.items() if t < lo - self.settle_s]:
            del self._rx_seen[key]  # received but never seen sent (e.g. sent before we started)

    def _delivered_fraction(self) -> float | None:
        if not self._settled:
            return None
        return sum(got for _, got in self._settled) / len(self._settled)

    def snapshot(self, now_wall: float) -> EvalMetrics:
        self._resolve(now_wall)
        self._settle(now_wall)
        lo = now_wall - self.window_s
        while self._samples and self._samples[0].t_wall < lo:
            self._samples.popleft()
        for q in self._tx.values():
            while q and q[0][0] < lo:
                q.popleft()
        v = [x for s in self._samples for x in s.vehicle_sq]
        o = [x for s in self._samples for x in s.object_sq]
        lat = [s.latency_ms for s in self._samples if s.latency_ms is not None]
        span = self.window_s
        self._seq += 1
        t_meas = 0.0 if self.t_meas is None else self.t_meas
        total = self.totals.summary()
        return EvalMetrics(
            fleet=self.fleet,
            sender=self.evaluator_id,
            seq=self._seq,
            t_wall=now_wall,
            t_meas=t_meas,
            t_sent=t_meas,
            window_s=self.window_s,
            fused_per_s=len(self._samples) / span,
            evaluated=self.evaluated,
            no_truth=self.no_truth,
            vehicle_rmse_m=float(np.sqrt(np.mean(v))) if v else None,
            object_rmse_m=float(np.sqrt(np.mean(o))) if o else None,
            vehicle_rmse_total_m=total["vehicle_rmse_m"],
            object_rmse_total_m=total["object_rmse_m"],
            e2e_latency_ms_p50=float(np.percentile(lat, 50)) if lat else None,
            e2e_latency_ms_p99=float(np.percentile(lat, 99)) if lat else None,
            tx_bytes_per_s={k: sum(n for _, n in q) / span for k, q in sorted(self._tx.items())},
            tx_msgs_per_s={k: len(q) / span for k, q in sorted(self._tx.items())},
            tx_bytes_per_msg={k: sum(n for _, n in q) / len(q) for k, q in sorted(self._tx.items()) if q},
            delivered_fraction=self._delivered_fraction(),
            **self.last,
        )

    def summary(self) -> dict:
        """Whole-run and steady-state figures for the final report (``*_steady``: t_meas >= burnin_s).

        Each of :data:`SCORE_KEYS` comes from :meth:`mapcontainer.evaluation.Totals.summary` (its
        ``coverage`` as ``object_coverage``), once over the whole run and once in steady state
        (named by :func:`steady_name`).
        """
        lat = self._lat_all.values()
        out = {
            "evaluated": self.evaluated,
            "no_truth": self.no_truth,
            "latency_refused": self.latency_refused,
            "sources_refused": self.sources_refused,
            "flagged_first_t": dict(sorted(self.flagged_first.items())),
            "t_meas_last": self.t_meas,
            "burnin_s": self.burnin_s,
            "gospa": {"p": GOSPA_P, "c_m": GOSPA_C_M, "alpha": GOSPA_ALPHA},
        }
        whole, steady = self.totals.summary(), self.totals_steady.summary()
        for key in SCORE_KEYS:
            name = "object_coverage" if key == "coverage" else key
            out[name] = whole[key]
            out[steady_name(name)] = steady[key]
        out.update(
            {
                "e2e_latency_ms_p50": float(np.percentile(lat, 50)) if len(lat) else None,
                "e2e_latency_ms_p99": float(np.percentile(lat, 99)) if len(lat) else None,
                "tx_bytes_total": dict(sorted(self.tx_bytes_total.items())),
                "tx_msgs_total": dict(sorted(self.tx_msgs_total.items())),
                "tx_bytes_per_msg": {k: self.tx_bytes_total[k] / n for k, n in sorted(self.tx_msgs_total.items()) if n},
                "directed_messages_settled": self.sent_total,
                "delivered_fraction": self.delivered_total / self.sent_total if self.sent_total else None,
            }
        )
        return out
