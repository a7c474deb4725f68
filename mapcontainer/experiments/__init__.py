"""Experiments: the paper's results, network degradation; each writes JSON/CSV, Markdown and PNG plots.

* :func:`run_paper_experiment` — ``mapc experiment paper`` (figure exp_sim, Tables res1/res2, ANEES, bytes).
* :func:`run_network_sweep` — ``mapc experiment network``; :func:`run_network_point` and
  :func:`write_network_outputs` are shared with the live-fleet variant (same row keys, ``NETWORK_COLUMNS``).

Runs are independent tasks, each with its own seed: :func:`.runner.run_all` sends them to an executor
(:mod:`.executors`: this process, a local process pool, or a Dask cluster), keeps each finished one in
``OUT/tasks`` (:mod:`.store`: a rerun resumes) and gives the results in task order, so the outputs do not
depend on what ran them; what they cost goes to ``timing.json``. Progress on stderr.
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
