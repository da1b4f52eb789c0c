"""Task runners for the CropCraft flows: ``threads`` (default), ``dask`` (a local cluster) or
``dask://host:port`` (an existing Dask scheduler), through prefect-dask.

Tasks exchange store keys and small records only, so any runner works; on Dask the workers need
the ``cropcraft`` package and credentials for the scene store in their own environment.
"""

from __future__ import annotations

import os
from typing import Any

from cropcraft_core.errors import ConfigError

RUNNERS = ("threads", "dask", "dask://HOST:PORT")


def parse_runner(spec: str | None) -> tuple[str, str | None]:
    """``(kind, address)`` of a runner spec; ConfigError for anything else."""
    spec = (spec or "threads").strip()
    if spec == "threads":
        return "threads", None
    if spec == "dask":
        return "dask", None
    if spec.startswith("dask://"):
        hostport = spec[len("dask://") :].strip("/")
        host, sep, port = hostport.rpartition(":")
        if not sep or not host or not port.isdigit():
            raise ConfigError(
                f"runner {spec!r}: expected dask://HOST:PORT, e.g. dask://10.0.0.5:8786"
            )
        return "dask", f"tcp://{host}:{port}"
    raise ConfigError(f"unknown runner {spec!r}: choose threads, dask or dask://HOST:PORT")


def make_task_runner(spec: str | None = "threads", *, workers: int | None = None) -> Any:
    """A Prefect task runner for ``spec``.

    threads: ``ThreadPoolTaskRunner`` with ``workers`` threads (default: CPU count, at most 8).
    dask: ``DaskTaskRunner`` over a temporary :func:`local_cluster` of ``workers``
    single-threaded worker processes (default 2). dask://host:port: ``DaskTaskRunner(address=...)``.
    """
    kind, address = parse_runner(spec)
    if kind == "threads":
        from prefect.task_runners import ThreadPoolTaskRunner

        n = workers or min(8, os.cpu_count() or 2)
        return ThreadPoolTaskRunner(max_workers=n)
    try:
        from prefect_dask import DaskTaskRunner
    except ImportError as exc:  # pragma: no cover - a dependency
        raise ConfigError(f"runner {spec!r} needs prefect-dask: pip install prefect-dask") from exc
    if address:
        return DaskTaskRunner(address=address)
    return DaskTaskRunner(
        cluster_class=local_cluster,
        cluster_kwargs={
            "n_workers": workers or 2,
            "threads_per_worker": 1,
            "processes": True,
            "dashboard_address": None,
        },
    )


def local_cluster(**kwargs: Any) -> Any:
    """The ``dask`` runner's ``LocalCluster`` (``kwargs`` as LocalCluster's), started when the
    flow starts its task runner, with workers that compute as ``cropcraft``'s own processes do:

    - no ``MALLOC_TRIM_THRESHOLD_`` (Dask's nanny default of 64 KiB made every large array a
      fresh ``mmap``: a fit seed ran 1.9x slower, benchmarks/RESULTS.md *#dask-malloc*; stages
      also undo it themselves on any worker, ``cropcraft_core.parallel.reuse_freed_memory``);
    - the flow's Prefect API (``PREFECT_API_URL``), so that task runs report to the server the
      flow reports to, instead of each worker starting an ephemeral server of its own.
    """
    import dask
    from distributed import LocalCluster

    env = {}
    api = _flow_api_url()
    if api:
        env["PREFECT_API_URL"] = api
    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        return LocalCluster(env=env, **kwargs)


def _flow_api_url() -> str | None:
    """The HTTP address of the Prefect API this process talks to (a server's, or the ephemeral
    server's that the flow started), None where there is none to share (an in-process app)."""
    from prefect.client.orchestration import get_client

    try:
        url = str(get_client(sync_client=True).api_url).rstrip("/")
    except Exception:  # no API at all: the workers do as they would have
        return None
    return url if url.startswith(("http://", "https://")) and "//ephem" not in url else None
