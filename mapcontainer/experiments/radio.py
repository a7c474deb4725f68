"""Radio model validation: PRR against distance (LOS, NLOS) per PHY profile, CBR against density.

``mapc experiment radio --out DIR`` writes ``radio_validation.json`` (every point: the published
model's PRR, the simulated value and their difference, within
:data:`~mapcontainer.radio.validation.PRR_TOLERANCE` or not; the path loss against ns-3's published
TR 37.885 vectors), ``prr_vs_distance.png`` and ``cbr_vs_density.png``. What is compared with what is in
:mod:`mapcontainer.radio.validation`: the simulator, with the preset's parameters in its source's scenario
(a straight road, no vehicle blockage, no background traffic), against reference curves computed from
the published numbers of ``configs/radio/published.yaml``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import jsonout
from ..channel import load_profile
from ..radio.link import RadioProfile
from ..radio.propagation import LOS, NLOS, PropagationParams, mean_path_loss_db
from ..radio.validation import (
    PRR_TOLERANCE,
    SOURCES,
    analytic_cbr,
    published,
    reference_prr,
    simulated_cbr,
    simulated_prr,
)

__all__ = [
    "DISTANCES_M",
    "PHY_PROFILES",
    "link_cost",
    "ns3_path_loss_check",
    "run_radio_validation",
    "source_scenario",
]

PHY_PROFILES = ("its-g5", "cv2x-mode4")
DISTANCES_M = tuple(float(d) for d in range(25, 501, 25))  # the sources' 0:25:500 m grid without 0
DENSITIES_PER_KM = (10.0, 30.0, 60.0, 90.0, 120.0)
STATES = {"LOS": LOS, "NLOS": NLOS}


def source_scenario(profile: RadioProfile) -> RadioProfile:
    """The profile in its source's scenario: no vehicle blockage, no background traffic."""
    return profile.model_copy(
        update={"radio": profile.radio.model_copy(update={"vehicle_blockage": False, "background_rate_hz": 0.0})}
    )


def link_cost(
    vehicles: int | None = 100,
    duration_s: float = 3.0,
    profiles: tuple[str, ...] = ("dsrc", "its-g5", "cv2x-mode4"),
    scenario: str = "paper-urban",
    seed: int = 0,
) -> dict:
    """CPU cost of the link model: one in-process run (distributed, warm start, signed) of ``scenario``
    with ``vehicles`` connected vehicles (None: the scenario's) per profile. Per run: the process's CPU
    seconds, the CPU seconds inside the channel's methods (timed by wrapping ``send``, ``observe``,
    ``on_air``, ``deliver``) with each method's calls and mean CPU per call (``observe``: once a frame,
    what the live relay does per truth message), and the run's CPU over the first profile's (today's link).
    """
    import time

    from .. import channel as classic
    from ..pipeline import run_pipeline
    from ..radio import link as radio_link
    from ..sim import load_scenario
    from ..sim.config import scale_scenario

    sc = scale_scenario(load_scenario(scenario), vehicles)
    rows = []
    for name in profiles:
        prof = load_profile(name)
        cls = radio_link.RadioChannel if isinstance(prof, RadioProfile) else classic.Channel
        spent: dict[str, list[float]] = {}

        def timed(method: str, orig, spent=spent):
            acc = spent.setdefault(method, [0.0, 0])

            def call(self, *a, **k):
                t0 = time.process_time()
                try:
                    return orig(self, *a, **k)
                finally:
                    acc[0] += time.process_time() - t0
                    acc[1] += 1

            return call

        saved = {m: getattr(cls, m) for m in ("send", "observe", "on_air", "deliver") if hasattr(cls, m)}
        for m, orig in saved.items():
            setattr(cls, m, timed(m, orig))
        t0 = time.process_time()
        try:
            res = run_pipeline(sc, seed=seed, duration_s=duration_s, network=prof, start="warm", signing=True)
        finally:
            for m, orig in saved.items():
                setattr(cls, m, orig)
        rows.append(
            {
                "profile": name,
                "run_cpu_s": round(time.process_time() - t0, 3),
                "channel_cpu_s": round(sum(v[0] for v in spent.values()), 6),  # a short run spends < 10 ms here
                "per_call_cpu_ms": {m: round(1e3 * v[0] / max(1, v[1]), 3) for m, v in spent.items()},
                "calls": {m: v[1] for m, v in spent.items()},
                "delivered_msgs": int(res.channel_stats.get("delivered_msgs", 0)),
            }
        )
    for r in rows:
        r["run_cpu_vs_first"] = round(r["run_cpu_s"] / rows[0]["run_cpu_s"], 3)
    return {
        "scenario": sc.name,
        "connected_vehicles": sc.n_connected,
        "duration_s": duration_s,
        "seed": seed,
        "runs": rows,
    }


def ns3_path_loss_check() -> list[dict]:
    """The model's TR 37.885 path loss (``tr37885_urban`` / ``tr37885_highway``) at ns-3's published test
    vectors (``published.yaml``: ``ns3_tr37885_pathloss``): one row per vector, with the difference (dB)."""
    ref = published()["ns3_tr37885_pathloss"]
    rows = []
    for family in ("urban", "highway"):
        prm = PropagationParams(family=f"tr37885_{family}", frequency_hz=ref["frequency_hz"])
        for label, state in STATES.items():
            for d, pl in ref[family][label]:
                got = float(mean_path_loss_db(prm, np.array([d]), state)[0])
                rows.append(
                    {
                        "family": family,
                        "state": label,
                        "distance_m": d,
                        "ns3_db": pl,
                        "model_db": round(got, 4),
                        "diff_db": round(got - pl, 4),
                        "within_tolerance": abs(got - pl) <= ref["tolerance_db"],
                    }
                )
    return rows


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
            a = reference_prr(SOURCES[name], d, state)
            s = simulated_prr(prof, d, state, n=messages, seed=seed)
            prr.append(
                {
                    "profile": name,
                    "source": SOURCES[name],
                    "state": label,
                    "distance_m": d.tolist(),
                    "reference": np.round(a, 4).tolist(),
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
    pl = ns3_path_loss_check()
    doc = {
        "published": "mapcontainer/configs/radio/published.yaml",
        "messages_per_point": messages,
        "seed": seed,
        "prr_tolerance": PRR_TOLERANCE,
        "prr": prr,
        "cbr_80211p_10hz_190bytes": cbr,
        "path_loss_vs_ns3": pl,
        "all_within_tolerance": all(p["within_tolerance"] for p in prr + pl),
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
            a.plot(p["distance_m"], p["reference"], "-", color=colour, label=f"{p['state']}: published model")
            a.plot(p["distance_m"], p["simulated"], "o", ms=3.5, color=colour, label=f"{p['state']}: simulated")
            lo = np.asarray(p["reference"]) - PRR_TOLERANCE
            a.fill_between(p["distance_m"], lo, lo + 2 * PRR_TOLERANCE, color=colour, alpha=0.12)
        a.set(
            title=f"{name} vs {SOURCES[name]}: PRR (band +-{PRR_TOLERANCE})",
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
