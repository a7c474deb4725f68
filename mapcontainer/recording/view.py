"""Our messages drawn in Rerun (the viewer of ``mapc view``): pure conversion, no network of ours.

:class:`RerunView` turns each message into Rerun archetypes on a ``rerun.RecordingStream``; the
services side (``services.viewer``) feeds it from a live fleet or a recording and serves Rerun's web
viewer, which the ``rerun-sdk`` wheel ships (WebAssembly, served from this machine: no CDN).

Entities, in the map frame (ENU, metres), on the timeline ``scenario`` (``t_meas``, seconds):

* ``map/lanes`` (lane lines), ``map/landmarks`` (poles as segments, point landmarks), static;
* ``truth/vehicles`` (green boxes with ids) and ``truth/obstacles`` (grey points: the ghosts of what
  the fused picture should hold);
* ``fused/vehicles`` (orange boxes with ids) and ``fused/vehicle_covariance`` (their position
  covariance as ellipsoids), ``fused/objects`` (ellipsoids with track ids);
* ``downlink/<vid>``: the host's downlink as vehicle ``vid`` received it (``downlink_rx``: what the others know
  about its position, a flat ellipse of the horizontal covariance at its centre), coloured by what the vehicle
  did with it as its priors say (``VehiclePrior.downlink``, ``prior_tx``): cyan when it used it (fused, or
  seeded its localizer), red when its gate refused it, grey until a prior says; labelled ``<vid> ← others:
  <status>``. A direction the others know nothing about is drawn ``DOWNLINK_MAX_SIGMA_M`` long;
* ``health`` (a table of every service's state and figures, on the ``wall`` timeline) and
  ``figures/*`` (the evaluator's RMSEs and latency as scalars).

Ellipsoids are drawn at :data:`~.foxglove.SIGMAS` standard deviations: half sizes SIGMAS sqrt(w) of the
eigenvalues w of the 3x3 position covariance, rotated by its eigenvectors.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from schemas.arrays import cov_from_upper
from schemas.codec import Rejection, decode
from schemas.models import EvalMetrics, FusedState, GroundTruth, HealthStatus, PoseDownlink, VehiclePrior
from schemas.topics import topic

from ..geometry import rpy_to_matrix
from .foxglove import SIGMAS, VEHICLE_SIZE, _quat

__all__ = ["COLORS", "DOWNLINK_MAX_SIGMA_M", "RerunView", "downlink_ellipse"]

COLORS = {
    "lane": (0, 150, 150),
    "pole": (200, 160, 0),
    "light": (220, 30, 30),
    "sign": (40, 80, 230),
    "truth": (30, 200, 50),
    "obstacle": (150, 150, 150),
    "fused": (255, 128, 0),
    "object": (230, 40, 190),
    "downlink_used": (0, 200, 255),
    "downlink_refused": (230, 0, 0),
    "downlink_unknown": (120, 120, 200),
}
# what a vehicle did with the downlink (VehiclePrior.downlink) -> its colour
DOWNLINK_COLORS = {"fused": "downlink_used", "seeded": "downlink_used", "refused": "downlink_refused"}
DOWNLINK_MAX_SIGMA_M = 10.0  # a direction without information is drawn this long (1 sigma)
DOWNLINK_THICKNESS_M = 0.05  # the ellipse's half height: a flat disc on the road


def _xyzw(R: np.ndarray) -> list[float]:
    q = _quat(R)
    return [q["x"], q["y"], q["z"], q["w"]]


def _axes(C: np.ndarray) -> tuple[np.ndarray, list[float]]:
    """Half sizes and rotation (x, y, z, w) of the ellipsoid of a 3x3 covariance at SIGMAS."""
    C = 0.5 * (np.asarray(C, float) + np.asarray(C, float).T)
    w, U = np.linalg.eigh(C)
    if np.linalg.det(U) < 0:
        U[:, 2] = -U[:, 2]
    return SIGMAS * np.sqrt(np.maximum(w, 1e-8)), _xyzw(U)


def downlink_ellipse(m: PoseDownlink) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """Centre, half sizes and rotation (x, y, z, w) of a downlink's horizontal ellipse: the eigen-decomposition
    Y = U diag(w) U^T of the information of x, y gives the axes U and the 1-sigmas 1 / sqrt(w) (at most
    DOWNLINK_MAX_SIGMA_M: a direction without information), drawn at SIGMAS; DOWNLINK_THICKNESS_M high."""
    Y = cov_from_upper(np.asarray(m.pose_info, float))[:2, :2]
    w, U = np.linalg.eigh(0.5 * (Y + Y.T))
    sigma = np.minimum(1.0 / np.sqrt(np.maximum(w, 1e-12)), DOWNLINK_MAX_SIGMA_M)
    R = np.eye(3)
    R[:2, :2] = U if np.linalg.det(U) > 0 else U[:, ::-1]
    sigma = sigma if np.linalg.det(U) > 0 else sigma[::-1]
    half = np.array([SIGMAS * sigma[0], SIGMAS * sigma[1], DOWNLINK_THICKNESS_M])
    return np.asarray(m.pose[:3], float), half, _xyzw(R)


class RerunView:
    """Draws messages on ``rec`` (a ``rerun.RecordingStream``); :meth:`handle` takes a key and its payload."""

    def __init__(self, rec: Any, verifier: Any = None):
        import rerun as rr

        self.rr = rr
        self.rec = rec
        self.verifier = verifier  # the fleet's CA (a Verifier): draw only truth, fused states and metrics it signed
        self.refused: dict[str, int] = {}  # what did not verify, by reason
        self.health: dict[str, tuple[str, str, dict]] = {}
        self._truth, self._fused, self._health, self._metrics = (
            topic("truth"),
            topic("fused"),
            topic("health"),
            topic("metrics"),
        )
        self._downlink, self._prior = topic("downlink_rx"), topic("prior_tx")
        self.downlinks: dict[str, PoseDownlink] = {}  # vid -> the newest downlink it received
        self.downlink_status: dict[str, str] = {}  # vid -> what it did with the downlink, as its newest prior says
        self.drawn = {"truth": 0, "fused": 0, "health": 0, "metrics": 0, "downlink": 0}

    def layout(self) -> None:
        """The page: the 3-D scene large on the left, the services' health and the figures on the right."""
        import rerun.blueprint as rrb

        self.rec.send_blueprint(
            rrb.Blueprint(
                rrb.Horizontal(
                    rrb.Spatial3DView(
                        name="map frame", origin="/", contents=["map/**", "truth/**", "fused/**", "downlink/**"]
                    ),
                    rrb.Vertical(
                        rrb.TextDocumentView(name="health", origin="health"),
                        rrb.TimeSeriesView(name="figures", origin="figures"),
                    ),
                    column_shares=[3, 1],
                ),
                rrb.BlueprintPanel(state="collapsed"),
                rrb.SelectionPanel(state="collapsed"),
                rrb.TimePanel(state="collapsed"),
            )
        )

    def log_map(self, hdmap) -> None:
        rr = self.rr
        strips = [np.asarray(ln.points, float) for ln in hdmap.lane_lines]
        self.rec.log("map/lanes", rr.LineStrips3D(strips, colors=[COLORS["lane"]], radii=0.08), static=True)
        poles = [np.stack([f.base, f.top]) for f in hdmap.poles]
        self.rec.log("map/landmarks/poles", rr.LineStrips3D(poles, colors=[COLORS["pole"]], radii=0.15), static=True)
        pts = np.array([f.p_map for f in hdmap.points], float).reshape(-1, 3)
        cols = [COLORS["light"] if f.cls == "traffic_light" else COLORS["sign"] for f in hdmap.points]
        self.rec.log("map/landmarks/points", rr.Points3D(pts, colors=cols, radii=0.4), static=True)

    def _boxes(self, poses, ids, color) -> Any:
        poses = np.asarray(poses, float).reshape(-1, 6)
        return self.rr.Boxes3D(
            centers=poses[:, :3] + [0, 0, VEHICLE_SIZE[2] / 2],
            half_sizes=[[s / 2 for s in VEHICLE_SIZE]] * len(poses),
            quaternions=[self.rr.Quaternion(xyzw=_xyzw(rpy_to_matrix(*p[3:]))) for p in poses],
            colors=[color],
            labels=list(ids),
            fill_mode="solid",
        )

    def truth(self, m: GroundTruth) -> None:
        rr = self.rr
        self.rec.set_time("scenario", duration=float(m.t_meas))
        self.rec.log("truth/vehicles", self._boxes(m.vehicle_pose, m.vehicle_ids, COLORS["truth"]))
        obs = np.asarray(m.obstacle_p_map, float).reshape(-1, 3)
        self.rec.log("truth/obstacles", rr.Points3D(obs + [0, 0, 0.9], colors=[COLORS["obstacle"]], radii=0.4))
        self.drawn["truth"] += 1

    def fused(self, m: FusedState) -> None:
        rr = self.rr
        self.rec.set_time("scenario", duration=float(m.t_meas))
        poses = np.asarray(m.vehicle_pose, float).reshape(-1, 6)
        self.rec.log("fused/vehicles", self._boxes(poses, m.vehicle_ids, COLORS["fused"]))
        pc = cov_from_upper(np.asarray(m.vehicle_pose_cov, float).reshape(-1, 21))
        ax = [_axes(C[:3, :3]) for C in pc]
        self.rec.log(
            "fused/vehicle_covariance",
            rr.Ellipsoids3D(
                centers=poses[:, :3],
                half_sizes=[a for a, _ in ax],
                quaternions=[rr.Quaternion(xyzw=q) for _, q in ax],
                colors=[COLORS["fused"]],
            ),
        )
        ps = np.asarray(m.object_p_map, float).reshape(-1, 3)
        oc = cov_from_upper(np.asarray(m.object_cov, float).reshape(-1, 6))
        ax = [_axes(C) for C in oc]
        self.rec.log(
            "fused/objects",
            rr.Ellipsoids3D(
                centers=ps,
                half_sizes=[a for a, _ in ax],
                quaternions=[rr.Quaternion(xyzw=q) for _, q in ax],
                colors=[COLORS["object"]],
                labels=[f"#{int(i)}" for i in m.object_id],
                fill_mode="solid",
            ),
        )
        self.drawn["fused"] += 1

    def downlink(self, m: PoseDownlink) -> None:
        """A downlink its target received: drawn with what the target last said it did with one."""
        self.downlinks[m.target] = m
        self._draw_downlink(m.target, float(m.t_meas))

    def prior(self, m: VehiclePrior) -> None:
        """A vehicle's prior: what it did with the downlink this frame recolours its downlink."""
        if m.downlink is None or self.downlink_status.get(m.sender) == m.downlink:
            return
        self.downlink_status[m.sender] = m.downlink
        if m.sender in self.downlinks:
            self._draw_downlink(m.sender, float(m.t_meas))

    def _draw_downlink(self, vid: str, t: float) -> None:
        centre, half, q = downlink_ellipse(self.downlinks[vid])
        status = self.downlink_status.get(vid)
        color = COLORS[DOWNLINK_COLORS.get(status or "", "downlink_unknown")]
        self.rec.set_time("scenario", duration=t)
        self.rec.log(
            f"downlink/{vid}",
            self.rr.Ellipsoids3D(
                centers=[centre],
                half_sizes=[half],
                quaternions=[self.rr.Quaternion(xyzw=q)],
                colors=[color],
                labels=[f"{vid} ← others: {status or 'not said yet'}"],
                fill_mode="solid",
            ),
        )
        self.drawn["downlink"] += 1

    def health_table(self, m: HealthStatus, wall_ns: int) -> None:
        figs = {k: v for k, v in (m.figures or {}).items() if isinstance(v, int | float)}
        self.health[f"{m.role}/{m.sender}"] = (m.state, m.last_error or "", figs)
        rows = ["| service | state | figures |", "|---|---|---|"]
        for name, (state, err, f) in sorted(self.health.items()):
            shown = ", ".join(f"{k} {v:.3g}" for k, v in sorted(f.items())[:8])
            rows.append(f"| {name} | {state}{' (' + err + ')' if err else ''} | {shown} |")
        self.rec.set_time("wall", timestamp=wall_ns * 1e-9)
        self.rec.log("health", self.rr.TextDocument("\n".join(rows), media_type="text/markdown"))
        self.drawn["health"] += 1

    def metrics(self, m: EvalMetrics, wall_ns: int) -> None:
        self.rec.set_time("wall", timestamp=wall_ns * 1e-9)
        for name in ("vehicle_rmse_m", "object_rmse_m", "e2e_latency_ms_p50"):
            v = getattr(m, name, None)
            if isinstance(v, int | float) and np.isfinite(v):
                self.rec.log(f"figures/{name}", self.rr.Scalars(float(v)))
        self.drawn["metrics"] += 1

    def handle(self, key: str, payload: bytes, wall_ns: int) -> bool:
        """Draw one message of ``key``; False if it is not one drawn, does not verify (counted in
        ``refused``; with a verifier: truth signed by the world, a fused state by its host or standby,
        metrics by the evaluator, a downlink by its host, a prior by its vehicle) or does not decode (a
        downlink about another vehicle than the one whose key it came on: refused, ``wrong_target``)."""
        from ..security import fused_signers, inner_payload

        if self._truth.parse(key) is not None:
            m = self._believed(payload, wall_ns, GroundTruth, "world")
            return bool(m) and (self.truth(m) is None)
        if (where := self._fused.parse(key)) is not None:
            m = self._believed(payload, wall_ns, FusedState, fused_signers(where["hid"]))
            return bool(m) and (self.fused(m) is None)
        if self._health.parse(key) is not None:
            m = decode(inner_payload(payload), HealthStatus)
            return bool(m) and (self.health_table(m, wall_ns) is None)
        if self._metrics.parse(key) is not None:
            m = self._believed(payload, wall_ns, EvalMetrics, "evaluator")
            return bool(m) and (self.metrics(m, wall_ns) is None)
        if (where := self._downlink.parse(key)) is not None:  # signed by the host, for the vehicle of the key
            m = self._believed(payload, wall_ns, PoseDownlink, where["src"])
            if m and m.target != where["dst"]:
                self.refused["wrong_target"] = self.refused.get("wrong_target", 0) + 1
                return False
            return bool(m) and (self.downlink(m) is None)
        if (where := self._prior.parse(key)) is not None:  # signed by its vehicle
            m = self._believed(payload, wall_ns, VehiclePrior, where["src"])
            return bool(m) and (self.prior(m) is None)
        return False

    def _believed(self, payload: bytes, wall_ns: int, model, senders):
        from ..security import unwrap

        inner = unwrap(payload, self.verifier, wall_ns * 1e-9, senders)
        if isinstance(inner, Rejection):
            self.refused[inner.reason] = self.refused.get(inner.reason, 0) + 1
            return None
        return decode(inner, model)
