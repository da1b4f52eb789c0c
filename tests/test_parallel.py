"""The worker processes that `cropcraft fit --workers` and the benchmarks spread seeds over:
stopped at once on an exception or Ctrl-C, gone when their parent dies, and deaf to the
Ctrl-C their parent handles."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from concurrent.futures.process import EXTRA_QUEUED_CALLS, BrokenProcessPool
from pathlib import Path

import pytest

from cropcraft_core.parallel import default_workers, processes

ROOT = Path(__file__).resolve().parents[1]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (exited, not yet reaped) counts as gone
    stat = Path(f"/proc/{pid}/stat")
    return not (stat.exists() and stat.read_text().split(") ", 1)[1].startswith("Z"))


def _gone_within(pids: list[int], seconds: float) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if not any(_alive(p) for p in pids):
            return True
        time.sleep(0.1)
    return False


def _started_workers(ex, n: int) -> list[int]:
    """Run a no-op on every worker, so all ``n`` have started, and return their pids."""
    for f in [ex.submit(os.getpid) for _ in range(4 * n)]:
        f.result()
    assert len(ex._processes) == n
    return sorted(ex._processes)


def test_an_exception_stops_running_jobs_at_once_and_workers_ignore_ctrl_c():
    t = time.monotonic()
    with pytest.raises(KeyboardInterrupt), processes(2) as ex:
        pids = _started_workers(ex, 2)
        running = [ex.submit(time.sleep, 120) for _ in range(2)]
        queued = [ex.submit(time.sleep, 120) for _ in range(6)]
        time.sleep(0.5)
        os.kill(pids[0], signal.SIGINT)  # a Ctrl-C reaches the workers too: they leave it
        time.sleep(0.5)
        assert _alive(pids[0]) and not any(f.done() for f in running)
        raise KeyboardInterrupt  # the parent's Ctrl-C
    assert _gone_within(pids, 10)
    assert time.monotonic() - t < 30  # not the 120 s the running jobs had left
    # none ran on: cancelled, or broken off where already handed to the pool's call queue,
    # which holds the workers' number plus EXTRA_QUEUED_CALLS once the running two have left it
    for f in running + queued:
        assert f.cancelled() or isinstance(f.exception(), BrokenProcessPool)
    assert sum(f.cancelled() for f in queued) >= len(queued) - (2 + EXTRA_QUEUED_CALLS)


def test_a_finished_block_waits_for_its_jobs():
    with processes(2) as ex:
        f = ex.submit(sum, [1, 2, 3])
    assert f.result() == 6
    with processes(1) as ex:  # one worker: in this process, nothing to stop
        assert ex is None


def test_workers_exit_when_their_parent_is_killed(tmp_path):
    """A scheduler kills the fit: its workers do not go on fitting for no one."""
    script = (
        "import os, sys, time\n"
        "from cropcraft_core.parallel import pool\n"
        "ex = pool(2)\n"
        "fs = [ex.submit(time.sleep, 120) for _ in range(2)]\n"
        "time.sleep(3)\n"
        "print(' '.join(map(str, ex._processes)), flush=True)\n"
        "time.sleep(120)\n"
    )
    parent = subprocess.Popen(
        [sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE, text=True
    )
    try:
        pids = [int(p) for p in parent.stdout.readline().split()]
        assert len(pids) == 2 and all(_alive(p) for p in pids)
        parent.kill()
        parent.wait(10)
        assert _gone_within(pids, 10)
    finally:
        parent.kill()


def test_default_workers_one_per_cpu_at_most_one_per_job():
    cpus = len(os.sched_getaffinity(0))
    assert default_workers(1) == 1
    assert default_workers(0) == 1
    assert default_workers(10**6) == cpus
    assert default_workers(2) == min(2, cpus)


_FAULTS = """
import json, resource, sys
import numpy as np
from cropcraft_core.parallel import reuse_freed_memory

def faults():
    # 40 arrays of 8 MB, each filled and freed, as a fit evaluation's depth maps are
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(40):
        a = np.empty(1_000_000)
        a.fill(1.0)
        del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0

faults()  # numpy's own start-up
before = faults()
applied = reuse_freed_memory()
again = reuse_freed_memory()
after = faults()
print(json.dumps({"before": before, "after": after, "applied": applied, "again": again}))
"""


def _faults(env: dict[str, str]) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")} | env
    out = subprocess.run(
        [sys.executable, "-c", _FAULTS], env=env, cwd=ROOT, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    import json

    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_freed_arrays_are_reused_again_on_a_dask_workers_malloc_settings():
    """A Dask nanny pins MALLOC_TRIM_THRESHOLD_=65536 on its workers: every large array is then
    a fresh mmap whose pages fault in one by one; ``reuse_freed_memory`` undoes it, once."""
    pinned = _faults({"MALLOC_TRIM_THRESHOLD_": "65536"})
    assert pinned["applied"] and not pinned["again"]
    assert pinned["after"] < pinned["before"] / 10, pinned
    # without the pin glibc's own dynamic thresholds already reuse freed arrays: left alone
    plain = _faults({})
    assert not plain["applied"] and plain["before"] < pinned["before"] / 10, (plain, pinned)


def test_a_jobs_numba_share_is_its_threads_own_and_restored(monkeypatch):
    """Numba's thread count is per calling thread: a fit seed takes its share of the cores in
    its own thread, other threads keep theirs, and its thread gets the old count back."""
    import threading

    import numba

    from cropcraft_core.parallel import numba_threads_per_job

    cores = numba.config.NUMBA_NUM_THREADS
    before = numba.get_num_threads()
    seen: dict[str, int] = {}
    inside = threading.Event()
    done = threading.Event()

    def other():
        inside.wait(30)
        seen["other"] = numba.get_num_threads()
        done.set()

    t = threading.Thread(target=other)
    t.start()
    with numba_threads_per_job(10) as n:
        assert n == numba.get_num_threads() == max(1, cores // 10)
        inside.set()
        done.wait(30)
    t.join()
    assert seen["other"] == cores  # a fresh thread: numba's default, untouched
    assert numba.get_num_threads() == before
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    with numba_threads_per_job(1) as n:
        assert n == before  # alone: every core this thread had
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # a Dask worker's budget per task
    with numba_threads_per_job(1) as n:
        assert n == 1
    assert numba.get_num_threads() == before


def test_a_worker_whose_parent_died_while_it_started_exits():
    """Spawning takes seconds on busy cores: a worker whose pool's process was killed before
    its initialiser ran has been reparented by then, and exits at once rather than wait for
    a parent it no longer has (it read the new parent as its own, and lived on)."""
    script = (
        "import os, time\n"
        "from cropcraft_core.parallel import one_thread\n"
        "one_thread(None, parent=os.getppid() + 1_000_000)\n"  # not this process's parent
        "time.sleep(60)\n"
    )
    t = time.monotonic()
    run = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, timeout=50, capture_output=True, text=True
    )
    assert run.returncode == 1 and not run.stderr  # the watcher's exit, not an error
    assert time.monotonic() - t < 40
