"""Limit the BLAS thread pools of the whole process (numpy's and scipy's OpenBLAS) with threadpoolctl.

The container's linear algebra is many small dense matrices (3x3 ... a few hundred). On a 2-core
machine OpenBLAS's worker threads cost more than they give: waking them for a 600x600 triangular
inverse measured 5 ms or 370 ms depending on what else was running, and 5-25 ms spikes on 36x36
solves; one thread makes those times steady. It changes the whole process, so the processes that
fuse (the host service's worker, benchmarks, experiment workers) call it, not library code.
"""

from __future__ import annotations

from threadpoolctl import threadpool_limits

__all__ = ["limit_blas_threads"]


def limit_blas_threads(n: int = 1) -> None:
    """Use at most ``n`` BLAS threads in this process from now on."""
    if n < 1:
        raise ValueError(f"n must be at least 1, got {n}")
    # threadpoolctl limits the libraries loaded so far: load numpy's and scipy's BLAS first (a process that
    # calls this before anything imported them, such as a fresh experiment worker, had no BLAS to limit)
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401

    threadpool_limits(limits=n, user_api="blas")
