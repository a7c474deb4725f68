"""Simulated sensors of a connected vehicle: camera, GNSS, odometry and an object detector.

Each sensor owns its random generator, so a vehicle's measurements depend only on the seed and
the true trajectories; each error source (calibration, persistent detector error, class confusion)
draws from a generator of its own, so switching one leaves the other streams as they were.
Parameters and their units: configs/sensors/default.yaml.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from schemas import LandmarkClass, ObjectClass

from .. import geometry as geo
from ..hdmap.model import HDMap
from .actors import ActorState
from .config import CalibrationErrorConfig, CameraConfig, DetectorConfig, GnssConfig, OdometryConfig
from .scene import ActorBoxes, RangeIndex, as_boxes

__all__ = ["Camera", "CameraObservation", "Gnss", "ObjectDetector", "Odometry", "occluded", "true_calibration"]

_OBJECT_CLASSES = np.array([ObjectClass.PEDESTRIAN, ObjectClass.VEHICLE, ObjectClass.CYCLIST], dtype=np.uint8)

_POLE_SAMPLES = 16
_LANE_SPACING_M = 0.5
_SOLID_RUN_M = 5.0


def occluded(
    origin,
    targets,
    boxes: ActorBoxes | Sequence[ActorState],
    exclude: np.ndarray | None = None,
    idx: np.ndarray | None = None,
) -> np.ndarray:
    """Which of the segments origin -> target (N, 3) pass through any actor box (slab test, all boxes at
    once: in each box's frame, the segment's entry and exit parameters over the three slabs).

    ``idx``: the boxes that may occlude (indices into ``boxes``; None: all of them). ``exclude``
    (N, number of those boxes) marks boxes that cannot occlude a target (its own box, the observer's).
    """
    targets = np.asarray(targets, dtype=float).reshape(-1, 3)
    boxes = as_boxes(boxes)
    idx = np.arange(len(boxes)) if idx is None else np.asarray(idx, dtype=int)
    if not len(idx) or not len(targets):
        return np.zeros(len(targets), dtype=bool)
    origin = np.asarray(origin, dtype=float)
    yaw, size = boxes.yaw[idx], boxes.size[idx]
    c, s = np.cos(yaw), np.sin(yaw)
    R_T = np.zeros((len(idx), 3, 3))  # map -> box frame
    R_T[:, 0, 0], R_T[:, 0, 1], R_T[:, 1, 0], R_T[:, 1, 1], R_T[:, 2, 2] = c, s, -s, c, 1.0
    o = np.einsum("mij,mj->mi", R_T, origin - boxes.p_map[idx])[:, None, :]  # (M, 1, 3)
    d = np.einsum("mij,nj->mni", R_T, targets - origin)  # (M, N, 3)
    zero = np.zeros(len(idx))
    lo = np.column_stack([-size[:, 0] / 2, -size[:, 1] / 2, zero])[:, None, :]
    hi = np.column_stack([size[:, 0] / 2, size[:, 1] / 2, size[:, 2]])[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o) / d
        t2 = (hi - o) / d
    parallel = np.abs(d) < 1e-12
    inside = (o >= lo) & (o <= hi)
    tmin = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)).max(axis=2)
    tmax = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2)).min(axis=2)
    hit = (tmax >= tmin) & (tmin > 1e-6) & (tmin < 1.0 - 1e-6)  # (M, N)
    if exclude is not None:
        hit &= ~np.asarray(exclude, dtype=bool).T
    return hit.any(axis=0)


@dataclass(frozen=True)
class CameraObservation:
    points_uv: np.ndarray  # (N, 2)
    points_cls: np.ndarray  # (N,) LandmarkClass codes
    point_ids: np.ndarray  # (N,) map feature id, -1 for clutter
    poles_uv: np.ndarray  # (M, 4)
    pole_ids: np.ndarray  # (M,) map feature id, -1 for clutter
    lane_mask: np.ndarray  # (H, W) uint8, 255 = lane marking


def true_calibration(
    intr: geo.CameraIntrinsics, T_body_cam: np.ndarray, err: CalibrationErrorConfig, rng: np.random.Generator | None
) -> tuple[geo.CameraIntrinsics, np.ndarray]:
    """The true intrinsics and T_body_cam of a camera whose reported calibration is (intr, T_body_cam).

    R_body_cam = R_body_cam_reported Exp(w), w ~ N(0, rotation_sigma^2 I) in the camera frame;
    t_body_cam = t_reported + N(0, translation_sigma^2 I); f = f_reported (1 + N(0, focal_sigma^2)) for fx
    and fy; (cx, cy) + N(0, principal_point_sigma_px^2 I). Ten draws from ``rng`` (also when the error is
    off or zero, so that the stream stays aligned); (intr, T_body_cam) unchanged when off or rng is None.
    """
    if rng is None:
        return intr, T_body_cam
    z = rng.normal(size=10)
    if not err.enabled:
        return intr, T_body_cam
    T = np.array(T_body_cam, dtype=float)
    T[:3, :3] = T[:3, :3] @ geo.so3_exp(z[:3] * err.rotation_sigma_rad)
    T[:3, 3] += z[3:6] * err.translation_sigma_m
    true = geo.CameraIntrinsics(
        intr.fx * (1 + err.focal_sigma * z[6]),
        intr.fy * (1 + err.focal_sigma * z[7]),
        intr.cx + err.principal_point_sigma_px * z[8],
        intr.cy + err.principal_point_sigma_px * z[9],
        intr.width,
        intr.height,
    )
    return true, T


class Camera:
    """A pinhole camera with landmark and lane-marking detectors.

    ``reported_intr`` and ``T_body_cam_reported`` are the calibration the vehicle believes (its
    CameraInfo); ``intr`` and ``T_body_cam`` the true ones it renders with (equal without calibration
    error: ``calib_rng`` None or ``cfg.calibration_error`` off). ``clutter`` False: no false landmarks.
    ``cull`` False: every frame projects every landmark and lane segment of the map (the brute force);
    otherwise those within range are found by :class:`~.scene.RangeIndex`, with the same frames.
    """

    def __init__(
        self,
        cfg: CameraConfig,
        hdmap: HDMap,
        rng: np.random.Generator,
        calib_rng: np.random.Generator | None = None,
        clutter: bool = True,
        cull: bool = True,
    ):
        self.cfg = cfg
        self.rng = rng
        self.clutter = clutter
        self.reported_intr = geo.CameraIntrinsics(
            cfg.f_px, cfg.f_px, (cfg.width - 1) / 2, (cfg.height - 1) / 2, cfg.width, cfg.height
        )
        self.T_body_cam_reported = geo.camera_extrinsic(*cfg.mount_xyz_m, pitch=cfg.pitch_rad)
        self.intr, self.T_body_cam = true_calibration(
            self.reported_intr, self.T_body_cam_reported, cfg.calibration_error, calib_rng
        )
        cls_code = {"traffic_light": LandmarkClass.TRAFFIC_LIGHT, "sign": LandmarkClass.SIGN}
        self._pt_xyz = np.array([f.p_map for f in hdmap.points]).reshape(-1, 3)
        self._pt_cls = np.array([cls_code[f.cls] for f in hdmap.points], dtype=np.uint8)
        self._pt_id = np.array([f.id for f in hdmap.points], dtype=int)
        self._pole_base = np.array([f.base for f in hdmap.poles]).reshape(-1, 3)
        self._pole_top = np.array([f.top for f in hdmap.poles]).reshape(-1, 3)
        self._pole_id = np.array([f.id for f in hdmap.poles], dtype=int)
        # Lane segments between consecutive painted samples; a "run" is one dash or 5 m of a solid line.
        a, b, run = [], [], []
        n_runs = 0
        for line in hdmap.lane_lines:
            s = np.arange(0.0, line.polyline.length, _LANE_SPACING_M)
            if line.kind == "dashed":
                period = line.dash_m + line.gap_m
                s = s[np.mod(s, period) < line.dash_m - 1e-9]
                run_of = np.floor(s / period).astype(int)
            else:
                run_of = np.floor(s / _SOLID_RUN_M).astype(int)
            p = line.polyline.point_at(s)
            step = np.diff(s)
            ok = step < 1.5 * _LANE_SPACING_M
            a.append(p[:-1][ok])
            b.append(p[1:][ok])
            run.append(run_of[:-1][ok] + n_runs)
            n_runs += int(run_of.max(initial=0)) + 1
        self._lane_a = np.vstack(a) if a else np.zeros((0, 3))
        self._lane_b = np.vstack(b) if b else np.zeros((0, 3))
        self._lane_run = np.concatenate(run) if run else np.zeros(0, int)
        self._n_runs = n_runs
        self._pt_index = RangeIndex(self._pt_xyz[:, :2], cull)
        # A pole's samples lie over the segment from its base to its top: within its half length (in the
        # plane; 0 when upright) of its middle.
        lean = np.linalg.norm(self._pole_top[:, :2] - self._pole_base[:, :2], axis=1) / 2
        self._pole_reach_m = float(lean.max(initial=0.0))
        self._pole_index = RangeIndex((self._pole_base[:, :2] + self._pole_top[:, :2]) / 2, cull)
        self._lane_index = RangeIndex(self._lane_a[:, :2], cull)

    def _p_detect(self, r: np.ndarray) -> np.ndarray:
        c = self.cfg
        return c.p_detect_near + (c.p_detect_far - c.p_detect_near) * np.clip(r / c.range_m, 0, 1)

    def observe(self, pose, actors: ActorBoxes | Sequence[ActorState], skip: int | None = None) -> CameraObservation:
        """One frame from a body at ``pose``. ``actors``: every actor but the observer (a list), or every
        actor with the observer's own index ``skip`` (the World's :class:`~.scene.ActorBoxes` of the tick).

        Only the boxes within reach of the camera's range are tested for occlusion, and only the lane
        segments that land in the image are drawn: the frame is the same as with every box and segment.
        """
        c, rng = self.cfg, self.rng
        boxes = as_boxes(actors)
        T_map_cam = geo.pose_to_matrix(pose) @ self.T_body_cam
        T_cam_map = geo.inverse(T_map_cam)
        cam_c = T_map_cam[:3, 3]
        # A box hides a point within range_m only if the box comes within range_m of the camera.
        hiders = boxes.near(cam_c, c.range_m + boxes.reach_m, skip)

        # Point landmarks: those within range (horizontally first) are projected.
        near = self._pt_index.near(cam_c, c.range_m)
        xyz = self._pt_xyz[near]
        uv, z = geo.project_points(self.intr, T_cam_map, xyz)
        r = np.linalg.norm(xyz - cam_c, axis=1)
        vis = (z > c.min_depth_m) & (r <= c.range_m)
        vis[vis] &= self.intr.in_image(uv[vis])
        vis[vis] &= ~occluded(cam_c, xyz[vis], boxes, idx=hiders)
        u = rng.random(len(self._pt_xyz))  # one draw per landmark of the map: the stream stays aligned
        det = vis & (u[near] < self._p_detect(r))
        pts = uv[det] + rng.normal(0.0, c.pixel_sigma_px, (int(det.sum()), 2))
        pts_cls, pts_id = self._pt_cls[near[det]], self._pt_id[near[det]]

        # Poles: the visible run of samples between base and top.
        poles, pole_ids = [], []
        near = self._pole_index.near(cam_c, c.range_m + self._pole_reach_m)
        if len(near):
            base, top = self._pole_base[near], self._pole_top[near]
            f = np.linspace(0.0, 1.0, _POLE_SAMPLES)
            samples = base[:, None] + f[None, :, None] * (top - base)[:, None]
            flat = samples.reshape(-1, 3)
            suv, sz = geo.project_points(self.intr, T_cam_map, flat)
            ok = (sz > c.min_depth_m) & (np.linalg.norm(flat - cam_c, axis=1) <= c.range_m)
            ok[ok] &= self.intr.in_image(suv[ok])
            ok[ok] &= ~occluded(cam_c, flat[ok], boxes, idx=hiders)
            ok = ok.reshape(len(near), _POLE_SAMPLES)
            suv = suv.reshape(len(near), _POLE_SAMPLES, 2)
            r_pole = np.linalg.norm(base - cam_c, axis=1)
            for i in np.flatnonzero(ok.sum(axis=1) >= 2):
                idx = np.flatnonzero(ok[i])
                seg = np.concatenate([suv[i, idx[0]], suv[i, idx[-1]]])
                if np.hypot(*(seg[2:] - seg[:2])) < 15.0 or rng.random() >= self._p_detect(r_pole[i]):
                    continue
                poles.append(seg + rng.normal(0.0, c.pixel_sigma_px, 4))
                pole_ids.append(self._pole_id[near[i]])

        # Clutter.
        n_cp = rng.poisson(c.clutter_points_per_frame if self.clutter else 0.0)
        if n_cp:
            pts = np.vstack([pts, rng.uniform((0, 0), (c.width - 1, c.height - 1), (n_cp, 2))])
            pts_cls = np.concatenate([pts_cls, rng.choice([LandmarkClass.TRAFFIC_LIGHT, LandmarkClass.SIGN], n_cp)])
            pts_id = np.concatenate([pts_id, -np.ones(n_cp, int)])
        for _ in range(rng.poisson(c.clutter_poles_per_frame if self.clutter else 0.0)):
            u, v = rng.uniform(0, c.width - 1), rng.uniform(0, c.height / 2)
            poles.append(np.array([u, v + rng.uniform(30, 200), u + rng.normal(0, 3), v]))
            pole_ids.append(-1)

        return CameraObservation(
            points_uv=np.asarray(pts, dtype=float).reshape(-1, 2),
            points_cls=np.asarray(pts_cls, dtype=np.uint8),
            point_ids=np.asarray(pts_id, dtype=int),
            poles_uv=np.asarray(poles, dtype=float).reshape(-1, 4),
            pole_ids=np.asarray(pole_ids, dtype=int),
            lane_mask=self._lane_mask(T_cam_map, cam_c, boxes, skip),
        )

    def _lane_mask(self, T_cam_map, cam_c, boxes: ActorBoxes, skip: int | None) -> np.ndarray:
        """Render the lane segmentation: projected painted markings, dropout, jitter, occlusion.

        Every segment in front of the camera draws its jitter (the noise stream stays as it is); a
        segment whose thick line lies wholly beside the image is not drawn (it would paint nothing).
        Segments of one thickness are drawn by one call (cv2.polylines draws each two-point polyline as
        cv2.line does).
        """
        c, rng = self.cfg, self.rng
        mask = np.zeros((c.height, c.width), np.uint8)
        near = self._lane_index.near(cam_c, c.lane_range_m)
        near = near[np.linalg.norm(self._lane_a[near, :2] - cam_c[:2], axis=1) <= c.lane_range_m]
        kept_runs = rng.random(self._n_runs) >= c.lane_dropout  # one draw per run of the map
        sel = near[kept_runs[self._lane_run[near]]]
        a, b = self._lane_a[sel], self._lane_b[sel]
        uv_a, z_a = geo.project_points(self.intr, T_cam_map, a)
        uv_b, z_b = geo.project_points(self.intr, T_cam_map, b)
        front = (z_a > c.min_depth_m) & (z_b > c.min_depth_m)
        uv_a, uv_b = uv_a[front], uv_b[front]
        z = 0.5 * (z_a[front] + z_b[front])
        jitter = rng.normal(0.0, c.lane_pixel_sigma_px, (len(z), 2))
        thick = np.clip(np.rint(self.intr.fx * c.lane_marking_width_m / z), 1, 40).astype(int)
        pa = np.rint((uv_a + jitter) * 4).astype(np.int32)  # 2 fractional bits for cv2's shift
        pb = np.rint((uv_b + jitter) * 4).astype(np.int32)
        lim = 4 * 10 * max(c.width, c.height)
        keep = (np.abs(pa) < lim).all(axis=1) & (np.abs(pb) < lim).all(axis=1)
        keep &= _in_view(pa, pb, thick, c.width, c.height)
        _draw_lines(mask, pa[keep], pb[keep], thick[keep])
        # Actors hide the road behind them (one projection of every near actor's 8 box corners).
        near_idx = boxes.near(cam_c, c.lane_range_m + 5, skip)
        near_idx = near_idx[np.linalg.norm(boxes.p_map[near_idx, :2] - cam_c[:2], axis=1) <= c.lane_range_m + 5]
        if len(near_idx):
            uv, zc = geo.project_points(self.intr, T_cam_map, boxes.corners(near_idx).reshape(-1, 3))
            for uv_o, z_o in zip(uv.reshape(-1, 8, 2), zc.reshape(-1, 8), strict=True):
                if not np.any(z_o < 0.2):
                    cv2.fillConvexPoly(mask, cv2.convexHull(np.rint(uv_o).astype(np.int32)), 0)
        return mask


def _in_view(pa: np.ndarray, pb: np.ndarray, thick: np.ndarray, width: int, height: int) -> np.ndarray:
    """Which lines (end points ``pa``, ``pb`` in pixels x 4, widths ``thick`` px) may paint a pixel of a
    width x height image: not those with both ends beyond one edge by more than their width + 2 px (a
    thick line paints within half its width, plus rounding, of its segment)."""
    m = 4 * (thick[:, None] + 2)
    lo = np.minimum(pa, pb)
    hi = np.maximum(pa, pb)
    size = 4 * np.array([width - 1, height - 1])
    return ((hi >= -m) & (lo <= size + m)).all(axis=1)


def _draw_lines(mask: np.ndarray, pa: np.ndarray, pb: np.ndarray, thick: np.ndarray) -> None:
    """cv2.line(mask, pa[i], pb[i], 255, thick[i], LINE_8, shift=2) for every i, one call per width."""
    if not len(thick):
        return
    seg = np.stack([pa, pb], axis=1)
    order = np.argsort(thick, kind="stable")
    widths, starts = np.unique(thick[order], return_index=True)
    for t, group in zip(widths, np.split(order, starts[1:]), strict=True):
        cv2.polylines(mask, list(seg[group]), False, 255, int(t), cv2.LINE_8, 2)


class Gnss:
    """Fix = truth + white noise + Gauss-Markov bias + multipath episodes (horizontal jumps)."""

    def __init__(self, cfg: GnssConfig, rng: np.random.Generator):
        self.cfg = cfg
        self.rng = rng
        self.bias = rng.normal(0.0, cfg.bias_sigma_m, 2)
        self.jump = np.zeros(2)
        self.jump_until = -np.inf

    def measure(self, t: float, p_true, dt: float) -> tuple[np.ndarray, float, float]:
        """(p_map fix, reported sigma_h, reported sigma_v) at time t; advances the error state by dt."""
        c, rng = self.cfg, self.rng
        phi = np.exp(-dt / c.bias_tau_s)
        self.bias = phi * self.bias + np.sqrt(1 - phi**2) * c.bias_sigma_m * rng.normal(size=2)
        if t >= self.jump_until:
            self.jump = np.zeros(2)
            if rng.random() < c.multipath_rate_per_s * dt:
                ang = rng.uniform(0, 2 * np.pi)
                self.jump = rng.uniform(*c.multipath_jump_m) * np.array([np.cos(ang), np.sin(ang)])
                self.jump_until = t + rng.uniform(*c.multipath_duration_s)
        err = np.concatenate(
            [self.bias + self.jump + rng.normal(0, c.white_sigma_m, 2), [rng.normal(0, c.vertical_sigma_m)]]
        )
        return np.asarray(p_true, float) + err, c.reported_sigma_h_m, c.reported_sigma_v_m


class Odometry:
    """Wheel speed with a per-vehicle scale error, gyro yaw rate with a per-vehicle bias."""

    def __init__(self, cfg: OdometryConfig, rng: np.random.Generator):
        self.cfg = cfg
        self.rng = rng
        self.scale = 1.0 + rng.normal(0.0, cfg.speed_scale_sigma)
        self.yaw_bias = rng.normal(0.0, cfg.yaw_rate_bias_sigma_radps)

    def measure(self, speed: float, yaw_rate: float) -> tuple[float, float]:
        c, rng = self.cfg, self.rng
        return (
            float(speed * self.scale + rng.normal(0, c.speed_sigma_mps)),
            float(yaw_rate + self.yaw_bias + rng.normal(0, c.yaw_rate_sigma_radps)),
        )


class ObjectDetector:
    """Body-frame object positions with range-dependent noise, misses, false alarms and occlusion.

    Noise model: along the line of sight sigma_r = a_r + b_r * r, across it sigma_t = a_t + b_t * r,
    vertically sigma_z; C(p) = R diag(sigma_r^2, sigma_t^2, sigma_z^2) R^T with R the rotation from
    line-of-sight axes to the body frame, L(p) its Cholesky factor. A detection of a target at p is

        z = p' + L(p) (sqrt(1 - f) n + sqrt(f) u_k),   n ~ N(0, I) white,
        u_k = phi u_{k-1} + sqrt(1 - phi^2) w,  phi = exp(-dt / tau),  u_0, w ~ N(0, I),

    with p' = T_body_cam_reported T_cam_body p the position seen through a camera whose true extrinsic
    differs from the reported one (``T_rep_true``; identity without calibration error), u the persistent
    error of this (observer, target) pair (a first-order Gauss-Markov process, f = persistent_fraction)
    and the reported covariance s^2 C(z) at the measured position (s = exp(N(0, reported_scale_sigma))
    per vehicle). With ``cfg.errors`` off: f = 0, s = 1 and the covariance at the true position, C(p).
    A detection's class is another one with probability ``cfg.class_confusion.p``.
    False objects: ghosts born uniform in the field of view that stay where they appeared (map frame)
    for an exponential lifetime (``false_alarm_lifetime_s``; 0: a new set every frame).
    """

    def __init__(
        self,
        cfg: DetectorConfig,
        sensor_xyz_body,
        rng: np.random.Generator,
        err_rng: np.random.Generator | None = None,
        confusion_rng: np.random.Generator | None = None,
        T_rep_true: np.ndarray | None = None,
        clutter: bool = True,
    ):
        self.cfg = cfg
        self.rng = rng
        self.err_rng = err_rng
        self.confusion_rng = confusion_rng
        self.clutter = clutter
        self.sensor_body = np.asarray(sensor_xyz_body, dtype=float)
        self.T_rep_true = np.eye(4) if T_rep_true is None else np.asarray(T_rep_true, dtype=float)
        errs = cfg.errors.enabled and err_rng is not None
        z = err_rng.normal() if err_rng is not None else 0.0
        self.persistent_fraction = cfg.errors.persistent_fraction if errs else 0.0
        self.sigma_scale = float(np.exp(cfg.errors.reported_scale_sigma * z)) if errs else 1.0
        self.cov_at_measurement = errs
        self._persistent: dict[str, tuple[np.ndarray, float]] = {}  # target id -> (u, t of u)
        self._ghosts: list[tuple[np.ndarray, int, float]] = []  # (p_map, class, end time)
        self._t_last: float | None = None

    def covariance(self, p_body: np.ndarray) -> np.ndarray:
        """Nominal (N, 3, 3) covariance of detections at body positions p_body (N, 3)."""
        c = self.cfg
        rel = p_body[:, :2] - self.sensor_body[:2]
        r = np.linalg.norm(rel, axis=1)
        beta = np.arctan2(rel[:, 1], rel[:, 0])
        sr = c.sigma_radial_m[0] + c.sigma_radial_m[1] * r
        st = c.sigma_tangential_m[0] + c.sigma_tangential_m[1] * r
        u = np.stack([np.cos(beta), np.sin(beta), np.zeros_like(beta)], axis=1)
        t = np.stack([-np.sin(beta), np.cos(beta), np.zeros_like(beta)], axis=1)
        return (
            sr[:, None, None] ** 2 * u[:, :, None] * u[:, None, :]
            + st[:, None, None] ** 2 * t[:, :, None] * t[:, None, :]
            + np.diag([0.0, 0.0, c.sigma_vertical_m**2])
        )

    def _reported_cov(self, truth: np.ndarray, measured: np.ndarray) -> np.ndarray:
        if self.cov_at_measurement:
            return self.sigma_scale**2 * self.covariance(measured)
        return self.covariance(truth)

    def _persistent_part(self, ids: list[str], t: float | None) -> np.ndarray:
        """u (K, 3) of the targets ``ids`` at time t, advanced from their last value (fresh without t)."""
        out = np.zeros((len(ids), 3))
        if self.persistent_fraction <= 0.0 or self.err_rng is None:
            return out
        tau = self.cfg.errors.tau_s
        for i, tid in enumerate(ids):
            w = self.err_rng.normal(size=3)
            last = self._persistent.get(tid) if t is not None else None
            if last is None:
                u = w
            else:
                phi = np.exp(-max(t - last[1], 0.0) / tau)
                u = phi * last[0] + np.sqrt(1.0 - phi**2) * w
            if t is not None:
                self._persistent[tid] = (u, t)
            out[i] = u
        return out

    def _confuse(self, cls: np.ndarray) -> np.ndarray:
        """Each class replaced by another object class with probability ``class_confusion.p``."""
        if self.confusion_rng is None or not len(cls):
            return cls
        u = self.confusion_rng.random((len(cls), 2))
        cc = self.cfg.class_confusion
        if not cc.enabled or cc.p <= 0:
            return cls
        out = cls.copy()
        for i in np.flatnonzero(u[:, 0] < cc.p):
            others = _OBJECT_CLASSES[_OBJECT_CLASSES != cls[i]]
            out[i] = others[min(int(u[i, 1] * len(others)), len(others) - 1)]
        return out

    def _uniform_in_view(self, n: int) -> np.ndarray:
        """n body-frame points (n, 3) on the ground, uniform in range (3 m to range_m) and bearing."""
        c, rng = self.cfg, self.rng
        rr = rng.uniform(3.0, c.range_m, n)
        bb = rng.uniform(-np.radians(c.fov_deg) / 2, np.radians(c.fov_deg) / 2, n)
        return np.column_stack([rr * np.cos(bb), rr * np.sin(bb), np.zeros(n)]) + self.sensor_body * [1, 1, 0]

    def _false_alarms(self, observer: ActorState, t: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """False objects of this frame: where they are (K, 3) and where they are measured (K, 3) in the
        body frame, and their classes (K,). A new set every frame stands still (no noise of its own)."""
        c, rng = self.cfg, self.rng
        rate = c.false_alarms_per_frame if self.clutter else 0.0
        life = c.false_alarm_lifetime_s
        if life <= 0.0 or t is None:  # a new set every frame
            n_fa = rng.poisson(rate)
            if not n_fa:
                return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.uint8)
            fa = self._uniform_in_view(n_fa)
            return fa, fa, rng.choice([1, 2], n_fa).astype(np.uint8)
        # Ghosts: a stationary population of mean `rate`; births at rate / life per second.
        T_map_body = geo.pose_to_matrix(observer.pose)
        dt = 0.0 if self._t_last is None else max(t - self._t_last, 0.0)
        n_new = rng.poisson(rate if self._t_last is None else rate * dt / life)
        self._t_last = t
        if n_new:
            p_map = geo.transform_points(T_map_body, self._uniform_in_view(n_new)).reshape(-1, 3)
            cls = rng.choice([1, 2], n_new)
            ends = t + rng.exponential(life, n_new)
            self._ghosts += [(p_map[i], int(cls[i]), float(ends[i])) for i in range(n_new)]
        self._ghosts = [g for g in self._ghosts if g[2] > t]
        if not self._ghosts:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.uint8)
        p_body = geo.transform_points(geo.inverse(T_map_body), np.array([g[0] for g in self._ghosts])).reshape(-1, 3)
        p_body[:, 2] = 0.0
        rel = p_body[:, :2] - self.sensor_body[:2]
        r = np.linalg.norm(rel, axis=1)
        inview = (r <= c.range_m) & (np.abs(np.arctan2(rel[:, 1], rel[:, 0])) <= np.radians(c.fov_deg) / 2)
        cls = np.array([g[1] for g in self._ghosts], dtype=np.uint8)
        p_body = p_body[inview]
        L = np.linalg.cholesky(self.covariance(p_body))
        return p_body, p_body + np.einsum("nij,nj->ni", L, rng.normal(size=p_body.shape)), cls[inview]

    def candidate_radius(self, T_map_body: np.ndarray, sensor_map: np.ndarray, boxes: ActorBoxes) -> float:
        """How far from the sensor (horizontally, map frame) a target in range can be.

        The range is measured in the body's x-y plane, which tilts with the body's roll and pitch. For a
        target at horizontal distance h and height difference dz from the sensor, with the body z axis at
        an angle theta from the vertical (sin theta = s), its body-frame height is at most |dz| + h s, so
        its distance in the body's x-y plane is at least sqrt(h^2 (1 - s^2) - 2 |dz| h s): in range only if
        h <= (|dz| s + sqrt(dz^2 s^2 + (1 - s^2) R^2)) / (1 - s^2), dz bounded by the actors' heights
        (their footprint centres'). Inf (every actor) for a body tilted by 30 degrees or more.
        """
        R = self.cfg.range_m
        s = float(np.hypot(T_map_body[0, 2], T_map_body[1, 2]))
        if s >= 0.5:  # tipped over by more than 30 degrees: look at every actor
            return np.inf
        dz = max(abs(z - float(sensor_map[2])) for z in boxes.z_range_m)
        return (dz * s + np.sqrt(dz**2 * s**2 + (1 - s**2) * R**2)) / (1 - s**2) * (1 + 1e-9) + 1e-6

    def observe(self, observer: ActorState, actors: ActorBoxes | Sequence[ActorState], t=None, skip: int | None = None):
        """Detections by ``observer`` at time ``t`` (true scenario time; None: no persistent error and no
        ghosts, each call stands alone): (p_body (K,3), cov (K,3,3), cls (K,), truth ids).

        ``actors``: every actor but the observer (a list), or every actor with the observer's own index
        ``skip`` (the World's :class:`~.scene.ActorBoxes` of the tick). The targets are those actors, the
        occluders of a target every one of them but itself. Only the actors within reach of the range
        are looked at (:meth:`candidate_radius`); a miss is drawn for every target all the same, so the
        noise streams are those of a detector that looks at every actor.
        """
        c, rng = self.cfg, self.rng
        boxes = as_boxes(actors)
        T_map_body = geo.pose_to_matrix(observer.pose)
        T_body_map = geo.inverse(T_map_body)
        sensor_map = geo.transform_points(T_map_body, self.sensor_body)
        n_targets = len(boxes) - (skip is not None)
        radius = self.candidate_radius(T_map_body, sensor_map, boxes)
        cand = boxes.near(sensor_map, radius, skip)
        p_tgt = boxes.p_map[cand]
        p_body = geo.transform_points(T_body_map, p_tgt).reshape(-1, 3)
        rel = p_body[:, :2] - self.sensor_body[:2]
        r = np.linalg.norm(rel, axis=1)
        bearing = np.arctan2(rel[:, 1], rel[:, 0])
        vis = (r <= c.range_m) & (np.abs(bearing) <= np.radians(c.fov_deg) / 2)
        if vis.any():
            seen_idx = cand[vis]
            centres = p_tgt[vis] + np.array([[0.0, 0.0, 1.0]]) * (boxes.size[seen_idx, 2] / 2)[:, None]
            hiders = boxes.near(sensor_map, radius + boxes.reach_m, skip)
            blocked = occluded(sensor_map, centres, boxes, seen_idx[:, None] == hiders[None, :], idx=hiders)
            vis[np.flatnonzero(vis)[blocked]] = False
        p_det = c.p_detect_near + (c.p_detect_far - c.p_detect_near) * np.clip(r / c.range_m, 0, 1)
        u = rng.random(n_targets)  # one draw per target, in the actors' order
        pos = cand if skip is None else cand - (cand > skip)
        det = vis & (u[pos] < p_det)
        truth = p_body[det]
        ids: list[str | None] = [str(i) for i in boxes.ids[cand[det]]]
        cls = boxes.cls[cand[det]]
        L = np.linalg.cholesky(self.covariance(truth))
        f = self.persistent_fraction
        e = np.sqrt(1.0 - f) * rng.normal(size=truth.shape) + np.sqrt(f) * self._persistent_part(ids, t)
        seen = geo.transform_points(self.T_rep_true, truth).reshape(-1, 3)
        noisy = seen + np.einsum("nij,nj->ni", L, e)
        cov = self._reported_cov(truth, noisy)
        fa, fa_noisy, fa_cls = self._false_alarms(observer, t)
        if len(fa):
            noisy = np.vstack([noisy, fa_noisy])
            cov = np.concatenate([cov, self._reported_cov(fa, fa_noisy)])
            cls = np.concatenate([cls, fa_cls])
            ids += [None] * len(fa)
        return noisy, cov, self._confuse(cls), ids
