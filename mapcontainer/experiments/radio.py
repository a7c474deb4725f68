"""Radio model validation: PRR against distance (LOS, NLOS) per PHY profile, CBR against density.

``mapc experiment radio --out DIR`` writes ``radio_validation.json`` (every point: the sources' closed
form, the simulated value and their difference, within :data:`~mapcontainer.radio.validation.PRR_TOLERANCE`
or not), ``prr_vs_distance.png`` and ``cbr_vs_density.png``. What is compared with what is in
:mod:`mapcontainer.radio.validation`: the simulator against the closed-form models of the sources, with
the sources' parameters (their scenario: a straight road, no vehicle blockage, no background traffic).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import jsonout
from ..channel import load_profile
from ..radio.link import RadioProfile
from ..radio.propagation import LOS, NLOS
from ..radio.validation import PRR_TOLERANCE, analytic_cbr, analytic_prr, simulated_cbr, simulated_prr

__all__ = ["DISTANCES_M", "PHY_PROFILES", "source_scenario", "run_radio_validation"]

PHY_PROFILES = ("its-g5", "cv2x-mode4")
DISTANCES_M = tuple(float(d) for d in range(25, 501, 25))  # the sources' 0:25:500 m grid without 0
DENSITIES_PER_KM = (10.0, 30.0, 60.0, 90.0, 120.0)
STATES = {"LOS": LOS, "NLOS": NLOS}


def source_scenario(profile: RadioProfile) -> RadioProfile:
    """The profile in its source's scenario: no vehicle blockage, no background traffic."""
    return profile.model_copy(
        update={"radio": profile.radio.model_copy(update={"vehicle_blockage": False, "background_rate_hz": 0.0})}
    )


def run_radio_validation(
    out_dir: str | Path, messages: int = 1000, seed: int = 0, distances_m=DISTANCES_M, densities_per_km=DENSITIES_PER_KM
) -> dict:
    """Run every comparison and write the JSON and the two figures; returns the JSON document."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    d = np.asarray(distances_m, dtype=float)
    prr = []
    for name in PHY_PROFILES:
        prof = source_scenario(load_profile(name))
        for label, state in STATES.items():
            a = analytic_prr(prof, d, state)
            s = simulated_prr(prof, d, state, n=messages, seed=seed)
            prr.append(
                {
                    "profile": name,
                    "state": label,
                    "distance_m": d.tolist(),
                    "analytic": np.round(a, 4).tolist(),
                    "simulated": np.round(s, 4).tolist(),
                    "max_abs_diff": round(float(np.max(np.abs(a - s))), 4),
                    "within_tolerance": bool(np.all(np.abs(a - s) <= PRR_TOLERANCE)),
                }
            )
    prof = source_scenario(load_profile("its-g5"))
    cbr = []
    for dens in densities_per_km:
        beta = dens / 1000.0
        sim, _ = simulated_cbr(prof, beta, seed=seed)
        cbr.append(
            {
                "density_per_km": dens,
                "analytic": round(analytic_cbr(prof, beta, 10.0, 190), 4),
                "simulated": round(sim, 4),
            }
        )
    doc = {
        "messages_per_point": messages,
        "seed": seed,
        "prr_tolerance": PRR_TOLERANCE,
        "prr": prr,
        "cbr_80211p_10hz_190bytes": cbr,
        "all_within_tolerance": all(p["within_tolerance"] for p in prr),
    }
    (out / "radio_validation.json").write_text(jsonout.dumps(doc) + "\n")
    _plots(doc, out)
    return doc


def _plots(doc: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, len(PHY_PROFILES), figsize=(6 * len(PHY_PROFILES), 4.2), squeeze=False)
    for j, name in enumerate(PHY_PROFILES):
        a = ax[0, j]
        for p, colour in zip([p for p in doc["prr"] if p["profile"] == name], ("tab:blue", "tab:red"), strict=False):
            a.plot(p["distance_m"], p["analytic"], "-", color=colour, label=f"{p['state']}: source's closed form")
            a.plot(p["distance_m"], p["simulated"], "o", ms=3.5, color=colour, label=f"{p['state']}: simulated")
            lo = np.asarray(p["analytic"]) - PRR_TOLERANCE
            a.fill_between(p["distance_m"], lo, lo + 2 * PRR_TOLERANCE, color=colour, alpha=0.12)
        a.set(
            title=f"{name}: PRR vs distance (band: +-{PRR_TOLERANCE})",
            xlabel="distance (m)",
            ylabel="PRR",
            ylim=(-0.02, 1.02),
        )
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "prr_vs_distance.png", dpi=110)
    plt.close(fig)

    rows = doc["cbr_80211p_10hz_190bytes"]
    fig, a = plt.subplots(figsize=(5.5, 4))
    x = [r["density_per_km"] for r in rows]
    a.plot(x, [r["analytic"] for r in rows], "-", label="Sepulcre et al. 2021 eq. (34)")
    a.plot(x, [r["simulated"] for r in rows], "o", label="simulated (its-g5, no blockage)")
    a.set(title="802.11p CBR vs density (10 Hz, 190 B)", xlabel="vehicles per km", ylabel="CBR")
    a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "cbr_vs_density.png", dpi=110)
    plt.close(fig)
