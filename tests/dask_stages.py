"""Prefect tasks the Dask tests run on a cluster's workers: in a module of their own, which the
workers import by name (a task defined in a test module is pickled by value, and pytest's
import of that module is not the one the workers would make)."""

from __future__ import annotations

import time
from pathlib import Path

from prefect import task


@task
def long_stage(marker: str) -> int:
    """A stage that runs two minutes, saying when it started (``marker`` touched)."""
    Path(marker).touch()
    time.sleep(120)
    return 1
