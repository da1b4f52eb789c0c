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
    dask: ``DaskTaskRunner`` over a temporary ``LocalCluster`` of ``workers`` single-threaded
    worker processes (default 2). dask://host:port: ``DaskTaskRunner(address=...)``.
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
        cluster_kwargs={
            "n_workers": workers or 2,
            "threads_per_worker": 1,
            "processes": True,
            "dashboard_address": None,
        }
    )
