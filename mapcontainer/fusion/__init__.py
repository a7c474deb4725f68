"""Host container: reorder buffer, association, sliding-window factor graph (paper §III-D).

The names below are imported on first use (PEP 562): ``mapcontainer.fusion.params`` and ``.gate`` load
without the solver, so a process that only configures a host (the host service's main process) does not
import GTSAM.
"""

from importlib import import_module

__all__ = [
    "Container",
    "FusionGraph",
    "FusionParams",
    "HostCore",
    "IngestResult",
    "ReorderBuffer",
    "Tracker",
    "limit_blas_threads",
    "observations_to_map",
]

_WHERE = {
    "Container": ".container",
    "FusionGraph": ".graph",
    "FusionParams": ".params",
    "HostCore": ".hostcore",
    "IngestResult": ".hostcore",
    "ReorderBuffer": ".buffer",
    "Tracker": ".association",
    "limit_blas_threads": ".blas",
    "observations_to_map": ".association",
}


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(import_module(_WHERE[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
