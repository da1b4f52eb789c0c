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


def process_gone(pid: int) -> bool:
    """Whether no process of this host's pid namespace has ``pid`` (another user's live
    process, which the signal may not reach, is there; an impossible pid is not gone)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except (OSError, OverflowError):  # no permission: another user's process is there
        return False
    return False


def exit_when_orphaned(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(ORPHAN_CHECK_S)
    os._exit(1)  # reparented: the parent is gone, and nobody will read what this computes


def one_thread(shared: dict[str, Any] | None, parent: int) -> None:
    """Worker process initialiser: one BLAS and one numba thread per process (two numba threads
    per process on 2 cores measurably oversubscribe), and the run's shared inputs; Ctrl-C is
    the parent's to handle, and the worker exits when its parent dies. ``parent``: the pid of
    the process that made the pool (:func:`pool` passes it), so that a worker still starting
    when its parent was killed (spawning takes seconds on busy cores) exits at once: read here
    (``os.getppid``), the pid would be its new parent's, and it never would."""
    import numba
    from threadpoolctl import threadpool_limits

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=exit_when_orphaned, args=(parent,), daemon=True).start()
    threadpool_limits(1)
    numba.set_num_threads(1)
    SHARED.update(shared or {})


#: glibc's ``mallopt`` parameters (``malloc.h``) and the environment variables that set them.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
MALLOC_ENV = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_")
#: What :func:`reuse_freed_memory` sets: glibc's own upper limits for its dynamic thresholds on
#: 64-bit (mmap 32 MiB; trim twice that), so a freed depth map or GP matrix is reused by the next
#: evaluation instead of being returned to the kernel and faulted back in, zeroed, page by page.
HEAP_MMAP_THRESHOLD = 32 * 1024 * 1024
HEAP_TRIM_THRESHOLD = 2 * HEAP_MMAP_THRESHOLD
_heap_reset = False


def reuse_freed_memory() -> bool:
    """Undo a small malloc trim or mmap threshold pinned by the environment; True if it did.

    Dask's nanny starts every worker with ``MALLOC_TRIM_THRESHOLD_=65536`` (its
    ``distributed.nanny.pre-spawn-environ``), and glibc then also stops raising its mmap
    threshold above 128 KiB: every array over 128 KiB that a fit evaluation allocates (depth
    maps, histograms' inputs, the GP's matrices) is a fresh ``mmap`` whose pages the kernel
    zeroes on first touch, and is unmapped when freed. Measured on the demo's observation
    (benchmarks/RESULTS.md, *#dask-malloc*): 14x the page faults, one evaluation 22 % slower,
    a BO seed 1.9x slower (the optimiser 2.5x), a third of the CPU time in the kernel. The
    thresholds are set back to glibc's own dynamic maxima (:data:`HEAP_MMAP_THRESHOLD`) with
    ``mallopt``. Nothing happens where neither variable is set (glibc's dynamic thresholds are
    left to work), where the process is not on glibc, or after the first call.
    """
    global _heap_reset
    if _heap_reset or not any(os.environ.get(k) for k in MALLOC_ENV):
        return False
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (macOS, musl): nothing to undo
        return False
    ok = mallopt(_M_MMAP_THRESHOLD, HEAP_MMAP_THRESHOLD) == 1
    ok = mallopt(_M_TRIM_THRESHOLD, HEAP_TRIM_THRESHOLD) == 1 and ok
    _heap_reset = True
    return ok


@contextmanager
def numba_threads_per_job(jobs: int) -> Iterator[int]:
    """Run this thread's numba kernels on an even share of the cores while ``jobs`` like it run
    at once (at least one thread each); numba's thread count is per calling thread, so other
    threads' kernels are untouched, and the count is restored on exit (a thread pool's thread
    runs other stages after this one). Yields the count.

    A flow maps its fit seeds over as many workers as there are cores: each seed's kernels on
    every core oversubscribe them (two processes on two cores: one evaluation 233-239 ms with
    numba's two threads each, 187-199 ms with one; in one process's threads about neutral;
    benchmarks/RESULTS.md *#dask-malloc*), while a stage that runs alone (the stereo, the
    aggregate) keeps them all. A process whose ``OMP_NUM_THREADS`` says how many threads a task
    may take (a Dask worker's 1, where many scenes' seeds share a large host) caps the share.
    """
    import numba

    old = numba.get_num_threads()
    cores = numba.config.NUMBA_NUM_THREADS
    omp = os.environ.get("OMP_NUM_THREADS", "")
    if omp.isdigit() and int(omp) >= 1:  # the process's own thread budget per task (Dask: 1)
        cores = min(cores, int(omp))
    n = max(1, cores // max(1, int(jobs)))
    numba.set_num_threads(min(n, old))
    try:
        yield numba.get_num_threads()
    finally:
        numba.set_num_threads(old)


def pool(workers: int, shared: dict[str, Any] | None = None) -> Executor | None:
    """``workers`` spawned single-threaded processes that each get ``shared`` once (in
    :data:`SHARED`); None (work in-process, ``shared`` set here) for ``workers`` ≤ 1."""
    if workers <= 1:
        SHARED.update(shared or {})
        return None
    ctx = multiprocessing.get_context("spawn")
    return ProcessPoolExecutor(
        workers, mp_context=ctx, initializer=one_thread, initargs=(shared, os.getpid())
    )


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
