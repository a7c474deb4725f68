"""V2X link model: loss, bandwidth queue, latency and jitter per directed link (docs/architecture.md, "The V2X channel").

A pure core: no I/O, no threads, no clock. Time is always an argument (seconds, any epoch), so the
same :class:`Channel` runs on the simulated clock of ``pipeline.py`` and on wall-clock seconds in the
channel relay service (``send`` on every received message, sleep until ``next_arrival()``, then
``deliver(now)`` and republish). Link parameters are a :class:`NetworkProfile`, one YAML file per
preset in ``configs/network/``.
"""

from __future__ import annotations

import hashlib
import heapq
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from .config import find_preset, list_presets, read_yaml, validate_model

__all__ = [
    "DROP_CAUSES",
    "Channel",
    "Delivery",
    "GilbertElliott",
    "NetworkProfile",
    "list_profiles",
    "load_profile",
]

NonNeg = Annotated[float, Field(ge=0)]
Probability = Annotated[float, Field(ge=0, le=1)]

DROP_CAUSES = ("loss", "queue_full")
"""Reasons a message is dropped, the keys of ``stats()["dropped_msgs"]`` and ``["dropped_bytes"]``."""

_QUEUE_EPS_BYTES = 1e-6  # float slack in the backlog comparison (backlog is derived from times)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class GilbertElliott(_Strict):
    r"""Two-state Markov (Gilbert–Elliott) loss, advanced once per message put on the air.

    In state :math:`s_k \in \{G, B\}` message *k* is lost with probability ``loss_good`` or
    ``loss_bad``; then the state moves G→B with ``p_good_to_bad`` and B→G with ``p_bad_to_good``.

    .. math::
        \pi_B = \frac{p_{GB}}{p_{GB} + p_{BG}}, \qquad
        \bar p = (1 - \pi_B)\, p_G + \pi_B\, p_B, \qquad
        E[\text{bad sojourn}] = 1 / p_{BG} \text{ messages}.
    """

    p_good_to_bad: Probability
    p_bad_to_good: Probability
    loss_good: Probability = 0.0
    loss_bad: Probability = 1.0

    @model_validator(mode="after")
    def _ergodic(self) -> GilbertElliott:
        if self.p_good_to_bad + self.p_bad_to_good <= 0:
            raise ValueError("p_good_to_bad and p_bad_to_good are both 0: the chain never moves")
        return self

    @property
    def p_bad(self) -> float:
        """Stationary probability of the bad state, pi_B."""
        return self.p_good_to_bad / (self.p_good_to_bad + self.p_bad_to_good)

    @property
    def mean_loss(self) -> float:
        """Stationary loss probability (1 - pi_B) loss_good + pi_B loss_bad."""
        return (1.0 - self.p_bad) * self.loss_good + self.p_bad * self.loss_bad


class NetworkProfile(_Strict):
    """Parameters of every link of a V2X channel (configs/network/NAME.yaml; units in the field names).

    All fields but ``name`` have defaults that describe an ideal link, so a profile for a sweep is
    ``NetworkProfile.custom(latency_ms=50, loss=0.1, bandwidth_bps=1e6)``.
    """

    name: str
    description: str = ""
    latency_ms: NonNeg = Field(0.0, description="base one-way latency after serialization (ms)")
    jitter_ms: NonNeg = Field(
        0.0, description="mean extra delay; each message adds U[0, 2*jitter_ms] to latency_ms (ms)"
    )
    loss: Probability = Field(0.0, description="Bernoulli loss probability per message (burst is None)")
    burst: GilbertElliott | None = Field(None, description="Gilbert–Elliott loss instead of `loss`")
    bandwidth_bps: float | None = Field(None, gt=0, description="link capacity (bit/s); None = unlimited")
    queue_bytes: int = Field(65536, gt=0, description="serialization queue bound, tail drop beyond (bytes)")
    duplicate: Probability = Field(0.0, description="probability a delivered message arrives twice")
    shared_medium: bool = Field(False, description="all links share one queue and bandwidth_bps")

    @model_validator(mode="after")
    def _consistent(self) -> NetworkProfile:
        if self.burst is not None and self.loss != 0:
            raise ValueError(
                f"loss={self.loss} is ignored when burst is set; set loss to 0 "
                "(burst.loss_good / burst.loss_bad give the loss)"
            )
        if self.shared_medium and self.bandwidth_bps is None:
            raise ValueError("shared_medium needs a finite bandwidth_bps (an unlimited medium is not shared)")
        return self

    @classmethod
    def custom(cls, name: str = "custom", **fields: Any) -> NetworkProfile:
        """A validated profile from keyword fields (defaults: ideal link); ValueError on bad values."""
        return cls.model_validate({"name": name, **fields})

    @property
    def mean_loss(self) -> float:
        """Expected fraction of messages lost on the air (queue drops not included)."""
        return self.burst.mean_loss if self.burst is not None else self.loss

    @property
    def mean_latency_s(self) -> float:
        """Expected latency after serialization, latency_ms + jitter_ms, in seconds."""
        return (self.latency_ms + self.jitter_ms) / 1000.0


def list_profiles() -> list[str]:
    """Names of the network presets (``network/`` of the built-in and the user's config directories)."""
    return list(list_presets("network"))


def load_profile(name_or_path: str | Path) -> NetworkProfile:
    """A preset by name (configs/network/NAME.yaml) or a YAML file by path; ConfigError on any problem.

    A file without a ``name`` key takes its file name (stem). A file with a ``radio`` section is a
    :class:`~mapcontainer.radio.link.RadioProfile` (a NetworkProfile whose loss the radio model decides).
    """
    path = Path(name_or_path)
    if not path.suffix:
        path = find_preset("network", str(name_or_path), "network profile")
    data = read_yaml(path)
    data.setdefault("name", path.stem)
    if isinstance(data, dict) and "radio" in data:  # a geometric radio profile (mapcontainer.radio)
        from .radio.link import RadioProfile

        return validate_model(RadioProfile, data, path)
    return validate_model(NetworkProfile, data, path)


@dataclass(frozen=True)
class Delivery:
    """One message copy leaving the channel: ``t_sent`` when offered, ``t_arrive`` when received (s)."""

    src: str
    dst: str
    payload: bytes
    t_sent: float
    t_arrive: float
    duplicate: bool = False

    @property
    def latency(self) -> float:
        """Time arrived minus time sent (s), including queueing and serialization."""
        return self.t_arrive - self.t_sent

    @property
    def link(self) -> str:
        return f"{self.src}->{self.dst}"


def _new_counters() -> dict[str, Any]:
    return {
        "offered_msgs": 0,
        "offered_bytes": 0,
        "delivered_msgs": 0,
        "delivered_bytes": 0,
        "duplicated_msgs": 0,
        "duplicated_bytes": 0,
        "dropped_msgs": dict.fromkeys(DROP_CAUSES, 0),
        "dropped_bytes": dict.fromkeys(DROP_CAUSES, 0),
    }


def link_totals(counters: dict[tuple[str, str], dict[str, Any]], heap, total: dict[str, Any]) -> dict[str, Any]:
    """Totals (summed into the zeroed ``total``) and per-link copies (key ``"src->dst"`` under ``"links"``) of
    link counters, each with ``in_flight_*``: the messages of the delivery ``heap`` (entries ``(t, seq,
    Delivery)``) not delivered yet, extra copies excluded."""
    in_flight: dict[tuple[str, str], list[int]] = {}
    for _, _, d in heap:
        if not d.duplicate:
            f = in_flight.setdefault((d.src, d.dst), [0, 0])
            f[0] += 1
            f[1] += len(d.payload)
    total["in_flight_msgs"] = total["in_flight_bytes"] = 0
    links: dict[str, dict[str, Any]] = {}
    for key, counts in counters.items():
        c = {k: dict(v) if isinstance(v, dict) else v for k, v in counts.items()}
        c["in_flight_msgs"], c["in_flight_bytes"] = in_flight.get(key, (0, 0))
        links[f"{key[0]}->{key[1]}"] = c
        for k, v in c.items():
            if isinstance(v, dict):
                for cause, n in v.items():
                    total[k][cause] += n
            else:
                total[k] += v
    total["links"] = links
    return total


class _Server:
    """A FIFO serialization queue at a constant bit rate: only the time it becomes free is needed."""

    __slots__ = ("t_free",)

    def __init__(self) -> None:
        self.t_free = -math.inf


@dataclass
class _Link:
    rng: np.random.Generator
    server: _Server
    bad: bool = False  # Gilbert–Elliott state
    counters: dict[str, Any] = field(default_factory=_new_counters)


def _link_key(seed: int, src: str, dst: str) -> np.random.SeedSequence:
    """A per-link random stream: independent of other links' traffic, stable across runs and Pythons."""
    digest = hashlib.blake2b(f"{src}\x00{dst}".encode(), digest_size=16).digest()
    words = tuple(int.from_bytes(digest[i : i + 4], "little") for i in range(0, 16, 4))
    return np.random.SeedSequence(seed, spawn_key=words)


def checked_offer(src: str, dst: str, payload: bytes, t: float) -> tuple[bytes, float]:
    """A link's offer, checked: (the payload as bytes, the time sent as a finite float); TypeError or
    ValueError for anything else (every channel model's ``send``)."""
    if not isinstance(src, str) or not isinstance(dst, str):
        raise TypeError(f"src and dst must be str, got {type(src).__name__}, {type(dst).__name__}")
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise TypeError(f"payload must be bytes, got {type(payload).__name__}")
    t = float(t)
    if not math.isfinite(t):
        raise ValueError(f"time sent must be finite, got {t}")
    return bytes(payload), t


def pop_arrivals(
    heap: list[tuple[float, int, Delivery]], t: float, counters: Callable[[Delivery], dict[str, int]]
) -> list[Delivery]:
    """Remove and return every message copy in ``heap`` (time arrived, sequence, delivery) with time arrived
    <= t, in arrival order, each counted as delivered (and as duplicated if it is a copy) in ``counters(d)``,
    its link's counters. The one delivery queue of :class:`Channel` and the geometric radio's."""
    out: list[Delivery] = []
    while heap and heap[0][0] <= t:
        d = heapq.heappop(heap)[2]
        c = counters(d)
        n = len(d.payload)
        c["delivered_msgs"] += 1
        c["delivered_bytes"] += n
        if d.duplicate:
            c["duplicated_msgs"] += 1
            c["duplicated_bytes"] += n
        out.append(d)
    return out


class Channel:
    r"""V2X channel emulator: per directed link loss, serialization queue, latency and jitter.

    Message *k* of :math:`b_k` bytes is offered on link :math:`l = (src, dst)` at time sent
    :math:`t_k` (s). With bit rate :math:`R` = ``bandwidth_bps``, queue bound :math:`Q` =
    ``queue_bytes``, and :math:`F_l` the time the link's queue becomes free (one :math:`F` shared by
    all links when ``shared_medium``):

    .. math::
        q(t_k) &= \max(0, F_l - t_k)\, R / 8 \quad\text{(backlog: bytes not yet serialized)}\\
        \text{drop (queue\_full)} &\iff q(t_k) + b_k > Q\\
        t^{tx}_k &= \max(t_k, F_l) + 8 b_k / R, \qquad F_l \leftarrow t^{tx}_k\\
        \text{drop (loss)} &\sim \text{Bernoulli}(p) \text{ or Gilbert–Elliott (see GilbertElliott)}\\
        t^{arr}_k &= t^{tx}_k + L + J_k, \qquad J_k \sim \mathcal{U}[0, 2\sigma_J]

    with :math:`L` = ``latency_ms``/1000 and :math:`\sigma_J` = ``jitter_ms``/1000, so the latency
    after serialization has mean :math:`L + \sigma_J`, standard deviation :math:`\sigma_J/\sqrt3`, and
    is never below :math:`L`. Unlimited bandwidth (``R = None``) means :math:`t^{tx}_k = t_k` and no
    queue. Jitter is drawn per message, so messages overtake one another (reordering).

    A message lost on the air has still used the medium (it was transmitted, not received), so it
    occupies the queue; a queue-full drop never reaches the air and does not advance the
    Gilbert–Elliott chain (which starts in its stationary distribution). With probability ``duplicate``
    a delivered message arrives a second time at :math:`t^{tx}_k + L + J'_k` (independent jitter,
    ``Delivery.duplicate`` set); the copy uses no bandwidth. With ``shared_medium`` every directed
    link is a separate transmission on the one medium (a broadcast to n receivers costs n sends).

    Randomness: each link draws from its own stream seeded by ``(seed, src, dst)`` and every offered
    message consumes the same five uniforms whatever the profile, so runs are reproducible for a seed,
    a link's outcomes do not depend on other links' traffic, and sweeps share random numbers
    (the messages lost at loss=0.1 are a subset of those lost at loss=0.2 for the same seed).

    Counters (``stats()``): every offered message ends as exactly one of dropped (by cause),
    delivered, or in flight, so ``offered = dropped + (delivered - duplicated) + in_flight``.
    """

    def __init__(self, profile: NetworkProfile, seed: int) -> None:
        if not isinstance(profile, NetworkProfile):
            raise TypeError(f"profile must be a NetworkProfile, got {type(profile).__name__}")
        if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        self.profile = profile
        self.seed = int(seed)
        self._rate = profile.bandwidth_bps
        self._latency_s = profile.latency_ms / 1000.0
        self._jitter_span_s = 2.0 * profile.jitter_ms / 1000.0
        self._shared = _Server() if profile.shared_medium else None
        self._links: dict[tuple[str, str], _Link] = {}
        self._heap: list[tuple[float, int, Delivery]] = []
        self._seq = 0

    # -- link state -------------------------------------------------------------------------------

    def _link(self, src: str, dst: str) -> _Link:
        link = self._links.get((src, dst))
        if link is None:
            rng = np.random.default_rng(_link_key(self.seed, src, dst))
            burst = self.profile.burst
            u_state = rng.random()  # drawn for every profile, so streams line up across profiles
            bad = bool(burst is not None and u_state < burst.p_bad)
            server = self._shared if self._shared is not None else _Server()
            link = _Link(rng=rng, server=server, bad=bad)
            self._links[(src, dst)] = link
        return link

    def backlog_bytes(self, t: float, src: str | None = None, dst: str | None = None) -> float:
        """Bytes not yet serialized at time t on link src->dst (on the medium when shared)."""
        if self._rate is None:
            return 0.0
        if self._shared is not None:
            server = self._shared
        else:
            link = self._links.get((src, dst))  # type: ignore[arg-type]
            if link is None:
                return 0.0
            server = link.server
        return max(0.0, server.t_free - t) * self._rate / 8.0

    # -- the channel ------------------------------------------------------------------------------

    def send(self, src: str, dst: str, payload: bytes, t: float) -> bool:
        """Offer ``payload`` on link src->dst at time sent ``t`` (s).

        Returns False if it is dropped now (cause "loss" or "queue_full"), True if it is in flight;
        it leaves through :meth:`deliver`.
        """
        payload, t = checked_offer(src, dst, payload, t)
        nbytes = len(payload)
        link = self._link(src, dst)
        c = link.counters
        c["offered_msgs"] += 1
        c["offered_bytes"] += nbytes
        # always five uniforms per message: loss, GE transition, jitter, duplicate, duplicate's jitter
        u_loss, u_move, u_jit, u_dup, u_jit2 = link.rng.random(5)

        # serialization queue (FIFO, work-conserving, constant rate)
        t_tx = t
        if self._rate is not None:
            server = link.server
            backlog = max(0.0, server.t_free - t) * self._rate / 8.0
            if backlog + nbytes > self.profile.queue_bytes + _QUEUE_EPS_BYTES:
                return self._drop(c, "queue_full", nbytes)
            t_tx = max(t, server.t_free) + nbytes * 8.0 / self._rate
            server.t_free = t_tx

        # loss on the air
        burst = self.profile.burst
        if burst is None:
            lost = u_loss < self.profile.loss
        else:
            lost = u_loss < (burst.loss_bad if link.bad else burst.loss_good)
            link.bad = (u_move >= burst.p_bad_to_good) if link.bad else (u_move < burst.p_good_to_bad)
        if lost:
            return self._drop(c, "loss", nbytes)

        t_base = t_tx + self._latency_s
        self._push(Delivery(src, dst, payload, t, t_base + u_jit * self._jitter_span_s, False))
        if u_dup < self.profile.duplicate:
            self._push(Delivery(src, dst, payload, t, t_base + u_jit2 * self._jitter_span_s, True))
        return True

    def _drop(self, counters: dict[str, Any], cause: str, nbytes: int) -> bool:
        counters["dropped_msgs"][cause] += 1
        counters["dropped_bytes"][cause] += nbytes
        return False

    def _push(self, d: Delivery) -> None:
        heapq.heappush(self._heap, (d.t_arrive, self._seq, d))  # seq: ties leave in send order
        self._seq += 1

    def deliver(self, t: float) -> list[Delivery]:
        """Remove and return every message copy with time arrived <= t, in arrival order."""
        return pop_arrivals(self._heap, t, lambda d: self._links[(d.src, d.dst)].counters)

    def next_arrival(self) -> float | None:
        """Earliest pending time arrived (s), or None when nothing is in flight."""
        return self._heap[0][0] if self._heap else None

    def __len__(self) -> int:
        """Message copies in flight (duplicates included)."""
        return len(self._heap)

    # -- counters ---------------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        """Counters, totals and per link (key ``"src->dst"`` under ``"links"``).

        ``offered_*``: messages given to :meth:`send`; ``delivered_*``: copies returned by
        :meth:`deliver` (duplicates included); ``duplicated_*``: the extra copies among them;
        ``dropped_*``: by cause {"loss", "queue_full"}; ``in_flight_*``: offered messages not yet
        delivered (extra copies excluded). Bytes are payload bytes.
        """
        return link_totals({key: link.counters for key, link in self._links.items()}, self._heap, _new_counters())

    def reset_stats(self) -> None:
        """Zero the counters (link state, queues and messages in flight are kept).

        Messages in flight at the reset are counted as delivered later but not as offered, so the
        balance in the class docstring holds across a reset only if the channel was empty.
        """
        for link in self._links.values():
            link.counters = _new_counters()
