"""The ``dask`` runners' task runner: prefect-dask's, with the workers' progress on this
process's console.

A task on a Dask worker has no progress sink of its own (``tasks.common.set_progress_sink``):
it sends its progress to the scheduler as an event on ``tasks.common.PROGRESS_TOPIC``, and the
run's client, subscribed to that topic, hands each to this process's sink. Before, ``cropcraft
run --runner dask`` printed nothing through minutes of stereo and the whole fit (session 92's
Dask audit). Imported only where a Dask runner is asked for (prefect-dask is needed then).
"""

from __future__ import annotations

from typing import Any

from prefect_dask import DaskTaskRunner

from tasks.common import PROGRESS_TOPIC, deliver_event


class DaskTaskRunnerWithProgress(DaskTaskRunner):
    """``DaskTaskRunner`` whose client, once made, subscribes to the workers' progress."""

    @property
    def client(self) -> Any:
        fresh = self._client is None
        client = super().client
        if fresh:
            client.subscribe_topic(PROGRESS_TOPIC, deliver_event)
        return client
