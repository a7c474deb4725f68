r"""Physical layer: received power, noise, sensing and packet error rate from SINR.

Reception of one packet (the error types of Sepulcre et al. 2021, eqs. (1)-(6), and
Gonzalez-Martín et al. 2019, eq. (6)):

1. **SEN** — the received power :math:`P_r = P_t - PL - S` (dBm) is below the sensing threshold
   :math:`P_{sen}`: the receiver does not detect the packet.
2. **PRO** — detected, but lost to noise and fading: with probability :math:`PER(\mathrm{SINR})`,
   :math:`\mathrm{SINR} = P_r - 10\log_{10}(N + \sum I)` (mW sums).
3. **COL** — lost to an overlapping transmission (the same PER, with the interferer in the sum;
   :mod:`mapcontainer.radio.mac` says who overlaps).

PER curves (:data:`PER_TABLES`), piecewise linear in dB as the sources tabulate them:

* ``"80211p_qpsk_1/2"`` — IEEE 802.11p at 6 Mbit/s (QPSK, rate-1/2 convolutional code): frame error
  rate against :math:`E_b/N_0` from Goubet et al., "Low-Complexity Scalable Iterative Algorithms for
  IEEE 802.11p Receivers", IEEE TVT 64(9) 2015, Fig. 14 (L = 1), as tabulated by Sepulcre et al. 2021
  (their ``get_FER``); :math:`E_b/N_0 = \mathrm{SINR} + 10\log_{10}(B/R)`, B = 10 MHz, R the data rate.
* ``"ltev2x_qpsk_0.7"`` / ``"ltev2x_qpsk_0.5"`` — LTE-V2X sidelink, 190-byte packets, QPSK at code
  rate 0.7 (4 sub-channels, 10 RBs) or 0.5 (2 sub-channels, 12 RBs), 280 km/h relative speed, BLER
  against SINR from 3GPP R1-160284 ("DMRS enhancement of V2V"), as tabulated by Gonzalez-Martín et al.
  2019 (their ``get_BLER``). Noise in the packet's RBs: :math:`-95 - 10 \log_{10}(50/RBs)` dBm.

Defaults (both papers): transmit power 23 dBm, noise -95 dBm in 10 MHz (noise figure 9 dB); sensing
threshold -85 dBm (802.11p) and -90.5 dBm (LTE-V2X).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

__all__ = ["PER_TABLES", "PhyParams", "noise_dbm", "per", "to_mw"]

# x in dB (Eb/N0 for 802.11p, SINR for LTE-V2X), then the error rate; flat outside.
PER_TABLES: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    "80211p_qpsk_1/2": (
        (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0),
        (1.0, 1.0, 0.4, 1.5e-2, 4e-3, 3e-3, 2e-3, 1e-3),
    ),
    "ltev2x_qpsk_0.7": (
        (0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0, 16.0, 18.0, 20.0, 20.000001),
        (1.0, 0.9, 0.7, 0.4, 0.13, 0.045, 0.017, 0.007, 1e-3, 1e-3, 1e-3, 1e-4),
    ),
    "ltev2x_qpsk_0.5": (
        (-2.0, 0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0, 16.0, 18.0, 20.0, 20.000001),
        (1.0, 0.9, 0.7, 0.3, 0.09, 0.02, 0.002, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-4),
    ),
}


class PhyParams(BaseModel):
    """Radio parameters of every vehicle (units in the names; sources in the module docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    tx_power_dbm: float = Field(23.0, ge=-30, le=40)
    noise_dbm: float = Field(-95.0, description="thermal noise plus noise figure over the channel bandwidth")
    sensing_dbm: float = Field(-85.0, description="a packet received below this is not detected (SEN)")
    per_curve: Literal["80211p_qpsk_1/2", "ltev2x_qpsk_0.7", "ltev2x_qpsk_0.5"] = "80211p_qpsk_1/2"
    bandwidth_hz: float = Field(10e6, gt=0)
    data_rate_bps: float = Field(6e6, gt=0, description="802.11p: the MCS's rate; Eb/N0 = SINR + 10 log10(B/R)")
    resource_blocks: int | None = Field(
        None, ge=1, le=50, description="LTE-V2X: RBs of the data field; noise scales by RBs/50"
    )


def noise_dbm(p: PhyParams) -> float:
    """Noise power (dBm) in the bandwidth the packet occupies."""
    if p.resource_blocks is not None:
        return p.noise_dbm - 10.0 * np.log10(50.0 / p.resource_blocks)
    return p.noise_dbm


def to_mw(dbm: np.ndarray) -> np.ndarray:
    return 10.0 ** (np.asarray(dbm, dtype=float) / 10.0)


def per(p: PhyParams, sinr_db: np.ndarray) -> np.ndarray:
    """Packet error rate at ``sinr_db`` for the PHY's modulation and coding (linear interpolation)."""
    x, y = PER_TABLES[p.per_curve]
    s = np.asarray(sinr_db, dtype=float)
    if p.per_curve.startswith("80211p"):
        s = s + 10.0 * np.log10(p.bandwidth_hz / p.data_rate_bps)
    return np.interp(s, x, y)
