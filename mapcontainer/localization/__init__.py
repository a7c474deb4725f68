"""Self-localization by HD-map matching (the paper's "Map-matching Localization"), with a GNSS +
odometry fallback. Pure core: no I/O, deterministic.

* :mod:`.params` -- the localizer's inputs, result and parameters (shared by the modules below).
* :mod:`.matcher` -- one Levenberg-Marquardt solve for one camera frame (D_P, D_L, EDT lane
  residual, r_n, GNSS and prediction priors), assembled from its stages: :mod:`.matcher_types`
  (parameters, frame and result types), :mod:`.lanes` (the lane distance transform, lane search and
  residual), :mod:`.association`, :mod:`.residuals` and :mod:`.lm` (association rounds and LM).
* :mod:`.localizer` -- tracking over frames: odometry prediction, failure detection, fallback, recovery.
* :mod:`.ekf` -- the localizer's filter: prediction, match, GNSS and ground updates, as plain functions.
* :mod:`.startup` -- the localizer's phases (uninitialised, verifying, searching, tracking) as a state machine;
  :mod:`.basins` -- its candidate basins tracked as hypotheses (spawned, weighed, merged, their rivals), with
  :mod:`.hypotheses` -- their posterior masses and moments.
"""

from .lanes import lane_distance_transform
from .localizer import Localizer
from .matcher import MapMatcher
from .matcher_types import CameraFrame, MatcherParams, MatchResult
from .params import GnssMeasurement, LocalizationResult, LocalizerParams, OdometryMeasurement

__all__ = [
    "CameraFrame",
    "GnssMeasurement",
    "LocalizationResult",
    "Localizer",
    "LocalizerParams",
    "MapMatcher",
    "MatchResult",
    "MatcherParams",
    "OdometryMeasurement",
    "lane_distance_transform",
]
