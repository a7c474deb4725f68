"""Vehicle priors synthesised from the simulator's truth ("oracle localization"), for tests and benchmarks.

The pose is the true pose plus Gaussian noise drawn from a stated covariance (and that covariance is
reported); v_map is the true velocity plus noise; the objects are the sensor frame's detections as
they are. This isolates the host container from the map matcher.
"""

from __future__ import annotations

import numpy as np

from schemas import LocalizationQuality, ObjectObservations, VehiclePrior
from schemas.arrays import cov_to_upper

from ..sim.world import Tick

__all__ = ["OraclePriors", "pose_covariance"]


def pose_covariance(sigma_xy_m: float = 0.1, sigma_z_m: float = 0.05, sigma_rot_deg: float = 0.3) -> np.ndarray:
    """Diagonal 6x6 covariance over [x, y, z, roll, pitch, yaw]."""
    s = np.array([sigma_xy_m, sigma_xy_m, sigma_z_m, *np.radians([sigma_rot_deg] * 3)])
    return np.diag(s**2)


class OraclePriors:
    """VehiclePrior messages from simulator ticks: truth + noise with a stated covariance."""

    def __init__(self, fleet: str, seed: int, pose_cov: np.ndarray | None = None, v_sigma_mps: float = 0.1):
        self.fleet = fleet
        self.rng = np.random.default_rng(seed)
        self.pose_cov = pose_covariance() if pose_cov is None else np.asarray(pose_cov, dtype=float)
        self.L = np.linalg.cholesky(self.pose_cov)
        self.v_sigma = v_sigma_mps
        self._seq: dict[str, int] = {}

    def priors(self, tick: Tick, vids: list[str] | None = None) -> dict[str, VehiclePrior]:
        out = {}
        for vid in sorted(tick.frames) if vids is None else vids:
            frame = tick.frames[vid]
            st = tick.states[vid]
            pose = st.pose + self.L @ self.rng.normal(size=6)
            v = st.v_map + self.rng.normal(0.0, self.v_sigma, 3) * [1, 1, 0]
            seq = self._seq.get(vid, 0)
            self._seq[vid] = seq + 1
            out[vid] = VehiclePrior(
                fleet=self.fleet,
                sender=vid,
                seq=seq,
                t_meas=tick.t,
                t_sent=tick.t,
                pose=pose,
                pose_cov=cov_to_upper(self.pose_cov),
                v_map=v,
                quality=LocalizationQuality(mode="map_matching"),
                objects=ObjectObservations(
                    p_body_cm=frame.objects.p_body_cm, cov=frame.objects.cov, cls=frame.objects.cls
                ),
            )
        return out
