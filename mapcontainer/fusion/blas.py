"""Limit the threads of the OpenBLAS copies numpy and scipy bring (process-wide).

The container's linear algebra is many small dense matrices (3x3 ... a few hundred). On a small
machine OpenBLAS's worker threads cost more than they give: waking them for a 600x600 triangular
inverse measured 5 ms or 370 ms depending on what else was running, and 5-25 ms spikes on 36x36
solves. One thread makes those times steady. Without threadpoolctl in the environment, this calls
``*openblas_set_num_threads*`` in every loaded OpenBLAS library through ctypes (Linux: found in
/proc/self/maps; elsewhere nothing happens). It changes the whole process, so the host's worker
process and benchmarks call it, not library code that shares a process with others by default.
"""

from __future__ import annotations

import ctypes
import logging
from pathlib import Path

__all__ = ["limit_blas_threads"]

log = logging.getLogger(__name__)

_SETTERS = (
    "openblas_set_num_threads",
    "scipy_openblas_set_num_threads",
    "scipy_openblas_set_num_threads64_",
    "openblas_set_num_threads64_",
)


def _loaded_openblas() -> list[str]:
    maps = Path("/proc/self/maps")
    if not maps.exists():
        return []
    paths = {line.split()[-1] for line in maps.read_text().splitlines() if "openblas" in line.lower()}
    return sorted(p for p in paths if p.endswith(".so") or ".so." in p)


def limit_blas_threads(n: int = 1) -> int:
    """Set every loaded OpenBLAS to ``n`` threads; returns how many libraries were set."""
    import numpy  # noqa: F401  (load the libraries first)
    import scipy.linalg  # noqa: F401

    if n < 1:
        raise ValueError(f"thread count must be >= 1, got {n}")
    done = 0
    for path in _loaded_openblas():
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in _SETTERS:
            fn = getattr(lib, name, None)
            if fn is not None:
                fn(ctypes.c_int(n))
                done += 1
                break
    log.debug("OpenBLAS threads set to %d in %d libraries", n, done)
    return done
