r"""The geometric V2X link: a :class:`RadioChannel` with the :class:`~mapcontainer.channel.Channel` interface.

Pure core (no I/O, no clock, time an argument), used alike by the in-process pipeline and the channel
relay service. Where the vehicles are comes from :meth:`RadioChannel.observe` (the world's truth:
connected vehicles, which send, and the other vehicles, which block and, with
``background_rate_hz``, transmit CAM-like traffic that loads the medium). Every message put on the air
by :meth:`RadioChannel.send` (one transmission however many receivers it is offered to: a broadcast)
is received, or not, by each receiver as :mod:`~.propagation`, :mod:`~.obstacles`, :mod:`~.phy` and
:mod:`~.mac` say:

.. math::
    P_{r} = P_t - PL(d, \text{state}) - L_{v} - S, \qquad
    \text{delivered} \iff P_r \ge P_{sen} \wedge u_1 \ge PER(P_r - N) \wedge \text{no destructive overlap}

and arrives after the access delay (802.11p: back-off and air time; C-V2X: the wait for the reserved
subframe) plus the profile's ``latency_ms`` and jitter (processing above the radio). Drops are
counted by radio cause (``dcc``, ``sensing``, ``propagation``, ``collision``, ``half_duplex``) and, summed, as
the link model's ``loss`` cause. Per-message uniforms are counter-based hashes of (seed, directed
link, message count on that link), so a run is reproducible and a link's fate does not depend on
other links' traffic order.

A receiver that is not a vehicle (the host container) is placed at a vehicle with :meth:`place`
(the container runs on the ego). A message from or to a node whose position is unknown is delivered
on the base latency alone and counted as ``unlocated`` (the relay before the first truth message).
"""

from __future__ import annotations

import heapq
from collections import deque
from collections.abc import Mapping
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from ..channel import Delivery, NetworkProfile, checked_offer, link_totals, pop_arrivals
from .dcc import DccParams, ReactiveDcc
from .hashing import directed_keys, link_keys, node_key, uniforms
from .mac import Csma, MacParams, Sps, airtime_s
from .obstacles import Buildings, vehicle_blocked
from .phy import PhyParams, noise_dbm, per, to_mw
from .propagation import LOS, NLOS, NLOSV, PropagationParams, Shadowing, mean_path_loss_db, nlosv_loss_db

__all__ = ["RADIO_CAUSES", "RadioChannel", "RadioParams", "RadioProfile", "make_channel"]

RADIO_CAUSES = ("dcc", "sensing", "propagation", "collision", "half_duplex")


class RadioParams(BaseModel):
    """The geometric radio model of a profile (``radio:`` in configs/network/NAME.yaml)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    propagation: PropagationParams = PropagationParams()
    phy: PhyParams = PhyParams()
    mac: MacParams = MacParams()
    dcc: DccParams = Field(DccParams(), description="ETSI reactive DCC on every sender (off unless enabled)")
    buildings: bool = Field(True, description="NLOS behind the map's buildings (obstacles.Buildings.from_map)")
    building_file: str | None = Field(
        None, description="a SUMO additional file whose 'building' polygons are the buildings (instead of the map's)"
    )
    building_cell_m: float = Field(1.0, gt=0)
    building_setback_m: float = Field(2.0, ge=0, description="open ground beyond road and sidewalk edges")
    vehicle_blockage: bool = Field(True, description="NLOSv behind other vehicles")
    vehicle_half_width_m: float = Field(0.9, gt=0)
    background_rate_hz: float = Field(0.0, ge=0, description="messages/s each non-connected vehicle sends")
    background_bytes: int = Field(300, ge=1, description="size of those messages (a CAM with certificate)")


class RadioProfile(NetworkProfile):
    """A network profile whose loss comes from the radio model; ``latency_ms``/``jitter_ms`` are the
    processing delay above the radio (the access delay is the model's)."""

    radio: RadioParams = RadioParams()

    @model_validator(mode="after")
    def _radio_decides(self) -> RadioProfile:
        if (
            self.loss
            or self.burst is not None
            or self.bandwidth_bps is not None
            or self.shared_medium
            or self.duplicate
        ):
            raise ValueError(
                "a radio profile takes its loss, capacity and contention from the radio model: "
                "loss, burst, bandwidth_bps, shared_medium and duplicate must be left at their defaults"
            )
        return self


def make_channel(profile: NetworkProfile, seed: int, hdmap=None):
    """The channel for a profile: a :class:`RadioChannel` (with the map's buildings) for a radio
    profile, else the classic :class:`~mapcontainer.channel.Channel`."""
    if isinstance(profile, RadioProfile):
        r = profile.radio
        b = None
        if r.buildings and r.building_file is not None:
            b = Buildings.from_sumo(r.building_file, cell_m=r.building_cell_m)
        elif r.buildings and hdmap is not None:
            b = Buildings.from_map(hdmap, cell_m=r.building_cell_m, setback_m=r.building_setback_m)
        return RadioChannel(profile, seed, b)
    from ..channel import Channel

    return Channel(profile, seed)


def _new_counters() -> dict[str, Any]:
    return {
        "offered_msgs": 0,
        "offered_bytes": 0,
        "delivered_msgs": 0,
        "delivered_bytes": 0,
        "duplicated_msgs": 0,
        "duplicated_bytes": 0,
        "unlocated_msgs": 0,
        "dropped_msgs": {"loss": 0, "queue_full": 0},
        "dropped_bytes": {"loss": 0, "queue_full": 0},
        "radio_drops": dict.fromkeys(RADIO_CAUSES, 0),
        "radio_drop_bytes": dict.fromkeys(RADIO_CAUSES, 0),
    }


class RadioChannel:
    """Geometric V2X channel (module docstring): ``observe`` positions, then ``send``/``deliver``."""

    def __init__(self, profile: RadioProfile, seed: int, buildings: Buildings | None = None) -> None:
        if not isinstance(profile, RadioProfile):
            raise TypeError(f"profile must be a RadioProfile, got {type(profile).__name__}")
        if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        self.profile = profile
        self.radio = r = profile.radio
        self.seed = int(seed)
        self.buildings = buildings if buildings is not None else Buildings.empty()
        self.shadowing = Shadowing(r.propagation, seed)
        self.noise_mw = float(to_mw(noise_dbm(r.phy)))
        self.mac: Csma | Sps = Csma(r.mac, r.phy) if r.mac.access == "csma" else Sps(r.mac, r.phy, seed)
        self._latency_s = profile.latency_ms / 1000.0
        self._jitter_span_s = 2.0 * profile.jitter_ms / 1000.0
        self._places: dict[str, str] = {}
        self._pos: dict[str, np.ndarray] = {}
        self._prev: dict[str, np.ndarray] = {}
        self._background: set[str] = set()
        self._bg_last: dict[str, float] = {}
        self.names: list[str] = []
        self._index: dict[str, int] = {}
        self.power_dbm = np.zeros((0, 0))
        self.state = np.zeros((0, 0), dtype=np.int8)
        self._rate = np.zeros(0)
        self._air = np.zeros(0)
        self._cbr = np.zeros(0)
        self._tx_log: deque[tuple[float, str, float]] = deque()
        self._t0: float | None = None
        self._last_tx: dict[str, tuple] = {}
        self._dcc: dict[str, ReactiveDcc] = {}
        self._keys: dict[str, int] = {}
        self._msg_n: dict[tuple[str, str], int] = {}
        self._links: dict[tuple[str, str], dict[str, Any]] = {}
        self._heap: list[tuple[float, int, Delivery]] = []
        self._seq = 0
        self._cbr_acc: dict[str, list] = {}  # connected vehicle -> [sum, count, max] of its CBR samples
        self.state_counts = {"los": 0, "nlosv": 0, "nlos": 0}

    # -- geometry -----------------------------------------------------------------------------------

    def place(self, receiver: str, node: str) -> None:
        """Receiver ``receiver`` (e.g. "host") sits at vehicle ``node`` (its on-board messages need no radio)."""
        self._places[receiver] = node

    def observe(self, t: float, nodes: Mapping[str, Any], others: Mapping[str, Any] | None = None) -> None:
        """Positions (map x, y) at ``t`` of the connected vehicles ``nodes`` and the other vehicles ``others``."""
        others = dict(others or {})
        pos = {k: np.asarray(v, float).reshape(-1)[:2] for k, v in nodes.items()}
        opos = {k: np.asarray(v, float).reshape(-1)[:2] for k, v in others.items() if k not in pos}
        self._background = set(opos) if self.radio.background_rate_hz > 0 else set()
        senders = {**pos, **{k: opos[k] for k in opos if k in self._background}}
        self._prev = {k: self._pos.get(k, p) for k, p in senders.items()}
        self._pos = senders
        self.names = list(senders)
        self._index = {n: i for i, n in enumerate(self.names)}
        vehicles = [senders[nm] for nm in self.names] + [p for k, p in opos.items() if k not in self._background]
        self._geometry(np.array([senders[nm] for nm in self.names]).reshape(-1, 2), np.array(vehicles).reshape(-1, 2))
        self._background_traffic(t)
        self._update_load(t)
        for n in pos:  # running sums: the relay runs for hours
            c = float(self._cbr[self._index[n]])
            acc = self._cbr_acc.setdefault(n, [0.0, 0, 0.0])
            acc[0] += c
            acc[1] += 1
            acc[2] = max(acc[2], c)

    def observe_truth(self, truth, t: float | None = None) -> None:
        """:meth:`observe` from a :class:`schemas.GroundTruth` at ``t`` (default its ``t_meas``; the relay
        passes its own clock): its connected vehicles send, its obstacles of class vehicle block (and send
        background traffic); pedestrians do neither."""
        from schemas import ObjectClass

        nodes = {v: np.asarray(p[:2], float) for v, p in zip(truth.vehicle_ids, truth.vehicle_pose, strict=True)}
        is_vehicle = np.asarray(truth.obstacle_cls) == int(ObjectClass.VEHICLE)
        others = {
            str(int(i)): np.asarray(p[:2], float)
            for i, p, v in zip(truth.obstacle_id, truth.obstacle_p_map, is_vehicle, strict=True)
            if v
        }
        self.observe(float(truth.t_meas) if t is None else float(t), nodes, others)

    def _geometry(self, p: np.ndarray, vehicles: np.ndarray) -> None:
        r = self.radio
        n = len(p)
        self.power_dbm = np.full((n, n), r.phy.tx_power_dbm)
        self.state = np.zeros((n, n), dtype=np.int8)
        if n < 2:
            return
        iu, ju = np.triu_indices(n, 1)
        a, b = p[iu], p[ju]
        d = np.maximum(np.hypot(*(b - a).T), 0.1)
        state = np.full(len(d), LOS, dtype=np.int8)
        if r.vehicle_blockage and len(vehicles):
            # `vehicles` lists the senders first, in the order of `names`: a link's ends are not its blockers
            ends = np.arange(n)
            state[vehicle_blocked(a, b, ends[iu], ends[ju], vehicles, r.vehicle_half_width_m)] = NLOSV
        if r.buildings and self.buildings.mask.any():
            state[self.buildings.crossed_m(a, b) > 0] = NLOS
        nk = np.array([self._node_key(nm) for nm in self.names], dtype=np.uint64)
        keys = link_keys(nk[iu], nk[ju])
        moved = np.array([np.hypot(*(self._pos[self.names[i]] - self._prev[self.names[i]])) for i in range(n)])
        shadow = self.shadowing.update(keys, moved[iu] + moved[ju], state)
        loss = mean_path_loss_db(r.propagation, d, state) + shadow
        v = state == NLOSV
        if v.any():
            loss[v] += nlosv_loss_db(r.propagation, d[v], uniforms(self.seed, keys[v], 0, lane=7))
        self.power_dbm[iu, ju] = self.power_dbm[ju, iu] = r.phy.tx_power_dbm - loss
        self.state[iu, ju] = self.state[ju, iu] = state
        for code, name in ((LOS, "los"), (NLOSV, "nlosv"), (NLOS, "nlos")):
            self.state_counts[name] += int((state == code).sum())

    def _background_traffic(self, t: float) -> None:
        rate = self.radio.background_rate_hz
        for name in self._background:
            last = self._bg_last.get(name)
            if last is None or t - last >= 1.0 / rate - 1e-9:
                self._bg_last[name] = t
                self._register(name, ("bg", t), self.radio.background_bytes, t)

    def _register(self, src: str, key: tuple, nbytes: int, t: float) -> dict | None:
        """One transmission of ``src`` on the air (a broadcast, whatever the number of receivers); None
        if the sender's DCC gate refuses it."""
        last = self._last_tx.get(src)
        if last is not None and last[0] == key:
            return last[1]
        if self.radio.dcc.enabled and not self._dcc_for(src).allow(t):
            self._last_tx[src] = (key, None)
            return None
        air = float(airtime_s(nbytes, self.radio.phy.data_rate_bps))
        info: dict[str, Any] = {"air": air, "t": t}
        if isinstance(self.mac, Sps):
            info["res"] = self.mac.transmit(src, nbytes, t, self.names, self.power_dbm)
            info["air"] = 1e-3
        self._tx_log.append((t, src, info["air"]))
        self._last_tx[src] = (key, info)
        return info

    def _node_key(self, name: str) -> int:
        k = self._keys.get(name)
        if k is None:
            k = self._keys[name] = node_key(name)
        return k

    def _dcc_for(self, node: str) -> ReactiveDcc:
        d = self._dcc.get(node)
        if d is None:
            d = self._dcc[node] = ReactiveDcc(self.radio.dcc)
        return d

    def dcc_states(self) -> dict[str, int]:
        """Each sender's DCC state (0 = Relaxed) at the last observation (empty without DCC)."""
        return {n: d.state for n, d in self._dcc.items()}

    def _update_load(self, t: float) -> None:
        w = self.radio.mac.rate_window_s
        while self._tx_log and self._tx_log[0][0] < t - w - 1e-9:
            self._tx_log.popleft()
        n = len(self.names)
        count, air = np.zeros(n), np.zeros(n)
        for t_tx, src, a in self._tx_log:  # the window [t - w, t): this instant's sends are not in yet
            i = self._index.get(src)
            if i is not None and t_tx < t - 1e-9:
                count[i] += 1
                air[i] += a
        self._air = np.where(count > 0, air / np.maximum(count, 1), 0.0)
        if self._t0 is None:
            self._t0 = t
        span = min(w, t - self._t0)  # a run younger than the window: its own length
        self._rate = count / span if span > 0 else count * 0.0
        if isinstance(self.mac, Csma):
            self._cbr = self.mac.cbr(self.power_dbm, self._rate, self._air) if n else np.zeros(0)
        else:
            self._cbr = self.mac.cbr(self.names, self.power_dbm, t) if n else np.zeros(0)
        if self.radio.dcc.enabled:
            for i, name in enumerate(self.names):
                self._dcc_for(name).update(t, float(self._cbr[i]))

    # -- the channel ------------------------------------------------------------------------------

    def _link(self, src: str, dst: str) -> dict[str, Any]:
        c = self._links.get((src, dst))
        if c is None:
            c = self._links[(src, dst)] = _new_counters()
        return c

    def on_air(self, src: str, payload: bytes, t: float) -> None:
        """A transmission of ``src`` that no modelled receiver is offered (it still loads the medium)."""
        if src in self._index:
            self._register(src, (float(t), len(payload), hash(bytes(payload))), len(payload), float(t))

    def send(self, src: str, dst: str, payload: bytes, t: float) -> bool:
        """Offer ``payload`` from ``src`` to ``dst`` at ``t`` (s); False if it is lost, True if in flight."""
        payload, t = checked_offer(src, dst, payload, t)
        nbytes = len(payload)
        c = self._link(src, dst)
        c["offered_msgs"] += 1
        c["offered_bytes"] += nbytes
        m = self._msg_n.get((src, dst), 0)
        self._msg_n[(src, dst)] = m + 1
        key = directed_keys(self._node_key(src), self._node_key(dst))
        u = uniforms(self.seed, key, m, np.arange(4)).tolist()  # lanes: PER, collision, back-off, jitter
        rx = self._places.get(dst, dst)
        i, j = self._index.get(src), self._index.get(rx)
        if i is None or j is None:
            c["unlocated_msgs"] += 1
            return self._push(src, dst, payload, t, t, u[3])
        if i == j:
            return self._push(src, dst, payload, t, t, u[3])
        info = self._register(src, (t, nbytes, hash(payload)), nbytes, t)
        if info is None:
            return self._drop(c, "dcc", nbytes)
        phy = self.radio.phy
        pr = float(self.power_dbm[i, j])
        if pr < phy.sensing_dbm:
            return self._drop(c, "sensing", nbytes)
        per0 = float(per(phy, pr - 10 * np.log10(self.noise_mw)))
        if u[0] < per0:
            return self._drop(c, "propagation", nbytes)
        if isinstance(self.mac, Csma):
            ok = self.mac.collision_free(i, j, self.power_dbm, self._rate, self._air, self._cbr, self.noise_mw)
            if u[1] >= ok:
                return self._drop(c, "collision", nbytes)
            t_tx = t + self.mac.access_delay_s(u[2], info["air"], float(self._cbr[i]))
        else:
            res = info["res"]
            co, same = self.mac.interferers(src, res, t)
            if rx in same:
                return self._drop(c, "half_duplex", nbytes)
            ks = [self._index[k] for k in co if k in self._index]
            if ks:
                sinr = pr - 10 * np.log10(self.noise_mw + to_mw(self.power_dbm[ks, j]).sum())
                p_int = (float(per(phy, sinr)) - per0) / (1.0 - per0)
                if u[1] < p_int:
                    return self._drop(c, "collision", nbytes)
            t_tx = t + self.mac.delay_s(res, t)
        return self._push(src, dst, payload, t, t_tx, u[3])

    def _drop(self, c: dict[str, Any], cause: str, nbytes: int) -> bool:
        c["radio_drops"][cause] += 1
        c["radio_drop_bytes"][cause] += nbytes
        c["dropped_msgs"]["loss"] += 1
        c["dropped_bytes"]["loss"] += nbytes
        return False

    def _push(self, src: str, dst: str, payload: bytes, t: float, t_tx: float, u_jit: float) -> bool:
        d = Delivery(src, dst, payload, t, t_tx + self._latency_s + u_jit * self._jitter_span_s, False)
        heapq.heappush(self._heap, (d.t_arrive, self._seq, d))
        self._seq += 1
        return True

    def deliver(self, t: float) -> list[Delivery]:
        """Remove and return every message with time arrived <= t, in arrival order."""
        return pop_arrivals(self._heap, t, lambda d: self._links[(d.src, d.dst)])

    def next_arrival(self) -> float | None:
        return self._heap[0][0] if self._heap else None

    def __len__(self) -> int:
        return len(self._heap)

    # -- figures ----------------------------------------------------------------------------------

    def cbr(self) -> dict[str, float]:
        """The latest CBR per transmitting node (background vehicles included)."""
        return {n: float(self._cbr[i]) for i, n in enumerate(self.names)} if len(self._cbr) == len(self.names) else {}

    def stats(self) -> dict[str, Any]:
        """The classic channel's counters (radio drops summed as ``loss``) plus ``radio_drops`` by cause,
        ``unlocated_msgs``, ``cbr`` per connected vehicle (mean and max over observations) and
        ``link_states`` (pair-observations that were LOS / NLOSv / NLOS)."""
        total = link_totals(self._links, self._heap, _new_counters())
        total["cbr"] = {n: {"mean": a[0] / a[1], "max": a[2]} for n, a in self._cbr_acc.items() if a[1]}
        total["link_states"] = dict(self.state_counts)
        if self.radio.dcc.enabled:
            total["dcc_gated"] = {n: d.gated for n, d in self._dcc.items() if n in self._cbr_acc}
        return total

    def reset_stats(self) -> None:
        for key in self._links:
            self._links[key] = _new_counters()
        self._cbr_acc = {}
        self.state_counts = {"los": 0, "nlosv": 0, "nlos": 0}
