"""Host container: reorder buffer, association, sliding-window factor graph (paper §III-D)."""

from .association import Tracker, observations_to_map
from .blas import limit_blas_threads
from .buffer import ReorderBuffer
from .container import Container, IngestResult
from .graph import FusionGraph
from .params import FusionParams

__all__ = [
    "Container",
    "FusionGraph",
    "FusionParams",
    "IngestResult",
    "ReorderBuffer",
    "Tracker",
    "limit_blas_threads",
    "observations_to_map",
]
