"""The flows' task runners: the specs, and the local Dask cluster's workers compute as
cropcraft's own processes do (no pinned malloc trim) and report to the flow's Prefect API (the
``processes`` runner runs the scene flow in ``test_flows``)."""

from __future__ import annotations

import os

import pytest

from cropcraft_core.errors import ConfigError
from cropcraft_core.kernels import PORTABLE
from cropcraft_core.store import numeric_kernels
from flows.runners import local_cluster, make_task_runner, parse_runner


def test_runner_specs_parse_or_name_the_problem():
    assert parse_runner(None) == ("processes", None)  # the default
    assert parse_runner("threads") == ("threads", None)
    assert parse_runner("processes") == ("processes", None)
    assert parse_runner("dask") == ("dask", None)
    assert parse_runner("dask://10.0.0.5:8786") == ("dask", "tcp://10.0.0.5:8786")
    with pytest.raises(ConfigError, match="dask://HOST:PORT"):
        parse_runner("dask://nohost")
    with pytest.raises(ConfigError, match="unknown runner"):
        parse_runner("ray")


def _worker_env() -> dict:
    from cropcraft_core.store import numeric_kernels

    return {
        "kernels": numeric_kernels(),
        "malloc": os.environ.get("MALLOC_TRIM_THRESHOLD_"),
        "numba_env": os.environ.get("NUMBA_NUM_THREADS"),
        "api": os.environ.get("PREFECT_API_URL"),
        "omp": os.environ.get("OMP_NUM_THREADS"),
    }


def test_local_cluster_workers_compute_like_cropcrafts_own_processes():
    pytest.importorskip("prefect_dask")
    from distributed import Client
    from prefect.settings import PREFECT_API_URL, temporary_settings

    url = "http://127.0.0.1:4200/api"  # the address is only handed on, never called here
    runner = make_task_runner("dask", workers=1)
    assert runner.cluster_class is local_cluster
    with temporary_settings({PREFECT_API_URL: url}):
        cluster = local_cluster(**runner.cluster_kwargs)
    with cluster, Client(cluster) as client:
        env = client.submit(_worker_env, pure=False).result(timeout=120)
    # numba keeps every core for a stage that runs alone; fit seeds take their share themselves
    numba_env = os.environ.get("NUMBA_NUM_THREADS")
    # the CPU kernels the flow's own process runs (cropcraft_core.kernels)
    kernels = numeric_kernels()
    assert env == {
        "kernels": kernels,
        "malloc": None,
        "numba_env": numba_env,
        "api": url,
        "omp": "1",
    }


def test_shipped_dask_worker_config_drops_the_malloc_pin():
    """``deploy/dask`` (DASK_CONFIG for remote workers, set in the images) leaves the worker
    processes' malloc alone and pins their CPU kernels as CropCraft's own processes do."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    code = (
        "import json; from distributed.nanny import _get_env_variables as g; "
        "print(json.dumps(g('distributed.nanny.pre-spawn-environ')))"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MALLOC_", "DASK_"))}
    out = subprocess.run(
        [sys.executable, "-c", code],
        env={**env, "DASK_CONFIG": str(root / "deploy" / "dask")},
        capture_output=True,
        text=True,
        check=True,
    )
    spawn_env = json.loads(out.stdout)
    assert "MALLOC_TRIM_THRESHOLD_" not in spawn_env
    assert spawn_env["OMP_NUM_THREADS"] == "1"  # Dask's own default, kept
    assert {k: spawn_env.get(k) for k in PORTABLE} == PORTABLE


def test_the_cli_names_the_flows_default_runner():
    """The CLI writes the default out (importing flows.runners would load Prefect for every
    command); it must be the flows' own."""
    import argparse

    from flows.runners import DEFAULT_RUNNER
    from flows.service_cli import _add_common

    parser = argparse.ArgumentParser()
    _add_common(parser)
    assert parser.parse_args([]).runner == DEFAULT_RUNNER


_NAP_FLOW = """
import os, sys, time
from prefect import flow, task
from flows.runners import LocalProcessPool


@task
def nap(seconds: float) -> float:
    open(os.environ["NAP_STARTED"], "w").close()
    time.sleep(seconds)
    return seconds


@flow(task_runner=LocalProcessPool(max_workers=2))
def napping(seconds: float) -> float:
    return nap.submit(seconds).result()
"""

_NAP_COMMAND = """
import signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)  # as a terminal's foreground job
from flows.cli import interrupt_deadline
from flows.service_cli import _before_flow_run, _named_errors_in_one_line
import napflow
if __name__ == "__main__":
    _before_flow_run()
    try:
        with interrupt_deadline(grace_s=60), _named_errors_in_one_line():
            napflow.napping(300)
    except KeyboardInterrupt:
        print("cropcraft: interrupted", file=sys.stderr)
        sys.exit(130)
"""


def _napping_command(tmp_path):
    """``_NAP_COMMAND`` started as a terminal's job (its own group), and the file its task
    touches once it runs in a pool worker."""
    import subprocess
    import sys
    from pathlib import Path

    (tmp_path / "napflow.py").write_text(_NAP_FLOW)
    (tmp_path / "run.py").write_text(_NAP_COMMAND)
    root = Path(__file__).resolve().parents[1]
    started = tmp_path / "started"
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}  # a temporary server
    env.update(
        PYTHONPATH=os.pathsep.join([str(tmp_path), str(root)]),
        NAP_STARTED=str(started),
        PREFECT_HOME=str(tmp_path / "prefect"),
        PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS="180",
        # as flows.cli.main sets it: the server's telemetry heartbeat, racing its own start on
        # SQLite, printed a "database is locked" traceback now and then (a flaky test)
        PREFECT_SERVER_ANALYTICS_ENABLED="false",
    )
    proc = subprocess.Popen(
        [sys.executable, str(tmp_path / "run.py")],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own group, as a terminal's job
    )
    return proc, started


def _napping_family(proc, started):
    """The command's processes (its server, its pool's workers) once its task is napping."""
    import time

    import psutil

    deadline = time.monotonic() + 300
    while not started.exists():
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
        time.sleep(0.2)
    return psutil.Process(proc.pid).children(recursive=True)


def test_ctrl_c_on_a_flow_ends_it_in_seconds_in_one_line_each(tmp_path):
    """Ctrl-C during a stage of ``cropcraft run`` (SIGINT to the terminal's whole foreground
    group) printed 115–151 lines holding 4–5 tracebacks and ended only by the 15 s forced
    path (session 91's CLI audit): the same Ctrl-C had stopped Prefect's temporary server, so
    the flow's crash handling retried it, and the task's ``KeyboardInterrupt`` from a pool
    worker killed the pool's manager thread, whose other worker then held the exit. Now the
    server, apart from the group, records the crash; the worker hands the interrupt back as
    an Exception; the command ends in seconds, no traceback, no process left."""
    import signal
    import time

    import psutil

    proc, started = _napping_command(tmp_path)
    try:
        family = _napping_family(proc, started)
        server = [p for p in family if "prefect.server.api.server" in " ".join(p.cmdline())]
        assert len(server) == 1 and os.getsid(server[0].pid) == server[0].pid  # apart
        t0 = time.monotonic()
        os.killpg(proc.pid, signal.SIGINT)  # what the terminal does on Ctrl-C
        _, err = proc.communicate(timeout=60)
        elapsed = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert elapsed < 10, (elapsed, err)  # before: 20 s, the forced path
    assert "Traceback" not in err and "ending its processes" not in err, err
    assert "Finished in state Crashed" in err, err  # the server was there to record it
    assert "cropcraft: interrupted" in err and len(err.strip().splitlines()) <= 12, err
    time.sleep(1)
    left = [p for p in family if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    assert not left, [p.cmdline() for p in left]


def test_a_killed_commands_pool_workers_end_with_it(tmp_path):
    """A ``kill -9`` of ``cropcraft run`` left its pool workers running: they finished their
    stage and wrote it into the scene, over the files of a rerun that already held it (session
    93's overlap audit). A worker mid-stage now ends within seconds of its command, and so does
    the temporary server."""
    import signal
    import time

    import psutil

    proc, started = _napping_command(tmp_path)
    try:
        family = _napping_family(proc, started)
        assert len(family) >= 2  # the server and the pool's worker(s), one napping
        os.kill(proc.pid, signal.SIGKILL)  # the command alone, as kill -9 PID
        proc.wait(timeout=30)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            left = [p for p in family if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
            if not left:
                break
            time.sleep(0.5)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    left = [p for p in family if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    for p in left:
        p.kill()
    assert not left, [p.cmdline() for p in left]


def test_an_existing_dask_cluster_is_checked_before_the_run(tmp_path):
    """dask://HOST:PORT with no scheduler there gave a 171-line traceback twice after ~126 s;
    a scheduler without workers hung the run for good, silent (session 92's Dask audit). Both
    are one-line ConfigErrors within the wait; a scheduler with a worker is taken."""
    import socket
    import time

    from distributed import LocalCluster

    from flows.runners import check_cluster

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match=f"no Dask scheduler answers at tcp://127.0.0.1:{port}"):
        make_task_runner(f"dask://127.0.0.1:{port}")  # the runner a run would get
    assert time.monotonic() - t0 < 60
    with LocalCluster(
        n_workers=0, processes=False, dashboard_address=None, scheduler_port=0
    ) as cluster:
        address = cluster.scheduler_address
        with pytest.raises(ConfigError, match="has no workers .*: start them as deploy/README"):
            check_cluster(address, wait_s=2.0)
        cluster.scale(1)
        assert check_cluster(address, wait_s=60.0) == 1
