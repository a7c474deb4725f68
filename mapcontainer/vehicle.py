"""The vehicle agent: one connected vehicle's on-board logic, as a pure core class.

``VehicleAgent.handle(t, frame)`` turns one SensorFrame into the message the vehicle puts on the
V2X link: a :class:`~schemas.VehiclePrior` in distributed mode (self-localization by HD-map
matching, plus this frame's object detections in the body frame with covariance — not filtered
tracks: the host treats each message as independent evidence), or a
:class:`~schemas.RawObservations` in centralized mode (the host localizes the vehicle itself). The
raw message's lane mask is pooled to the width the host's map matcher uses
(``MatcherParams.lane_dt_max_width_px``, :func:`mapcontainer.lanemask.pool`, the matcher's own
pooling) and sent in ``lane_mask_pooled_png``: a wider one would cost bytes the host throws away on
arrival.

A frame the agent cannot use comes back as a :class:`~schemas.Rejection` and changes nothing:
``future`` (measured more than ``FUTURE_TOLERANCE_S`` after the time it is handled: a broken clock,
which would otherwise move the localizer's time ahead and make every later frame look old) and
``bad_input`` (the localizer refused it: time going backwards, non-finite odometry or GNSS).
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import replace
from typing import Generic, Literal, TypeVar

import numpy as np

from schemas import (
    LocalizationQuality,
    Observations,
    PoseDownlink,
    RawObservations,
    Rejection,
    VehiclePrior,
    body_pose_cov,
    decode,
)
from schemas.arrays import cov_to_upper

from . import lanemask
from .geometry import CameraIntrinsics
from .hdmap.model import HDMap
from .localization import CameraFrame, LocalizationResult, Localizer, LocalizerParams
from .localization.health import PoseHealth, PoseHealthParams, advance, verdict
from .localization.startup import Phase
from .onboard import DownlinkFusion, DownlinkParams, Onboard

__all__ = ["FUTURE_TOLERANCE_S", "FrameBacklog", "Mode", "VehicleAgent", "camera_frame"]

Mode = Literal["distributed", "centralized"]
FUTURE_TOLERANCE_S = 1.0  # as the host's (FusionParams.future_tolerance_s)


T = TypeVar("T")


class FrameBacklog(Generic[T]):
    """The frames waiting for a vehicle that may fall behind: the newest is matched, the ones before it are stale.

    ``put`` (the receiving thread) appends a frame; ``take`` (the worker) returns every frame waiting, in arrival
    order, as (stale, newest): the stale ones go to :meth:`VehicleAgent.skip` (the localizer steps through their
    odometry and GNSS fix without the camera, so no stretch of the path goes unmeasured), the newest to
    :meth:`VehicleAgent.handle`. A vehicle whose frame takes longer than the frame period therefore always
    matches the freshest frame there is, and its priors are at most one frame period plus one frame's work
    old, instead of queueing frames it then matches late. At most ``max_waiting`` wait: beyond, the oldest is
    dropped whole (:meth:`pop_dropped` counts them: a flood must not grow the backlog without bound). Thread-safe.
    """

    def __init__(self, max_waiting: int = 256):
        if max_waiting < 1:
            raise ValueError(f"max_waiting must be at least 1, got {max_waiting}")
        self.max_waiting = max_waiting
        self._dropped = 0
        self._items: deque[T] = deque()
        self._ready = threading.Condition()

    def put(self, item: T) -> None:
        with self._ready:
            if len(self._items) >= self.max_waiting:
                self._items.popleft()
                self._dropped += 1
            self._items.append(item)
            self._ready.notify()

    def take(self, timeout_s: float | None = None) -> tuple[list[T], T] | None:
        """Every frame waiting as (stale, newest), waiting up to ``timeout_s`` for one (None: none came)."""
        with self._ready:
            if not self._ready.wait_for(lambda: bool(self._items), timeout_s):
                return None
            items = list(self._items)
            self._items.clear()
        return items[:-1], items[-1]

    def pop_dropped(self) -> int:
        """Frames dropped whole since the last call."""
        with self._ready:
            n, self._dropped = self._dropped, 0
        return n

    def __len__(self) -> int:
        with self._ready:
            return len(self._items)


def _max_pixels(obs: Observations) -> int:
    """A mask larger than the image is refused before it is inflated (a few kB of PNG can hold gigabytes)."""
    return obs.camera.width * obs.camera.height


def camera_frame(obs: Observations) -> CameraFrame:
    """The matcher's view of a SensorFrame / RawObservations (decodes the lane-mask PNG).

    The mask is ``lane_mask_pooled_png`` if the message has one (pooled by an integer factor, e.g.
    640x360 of a 1280x720 camera), else ``lane_mask_png`` (the camera's resolution, as every message
    before the pooled field): the matcher scales pixel coordinates by the mask's width over the camera's."""
    cam = obs.camera
    png = obs.lane_mask_pooled_png or obs.lane_mask_png
    mask = lanemask.decode(png, _max_pixels(obs)) if png else None
    return CameraFrame(
        intr=CameraIntrinsics(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height),
        T_body_cam=np.asarray(cam.T_body_cam, dtype=float),
        points_uv=np.asarray(obs.points_uv, dtype=float),
        points_cls=np.asarray(obs.points_cls),
        poles_uv=np.asarray(obs.poles_uv, dtype=float),
        lane_mask=mask,
    )


class VehicleAgent:
    """One connected vehicle: localizes against the HD map and builds its V2X message."""

    def __init__(
        self,
        hdmap: HDMap,
        vehicle_id: str,
        fleet: str,
        mode: Mode = "distributed",
        params: LocalizerParams | None = None,
        initial_pose: tuple[np.ndarray, np.ndarray] | None = None,
        raw_mask_max_width_px: int | None = None,
        health: PoseHealthParams | None = None,
        downlink: DownlinkParams | None = None,
    ):
        """``initial_pose``: (pose (6,), covariance 6x6) known at start, see :meth:`Localizer.reset`;
        without it the vehicle initialises from GNSS, the map's driving directions and the camera.
        ``raw_mask_max_width_px``: the widest lane mask sent in centralized mode (None: the matcher's
        ``lane_dt_max_width_px``, the width the host's matcher pools any wider mask to).
        ``health``: the thresholds of :meth:`health` (:mod:`.localization.health`).
        ``downlink``: how the host's downlink is used (:mod:`.onboard`; it is only used when one arrives,
        :meth:`receive_downlink`)."""
        if mode not in ("distributed", "centralized"):
            raise ValueError(f"mode must be 'distributed' or 'centralized', got {mode!r}")
        self.vehicle_id = vehicle_id
        self.fleet = fleet
        self.mode = mode
        self.localizer = Localizer(hdmap, params or LocalizerParams(), initial_pose=initial_pose)
        width = raw_mask_max_width_px
        if width is None:
            width = self.localizer.params.matcher.lane_dt_max_width_px
        if width <= 0:
            raise ValueError(f"raw_mask_max_width_px must be positive, got {raw_mask_max_width_px}")
        self.raw_mask_max_width_px = int(width)
        self._seq = 0
        self.last: VehiclePrior | None = None
        self.last_result: LocalizationResult | None = None  # the localizer's, with its filtered estimate
        self.health_params = health or PoseHealthParams()
        self.pose_health = PoseHealth()  # whether the vehicle knows where it is, after the newest step
        self.downlink = DownlinkFusion(vehicle_id, fleet, downlink or DownlinkParams())
        self.onboard: Onboard | None = None  # the on-board estimate of the newest frame (own, or with the downlink)
        self._seeded_start: int | None = None  # the localizer's start count that a downlink seeded

    def receive_downlink(self, payload: bytes) -> str | None:
        """A PoseDownlink from the host (bytes as they arrived, verified if signed): kept for the next frames;
        the reason (counted) when it is refused."""
        msg = decode(payload, PoseDownlink)
        if isinstance(msg, Rejection):
            self.downlink.counts["received"] += 1
            self.downlink.counts[f"rejected_{msg.reason}"] += 1
            return msg.reason
        return self.downlink.receive(msg)

    def _seed_from_downlink(self, obs: Observations) -> None:
        """While the localizer searches for its start, a fresh downlink proposes one (:meth:`DownlinkFusion.seed`),
        which the localizer verifies as a known start."""
        res = self.last_result
        if self.localizer.phase is not Phase.SEARCHING or res is None or res.pose_filtered is None:
            return
        speed = float(obs.odometry.speed) if obs.odometry is not None else 0.0
        seed = self.downlink.seed(res.t, res.pose_filtered, res.cov_camera, speed, float(obs.t_meas))
        if seed is not None:
            self.localizer.reset(initial_pose=seed)
            self._seeded_start = self.localizer.stats.get("initialised", 0) + 1

    def _seeded(self) -> bool:
        """The localizer runs from a start the downlink seeded (its estimate holds some of the others' information)."""
        return self._seeded_start is not None and self.localizer.stats.get("initialised", 0) == self._seeded_start

    def _fuse_downlink(self, res: LocalizationResult) -> Onboard | None:
        """The on-board estimate of the body: the downlink is about the pose as the camera sees the map (the host's
        state: the others' objects sit where their cameras put them, and its cross-detections carry the error
        every frame repeats in their noise), so it is fused with the camera's covariance and that error
        (cov_filtered - cov_camera, common to both) is added after: fused with cov_filtered it would count
        the common error twice (the NEES of a 20 s urban run rose from about 2.7 to 4.2 of 2)."""
        if res.pose_filtered is None:
            return None
        self.downlink.record(res.t, res.pose_filtered, res.cov_camera)
        out = self.downlink.fuse(res.t, res.pose_filtered, res.cov_camera, correlated=self._seeded())
        return replace(out, cov=out.cov + (res.cov_filtered - res.cov_camera))

    def localize(self, t: float, obs: Observations) -> VehiclePrior | Rejection:
        """Self-localization of this frame as a VehiclePrior."""
        late = self._future(t, obs)
        if late is not None:
            return late
        self._seed_from_downlink(obs)
        res = self._step(obs.t_meas, camera_frame(obs), obs)
        if res.bad_input:
            return Rejection("bad_input", res.reason)
        self.last_result = res
        self.onboard = self._fuse_downlink(res)
        prior = VehiclePrior(
            fleet=self.fleet,
            sender=self.vehicle_id,
            seq=self._next_seq(),
            t_meas=obs.t_meas,
            t_sent=t,
            pose=res.pose_filtered if res.initialized else res.pose,
            pose_cov=cov_to_upper(res.cov_camera if res.initialized else res.cov),
            v_map=res.velocity_map,
            quality=LocalizationQuality(**res.quality()),
            objects=obs.objects,
            pose_filtered=True,
            pose_bias_sigma=np.asarray(self.localizer.params.match_bias_sigma, np.float16) if res.initialized else None,
            **self._integrity(res),
            downlink=self._downlink_said(),
        )
        self.last = prior
        return prior

    def _integrity(self, res: LocalizationResult) -> dict:
        """The prior's protection levels and their risk, while the localizer claims integrity (else neither)."""
        if res.protection_level is None:
            return {}
        return {
            "protection_level_m": np.asarray(res.protection_level, np.float32),
            "integrity_risk": float(self.localizer.params.integrity_risk),
        }

    def _downlink_said(self) -> str | None:
        """VehiclePrior.downlink: what the host's downlink did this frame."""
        if self._seeded():
            return "seeded"
        status = self.onboard.status if self.onboard is not None else "none"
        return {"fused": "fused", "fused_ci": "fused", "refused": "refused"}.get(status)

    def handle(self, t: float, frame: Observations) -> VehiclePrior | RawObservations | Rejection:
        """The V2X message for one sensor frame, sent at time t (a Rejection if the frame is refused)."""
        self._check_sender(frame)
        if self.mode == "distributed":
            return self.localize(t, frame)
        late = self._future(t, frame)
        if late is not None:
            return late
        try:
            mask = self._raw_mask(frame)
        except ValueError as exc:
            return Rejection("bad_input", f"lane mask: {exc}"[:200])
        return RawObservations(
            **frame.model_dump(exclude={"fleet", "sender", "seq", "t_sent", "lane_mask_png", "lane_mask_pooled_png"}),
            **mask,
            fleet=self.fleet,
            sender=self.vehicle_id,
            seq=self._next_seq(),
            t_sent=t,
        )

    def _raw_mask(self, frame: Observations) -> dict:
        """The raw message's lane-mask fields: the frame's mask pooled to ``raw_mask_max_width_px``
        (:func:`lanemask.pool_png`) in ``lane_mask_pooled_png``, or, narrow enough already, as it came."""
        png = frame.lane_mask_pooled_png or frame.lane_mask_png
        sent = lanemask.pool_png(png, self.raw_mask_max_width_px, _max_pixels(frame))
        if sent is frame.lane_mask_png:  # not pooled: at the camera's resolution, in its own field
            return {"lane_mask_png": sent, "lane_mask_pooled_png": None}
        return {"lane_mask_png": b"", "lane_mask_pooled_png": sent}

    def skip(self, t: float, frame: Observations) -> Rejection | None:
        """Keep what a frame the vehicle has no time to match still says: its odometry and GNSS fix.

        The localizer steps to the frame's time without its camera. Without this, the next frame's
        prediction spans the gap with only the odometry at its two ends: over 1.1 s dropped while
        turning at 35 degrees/s, that averaged a yaw rate of 35 and 0 degrees/s into a heading 11
        degrees off, which the following matches confirmed until GNSS reset the vehicle.
        Returns None, or the Rejection of a frame refused as :meth:`handle` refuses it.
        """
        self._check_sender(frame)
        refused = self._future(t, frame)
        if refused is None:
            res = self._step(frame.t_meas, None, frame)
            refused = Rejection("bad_input", res.reason) if res.bad_input else None
        return refused

    def _step(self, t_meas: float, camera: CameraFrame | None, obs: Observations) -> LocalizationResult:
        """One localizer step; the pose health follows it (:func:`.localization.health.advance`)."""
        inits = self.localizer.stats.get("initialised", 0)
        res = self.localizer.step(t_meas, camera, obs.odometry, obs.gnss)
        if not res.bad_input:
            matched = None if camera is None else res.mode == "map_matching"
            restarted = self.localizer.stats.get("initialised", 0) > inits
            self.pose_health = advance(
                self.pose_health, t_meas, self.localizer.phase, matched, restarted, self.health_params
            )
        return res

    def health(self) -> tuple[str, str | None]:
        """("ok", None), ("starting", why) or ("degraded", why): starting while it searches for its pose in its
        cold start, degraded while it does not know where it is (after a gap, a restart or a reset, until
        relocalized) or is not map-matched for long (:mod:`.localization.health`).
        Its own time is the newest step's; before the first step, "ok"."""
        return verdict(self.pose_health, self.health_params)

    @staticmethod
    def _future(t: float, frame: Observations) -> Rejection | None:
        if frame.t_meas > t + FUTURE_TOLERANCE_S:
            return Rejection("future", f"frame measured at {frame.t_meas:.3f} s handled at {t:.3f} s")
        return None

    def _check_sender(self, frame: Observations) -> None:
        if frame.sender != self.vehicle_id:
            raise ValueError(f"agent {self.vehicle_id} was given a frame from {frame.sender}")

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq - 1

    def figures(self) -> dict[str, float]:
        """Health figures: the latest localization quality."""
        if self.last is None:
            return {}
        q = self.last.quality
        return {
            "map_matching": float(q.mode == "map_matching"),
            "landmark_inliers": float(q.n_points + q.n_poles),
            "lane_inliers": float(q.n_lane),
            "pose_sigma_m": float(np.sqrt(np.trace(body_pose_cov(self.last)[:2, :2]))),
            "downlink_used": float(self.onboard is not None and self.onboard.used),
            **{f"downlink_{k}": float(v) for k, v in sorted(self.downlink.counts.items())},
        }
