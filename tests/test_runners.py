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
