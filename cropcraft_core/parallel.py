"""Worker processes for the work that fits many seeds on one machine (``cropcraft fit
--workers``, the benchmarks): the parallelism is the processes. Beyond one machine the flows
map the seeds as Prefect tasks on Dask (``flows/runners.py``).

Workers are spawned, not forked: numba's OpenMP threading layer aborts a process that forks
after using it ("fork() called from a process already using GNU OpenMP"), and the parent has
rendered observations by then. They leave Ctrl-C to the parent, which stops them at once
(:func:`processes`, :func:`stop`) instead of waiting minutes for the seeds they are running,
and they exit by themselves when the parent dies (a scheduler's kill), rather than go on
fitting for no one.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any

#: What ``pool(..., shared=...)`` handed each worker once (read by the jobs).
SHARED: dict[str, Any] = {}


#: Seconds between a worker's checks that its parent is alive.
ORPHAN_CHECK_S = 1.0


def _exit_when_orphaned(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(ORPHAN_CHECK_S)
    os._exit(1)  # reparented: the parent is gone, and nobody will read what this computes


def one_thread(shared: dict[str, Any] | None = None) -> None:
    """Worker process initialiser: one BLAS and one numba thread per process (two numba threads
    per process on 2 cores measurably oversubscribe), and the run's shared inputs; Ctrl-C is
    the parent's to handle, and the worker exits when its parent dies."""
    import numba
    from threadpoolctl import threadpool_limits

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_exit_when_orphaned, args=(os.getppid(),), daemon=True).start()
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


def stop(ex: Executor | None, *, now: bool = False) -> None:
    """Shut ``ex`` down after its jobs, or with ``now`` at once: queued jobs cancelled and the
    processes terminated mid-job (for an exception or a Ctrl-C on its way out; a seed's
    checkpoint is written atomically, so a later run resumes from its last one)."""
    if ex is None:
        return
    if not now:
        ex.shutdown()
        return
    if hasattr(ex, "terminate_workers"):  # Python 3.14's public way
        ex.terminate_workers()
        return
    procs = list((getattr(ex, "_processes", None) or {}).values())  # the executor's workers
    ex.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        p.terminate()
    for p in procs:
        p.join(10)


@contextmanager
def processes(workers: int, shared: dict[str, Any] | None = None) -> Iterator[Executor | None]:
    """:func:`pool` for a ``with`` block: stopped after its jobs when the block ends, at once
    (:func:`stop`) when it ends by an exception or Ctrl-C."""
    ex = pool(workers, shared)
    try:
        yield ex
    except BaseException:
        stop(ex, now=True)
        raise
    stop(ex)


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
