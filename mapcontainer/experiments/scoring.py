"""Per-frame error figures of the experiments: re-exported from :mod:`mapcontainer.evaluation`.

The scoring lives in one module for the live evaluator and the experiments; import from
``mapcontainer.evaluation`` in new code.
"""

from __future__ import annotations

from ..evaluation import (
    GATE_M,
    age_of_information,
    horizontal_sq_error,
    obstacle_errors,
    relative_target_errors,
    rmse_sq,
    vehicle_pose,
)

__all__ = [
    "GATE_M",
    "age_of_information",
    "horizontal_sq_error",
    "obstacle_errors",
    "relative_target_errors",
    "rmse_sq",
    "vehicle_pose",
]
