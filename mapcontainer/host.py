"""The host container in either architecture (paper, "Distributed Fusion Architecture").

* distributed: vehicles localize themselves and send VehiclePriors; the container decodes them.
* centralized: vehicles send RawObservations; the host runs one map matcher per sender itself
  (the same :class:`~mapcontainer.vehicle.VehicleAgent` code a vehicle runs) and fuses the result.
"""

from __future__ import annotations

from schemas import RawObservations, Rejection, VehiclePrior

from .fusion import Container, FusionParams
from .hdmap.model import HDMap
from .vehicle import Mode, VehicleAgent

__all__ = ["HostLocalizer", "make_host"]


class HostLocalizer:
    """RawObservations -> host-side self-localization -> VehiclePrior (or a Rejection): the
    centralized mode's ``localize`` for :class:`~mapcontainer.fusion.Container`, which screens the
    frames first (fleet, known senders, time, duplicates).

    Each sender's localizer must see its frames in time order: a frame older than the last one
    localized for that sender is rejected as ``out_of_order`` (the channel's jitter can reorder).
    A sender silent for ``idle_s`` of scenario time loses its localizer (a host without a list of
    known senders would otherwise keep one for every name it ever saw); if it comes back, it starts
    afresh.
    """

    def __init__(self, hdmap: HDMap, fleet: str, idle_s: float = 30.0):
        self.hdmap = hdmap
        self.fleet = fleet
        self.idle_s = idle_s
        self.agents: dict[str, VehicleAgent] = {}
        self._last_t: dict[str, float] = {}

    def __call__(self, raw: RawObservations) -> VehiclePrior | Rejection:
        last = self._last_t.get(raw.sender)
        if last is not None and raw.t_meas <= last:
            return Rejection("out_of_order", f"t_meas {raw.t_meas} <= {last} already localized for {raw.sender}")
        for sender in [s for s, t in self._last_t.items() if t < raw.t_meas - self.idle_s]:
            del self._last_t[sender], self.agents[sender]
        agent = self.agents.get(raw.sender)
        if agent is None:
            agent = self.agents[raw.sender] = VehicleAgent(self.hdmap, raw.sender, self.fleet)
        self._last_t[raw.sender] = raw.t_meas
        try:
            return agent.localize(raw.t_sent, raw)
        except ValueError as exc:  # e.g. a lane mask that is not an image
            return Rejection("invalid", str(exc)[:200])


def make_host(
    hdmap: HDMap,
    params: FusionParams,
    fleet: str,
    host_id: str,
    mode: Mode = "distributed",
    known_senders: set[str] | None = None,
) -> Container:
    """A host container for ``mode``; feed it payload bytes with ``ingest`` and call ``fuse``."""
    if mode == "distributed":
        return Container(params, fleet, host_id, known_senders)
    if mode == "centralized":
        from .fusion.joint import JointHost

        return JointHost(hdmap, params, fleet, host_id, known_senders)
    raise ValueError(f"mode must be 'distributed' or 'centralized', got {mode!r}")
