"""Parameters of the host container (validated; SI units unless a name says otherwise)."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from ..metrics import chi2_quantile

__all__ = ["FusionParams"]


class FusionParams(BaseModel):
    """Everything the host container's estimator and tracker can be tuned with.

    Defaults suit the simulator's detector (configs/sensors/default.yaml) and vehicle priors of about
    0.1 m / 0.3 deg; the models they tune are described in mapcontainer/fusion/graph.py and
    association.py.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    # ---- time
    window_s: float = Field(1.0, gt=0, description="sliding window: states older than fuse time - window_s are dropped")
    track_lag_s: float | None = Field(
        0.3,
        gt=0,
        description=(
            "an obstacle track's states older than its newest state by more than this are folded into its prior"
            " (the smoother's lag for tracks; vehicle poses stay for window_s). None: window_s"
        ),
    )
    time_merge_s: float = Field(
        0.02, ge=0, description="observations of one track closer in time than this share one state (async senders)"
    )
    future_tolerance_s: float = Field(1.0, ge=0, description="t_meas later than t_recv + this is refused ('future')")
    max_pending: int = Field(100_000, gt=0, description="reorder buffer capacity ('overflow' beyond)")

    # ---- association
    gate_probability: float = Field(
        0.99, gt=0, lt=1, description="chi-square (3 DoF) probability of the Mahalanobis gate in the map frame"
    )
    pregate_m: float = Field(
        15.0,
        gt=0,
        description="tracks and connected vehicles farther than this (Euclidean) from every detection of a message"
        " are not gated",
    )
    vehicle_gate_probability: float = Field(
        0.9999, gt=0, lt=1, description="gate for matching a detection to a connected vehicle's reported position"
    )
    birth_exclusion_probability: float = Field(
        0.9999,
        gt=0,
        lt=1,
        description="an unassigned detection this close to a track or vehicle nobody took starts no track",
    )
    merge_probability: float = Field(
        0.99, gt=0, lt=1, description="gate on position and velocity under which two confirmed tracks are one object"
    )
    clutter_density_m3: float = Field(
        1e-5,
        gt=0,
        description=(
            "spatial density (per m^3) of false alarms (detections of nothing): the"
            " detector's 0.1 false objects a frame over its 60 m, 120 deg, ~3 m high field of view (~1e-5)"
        ),
    )
    object_density_m3: float = Field(
        0.01,
        gt=0,
        description=(
            "spatial density (per m^3) of road users around the connected vehicles, before any is tracked, uniform"
            " over the map: one per 100 m^2, their centres within about 1 m of height. Times the share of recent"
            " detections no track explained, it is the density of objects not yet tracked. It overstates the paper"
            " scenarios' road users (0.0034-0.0039 per m^2 of road and sidewalk within 60 m of a connected vehicle,"
            " none off it); the centralized host's sure-association rule leans on the excess: at 0.004 on the road,"
            " suburban development seed 1004's fallback vehicle collapses again (docs/host.md, association)"
        ),
    )
    vehicle_association_probability: float = Field(
        0.9,
        gt=0,
        lt=1,
        description=(
            "a detection constrains a vehicle's pose (of the connected vehicle it is assigned to; of its observer"
            " when that is not map matching, centralized) only if its association is right with at least this"
            " probability against every other gated vehicle and track, clutter and objects not yet tracked"
        ),
    )
    merge_cycles: int = Field(3, ge=1, description="... for this many consecutive fuse() calls")
    vehicle_shadow_m: float = Field(
        1.5,
        gt=0,
        description=(
            "a confirmed track this near a connected vehicle's reported position (and within its gate) for"
            " merge_cycles calls is that vehicle, born while its pose was off, and is deleted (m): half a"
            " car's length, nearer than any two road users' centres"
        ),
    )
    vehicle_gate_max_dt_s: float = Field(
        0.5, gt=0, description="a connected vehicle's reported pose is used for gating up to this far from t_meas"
    )
    cross_obs_max_dt_s: float = Field(
        0.06, ge=0, description="a detection of a connected vehicle is tied to its pose state at most this far in time"
    )
    birth_hits: int = Field(
        3, ge=1, description="a tentative track is confirmed after detections at this many instants"
    )
    tentative_timeout_s: float = Field(
        0.35,
        gt=0,
        description=(
            "a tentative track without a detection this long is dropped, in measurement time: from its last"
            " detection to the newest t_meas fused (independent of V2X latency)"
        ),
    )
    death_s: float | None = Field(
        None, gt=0, description="a confirmed track without a detection this long is deleted (None: window_s)"
    )

    # ---- measurement models
    reweight_s: float = Field(
        0.5, ge=0, description="linearized detections get new Huber weights from the estimate while younger than this"
    )
    relinearize_rad: float = Field(0.02, gt=0, description="re-linearise a detection when its pose rotated this much")
    relinearize_m: float = Field(0.5, gt=0, description="... or moved this far from its linearization point")
    huber_k: float | None = Field(
        3.0, gt=0, description="Huber threshold on the whitened 3-D detection residual norm; None = Gaussian"
    )
    cross_dcs_phi: float | None = Field(
        11.34,
        gt=0,
        description=(
            "dynamic covariance scaling of cross-observations (detections of connected vehicles): weight"
            " min(1, 2 phi / (phi + chi2))^2 of the whitened squared residual chi2; 11.34 = chi2_3(0.99);"
            " None: Huber as the track detections. Needs huber_k (the reweighting)"
        ),
    )
    min_range_m: float = Field(0.5, gt=0, description="detections closer to the body origin than this are ignored")
    cross_localization: bool = Field(True, description="detections of connected vehicles constrain their poses")
    observer_yaw_sigma_max_rad: float = Field(
        math.radians(3.0),
        gt=0,
        description=(
            "an observer that is not map matching and reports a yaw 1-sigma above this (rad) cannot place its"
            " detections within a linear model: they move the tracks, never it (3 deg: the localizer's own bound"
            " for one local solve, LocalizerParams.search_sigma_yaw_rad; a vehicle searching for its start"
            " reports pi / sqrt(3))"
        ),
    )

    # ---- misbehaviour detection (mapcontainer/fusion/misbehaviour.py)
    misbehaviour: bool = Field(
        True,
        description="flag vehicles seen elsewhere than they say, reporting what is not there, or repeating instants",
    )
    misbehaviour_radius_m: float = Field(6.0, gt=0, description="a detection this near a vehicle is a sighting of it")
    misbehaviour_window_s: float = Field(2.0, gt=0, description="sightings of the last this many seconds decide")
    misbehaviour_min_sightings: int = Field(4, ge=1, description="an observer with this many sightings has a view")
    misbehaviour_min_observers: int = Field(
        2, ge=1, description="... by at least this many other vehicles (two vehicles alone cannot tell who lies)"
    )
    misbehaviour_offset_m: float = Field(
        0.6, gt=0, description="a view farther off than this, and than its covariance allows, disagrees (m)"
    )
    misbehaviour_probability: float = Field(
        0.999, gt=0, lt=1, description="... allows: its Mahalanobis distance within this chi-square quantile (2 dof)"
    )
    misbehaviour_trust_s: float = Field(
        10.0, gt=0, description="unused (only current views corroborate a vehicle); kept so older settings load"
    )
    misbehaviour_spread_m: float = Field(
        1.0,
        gt=0,
        description="a view accuses when its sightings' median distance from their median is below this, and "
        "observers agree on where they see a vehicle when their views are this near their median (m)",
    )
    ghost_range_m: float = Field(
        40.0, gt=0, description="an object this near a vehicle, in its view and not hidden, is one it should see (m)"
    )
    ghost_fov_deg: float = Field(100.0, gt=0, le=360, description="... within this field of view about its heading")
    ghost_observer_sigma_m: float = Field(
        0.5, gt=0, description="... if the vehicle knows where it is: its reported position 1-sigma below this (m)"
    )
    ghost_gate_m: float = Field(2.5, gt=0, description="a detection this near an object is one of it (m)")
    ghost_min_looks: int = Field(
        8, ge=1, description="an object one vehicle alone reports, that another should see this often in the window"
    )
    ghost_max_seen: float = Field(
        0.25, ge=0, lt=1, description="... and saw at most this fraction of those times, is denied: its track deleted"
    )
    ghost_min_denials: int = Field(
        3, ge=1, description="a vehicle with this many tracks denied within ghost_denial_window_s is flagged ..."
    )
    ghost_together_s: float = Field(
        0.5, gt=0, description="... or with two tracks denied within this of each other: two false objects at once (s)"
    )
    ghost_denial_window_s: float = Field(4.0, gt=0, description="... (s)")
    ghost_hold_s: float = Field(
        5.0, gt=0, description="a vehicle flagged for ghosts stays flagged this long after the last denial (s)"
    )
    clock_min_repeats: int = Field(
        3, ge=1, description="a vehicle with this many messages in the window that repeat an instant it sent ..."
    )
    clock_repeat_fraction: float = Field(
        0.3, gt=0, le=1, description="... and that are this fraction of its messages, is flagged while it repeats"
    )

    # ---- motion models
    accel_psd_vehicle: float = Field(
        2.0, gt=0, description="white-noise-on-acceleration PSD of obstacle vehicles, horizontal (m^2/s^3)"
    )
    accel_psd_pedestrian: float = Field(0.5, gt=0, description="... of pedestrians and cyclists, horizontal (m^2/s^3)")
    accel_psd_vertical: float = Field(0.01, gt=0, description="... vertical, every class (m^2/s^3)")
    speed_prior_vehicle_mps: float = Field(
        15.0, gt=0, description="zero-mean velocity prior sigma on a vehicle track's first state"
    )
    speed_prior_pedestrian_mps: float = Field(
        3.0, gt=0, description="... on a pedestrian or cyclist track's first state"
    )
    vehicle_velocity_sigma_mps: float = Field(
        0.5, gt=0, description="error of a reported v_map, used by the motion factor between a vehicle's frames (m/s)"
    )
    vehicle_accel_sigma_mps2: float = Field(
        3.0, gt=0, description="unmodelled acceleration in that motion factor (m/s^2)"
    )
    vehicle_rate_sigma_radps: float = Field(
        0.6,
        gt=0,
        description="rotation rate sigma of that motion factor (the relative rotation is not reported) (rad/s)",
    )
    motion_factor_max_dt_s: float = Field(0.5, gt=0, description="no motion factor between frames further apart")
    pose_error_persistent_fraction: float = Field(
        0.5,
        ge=0,
        lt=1,
        description=(
            "fraction of a vehicle's reported self-localization variance that persists over the window: its"
            " frames' whitened errors correlate by this much (a shared bias state, graph.py); 0 treats every"
            " frame's prior as independent evidence. Map matching tracks its pose from frame to frame, so its"
            " errors persist: measured correlation of its whitened horizontal errors 0.1-0.8 at 0.1 s and"
            " 0.1-0.45 at 1 s (paper-urban seed 0, paper-suburban seed 1, per vehicle); 0.5 is the upper end"
        ),
    )

    filtered_pose_error_persistent_fraction: float = Field(
        0.0,
        ge=0,
        lt=1,
        description=(
            "the same for a vehicle that sends its filtered estimate (VehiclePrior.pose_filtered): the fraction"
            " of its reported variance that the detections folded into track priors share with its later"
            " frames (its b is kept in those priors, so that they do not correct it as independent evidence)."
            " A filter's error moves slowly: measured correlation of its whitened 6-DoF errors 0.97 at 0.1 s,"
            " 0.88 at 0.3 s, 0.84 at 0.5 s, 0.81 at 1 s (paper-urban development seeds 1000-1002): 0.85 with"
            " filtered_pose_error_persistence_s 10 s fits 0.3-1 s, the ages at which detections are folded."
            " 0 (default): no b for a filtered sender, its folded detections' pose error independent of its"
            " later frames. 0.85 makes a lone vehicle's fused pose consistent (tests/unit/test_fusion_graph.py)"
            " but did not help the simulated fleets (development seeds, docs/host.md)"
        ),
    )
    filtered_pose_error_persistence_s: float = Field(
        10.0,
        gt=0,
        description="correlation time of that persistent part of a filtered estimate's error (s)",
    )

    detection_persistent_fraction: float = Field(
        0.5,
        ge=0,
        lt=1,
        description=(
            "share of a detection's reported variance that persists from frame to frame (the same object's shape,"
            " size prior and box fit: Schlager et al. 2020, SAE Int. J. CAV 3(3); configs/sensors/default.yaml"
            " detector.errors.persistent_fraction): it does not average out over one observer's detections of an"
            " object, so the object's covariance takes it in as a consider term (hostcore.observer_bias); 0: none"
        ),
    )
    detection_persistence_s: float = Field(
        2.0,
        gt=0,
        description="correlation time of that persistent part (first-order Gauss-Markov, per observer and object) (s)",
    )
    pose_error_persistence_s: float = Field(
        1.0,
        gt=0,
        description=(
            "correlation time of that persistent part (first-order Gauss-Markov): a track prior's dependence"
            " on a vehicle's persistent error fades by exp(-dt / this) as it ages (map matching: correlation"
            " 0.1-0.45 at 1 s, see pose_error_persistent_fraction)"
        ),
    )

    # ---- solver
    solver: Literal["sparse", "exact"] = Field(
        "sparse",
        description=(
            "elimination order of each solve. 'sparse': COLAMD over the whole window, so a track's states are"
            " eliminated next to its observers' frames and the cost follows the scene's local structure (a"
            " window with at most 24 latest states is ordered as 'exact', which is cheaper there);"
            " 'exact': the latest state of every vehicle and track ordered last, one dense root clique over"
            " all of them (cubic in their number): the test oracle. Both solve the same system exactly"
            " (mapcontainer/fusion/solver.py)"
        ),
    )
    max_iterations: int = Field(3, ge=1, description="Levenberg-Marquardt iterations per fuse() at most")
    relative_error_tol: float = Field(1e-3, gt=0, description="stop when the cost decreases by less than this fraction")
    model_tol: float = Field(
        0.02,
        ge=0,
        description=(
            "also stop when an undamped step's actual cost decrease matches the linear model's prediction to"
            " within this fraction of the cost (the step landed on the model's minimum; what remains is the"
            " Huber reweighting, measured at < 0.15 sigma on the latest states)"
        ),
    )
    lambda_initial: float = Field(0.0, ge=0, description="initial LM damping (0: try the Gauss-Newton step first)")

    @model_validator(mode="after")
    def _consistent(self):
        if self.death_s is not None and self.death_s > self.window_s + 1e-9:
            raise ValueError(
                f"death_s ({self.death_s}) must not exceed window_s ({self.window_s}): its states are gone"
            )
        return self

    @property
    def track_window_s(self) -> float:
        """How far back from its newest state a track keeps states: track_lag_s, at most window_s."""
        return self.window_s if self.track_lag_s is None else min(self.track_lag_s, self.window_s)

    @property
    def track_death_s(self) -> float:
        """death_s, or the window when unset."""
        return self.window_s if self.death_s is None else self.death_s

    @property
    def gate_chi2(self) -> float:
        """Mahalanobis-squared gate for a 3-D position."""
        return float(chi2_quantile(self.gate_probability, 3))
