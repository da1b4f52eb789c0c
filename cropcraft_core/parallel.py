"""Worker processes for the work that fits many seeds on one machine (``cropcraft fit
--workers``, the benchmarks): the parallelism is the processes. Beyond one machine the flows
map the seeds as Prefect tasks on Dask (``flows/runners.py``).

Workers are spawned, not forked: numba's OpenMP threading layer aborts a process that forks
after using it ("fork() called from a process already using GNU OpenMP"), and the parent has
rendered observations by then.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import Executor, ProcessPoolExecutor
from typing import Any

#: What ``pool(..., shared=...)`` handed each worker once (read by the jobs).
SHARED: dict[str, Any] = {}


def one_thread(shared: dict[str, Any] | None = None) -> None:
    """Worker process initialiser: one BLAS and one numba thread per process (two numba threads
    per process on 2 cores measurably oversubscribe), and the run's shared inputs."""
    import numba
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    numba.set_num_threads(1)
    SHARED.update(shared or {})


def pool(workers: int, shared: dict[str, Any] | None = None) -> Executor | None:
    """``workers`` spawned single-threaded processes that each get ``shared`` once (in
    :data:`SHARED`); None (work in-process, ``shared`` set here) for ``workers`` ≤ 1."""
    if workers <= 1:
        SHARED.update(shared or {})
        return None
    ctx = multiprocessing.get_context("spawn")
    return ProcessPoolExecutor(workers, mp_context=ctx, initializer=one_thread, initargs=(shared,))


def default_workers(jobs: int) -> int:
    """Processes for ``jobs`` independent jobs: one per CPU this process may run on, at most
    one per job, at least one."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cpus = os.cpu_count() or 1
    return max(1, min(jobs, cpus))


def run_jobs(ex: Executor | None, fn: Callable, jobs: list):
    """``fn`` over ``jobs`` in ``ex``'s processes, in order, or in-process without one."""
    return ex.map(fn, jobs) if ex is not None else map(fn, jobs)
