"""The host container in either architecture (paper, "Distributed Fusion Architecture").

* distributed: vehicles localize themselves and send VehiclePriors; the
  :class:`~mapcontainer.fusion.Container` fuses them in its sliding-window factor graph.
* centralized: vehicles send RawObservations; the :class:`~mapcontainer.fusion.joint.JointHost` estimates
  every vehicle and object jointly from them (the accuracy reference).
"""

from __future__ import annotations

from .fusion import Container, FusionParams
from .hdmap.model import HDMap
from .vehicle import Mode

__all__ = ["make_host"]


def make_host(
    hdmap: HDMap,
    params: FusionParams,
    fleet: str,
    host_id: str,
    mode: Mode = "distributed",
    known_senders: set[str] | None = None,
):
    """A host core for ``mode``; feed it payload bytes with ``ingest`` and call ``fuse``."""
    if mode == "distributed":
        return Container(params, fleet, host_id, known_senders)
    if mode == "centralized":
        from .fusion.joint import JointHost

        return JointHost(hdmap, params, fleet, host_id, known_senders)
    raise ValueError(f"mode must be 'distributed' or 'centralized', got {mode!r}")
