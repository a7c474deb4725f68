r"""Large-scale propagation between vehicles: path loss by link state, vehicle blockage, shadowing.

Link states (3GPP TR 37.885 §6.2.1): **LOS** (nothing in between), **NLOSv** (the straight line is
blocked only by vehicles) and **NLOS** (blocked by buildings). The state of a link is decided from
geometry (:mod:`mapcontainer.radio.obstacles`); this module turns (distance, state) into a mean path
loss and a shadowing standard deviation. Distances are in metres, losses in dB, frequencies in Hz.

Path-loss families (``family`` of :class:`PropagationParams`):

* ``"winner_b1"`` — WINNER+ B1 LOS, as used for V2V in 3GPP TR 36.885 (its V2V channel table; the
  table number A.1.4-1 is from memory, not re-checked against the document) and by the
  analytical models of Sepulcre et al., "Analytical Models of the Performance of IEEE 802.11p Vehicle
  to Vehicle Communications", IEEE TVT 2021 (their ``get_PL_SH``), and Gonzalez-Martín et al.,
  "Analytical Models of the Performance of C-V2X Mode 4 Vehicular Communications", IEEE TVT 68(2)
  2019:

  .. math::
      d_{BP} &= 4 (h_t - h_e)(h_r - h_e) f_c / c \\
      PL_{LOS}(d) &= 22.7 \log_{10} d + 27 + 20 \log_{10}(f_c/\mathrm{GHz}), \quad d < d_{BP}\\
      PL_{LOS}(d) &= 40 \log_{10} d + 7.56 - 17.3 \log_{10}(h_t - h_e) - 17.3 \log_{10}(h_r - h_e)
                    + 2.7 \log_{10}(f_c/\mathrm{GHz}), \quad d \ge d_{BP}

  never below free space :math:`20 \log_{10} d + 46.4 + 20 \log_{10}(f_c / 5\,\mathrm{GHz})`, and
  with :math:`d` floored at 3 m (as both papers' implementations do). :math:`h_e` is the environment
  height (0.5 m in the 802.11p paper, 0 in the C-V2X one).
* ``"tr37885_urban"`` — TR 37.885 Table 6.2.1-1, urban: :math:`PL_{LOS} = 38.77 + 16.7 \log_{10} d
  + 18.2 \log_{10} f_c`.
* ``"tr37885_highway"`` — TR 37.885 Table 6.2.1-1, highway: :math:`PL_{LOS} = 32.4 + 20 \log_{10} d
  + 20 \log_{10} f_c` (:math:`f_c` in GHz).

Every family uses the TR 37.885 urban NLOS loss for a building-blocked link,
:math:`PL_{NLOS} = 36.85 + 30 \log_{10} d + 18.9 \log_{10} f_c`, never below the family's LOS loss;
NLOSv is the LOS loss plus the vehicle-blockage loss of TR 37.885 §6.2.1 (:func:`nlosv_loss_db`).

Shadowing (TR 37.885 Table 6.2.1-1 / ns-3's ``ThreeGppV2vUrbanPropagationLossModel``): standard
deviation 3 dB for LOS and NLOSv, 4 dB for NLOS; spatially correlated with decorrelation distance
10 m (LOS) and 13 m (NLOS, NLOSv) in urban (ns-3's values; 25 m is the highway figure of TR 36.885 as we
recall it, not re-checked: set ``decorrelation_*_m`` for a highway). It is the
Gudmundson AR(1) process along the link's own motion, :class:`Shadowing`.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .hashing import link_keys, normals

__all__ = [
    "LOS",
    "NLOS",
    "NLOSV",
    "PropagationParams",
    "Shadowing",
    "mean_path_loss_db",
    "nlosv_loss_db",
    "shadowing_sigma_db",
]

LOS, NLOSV, NLOS = 0, 1, 2
"""Link states (int codes in arrays)."""

_C = 299_792_458.0
_MIN_D = 3.0


class PropagationParams(BaseModel):
    """Path loss, blockage and shadowing parameters (units in the names; sources in the module doc)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    family: Literal["winner_b1", "tr37885_urban", "tr37885_highway"] = "winner_b1"
    frequency_hz: float = Field(5.9e9, gt=1e9, lt=1e11)
    antenna_height_m: float = Field(1.5, gt=0, description="of every vehicle (TR 37.885: 1.5 m)")
    environment_height_m: float = Field(0.5, ge=0, description="WINNER+ B1 effective-height offset")
    blocker_height_m: float = Field(1.6, gt=0, description="a car (TR 37.885 vehicle types 1-2); 3.0 a truck")
    sigma_los_db: float = Field(3.0, ge=0)
    sigma_nlosv_db: float = Field(3.0, ge=0)
    sigma_nlos_db: float = Field(4.0, ge=0)
    decorrelation_los_m: float = Field(10.0, gt=0)
    decorrelation_nlos_m: float = Field(13.0, gt=0, description="also NLOSv")


def _log10d(d: np.ndarray) -> np.ndarray:
    return np.log10(np.maximum(np.asarray(d, dtype=float), _MIN_D))


def _los_db(p: PropagationParams, d: np.ndarray) -> np.ndarray:
    lg = _log10d(d)
    f_ghz = p.frequency_hz / 1e9
    if p.family == "tr37885_urban":
        return 38.77 + 16.7 * lg + 18.2 * np.log10(f_ghz)
    if p.family == "tr37885_highway":
        return 32.4 + 20.0 * lg + 20.0 * np.log10(f_ghz)
    h = p.antenna_height_m - p.environment_height_m
    if h <= 0:
        raise ValueError(f"antenna_height_m {p.antenna_height_m} must exceed environment_height_m")
    d_bp = 4.0 * h * h * p.frequency_hz / _C
    near = 22.7 * lg + 27.0 + 20.0 * np.log10(f_ghz)
    far = 40.0 * lg + 7.56 - 2 * 17.3 * np.log10(h) + 2.7 * np.log10(f_ghz)
    free = 20.0 * lg + 46.4 + 20.0 * np.log10(f_ghz / 5.0)
    return np.maximum(np.where(10.0**lg < d_bp, near, far), free)


def mean_path_loss_db(p: PropagationParams, d: np.ndarray, state: np.ndarray) -> np.ndarray:
    """Median path loss (dB) for distances ``d`` (m) and link states (LOS/NLOSV/NLOS), without the
    random NLOSv blockage loss and the shadowing."""
    d = np.asarray(d, dtype=float)
    state = np.broadcast_to(np.asarray(state), d.shape)
    los = _los_db(p, d)
    nlos = np.maximum(36.85 + 30.0 * _log10d(d) + 18.9 * np.log10(p.frequency_hz / 1e9), los)
    return np.where(state == NLOS, nlos, los)


def nlosv_loss_db(p: PropagationParams, d: np.ndarray, u: np.ndarray) -> np.ndarray:
    r"""Vehicle-blockage loss of an NLOSv link (TR 37.885 §6.2.1), from uniforms ``u`` in (0, 1).

    With antenna heights :math:`h_t = h_r = h` and blocker height :math:`h_b`: no loss if
    :math:`h > h_b`; else a log-normal loss with mean :math:`\mu_a` and standard deviation
    :math:`\sigma_a` (dB):

    .. math::
        \mu_a = 9 + \max(0, 15 \log_{10} d - 41),\ \sigma_a = 4.5 \quad (h < h_b)

    (the other case of the table, one antenna above and one below the blocker, cannot occur with one
    antenna height). The log-normal's parameters are :math:`m = \ln(\mu_a^2/\sqrt{\sigma_a^2+\mu_a^2})`,
    :math:`s = \sqrt{\ln(1 + \sigma_a^2/\mu_a^2)}`, as ns-3 implements it.
    """
    d = np.asarray(d, dtype=float)
    if p.antenna_height_m > p.blocker_height_m:
        return np.zeros_like(d)
    mu_a = 9.0 + np.maximum(0.0, 15.0 * _log10d(d) - 41.0)
    sigma_a = 4.5
    m = np.log(mu_a**2 / np.sqrt(sigma_a**2 + mu_a**2))
    s = np.sqrt(np.log(1.0 + sigma_a**2 / mu_a**2))
    from scipy.special import ndtri

    return np.exp(m + s * ndtri(np.clip(u, 1e-12, 1 - 1e-12)))


def shadowing_sigma_db(p: PropagationParams, state: np.ndarray) -> np.ndarray:
    """Shadowing standard deviation (dB) per link state."""
    state = np.asarray(state)
    return np.choose(state, [p.sigma_los_db, p.sigma_nlosv_db, p.sigma_nlos_db])


class Shadowing:
    r"""Correlated log-normal shadowing per unordered link, stable for a seed (Gudmundson's AR(1)).

    Each link {a, b} carries a unit-normal state :math:`z` that moves with the link's own motion
    :math:`\Delta_k = |\Delta p_a| + |\Delta p_b|` between two updates:

    .. math::
        z_k = \rho_k z_{k-1} + \sqrt{1 - \rho_k^2}\, n_k, \qquad \rho_k = e^{-\Delta_k / d_{corr}},
        \qquad S_k = \sigma(\text{state}_k)\, z_k \ \text{(dB)}

    so the shadowing of a standing link does not change, and two positions ``d_corr`` apart are
    correlated by 1/e. :math:`z_0` and every :math:`n_k` are drawn from a counter-based hash of (seed,
    link, k): a link's values do not depend on the other links, on the order of updates, or on the
    process (the in-process pipeline and the channel relay draw the same numbers). Reciprocal:
    :math:`S_{ab} = S_{ba}`.
    """

    def __init__(self, params: PropagationParams, seed: int) -> None:
        self.params = params
        self.seed = int(seed)
        self._keys = np.zeros(0, dtype=np.uint64)  # sorted; the links' state in the same order
        self._z = np.zeros(0)
        self._k = np.zeros(0, dtype=np.uint64)

    def update(self, keys: np.ndarray, moved_m: np.ndarray, state: np.ndarray) -> np.ndarray:
        """Advance links ``keys`` (uint64, from :func:`~.hashing.link_keys`; distinct) by their motion
        ``moved_m`` and return their shadowing (dB) in their ``state``."""
        keys = np.asarray(keys, dtype=np.uint64).reshape(-1)
        pos = np.searchsorted(self._keys, keys)
        found = pos < len(self._keys)
        found[found] = self._keys[pos[found]] == keys[found]
        z_prev = np.where(found, self._z[np.minimum(pos, len(self._z) - 1)] if len(self._z) else 0.0, 0.0)
        k = np.where(found, self._k[np.minimum(pos, len(self._k) - 1)] if len(self._k) else 0, 0).astype(np.uint64)
        draws = normals(self.seed, keys, k)
        d_corr = np.where(np.asarray(state) == LOS, self.params.decorrelation_los_m, self.params.decorrelation_nlos_m)
        moved = np.maximum(np.asarray(moved_m, dtype=float), 0.0)
        rho = np.exp(-moved / d_corr)
        z = np.where(found, rho * z_prev + np.sqrt(1.0 - rho**2) * draws, draws)
        step = ~found | (moved > 0)  # a standing link keeps its value and its counter
        k_new = k + step.astype(np.uint64)
        self._z[pos[found]] = z[found]
        self._k[pos[found]] = k_new[found]
        if (~found).any():
            all_keys = np.concatenate([self._keys, keys[~found]])
            order = np.argsort(all_keys, kind="stable")
            self._keys = all_keys[order]
            self._z = np.concatenate([self._z, z[~found]])[order]
            self._k = np.concatenate([self._k, k_new[~found]])[order]
        return shadowing_sigma_db(self.params, state) * z


__all__ += ["link_keys"]
