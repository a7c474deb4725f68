r"""Medium access: who else is on the air when a packet is, and the channel busy ratio (CBR).

Two access schemes (``access`` of :class:`MacParams`):

**802.11p CSMA/CA (analytical)** — :class:`Csma`. Transmitter *k* sends :math:`\lambda_k` packets per
second (measured over the last ``rate_window_s``) of air time :math:`T_k = 40\,\mu s + 8(B_k + H)/R`
(preamble and signal field, then the bytes with H = 30 bytes of MAC/LLC headers at the data rate R;
IEEE 802.11-2012 §18.4.3, as in Sepulcre et al. 2021). For a packet from *i* received by *j*, every
other transmitter *k* overlaps it with probability

.. math::
    p^{ov}_k = \begin{cases}
      1 - e^{-\lambda_k \sigma / (1 - \mathrm{CBR}_k)} & k \text{ senses } i \ (P_{ki} \ge P_{sen}):
        \text{both leave backoff in the same slot } \sigma = 13\,\mu s\\
      1 - e^{-\lambda_k (T_i + T_k)} & k \text{ is hidden from } i: \text{ALOHA-like vulnerable window}
    \end{cases}

(Poisson packet starts; the sensed case follows Sepulcre et al. 2021 eq. (22), the hidden case their
eq. (18) with the two-sided window of unslotted ALOHA). An overlap destroys the packet with the
excess error rate of their eq. (31), :math:`p^{int}_k = (PER(\mathrm{SINR}_k) - PER_0)/(1 - PER_0)`,
so the packet survives collisions with probability :math:`\prod_k (1 - p^{ov}_k p^{int}_k)`
(their eq. (26)). The receiver-busy error (*j* locked on another packet) is folded into the hidden
window; the exponential back-off's growth under load is not modelled. Access delay:
:math:`(AIFS + U[0, CW]\,\sigma)/(1 - \mathrm{CBR}_i) + T_i` with AIFS = 110 µs and CW = 15 (AC_BE,
ETSI EN 302 663): a busy medium freezes the back-off.

CBR at *j* (ETSI TS 102 687: the fraction of time the medium is sensed busy at -85 dBm) is
Sepulcre et al.'s eq. (34), :math:`\mathrm{CBR}_j = \min(1, \sum_k \lambda_k T_k [P_{kj} \ge P_{sen}])`
(own packets included): the load before overlaps are merged, an upper bound of the measured value.

**C-V2X sidelink mode 4 (simulated SPS)** — :class:`Sps`. The pool has :math:`N_{sf}` = RRI / 1 ms
subframes of ``subchannels`` sub-channels. Each transmitter reserves a subframe and a run of
sub-channels wide enough for its packet, and keeps it for a reselection counter drawn uniform in
[5, 15] transmissions (3GPP TS 36.321 §5.14.1.1, RRI = 100 ms); at 0 it keeps the reservation with
probability ``keep_probability``, else reselects (TS 36.213 §14.1.1.6): candidates reserved by a
transmitter it decodes with RSRP above ``rsrp_threshold_dbm`` (RSRP: the received power per resource
element, :math:`P - 10\log_{10}(12 \cdot \mathrm{RBs})`) are excluded, the threshold rising by 3 dB
until at least 20 % remain, then a candidate is drawn among the 20 % with the lowest sensed power
(S-RSSI). A packet waits for its reserved subframe; receivers that transmit in the same subframe lose it
(half duplex); packets on overlapping sub-channels of the same subframe add their power to the
interference (co-channel; the in-band emission of adjacent sub-channels is not modelled).
CBR at *j* (3GPP TS 36.214 §5.1.30): the fraction of sub-channels of the last RRI whose received
power exceeds ``cbr_rssi_dbm``.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .hashing import node_key, uniforms
from .phy import PhyParams, per, to_mw

__all__ = ["Csma", "MacParams", "Sps", "airtime_s"]

SLOT_S = 13e-6
CW_MIN = 15
HEADER_BYTES = 30
PREAMBLE_S = 40e-6
SUBFRAME_S = 1e-3


class MacParams(BaseModel):
    """Medium access parameters (units in the names; sources in the module docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    access: Literal["csma", "sps"] = "csma"
    rate_window_s: float = Field(1.0, gt=0, description="window of the measured transmit rates and CBR")
    aifs_s: float = Field(110e-6, ge=0, description="802.11p AIFS: 32 us + AIFSN 6 x 13 us (AC_BE, ETSI EN 302 663)")
    cw: int = Field(CW_MIN, ge=0, description="802.11p contention window (slots)")
    subchannels: int = Field(4, ge=1, le=20, description="SPS: sub-channels in the pool")
    subchannel_bytes: int = Field(190, ge=16, description="SPS: payload bytes one sub-channel carries")
    rri_s: float = Field(0.1, gt=0, description="SPS: resource reservation interval")
    keep_probability: float = Field(0.0, ge=0, le=0.8, description="SPS: P(keep) at reselection")
    rsrp_threshold_dbm: float = Field(-110.0, description="SPS: exclusion threshold on decoded reservations")
    rbs_per_subchannel: int = Field(10, ge=1, description="SPS: RBs of a sub-channel (RSRP per resource element)")
    cbr_rssi_dbm: float = Field(-94.0, description="SPS: a sub-channel is busy above this received power")


def airtime_s(nbytes: np.ndarray, rate_bps: float) -> np.ndarray:
    """802.11p frame duration: 40 us preamble and signal field, then (bytes + 30 header bytes) at the rate."""
    return PREAMBLE_S + 8.0 * (np.asarray(nbytes, dtype=float) + HEADER_BYTES) / rate_bps


class Csma:
    """802.11p CSMA/CA, analytical (module docstring). Pure: the caller supplies powers and rates."""

    def __init__(self, mac: MacParams, phy: PhyParams) -> None:
        self.mac, self.phy = mac, phy

    def cbr(self, power_dbm: np.ndarray, rate_hz: np.ndarray, air_s: np.ndarray) -> np.ndarray:
        """CBR per node from the received-power matrix ``power_dbm[k, j]`` (diagonal: own packets)."""
        sensed = power_dbm >= self.phy.sensing_dbm
        np.fill_diagonal(sensed, True)
        return np.minimum(1.0, (rate_hz * air_s) @ sensed)

    def access_delay_s(self, u: float, air_s: float, cbr: float) -> float:
        return (self.mac.aifs_s + u * self.mac.cw * SLOT_S) / max(1e-3, 1.0 - cbr) + air_s

    def collision_free(
        self,
        i: int,
        j: int,
        power_dbm: np.ndarray,
        rate_hz: np.ndarray,
        air_s: np.ndarray,
        cbr: np.ndarray,
        noise_mw: float,
    ) -> float:
        """P(no destructive overlap) for a packet i -> j, given it is detected (SEN passed)."""
        n = len(rate_hz)
        k = np.arange(n)
        others = (k != i) & (k != j) & (rate_hz > 0)
        if not others.any():
            return 1.0
        k = k[others]
        pr = power_dbm[i, j]
        per0 = float(per(self.phy, pr - 10 * np.log10(noise_mw)))
        if per0 >= 1.0:
            return 1.0
        sinr = pr - 10 * np.log10(noise_mw + to_mw(power_dbm[k, j]))
        p_int = np.clip((per(self.phy, sinr) - per0) / (1.0 - per0), 0.0, 1.0)
        senses = power_dbm[k, i] >= self.phy.sensing_dbm
        lam = rate_hz[k]
        p_ov = np.where(
            senses,
            1.0 - np.exp(-lam * SLOT_S / np.maximum(1e-3, 1.0 - cbr[k])),
            1.0 - np.exp(-lam * (air_s[i] + air_s[k])),
        )
        return float(np.prod(1.0 - p_ov * p_int))


class Sps:
    """C-V2X mode 4 semi-persistent scheduling, simulated per transmission (module docstring)."""

    def __init__(self, mac: MacParams, phy: PhyParams, seed: int) -> None:
        self.mac, self.phy, self.seed = mac, phy, int(seed)
        self.n_sf = max(1, int(round(mac.rri_s / SUBFRAME_S)))
        self.res: dict[str, tuple[int, int, int]] = {}  # node -> (subframe, first sub-channel, width)
        self.counter: dict[str, int] = {}
        self.draws: dict[str, int] = {}
        self.last_tx: dict[str, float] = {}

    def width(self, nbytes: int) -> int:
        return int(min(self.mac.subchannels, max(1, -(-int(nbytes) // self.mac.subchannel_bytes))))

    def _u(self, node: str, lane: int) -> float:
        c = self.draws.get(node, 0)
        self.draws[node] = c + 1
        return float(uniforms(self.seed, node_key(node), c, lane)[0])

    def _active(self, t: float) -> list[str]:
        return [n for n, tl in self.last_tx.items() if t - tl <= self.mac.rri_s * 1.5]

    def transmit(
        self, node: str, nbytes: int, t: float, names: list[str], power_dbm: np.ndarray
    ) -> tuple[int, int, int]:
        """The resource ``node`` uses for a packet offered at ``t`` (reselecting when its counter ran out)."""
        w = self.width(nbytes)
        res = self.res.get(node)
        if res is None or self.counter.get(node, 0) <= 0 or res[2] != w:
            if res is None or res[2] != w or self._u(node, 1) >= self.mac.keep_probability:
                res = self._select(node, w, t, names, power_dbm)
            self.counter[node] = 5 + int(self._u(node, 2) * 11)
            self.res[node] = res
        self.counter[node] -= 1
        self.last_tx[node] = t
        return res

    def _select(self, node: str, w: int, t: float, names: list[str], power_dbm: np.ndarray) -> tuple[int, int, int]:
        s_count = self.mac.subchannels - w + 1
        rssi = np.zeros((self.n_sf, self.mac.subchannels))  # mW sensed per (subframe, sub-channel)
        rsrp = np.full((self.n_sf, s_count), -np.inf)  # strongest decoded reservation over each candidate
        index = {n: i for i, n in enumerate(names)}
        me = index.get(node)
        if me is not None:
            for other in self._active(t):
                k = index.get(other)
                if k is None or other == node or other not in self.res:
                    continue
                p = power_dbm[k, me]
                sf, c0, wk = self.res[other]
                rssi[sf, c0 : c0 + wk] += to_mw(p)
                if p >= self.phy.sensing_dbm:  # its SCI is decoded: its reservation is known
                    r = p - 10 * np.log10(12 * self.mac.rbs_per_subchannel)
                    lo, hi = max(0, c0 - w + 1), min(s_count, c0 + wk)
                    rsrp[sf, lo:hi] = np.maximum(rsrp[sf, lo:hi], r)
        cand_rssi = np.stack([rssi[:, c : c + w].sum(axis=1) for c in range(s_count)], axis=1)
        th = self.mac.rsrp_threshold_dbm
        total = rsrp.size
        while (ok := rsrp < th).sum() < 0.2 * total:
            th += 3.0
        flat = np.flatnonzero(ok.ravel())
        tie = uniforms(self.seed, node_key(node), np.arange(total) + total * self.draws.get(node, 0), 4)
        order = flat[np.lexsort((tie[flat], cand_rssi.ravel()[flat]))]  # lowest S-RSSI first, ties at random
        best = order[: max(1, int(np.ceil(0.2 * total)))]
        pick = int(best[min(len(best) - 1, int(self._u(node, 3) * len(best)))])
        return (pick // s_count, pick % s_count, w)

    def delay_s(self, res: tuple[int, int, int], t: float) -> float:
        """From ``t`` to the end of the reserved subframe's next occurrence."""
        start = res[0] * SUBFRAME_S
        return (start - t) % self.mac.rri_s + SUBFRAME_S

    def interferers(self, src: str, res: tuple[int, int, int], t: float) -> tuple[list[str], list[str]]:
        """(co-channel interferers, same-subframe transmitters) of a packet of ``src`` on ``res``."""
        co, same = [], []
        for other in self._active(t):
            if other == src or other not in self.res:
                continue
            sf, c0, w = self.res[other]
            if sf == res[0]:
                same.append(other)
                if c0 < res[1] + res[2] and res[1] < c0 + w:
                    co.append(other)
        return co, same

    def cbr(self, names: list[str], power_dbm: np.ndarray, t: float) -> np.ndarray:
        """CBR per node of ``names``: busy sub-channels of the last RRI over all of them."""
        n = len(names)
        index = {nm: i for i, nm in enumerate(names)}
        grid = np.zeros((n, self.n_sf, self.mac.subchannels))
        for other in self._active(t):
            k = index.get(other)
            if k is None or other not in self.res:
                continue
            sf, c0, w = self.res[other]
            p = to_mw(power_dbm[k])
            p[k] = np.inf  # own transmission: busy
            grid[:, sf, c0 : c0 + w] += p[:, None]
        return (grid > to_mw(self.mac.cbr_rssi_dbm)).mean(axis=(1, 2))
