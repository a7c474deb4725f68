"""Independent runs of an experiment, in worker processes, with a progress bar."""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from typing import Any

from ..fusion.blas import limit_blas_threads
from .progress import Progress

__all__ = ["run_all"]


def run_all(
    fn: Callable[[Any], dict],
    tasks: Sequence,
    workers: int,
    label: str,
    note: Callable[[dict], str],
    progress: bool = True,
) -> list[dict]:
    """``fn(task)`` for every task, results in the order they finish; ``note(result)`` labels the bar.

    ``workers == 1`` runs them here, in order. Otherwise a pool of ``workers`` spawned processes runs
    them (``fn`` must be importable), each with one BLAS thread: the workers fill the cores, and
    OpenBLAS would start one thread per core in every worker (no measurable difference at 2 workers
    on 2 cores, where it rarely threads; workers x cores threads on a larger machine).
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    bar = Progress(len(tasks), label, enabled=progress)
    out: list[dict] = []
    try:
        with ExitStack() as stack:
            if workers == 1:
                results = map(fn, tasks)
            else:
                ctx = mp.get_context("spawn")
                pool = stack.enter_context(ctx.Pool(workers, initializer=limit_blas_threads, initargs=(1,)))
                results = pool.imap_unordered(fn, tasks)
            for r in results:
                out.append(r)
                bar.update(note=note(r))
    finally:
        bar.close()
    return out
