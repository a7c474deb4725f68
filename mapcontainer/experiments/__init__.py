"""Experiments: the paper's results, network degradation; each writes JSON/CSV, Markdown and PNG plots.

* :func:`run_paper_experiment` — ``mapc experiment paper`` (figure exp_sim, Tables res1/res2, ANEES, bytes).
* :func:`run_network_sweep` — ``mapc experiment network``; :func:`run_network_point` and
  :func:`write_network_outputs` are shared with the live-fleet variant (same row keys, ``NETWORK_COLUMNS``).

Runs are independent and go to a ``multiprocessing`` pool with the spawn context; progress on stderr.
"""

from .network import NETWORK_COLUMNS, run_network_point, run_network_sweep, sweep_profile, write_network_outputs
from .paper import PaperSettings, run_paper_experiment
from .progress import Progress

__all__ = [
    "NETWORK_COLUMNS",
    "PaperSettings",
    "Progress",
    "run_network_point",
    "run_network_sweep",
    "run_paper_experiment",
    "sweep_profile",
    "write_network_outputs",
]
