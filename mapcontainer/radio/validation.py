r"""Validation of the radio model: reception against distance, and channel load against density.

**Reception (PRR against distance)** for LOS and NLOS, for each PHY profile, against the analytical
models of the profiles' sources, with their stated parameters:

* 802.11p — Sepulcre et al., "Analytical Models of the Performance of IEEE 802.11p Vehicle to Vehicle
  Communications", IEEE TVT 2021, eq. (1) with the sensing error (12) and the propagation error (24) and
  no interferer (the low-density limit, where the collision terms (14), (26) vanish):

  .. math::
      PDR(d) = \int [P_t - PL(d) - s \ge P_{sen}]\,(1 - FER(P_t - PL(d) - s - N))\,\varphi_\sigma(s)\, ds

* C-V2X mode 4 — Gonzalez-Martín et al., "Analytical Models of the Performance of C-V2X Mode 4
  Vehicular Communications", IEEE TVT 68(2) 2019, eq. (6) without collisions: the same integral with
  the LTE-V2X BLER, times :math:`1 - \delta_{HD}`, :math:`\delta_{HD} = \lambda / 1000` (their eq. (7)).

For NLOS the integral uses the TR 37.885 NLOS path loss and its 4 dB shadowing (the sources model LOS
only; the NLOS curve checks the same closed form with the 3GPP parameters). The published figures
themselves (the papers' PDR plots, and the simulation curves the authors ship as MATLAB figures) are
not reproduced here: what is checked is that the simulator, message by message through
:class:`~.link.RadioChannel`, reproduces the sources' closed form at every distance within
:data:`PRR_TOLERANCE`.

**Channel load (CBR against density)**: vehicles every :math:`1/\beta` m on a straight road, each
sending :math:`\lambda` packets per second; Sepulcre et al.'s eq. (34),
:math:`CBR = \beta \lambda T \sum_d PSR(d)`, with :math:`PSR(d)` the probability that a packet from d
metres is sensed (their eq. (13)), is the closed form the simulated 802.11p CBR is checked against.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from .link import RadioChannel, RadioProfile
from .mac import airtime_s
from .obstacles import Buildings
from .phy import noise_dbm, per
from .propagation import LOS, NLOS, mean_path_loss_db, shadowing_sigma_db

__all__ = ["PRR_TOLERANCE", "analytic_cbr", "analytic_prr", "simulated_cbr", "simulated_prr"]

PRR_TOLERANCE = 0.05
"""Absolute PRR tolerance at every distance: 3.2 binomial standard deviations at p = 0.5 for 1000
messages per point, so a correct simulator fails a point about once in 700."""


def analytic_prr(profile: RadioProfile, d: np.ndarray, state: int, rate_hz: float = 10.0) -> np.ndarray:
    """The sources' closed-form PRR at distances ``d`` (module docstring), without interferers."""
    r = profile.radio
    d = np.asarray(d, dtype=float)
    sigma = float(shadowing_sigma_db(r.propagation, np.array(state)))
    s = np.linspace(-8.0, 8.0, 3201) * max(sigma, 1e-9)
    w = np.exp(-0.5 * (s / max(sigma, 1e-9)) ** 2)
    w /= w.sum()
    pr = r.phy.tx_power_dbm - mean_path_loss_db(r.propagation, d, state)[:, None] - s[None, :]
    ok = (pr >= r.phy.sensing_dbm) * (1.0 - per(r.phy, pr - noise_dbm(r.phy)))
    prr = ok @ w
    if r.mac.access == "sps":
        prr = prr * (1.0 - rate_hz * 1e-3)
    return prr


def simulated_prr(
    profile: RadioProfile, d: np.ndarray, state: int, n: int = 1000, seed: int = 0, nbytes: int = 190
) -> np.ndarray:
    """PRR per distance measured message by message through a :class:`RadioChannel`: a transmitter and a
    receiver ``d`` apart, both sending every 100 ms, that jump 400 m sideways between messages (so each
    message sees fresh shadowing, as the closed form's average does); for NLOS a building between them."""
    out = []
    for dist in np.asarray(d, dtype=float):
        hop = 400.0
        b = None
        if state == NLOS:
            y0 = dist / 2.0
            b = Buildings.from_polygons(
                [np.array([[-20, y0 - 2], [hop + 20, y0 - 2], [hop + 20, y0 + 2], [-20, y0 + 2]])]
            )
        ch = RadioChannel(profile, seed, b)
        ch.place("host", "rx")
        ok = 0
        for k in range(n):
            t = 0.1 * k
            x = hop * (k % 2)
            ch.observe(t, {"tx": (x, 0.0), "rx": (x, dist)})
            ch.on_air("rx", b"r" * nbytes, t)
            ok += ch.send("tx", "host", b"m" * nbytes, t)
        out.append(ok / n)
    return np.array(out)


def analytic_cbr(profile: RadioProfile, beta_per_m: float, rate_hz: float, nbytes: int) -> float:
    """Sepulcre et al. eq. (34): beta lambda T sum_d PSR(d), d over the road at 1 m steps to 1.5 km."""
    r = profile.radio
    d = np.arange(-1500.0, 1501.0)
    sigma = float(shadowing_sigma_db(r.propagation, np.array(LOS)))
    psr = ndtr((r.phy.tx_power_dbm - mean_path_loss_db(r.propagation, np.abs(d), LOS) - r.phy.sensing_dbm) / sigma)
    return float(beta_per_m * rate_hz * airtime_s(nbytes, r.phy.data_rate_bps) * psr.sum())


def simulated_cbr(
    profile: RadioProfile,
    beta_per_m: float,
    rate_hz: float = 10.0,
    nbytes: int = 190,
    road_m: float = 2000.0,
    seconds: float = 1.5,
    seed: int = 0,
) -> tuple[float, np.ndarray]:
    """Mean CBR of the vehicles in the middle third of a straight road of ``road_m`` with a vehicle every
    1/beta m (all connected, each sending ``rate_hz``), after ``seconds``; and every vehicle's CBR."""
    n = max(2, int(round(road_m * beta_per_m)))
    x = np.linspace(0.0, road_m, n)
    names = [f"v{i}" for i in range(n)]
    ch = RadioChannel(profile, seed)
    steps = int(round(seconds * rate_hz))
    payload = b"c" * nbytes
    for k in range(steps + 1):
        t = k / rate_hz
        ch.observe(t, {nm: (xi, 0.0) for nm, xi in zip(names, x, strict=True)})
        for nm in names:
            ch.on_air(nm, payload + nm.encode(), t)
    cbr = np.array([ch.cbr()[nm] for nm in names])
    mid = (x > road_m / 3) & (x < 2 * road_m / 3)
    return float(cbr[mid].mean()), cbr
